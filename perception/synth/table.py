"""Procedural tables: a top on four legs, a pedestal or two trestles.

Working frame: +z up, front towards -y, "left" is -x. Structural choices (recorded in ``variant``):

- ``top``: ``rect``, ``round`` or ``oval`` (trestle tables: ``rect`` or ``oval``);
- ``base``:
  - ``legs``: four legs of ``box``, ``round``, ``tapered`` or ``tapered_round`` section (``legs``), optional
    ``aprons`` under the top, ``stretchers`` ``H``, ``box`` (``staggered`` or not) or ``none``, and an
    optional lower ``shelf`` resting on the side stretchers between the legs;
  - ``pedestal``: one ``round`` or ``box`` column on three or four radiating feet or on a base plate
    (``pedestal_base``: ``feet3``, ``feet4``, ``plate``), optionally under a cleat plate (``cleat``);
  - ``trestle``: two trestles (foot + upright(s) + top bar) with ``uprights`` ``posts`` (two) or ``plank``
    (one), joined by ``stretchers`` ``none``, ``single`` (between the planks), ``double`` (between the
    post pairs) or ``low`` (between the feet, on the floor).
"""

from __future__ import annotations

import math

import numpy as np

from perception.synth.builder import Builder
from perception.synth.legs import SECTIONS, Leg, PlacedLeg
from perception.synth.primitives import box, prism, rotation_z
from perception.synth.sampling import chance, choice, uniform

__all__ = ["build_table"]

_ROUND_TOP_SIDES = 48
_CLEAT_OVERHANG = 0.03  # least overhang of a pedestal's top cleat beyond the column


def _add_top(b: Builder, shape: str, width: float, depth: float, thickness: float, z: float) -> None:
    extents = np.array([width, depth, thickness])
    if shape == "rect":
        vertices, faces = box(extents)
    else:
        vertices, faces = prism(
            0.5 * width, 0.5 * depth, 0.5 * width, 0.5 * depth, thickness, _ROUND_TOP_SIDES
        )
    b.add_mesh("top", vertices, faces, extents, (0.0, 0.0, z), "top")


