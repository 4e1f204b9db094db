"""Procedural table-top furniture (chairs, tables, cabinets) as assembly folders.

>>> import numpy as np
>>> from perception.synth import generate
>>> assembly = generate("chair", "3", np.random.default_rng(0), "chair_3_s0_00000")

``level`` "3" gives the finest parts (every board, leg, rail and slat a separate convex part); "mixed"
merges random connected sub-assemblies of that same level-3 object (the mixed object drawn from a
generator state merges the level-3 object drawn from the same state). See the category modules for the
structural choices; they are recorded in ``assembly.metadata["variant"]``, with ``"category"``,
``"level"``, ``"generator"``, ``"joints"`` (the designed contacts, pairs of part names) and ``"modules"``
(the sub-assembly each part belongs to); level-3 objects also carry ``"stages"`` (a designed assembly order:
part name -> rank, equal ranks in any order) and cabinets ``"max_stage_span"``, which the mixed level uses.

Every object is designed to be assembled by a robot with a parallel-jaw hand (a Franka Panda), one part after
the other: parts leave room for the fingers where the hand must hold them, and mixed merges are kept to those
that lock no part in (:mod:`perception.synth.merge`). ``planning.sequence.plan_assembly_sequence`` finds an
order for them.
"""

from __future__ import annotations

import numpy as np

from perception.synth.builder import GENERATOR, Builder
from perception.synth.cabinet import build_cabinet
from perception.synth.chair import build_chair
from perception.synth.merge import merge_parts
from perception.synth.table import build_table
from planning.assembly import Assembly

__all__ = ["generate", "CATEGORIES", "LEVELS", "GENERATOR"]

CATEGORIES = ("chair", "table", "cabinet")
LEVELS = ("3", "mixed")
_BUILDERS = {"chair": build_chair, "table": build_table, "cabinet": build_cabinet}


def generate(category: str, level: str, rng: np.random.Generator, name: str) -> Assembly:
    """One procedurally generated object of ``category`` at granularity ``level``, drawn from ``rng``.

    Deterministic for a given generator state. Raises ``ValueError`` on an unknown category or level, a
    ``rng`` that is not a ``numpy.random.Generator`` or an empty name.
    """
    if category not in CATEGORIES:
        raise ValueError(f"unknown category {category!r}; choose one of {', '.join(CATEGORIES)}")
    if isinstance(level, int) and not isinstance(level, bool):
        level = str(level)
    if level not in LEVELS:
        raise ValueError(f"unknown level {level!r}; choose one of {', '.join(LEVELS)}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(
            f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {type(rng).__name__}"
        )
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty string, got {name!r}")
    builder = Builder()
    variant = _BUILDERS[category](rng, builder)
    metadata = {"generator": GENERATOR, "category": category, "level": "3", "variant": variant}
    level3 = builder.finish(name, metadata)
    if level == "3":
        return level3
    return merge_parts(level3, rng, name)
