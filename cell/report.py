"""What ``python -m cell.run`` writes about a run: ``report.json``, the summary table and ``overview.png``.

``report.json`` (all poses ``{"position": [x, y, z], "quat_wxyz": [w, x, y, z]}``, metres)::

    {"success": bool, "exit_code": int, "failure": null | {"stage", "part", "message"},
     "inputs": {"image", "parts", "poses", "scene", "seed", "units", "density_kg_m3", "masses",
                "notes" (what the input readers changed or skipped: a picture cropped or padded to square, material
                and texture files beside the meshes)},
     "stages": {"perception": seconds, ...},
     "time_budget_s": float, "planning_cpu_s": {"standing": seconds, "upside_down": seconds (each build planned)},
     "planning_notes": [{"upside_down", "note"}, ...],
     "trajectory_duration_s": float, "world_from_assembly": pose, "jig_turn_deg": float, "jig_slide_m": float,
     "upside_down": bool, "world_from_build": pose (only when upside down),
     "parts": [{"name", "order", "target_assembly_from_part", "target_world_from_part",
                "repair": {"translation_m", "rotation_deg"}, "insertion_direction" (the frame built on the jig,
                +z up), "fastened_to",
                "grasp": {"part_from_tcp", "width_m", "opening_m", "pick_opening_m"}, "kitting_world_from_part",
                "carry_check" (how its carry to the target was checked: cell.task.CARRY_CHECKS),
                "kitting_wedged" (it lies wedged in the kit: no pose rests otherwise),
                "kitting_support" (what it lies on in the kit: "pedestal", "posts", or the board's part name),
                "final_world_from_part", "position_error_m", "rotation_error_deg", "within_tolerance"}, ...],
     "simulation": {...: what cell.simulate measured (contacts, limit violations, ...)}}

``overview.png``: the input image, the target assembly (predicted or given) and the simulated result, rendered
from the same viewpoint with the same colours, side by side.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from planning.assembly import Assembly, AssemblyPart
from planning.pose import Pose

OVERVIEW_PANEL_PX = 320
OVERVIEW_VIEW = (235.0, 25.0)  # azimuth, elevation (degrees): the bundled samples' viewpoint


def pose_json(pose: Pose | None) -> dict | None:
    return None if pose is None else pose.to_dict()


def write_json(path: Path, document: dict) -> None:
    path.write_text(json.dumps(document, indent=1, default=_plain, allow_nan=False) + "\n", encoding="utf-8")


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Pose):
        return value.to_dict()
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def summary_table(report: dict) -> str:
    """The parts in assembly order with their final errors, then the stage times and the verdict."""
    rows = [("#", "part", "insert", "grasp mm", "pos err mm", "rot err deg", "ok")]
    parts = sorted(report["parts"], key=lambda p: (p["order"] is None, p["order"] or 0))
    for part in parts:
        direction = part.get("insertion_direction")
        grasp = part.get("grasp")
        rows.append((
            "-" if part["order"] is None else str(part["order"]),
            part["name"],
            _direction_words(direction),
            "-" if not grasp else f"{grasp['width_m'] * 1000:.0f}",
            _number(part.get("position_error_m"), 1000.0, 1),
            _number(part.get("rotation_error_deg"), 1.0, 1),
            {True: "yes", False: "NO", None: "-"}[part.get("within_tolerance")],
        ))
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    stages = ", ".join(f"{name} {seconds:.1f} s" for name, seconds in report["stages"].items())
    lines.append("")
    lines.append(f"stages: {stages}")
    if report.get("trajectory_duration_s"):
        built = (", built upside down on the jig (insertions in its frame): turn the object over after"
                 if report.get("upside_down") else "")
        lines.append(f"robot program: {report['trajectory_duration_s']:.1f} s{built}")
    return "\n".join(lines)


def _number(value, scale: float, digits: int) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value * scale:.{digits}f}"


def _direction_words(direction) -> str:
    if direction is None:
        return "-"
    d = np.asarray(direction, dtype=np.float64)
    k = int(np.argmax(np.abs(d)))
    if abs(d[k]) > 0.999:
        return ("+" if d[k] > 0 else "-") + "xyz"[k]
    return "[" + ", ".join(f"{v:.2f}" for v in d) + "]"


def wrapped_caption(caption: str, text_width_px: Callable[[str], float], width_px: float) -> str:
    """``caption`` broken into lines (joined by newlines) at spaces so that no line is wider than ``width_px``
    as measured by ``text_width_px(text)``; a single word wider than that keeps a line of its own."""
    lines: list[str] = []
    for word in caption.split():
        if lines and text_width_px(f"{lines[-1]} {word}") <= width_px:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return "\n".join(lines)


def overview_image(image_rgb: np.ndarray | None, target: Assembly, final: Assembly | None,
                   seed: int = 0, target_caption: str = "target assembly",
                   result_caption: str = "simulated result",
                   agreement: tuple[np.ndarray, str] | None = None) -> np.ndarray:
    """Input image | its agreement with the target (``agreement``: a picture and its caption, for a run from a
    picture) | target assembly | simulated result (each ``OVERVIEW_PANEL_PX`` square, captioned)."""
    from PIL import Image, ImageDraw, ImageFont

    from cell.render import Appearance, AssemblyRenderer, CameraSpec, fitted_distance_m

    bounds = target.bounds()
    camera = CameraSpec(azimuth_deg=OVERVIEW_VIEW[0], elevation_deg=OVERVIEW_VIEW[1],
                        distance_m=fitted_distance_m(bounds), target_m=tuple(0.5 * (bounds[0] + bounds[1])),
                        width_px=OVERVIEW_PANEL_PX, height_px=OVERVIEW_PANEL_PX)
    appearance = Appearance.sample(np.random.default_rng(seed), len(target.parts))
    appearance = Appearance(appearance.part_rgb, np.array([[0.93, 0.93, 0.95], [0.78, 0.8, 0.84]]),
                            np.array([0.4, -0.3, 0.87]), np.ones(3), 0.5, 0.6, 0.1, False)
    panels, captions = [], []
    if image_rgb is not None:
        panels.append(np.asarray(Image.fromarray(image_rgb).resize((OVERVIEW_PANEL_PX, OVERVIEW_PANEL_PX))))
        captions.append("input image")
    if agreement is not None:
        panels.append(np.asarray(Image.fromarray(agreement[0]).resize((OVERVIEW_PANEL_PX, OVERVIEW_PANEL_PX),
                                                                      Image.NEAREST)))
        captions.append(agreement[1])
    for assembly, caption in ((target, target_caption), (final, result_caption)):
        if assembly is None:
            continue
        with AssemblyRenderer(assembly) as renderer:
            panels.append(renderer.render(camera, appearance).rgb)
        captions.append(caption)
    picture = Image.fromarray(np.concatenate(panels, axis=1))
    draw = ImageDraw.Draw(picture)
    try:
        font = ImageFont.load_default(size=15)
    except TypeError:  # Pillow < 10.1: the small bitmap font
        font = ImageFont.load_default()
    for k, caption in enumerate(captions):
        # the text starts 6 px into its panel and its white box reaches 4 px beyond it on each side
        caption = wrapped_caption(caption, lambda text: draw.textlength(text, font=font), OVERVIEW_PANEL_PX - 16)
        left, top, right, bottom = draw.textbbox((k * OVERVIEW_PANEL_PX + 6, 4), caption, font=font)
        draw.rectangle([left - 4, top - 3, right + 4, bottom + 3], fill=(255, 255, 255))
        draw.text((k * OVERVIEW_PANEL_PX + 6, 4), caption, fill=(0, 0, 0), font=font)
    return np.asarray(picture)


def assembly_with_poses(assembly: Assembly, poses: dict[str, Pose], name_suffix: str = "") -> Assembly:
    """``assembly`` with each named part moved to ``poses[name]`` (assembly frame); other parts left out."""
    parts = [AssemblyPart(p.name, p.mesh, poses[p.name], p.mesh_file) for p in assembly.parts if p.name in poses]
    return Assembly(assembly.name + name_suffix, parts, dict(assembly.metadata))