def _legs_base(rng, b: Builder, shape: str, width: float, depth: float, under: float, variant: dict) -> None:
    section = choice(rng, SECTIONS)
    tapered = section.startswith("tapered")
    leg_top = uniform(rng, 0.018 if tapered else 0.016, 0.04)
    leg_bottom = max(0.011, leg_top * uniform(rng, 0.55, 0.8)) if tapered else leg_top
    leg = Leg(section, leg_top, leg_bottom, under)
    hw = 0.5 * leg_top
    if shape == "rect":
        x_leg = 0.5 * width - uniform(rng, 0.0, 0.12) * width - hw
        y_leg = 0.5 * depth - uniform(rng, 0.0, 0.12) * depth - hw
    else:  # the legs' outer corners on an ellipse inside the top's outline
        s = uniform(rng, 0.72, 0.9) / math.sqrt(2.0)
        x_leg = s * 0.5 * width - hw
        y_leg = s * 0.5 * depth - hw
    placed = {}
    for fb, sy in (("front", -1.0), ("rear", 1.0)):
        for lr, sx in (("left", -1.0), ("right", 1.0)):
            name = f"leg_{fb}_{lr}"
            placed[name] = PlacedLeg(leg, sx * x_leg, sy * y_leg, 0.0)
            b.add_leg(name, placed[name], "base")
            b.join(name, "top")

    aprons = chance(rng, 0.6)
    if aprons:
        ap_h = uniform(rng, 0.025, min(0.07, 0.3 * under))
        ap_t = uniform(rng, max(0.008, 0.4 * leg_top), 0.8 * leg_top)
        lo, hi = under - ap_h, under
        pl = placed["leg_front_left"]
        reach = pl.reach(lo, hi)
        # outward offset: the apron stays within the leg's width, and (round legs) across the leg's axis
        limit = pl.leg.half_width_at(lo) - 0.5 * ap_t
        if leg.round:
            limit = min(limit, 0.5 * ap_t)
        offset = uniform(rng, 0.0, 1.0) * max(0.0, limit)
        z = under - 0.5 * ap_h
        for fb, sy in (("front", -1.0), ("rear", 1.0)):
            name = f"apron_{fb}"
            b.add_box(name, (2 * (x_leg - reach), ap_t, ap_h), (0.0, sy * (y_leg + offset), z), "base")
            b.join(name, f"leg_{fb}_left")
            b.join(name, f"leg_{fb}_right")
            b.join(name, "top")
        for lr, sx in (("left", -1.0), ("right", 1.0)):
            name = f"apron_{lr}"
            b.add_box(name, (ap_t, 2 * (y_leg - reach), ap_h), (sx * (x_leg + offset), 0.0, z), "base")
            b.join(name, f"leg_front_{lr}")
            b.join(name, f"leg_rear_{lr}")
            b.join(name, "top")

    shelf = chance(rng, 0.35)
    stretchers = choice(rng, ("H", "box")) if shelf else choice(rng, ("H", "box", "none"))
    staggered = False
    if stretchers != "none":
        st_w = uniform(rng, 0.55, 0.8) * leg.min_width
        st_h = uniform(rng, 0.01, 0.025)
        z_a = uniform(rng, 0.12, 0.3) * under
        staggered = stretchers == "box" and chance(rng, 0.5)
        # the side stretchers (and the shelf on them) stay well below the aprons (bottom >= 0.7 * under)
        z_b = min(z_a + uniform(rng, 1.3, 3.0) * st_h, 0.45 * under) if staggered else z_a
        pl = placed["leg_front_left"]
        reach_b = pl.reach(z_b - 0.5 * st_h, z_b + 0.5 * st_h)
        for lr, sx in (("left", -1.0), ("right", 1.0)):
            name = f"stretcher_{lr}"
            b.add_box(name, (st_w, 2 * (y_leg - reach_b), st_h), (sx * x_leg, 0.0, z_b), "base")
            b.join(name, f"leg_front_{lr}")
            b.join(name, f"leg_rear_{lr}")
        if stretchers == "H":
            y_mid = uniform(rng, -0.25, 0.25) * (y_leg - reach_b)
            b.add_box("stretcher_middle", (2 * (x_leg - 0.5 * st_w), st_w, st_h), (0.0, y_mid, z_b), "base")
            b.join("stretcher_middle", "stretcher_left")
            b.join("stretcher_middle", "stretcher_right")
        else:
            reach_a = pl.reach(z_a - 0.5 * st_h, z_a + 0.5 * st_h)
            for fb, sy in (("front", -1.0), ("rear", 1.0)):
                name = f"stretcher_{fb}"
                b.add_box(name, (2 * (x_leg - reach_a), st_w, st_h), (0.0, sy * y_leg, z_a), "base")
                b.join(name, f"leg_{fb}_left")
                b.join(name, f"leg_{fb}_right")
        if shelf:
            sh_t = uniform(rng, 0.006, 0.015)
            sh_lo = z_b + 0.5 * st_h
            reach_s = pl.reach(sh_lo, sh_lo + sh_t)
            size = (2 * x_leg + st_w, 2 * (y_leg - reach_s), sh_t)
            b.add_box("shelf", size, (0.0, 0.0, sh_lo + 0.5 * sh_t), "base")
            b.join("shelf", "stretcher_left")
            b.join("shelf", "stretcher_right")
            if stretchers == "H":
                b.join("shelf", "stretcher_middle")
            for name in placed:
                b.join("shelf", name)
    variant.update(
        legs=section,
        aprons=int(aprons),
        stretchers=stretchers,
        staggered=int(staggered),
        shelf=int(shelf),
    )


