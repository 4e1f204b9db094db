"""Regenerate the bundled sample objects: ``python -m scenes.make_samples``.

Each sample is a procedural level-3 object (``perception.synth``, object ``index`` of seed 0) written as an
assembly folder ``scenes/<category>/`` with its picture ``scenes/<category>/<category>.png``, rendered from a
fixed three-quarter view with seeded colours and lighting.
"""

from __future__ import annotations

import shutil

import numpy as np
from PIL import Image

from cell.render import Appearance, AssemblyRenderer, CameraSpec, fitted_distance_m
from perception.synth import generate
from planning.assembly import write_assembly
from scenes import SAMPLE_CATEGORIES, sample_folder, sample_image

# (synth seed, object index): chosen for clear pictures and a moderate part count
SAMPLE_OBJECTS = {"chair": (0, 6), "table": (0, 9), "cabinet": (0, 19)}
VIEW_AZIMUTH_DEG = 235.0  # the generator puts backs at +y: a front three-quarter view
VIEW_ELEVATION_DEG = 25.0


def make_sample(category: str) -> None:
    seed, index = SAMPLE_OBJECTS[category]
    assembly = generate(category, "3", np.random.default_rng([seed, index]), f"sample_{category}")
    folder = sample_folder(category)
    if folder.exists():
        shutil.rmtree(folder)
    write_assembly(assembly, folder)
    bounds = assembly.bounds()
    camera = CameraSpec(
        azimuth_deg=VIEW_AZIMUTH_DEG,
        elevation_deg=VIEW_ELEVATION_DEG,
        distance_m=fitted_distance_m(bounds),
        target_m=tuple(float(v) for v in 0.5 * (bounds[0] + bounds[1])),
    )
    with AssemblyRenderer(assembly) as renderer:
        view = renderer.render(camera, Appearance.sample(np.random.default_rng(index), len(assembly.parts)))
    Image.fromarray(view.rgb).save(sample_image(category))
    print(f"{category}: {len(assembly.parts)} parts -> {folder.name}/")


def main() -> None:
    for category in SAMPLE_CATEGORIES:
        make_sample(category)


if __name__ == "__main__":
    main()
