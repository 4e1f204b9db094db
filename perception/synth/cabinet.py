"""Procedural cabinets: a carcass of boards with shelves, doors and drawers.

Working frame: +z up, the front (doors, drawer fronts) towards -y, "left" is -x. The carcass is two sides,
a top, a bottom and a back panel; inside, optional shelves; on the front, overlay doors and drawer fronts.
Each drawer is five boards (front, two sides, back, bottom): its box slides between the carcass sides
(touching them), its front's back face rests against the carcass's front edges. Structural choices
(recorded in ``variant``):

- ``base``: ``none`` (the sides stand on the floor), ``plinth`` (two or four kick boards,
  ``plinth_boards``) or ``feet`` (four, ``box`` or ``round``, under the sides);
- ``top``: ``overlay`` (on the sides, with overhang) or ``inset`` (between the sides);
- ``back``: ``inset`` (between the sides) or ``overlay`` (on the sides' rear edges);
- ``bottom``: ``flush`` with the sides' lower ends or ``raised`` (only without a base);
- ``drawers`` 0-3 stacked at the ``drawer_position`` ``top`` or ``bottom`` of the interior, ``full`` when
  they fill it; a ``divider`` board separates them from the rest, which holds ``shelves`` (0-4) behind
  ``doors`` (0-2).

The part count stays within 20: drawers are drawn first, then the base, divider, doors and shelves within
what is left.
"""

from __future__ import annotations

import numpy as np

from perception.synth.builder import Builder
from perception.synth.legs import Leg, PlacedLeg
from perception.synth.sampling import chance, choice, integer, uniform

__all__ = ["build_cabinet"]

MAX_PARTS = 20
_MIN_SLOT = 0.055  # interior height of one drawer slot
_MIN_REGION = 0.08  # interior height of a door / shelf region next to drawers