def _pedestal_base(
    rng, b: Builder, shape: str, width: float, depth: float, under: float, variant: dict
) -> None:
    section = choice(rng, ("round", "box"), (0.65, 0.35))
    col_w = uniform(rng, 0.035, 0.065)
    r = 0.5 * col_w
    small = min(width, depth)
    kind = choice(rng, ("feet", "plate"))
    n_feet = 0
    if kind == "feet":
        n_feet = 4 if section == "box" else int(choice(rng, (3, 4)))
    plate_t = uniform(rng, 0.01, 0.025) if kind == "plate" else 0.0
    cleat = chance(rng, 0.5)
    cleat_t = uniform(rng, 0.01, 0.02) if cleat else 0.0
    column = Leg(section, col_w, col_w, under - cleat_t - plate_t)
    b.add_leg("column", PlacedLeg(column, 0.0, 0.0, plate_t), "base")
    if cleat:
        # overhanging the column by 3 cm or more all round: a fingertip fits under its edge
        least = col_w + 2 * _CLEAT_OVERHANG
        size = uniform(rng, max(0.3 * small, least), max(0.6 * small, least))
        extents = np.array([size, size, cleat_t])
        if shape == "rect":
            vertices, faces = box(extents)
        else:
            vertices, faces = prism(0.5 * size, 0.5 * size, 0.5 * size, 0.5 * size, cleat_t, _ROUND_TOP_SIDES)
        b.add_mesh("top_cleat", vertices, faces, extents, (0.0, 0.0, under - 0.5 * cleat_t), "base")
        b.join("column", "top_cleat")
        b.join("top_cleat", "top")
    else:
        b.join("column", "top")
    if kind == "plate":
        plate_shape = choice(rng, ("round", "square"))
        size = uniform(rng, max(0.45 * small, 0.18), 0.8 * small)
        extents = np.array([size, size, plate_t])
        if plate_shape == "square":
            vertices, faces = box(extents)
        else:
            vertices, faces = prism(0.5 * size, 0.5 * size, 0.5 * size, 0.5 * size, plate_t, _ROUND_TOP_SIDES)
        b.add_mesh("base_plate", vertices, faces, extents, (0.0, 0.0, 0.5 * plate_t), "base")
        b.join("column", "base_plate")
    else:
        foot_len = max(0.06, uniform(rng, 0.35, 0.48) * small - r)
        foot_w = uniform(rng, 0.015, min(0.04, 1.6 * r))
        # no lower than wide: held from above across its width (its fixture pad, a box, spreads beside a turned foot)
        foot_h = uniform(rng, max(0.02, foot_w), max(0.04, foot_w + 0.01))
        start = 0.0 if n_feet == 4 and (section == "box" or chance(rng, 0.5)) else 0.25 * math.pi
        if n_feet == 3:
            start = choice(rng, (0.5 * math.pi, -0.5 * math.pi))
        vertices, faces = box((foot_len, foot_w, foot_h))
        for k in range(n_feet):
            angle = start + 2.0 * math.pi * k / n_feet
            rot = rotation_z(angle)
            centre = rot @ np.array([r + 0.5 * foot_len, 0.0, 0.5 * foot_h])
            name = f"foot_{k + 1}"
            b.add_mesh(name, vertices, faces, (foot_len, foot_w, foot_h), centre, "base", rotation=rot)
            b.join(name, "column")
    variant.update(
        legs="none",
        column=section,
        pedestal_base=f"feet{n_feet}" if kind == "feet" else "plate",
        cleat=int(cleat),
        stretchers="none",
    )


