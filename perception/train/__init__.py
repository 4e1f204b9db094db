"""Training: ``python -m perception.train --config CONFIG --data DIR [DIR ...] --out DIR [--model KIND]``.

Modules: :mod:`~perception.train.run` (a run: resume, stages, export), :mod:`~perception.train.loop` (one
stage's optimisation loop), :mod:`~perception.train.stages` (what each stage trains and validates),
:mod:`~perception.train.checkpoint` (atomic checkpoints, RNG state, weights-only export),
:mod:`~perception.train.distributed` (torchrun / DistributedDataParallel), :mod:`~perception.train.cli`.
"""