def build_cabinet(rng: np.random.Generator, b: Builder) -> dict:
    """Add a cabinet's parts and joints to ``b``; return the variant record."""
    # --- structure and part budget ------------------------------------------------------------------------
    n_drawers = int(choice(rng, (0, 1, 2, 3), (0.3, 0.25, 0.25, 0.2)))
    budget = MAX_PARTS - 5 - 5 * n_drawers
    base_options = [("none", 0)] + [
        (k, n) for k, n in (("plinth", 2), ("plinth", 4), ("feet", 4)) if n <= budget
    ]
    base, base_parts = choice(rng, base_options, [2.0] + [1.0] * (len(base_options) - 1))
    budget -= base_parts
    region = n_drawers == 0 or (budget >= 1 and chance(rng, 0.65))  # a door/shelf region besides the drawers
    divider = n_drawers > 0 and region
    budget -= int(divider)
    n_doors = 0
    if region:
        allowed = min(2, budget) + 1
        n_doors = int(choice(rng, (0, 1, 2)[:allowed], (0.3, 0.35, 0.35)[:allowed]))
    budget -= n_doors
    n_shelves_wanted = integer(rng, 0, min(4, budget)) if region else 0
    top = choice(rng, ("overlay", "inset"))
    back = choice(rng, ("inset", "overlay"))

    # --- dimensions ---------------------------------------------------------------------------------------
    t = uniform(rng, 0.01, 0.02)  # carcass boards
    t_back = uniform(rng, 0.006, 0.01)
    overhang_side = uniform(rng, 0.0, 0.02) if top == "overlay" else 0.0
    overhang_front = uniform(rng, 0.0, 0.02) if top == "overlay" else 0.0
    width = uniform(rng, 0.25, 0.6 - 2 * overhang_side)
    depth = uniform(rng, 0.2, 0.45)
    base_h = uniform(rng, 0.02, 0.06) if base != "none" else 0.0
    min_interior = n_drawers * _MIN_SLOT + (_MIN_REGION + t if divider else 0.0) + (0.0 if n_drawers else 0.1)
    fixed = base_h + 2 * t  # bottom board and top board
    raise_h = uniform(rng, 0.01, 0.05) if base == "none" and chance(rng, 0.35) else 0.0
    height = uniform(rng, max(0.25, fixed + raise_h + min_interior + 0.01), 0.6)

    z0 = base_h  # sides' lower ends
    side_h = height - base_h - (t if top == "overlay" else 0.0)
    z_side_top = z0 + side_h
    inner_w = width - 2 * t
    y_front = -0.5 * depth
    y_back_limit = 0.5 * depth - t_back if back == "inset" else 0.5 * depth  # rear edge of boards inside
    inner_d = y_back_limit - y_front
    bottom_lo = z0 + raise_h
    zi0 = bottom_lo + t  # interior bottom
    zi1 = z_side_top - t if top == "inset" else z_side_top  # interior top

    # --- carcass ------------------------------------------------------------------------------------------
    side_size = (t, depth, side_h)
    for lr, sx in (("left", -1.0), ("right", 1.0)):
        b.add_box(f"side_{lr}", side_size, (sx * (0.5 * width - 0.5 * t), 0.0, z0 + 0.5 * side_h), "carcass")
    board_size = (inner_w, inner_d, t)
    y_board = 0.5 * (y_front + y_back_limit)
    b.add_box("bottom", board_size, (0.0, y_board, bottom_lo + 0.5 * t), "carcass")
    if top == "inset":
        b.add_box("top", board_size, (0.0, y_board, z_side_top - 0.5 * t), "carcass")
    else:
        rear = (0.5 * depth + (t_back if back == "overlay" else 0.0)) + uniform(rng, 0.0, 0.01)
        front = y_front - overhang_front
        size = (width + 2 * overhang_side, rear - front, t)
        b.add_box("top", size, (0.0, 0.5 * (front + rear), z_side_top + 0.5 * t), "carcass")
    if back == "inset":
        b.add_box(
            "back", (inner_w, t_back, side_h), (0.0, 0.5 * depth - 0.5 * t_back, z0 + 0.5 * side_h), "carcass"
        )
    else:
        b.add_box(
            "back", (width, t_back, side_h), (0.0, 0.5 * depth + 0.5 * t_back, z0 + 0.5 * side_h), "carcass"
        )
    for board in ("top", "bottom", "back"):
        b.join(board, "side_left")
        b.join(board, "side_right")
    b.join("top", "back")
    b.join("bottom", "back")

    # --- interior layout ----------------------------------------------------------------------------------
    interior = zi1 - zi0
    drawer_position = "none"
    drawer_lo = drawer_hi = region_lo = region_hi = 0.0
    if n_drawers:
        if divider:
            drawer_position = choice(rng, ("top", "bottom"))
            slot_max = (interior - t - _MIN_REGION) / n_drawers
            slot = uniform(rng, _MIN_SLOT, min(0.12, slot_max))
            band = n_drawers * slot
            if drawer_position == "bottom":
                drawer_lo, drawer_hi = zi0, zi0 + band
                div_lo = drawer_hi
                region_lo, region_hi = div_lo + t, zi1
            else:
                drawer_lo, drawer_hi = zi1 - band, zi1
                div_lo = drawer_lo - t
                region_lo, region_hi = zi0, div_lo
            b.add_box("divider", board_size, (0.0, y_board, div_lo + 0.5 * t), "shelves")
            b.join("divider", "side_left")
            b.join("divider", "side_right")
            b.join("divider", "back")
            div_mid = div_lo + 0.5 * t
        else:
            drawer_position = "full"
            drawer_lo, drawer_hi = zi0, zi1
    else:
        region_lo, region_hi = zi0, zi1

    # --- front faces: overlay fronts cover the carcass from its lower edge to the sides' top -------------
    front_lo, front_hi = bottom_lo, z_side_top
    gap = uniform(rng, 0.002, 0.004)
    edge = uniform(rng, 0.0, 0.4) * t  # how far the fronts stop short of the outer side faces
    front_t = uniform(rng, 0.01, 0.018)
    if n_drawers and divider:
        drawer_front = (front_lo, div_mid) if drawer_position == "bottom" else (div_mid, front_hi)
        region_front = (div_mid, front_hi) if drawer_position == "bottom" else (front_lo, div_mid)
    else:
        drawer_front = region_front = (front_lo, front_hi)

    # --- shelves and doors --------------------------------------------------------------------------------
    n_shelves = 0
    if region:
        shelf_t = uniform(rng, 0.008, t)
        span = region_hi - region_lo
        n_shelves = min(n_shelves_wanted, int((span - 0.04) // (0.04 + shelf_t)))
        setback = uniform(rng, 0.0, 0.03)
        step = span / (n_shelves + 1)
        for i in range(n_shelves):
            z = region_lo + (i + 1) * step + uniform(rng, -0.2, 0.2) * (step - shelf_t - 0.04)
            name = f"shelf_{i + 1}"
            size = (inner_w, inner_d - setback, shelf_t)
            b.add_box(name, size, (0.0, y_board + 0.5 * setback, z), "shelves")
            b.join(name, "side_left")
            b.join(name, "side_right")
            b.join(name, "back")
        door_h = region_front[1] - region_front[0] - gap
        door_z = 0.5 * (region_front[0] + region_front[1])
        y_door = y_front - 0.5 * front_t
        if n_doors == 1:
            b.add_box("door", (width - 2 * edge, front_t, door_h), (0.0, y_door, door_z), "doors")
            b.join("door", "side_left")
            b.join("door", "side_right")
        elif n_doors == 2:
            door_w = 0.5 * width - edge - 0.5 * gap
            for lr, sx in (("left", -1.0), ("right", 1.0)):
                name = f"door_{lr}"
                b.add_box(
                    name,
                    (door_w, front_t, door_h),
                    (sx * (0.5 * gap + 0.5 * door_w), y_door, door_z),
                    "doors",
                )
                b.join(name, f"side_{lr}")

    # --- drawers ------------------------------------------------------------------------------------------
    if n_drawers:
        slot = (drawer_hi - drawer_lo) / n_drawers
        box_h = slot - uniform(rng, 0.008, min(0.02, slot - 0.035))
        box_d = inner_d * uniform(rng, 0.6, 0.95)
        d_t = uniform(rng, 0.006, 0.012)
        d_bottom_t = uniform(rng, 0.006, 0.01)
        pitch = (drawer_front[1] - drawer_front[0]) / n_drawers
        front_h = pitch - gap
        y_box = y_front + 0.5 * box_d
        for k in range(n_drawers):
            # drawer 1 is the top one
            i = n_drawers - 1 - k
            lo = drawer_lo + i * slot
            name = f"drawer_{k + 1}"
            module = name
            f_lo = drawer_front[0] + i * pitch + 0.5 * gap
            b.add_box(f"{name}_front", (width - 2 * edge, front_t, front_h),
                      (0.0, y_front - 0.5 * front_t, f_lo + 0.5 * front_h), module)  # fmt: skip
            for lr, sx in (("left", -1.0), ("right", 1.0)):
                b.add_box(f"{name}_side_{lr}", (d_t, box_d, box_h),
                          (sx * (0.5 * inner_w - 0.5 * d_t), y_box, lo + 0.5 * box_h), module)  # fmt: skip
            inner = inner_w - 2 * d_t
            b.add_box(
                f"{name}_bottom", (inner, box_d, d_bottom_t), (0.0, y_box, lo + 0.5 * d_bottom_t), module
            )
            back_h = box_h - d_bottom_t
            b.add_box(f"{name}_back", (inner, d_t, back_h),
                      (0.0, y_front + box_d - 0.5 * d_t, lo + d_bottom_t + 0.5 * back_h), module)  # fmt: skip
            overlap = min(f_lo + front_h, lo + box_h) - max(f_lo, lo)
            if overlap < 0.01:
                raise RuntimeError(f"drawer {k + 1}: front and box overlap only {overlap:.4f} m in height")
            for lr in ("left", "right"):
                b.join(f"{name}_side_{lr}", f"{name}_front")
                b.join(f"{name}_side_{lr}", f"{name}_bottom")
                b.join(f"{name}_side_{lr}", f"{name}_back")
                b.join(f"{name}_side_{lr}", f"side_{lr}")
                b.join(f"{name}_front", f"side_{lr}")
            if f_lo < lo + d_bottom_t:  # the bottom's front edge reaches the front's back face
                b.join(f"{name}_bottom", f"{name}_front")
            b.join(f"{name}_bottom", f"{name}_back")
            if i == 0:  # the lowest drawer rests on the bottom board or the divider
                b.join(f"{name}_bottom", "bottom" if drawer_position in ("bottom", "full") else "divider")

    # --- base ---------------------------------------------------------------------------------------------
    if base == "plinth":
        kick_t = uniform(rng, 0.01, 0.02)
        side_in = uniform(rng, 0.0, 0.5) * t
        recess_front = uniform(rng, 0.0, 0.04)
        recess_rear = uniform(rng, 0.0, 0.02)
        y_kf = y_front + recess_front + 0.5 * kick_t
        y_kr = 0.5 * depth - recess_rear - 0.5 * kick_t
        size = (width - 2 * side_in, kick_t, base_h)
        for fb, y in (("front", y_kf), ("rear", y_kr)):
            name = f"plinth_{fb}"
            b.add_box(name, size, (0.0, y, 0.5 * base_h), "base")
            b.join(name, "side_left")
            b.join(name, "side_right")
        if base_parts == 4:
            length = (y_kr - 0.5 * kick_t) - (y_kf + 0.5 * kick_t)
            for lr, sx in (("left", -1.0), ("right", 1.0)):
                name = f"plinth_{lr}"
                x = sx * (0.5 * width - side_in - 0.5 * kick_t)
                b.add_box(name, (kick_t, length, base_h), (x, 0.5 * (y_kf + y_kr), 0.5 * base_h), "base")
                b.join(name, "plinth_front")
                b.join(name, "plinth_rear")
                b.join(name, f"side_{lr}")
    elif base == "feet":
        foot_section = choice(rng, ("box", "round"))
        foot_w = uniform(rng, 0.02, 0.04)
        inset = uniform(rng, 0.0, 0.4) * t
        foot = Leg(foot_section, foot_w, foot_w, base_h)
        x = 0.5 * width - inset - 0.5 * foot_w
        y = 0.5 * depth - inset - 0.5 * foot_w
        for fb, sy in (("front", -1.0), ("rear", 1.0)):
            for lr, sx in (("left", -1.0), ("right", 1.0)):
                name = f"foot_{fb}_{lr}"
                b.add_leg(name, PlacedLeg(foot, sx * x, sy * y, 0.0), "base")
                b.join(name, f"side_{lr}")

    return {
        "base": base,
        "plinth_boards": base_parts if base == "plinth" else 0,
        "top": top,
        "back": back,
        "bottom": "raised" if raise_h > 0.0 else "flush",
        "shelves": n_shelves,
        "doors": n_doors,
        "drawers": n_drawers,
        "drawer_position": drawer_position,
        "height": round(height, 4),
        "width": round(width, 4),
        "depth": round(depth, 4),
    }
