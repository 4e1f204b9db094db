"""Networks of the perception model (after Li et al., "Learning 3D Part Assembly from a Single Image", 2020).

Every network reads a padded batch (:func:`perception.data.collate`) and returns a dictionary with ``poses``
(a list of (quat (B, P, 4) w first and unit, trans (B, P, 3) normalised units) per supervised phase) and the
final ``quat``/``trans``; outputs in padded part slots are meaningless and never affect valid ones.
"""

from __future__ import annotations

from torch import nn

from perception.config import ModelConfig
from perception.model.assembler import AssemblyNet
from perception.model.baselines import BGRU, BGlobal, BInsOneHot

MODELS = {"ours": AssemblyNet, "b_gru": BGRU, "b_insonehot": BInsOneHot, "b_global": BGlobal}


def build_model(config: ModelConfig, kind: str = "ours") -> nn.Module:
    """A freshly initialised network of the given kind (``ours``, ``b_gru``, ``b_insonehot``, ``b_global``)."""
    if kind not in MODELS:
        raise ValueError(f"model must be one of {sorted(MODELS)}, got {kind!r}")
    # Not channels-last: faster on CPU, but torch 2.13's oneDNN convolution backward corrupts the heap with it for
    # layers of 4 or 8 channels and odd batch sizes (seen as segfaults); the default layout is safe.
    return MODELS[kind](config)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


__all__ = ["MODELS", "AssemblyNet", "BGRU", "BGlobal", "BInsOneHot", "build_model", "count_parameters"]