def _trestle_base(
    rng, b: Builder, shape: str, width: float, depth: float, under: float, variant: dict
) -> None:
    uprights = choice(rng, ("posts", "plank"))
    foot_w, foot_h = uniform(rng, 0.02, 0.045), uniform(rng, 0.015, 0.035)
    bar_w, bar_h = uniform(rng, 0.02, 0.045), uniform(rng, 0.015, 0.035)
    foot_len = depth * uniform(rng, 0.75, 1.0)
    if shape == "rect":
        x_tr = 0.5 * width - uniform(rng, 0.06, 0.16) * width - 0.5 * max(foot_w, bar_w)
        bar_len = depth * uniform(rng, 0.6, 0.95)
    else:  # the bar's outer corners stay inside the oval
        x_tr = 0.5 * width * uniform(rng, 0.55, 0.75) - 0.5 * bar_w
        reach = (x_tr + 0.5 * bar_w) / (0.5 * width)
        bar_len = min(depth * uniform(rng, 0.6, 0.95), 0.95 * depth * math.sqrt(1.0 - reach * reach))
    up_h = under - bar_h - foot_h
    shortest = min(foot_len, bar_len)
    if uprights == "posts":
        post_w = uniform(rng, 0.015, min(0.03, foot_w, bar_w))
        y_post = uniform(rng, 0.3, 1.0) * (0.5 * shortest - 0.5 * post_w - 0.005)
        post = Leg("box", post_w, post_w, up_h)
        stretchers = choice(rng, ("none", "double", "low"))
    else:
        plank_t = uniform(rng, 0.01, min(0.025, foot_w, bar_w))
        plank_w = uniform(rng, 0.35, 0.85) * shortest
        stretchers = choice(rng, ("none", "single", "low"))
    for lr, sx in (("left", -1.0), ("right", 1.0)):
        module = f"trestle_{lr}"
        foot, bar = f"trestle_{lr}_foot", f"trestle_{lr}_bar"
        b.add_box(foot, (foot_w, foot_len, foot_h), (sx * x_tr, 0.0, 0.5 * foot_h), module)
        b.add_box(bar, (bar_w, bar_len, bar_h), (sx * x_tr, 0.0, under - 0.5 * bar_h), module)
        b.join(bar, "top")
        if uprights == "posts":
            for fb, sy in (("front", -1.0), ("rear", 1.0)):
                name = f"trestle_{lr}_post_{fb}"
                b.add_leg(name, PlacedLeg(post, sx * x_tr, sy * y_post, foot_h), module)
                b.join(name, foot)
                b.join(name, bar)
        else:
            name = f"trestle_{lr}_plank"
            b.add_box(name, (plank_t, plank_w, up_h), (sx * x_tr, 0.0, foot_h + 0.5 * up_h), module)
            b.join(name, foot)
            b.join(name, bar)
    st_h = uniform(rng, 0.015, 0.04)
    z = foot_h + uniform(rng, 0.25, 0.7) * up_h
    if stretchers == "single":
        st_w = uniform(rng, 0.015, min(0.04, plank_w))
        b.add_box("stretcher", (2 * (x_tr - 0.5 * plank_t), st_w, st_h), (0.0, 0.0, z), "base")
        b.join("stretcher", "trestle_left_plank")
        b.join("stretcher", "trestle_right_plank")
    elif stretchers == "double":
        st_w = uniform(rng, 0.5, 0.9) * post_w
        for fb, sy in (("front", -1.0), ("rear", 1.0)):
            name = f"stretcher_{fb}"
            b.add_box(name, (2 * (x_tr - 0.5 * post_w), st_w, st_h), (0.0, sy * y_post, z), "base")
            b.join(name, f"trestle_left_post_{fb}")
            b.join(name, f"trestle_right_post_{fb}")
    elif stretchers == "low":
        low_h = uniform(rng, 0.6, 1.0) * foot_h
        st_w = uniform(rng, 0.015, 0.04)
        b.add_box("stretcher_low", (2 * (x_tr - 0.5 * foot_w), st_w, low_h), (0.0, 0.0, 0.5 * low_h), "base")
        b.join("stretcher_low", "trestle_left_foot")
        b.join("stretcher_low", "trestle_right_foot")
    variant.update(legs="none", uprights=uprights, stretchers=stretchers)


def build_table(rng: np.random.Generator, b: Builder) -> dict:
    """Add a table's parts and joints to ``b``; return the variant record."""
    base = choice(rng, ("legs", "pedestal", "trestle"))
    shape = choice(rng, ("rect", "oval") if base == "trestle" else ("rect", "round", "oval"))
    height = uniform(rng, 0.25, 0.6)
    top_t = uniform(rng, 0.012, 0.035)
    if shape == "round":
        width = depth = uniform(rng, 0.3, 0.6)
    elif shape == "oval":
        width = uniform(rng, 0.35, 0.6)
        depth = width * uniform(rng, 0.55, 0.85)
    elif base == "trestle":
        width = uniform(rng, 0.35, 0.6)
        depth = uniform(rng, 0.25, min(0.5, width))
    else:
        width, depth = uniform(rng, 0.3, 0.6), uniform(rng, 0.25, 0.6)
    under = height - top_t
    _add_top(b, shape, width, depth, top_t, height - 0.5 * top_t)
    variant: dict = {"top": shape, "base": base}
    {"legs": _legs_base, "pedestal": _pedestal_base, "trestle": _trestle_base}[base](
        rng, b, shape, width, depth, under, variant
    )
    # designed assembly order, from the floor up (the mixed level keeps merges consistent with it)
    names = [p.name for p in b.parts]

    def named(*prefixes: str) -> list[str]:
        return [n for n in names if n.startswith(prefixes)]

    b.set_stages(
        [
            named("leg_", "base_plate", "foot_", "trestle_left_foot", "trestle_right_foot"),
            named("stretcher_low", "stretcher_left", "stretcher_right", "stretcher_middle"),
            named("column", "trestle_left_p", "trestle_right_p"),  # columns, posts, planks
            named("shelf"),  # on the side stretchers, before the front and rear ones at its edges
            named("stretcher_front", "stretcher_rear") + (["stretcher"] if b.has("stretcher") else []),
            named("apron_", "top_cleat", "trestle_left_bar", "trestle_right_bar"),
            ["top"],
        ]
    )
    variant.update(
        height=round(height, 4), width=round(width, 4), depth=round(depth, 4), top_thickness=round(top_t, 4)
    )
    return variant
