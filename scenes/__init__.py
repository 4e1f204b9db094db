"""Bundled scenes and sample objects, found relative to the installed package (never the working directory).

``scenes/<category>/`` is an assembly folder (``assembly.json`` + ``parts/``) of a procedural level-3 object with
its rendered picture ``<category>.png``: the inputs of the README's main command.
"""

from __future__ import annotations

from pathlib import Path

SAMPLE_CATEGORIES = ("chair", "table", "cabinet")


def scenes_root() -> Path:
    """The folder of this package: bundled data lives beside this file."""
    return Path(__file__).resolve().parent


def sample_folder(category: str) -> Path:
    """The bundled sample assembly folder of a category, e.g. ``sample_folder("chair")``."""
    if category not in SAMPLE_CATEGORIES:
        raise ValueError(f"no bundled sample {category!r}; choose one of {', '.join(SAMPLE_CATEGORIES)}")
    return scenes_root() / category


def sample_image(category: str) -> Path:
    """The rendered picture of the bundled sample, e.g. ``scenes/chair/chair.png``."""
    return sample_folder(category) / f"{category}.png"
