"""Procedural cabinets: a carcass of boards with shelves, doors and drawers, with room for a robot hand.

Working frame: +z up, the front (doors, drawer fronts) towards -y, "left" is -x. The carcass is two sides, a
bottom, a top and a back panel; inside, optional shelves; on the front, overlay doors and drawer fronts. Each
drawer is five boards (front, two sides, back, bottom). Structural choices (recorded in ``variant``):

- ``base``: ``none`` (the sides stand on the floor, the ``bottom`` between them ``flush`` with their lower
  ends or ``raised``), ``plinth`` (two or four kick boards, ``plinth_boards``) or ``feet`` (four, ``box`` or
  ``round``, under the sides);
- ``top``: ``overlay`` (on the sides, overhanging them) or ``inset`` (between the sides);
- ``back``: ``inset`` (between the sides, set in from their rear edges) or ``overlay`` (on the sides' rear
  edges, only on open cabinets: no doors, no drawers);
- ``drawers`` 0-2 stacked at the ``drawer_position`` ``top`` or ``bottom`` of the interior, ``full`` when
  they fill it; a ``divider`` board separates them from the rest, which holds ``shelves`` (0-4) behind
  ``doors`` (0-2).

Every part leaves room for a parallel-jaw hand (a Franka Panda: 8 cm opening; fingers 2 cm wide, 1.4 cm thick at
the tip and 2.5 cm thick 3 cm behind the pads; a palm 3.9 cm behind the pads, 21 cm long along the closing
axis) to hold it at its place among the parts placed before it, as real furniture leaves room for hands and
hardware. A board is held across its thickness at an edge, the palm then spanning about 10 cm to both sides of
the board; so:

- the plinth's front kick board is recessed (a toe kick): a finger fits under the bottom's front edge;
- the back panel is set in from the sides' rear edges, so a carcass side can be held at its rear edge when
  fronts cover its front edge (a tall side's top edge is too far from its middle to be among a hand's choices);
- drawers are narrower than the opening by :data:`DRAWER_SIDE_GAP_M` or more each side (room for a finger
  beside each drawer side, where runners would go) and no deeper than they are wide; their bottoms sit raised
  in the sides (room for a finger under the bottom's front edge) and their backs stop at least
  :data:`DRAWER_BACK_ROOM_M` short of the carcass back (the palm over a drawer back reaches that far back); the
  lowest drawer stands on the carcass bottom or the divider, each drawer above it on two runner strips running
  from the front to the carcass back;
- an overlay top overhangs the sides and the fronts enough for a finger under it; under an inset top, and under
  the divider, the fronts stop short, leaving a finger-pull gap below the board's front edge;
- cabinets are no deeper than wide: horizontal boards (bottom, inset top, shelves) are held at their front
  edge (at their sides stand the carcass sides, at their back the back panel), and a hand picks the edges
  nearest a part's middle;
- doors and drawer fronts are held at their top edge, from above, before whatever lies above them is placed;
  shelves stay 2.5 cm below the doors' top edge, so a fingertip fits behind it; the fronts clear the floor by
  more than a planner's contact tolerance (a front standing on the floor would seem to hold up the drawer box
  behind it).

The designed assembly order (recorded for the mixed level, :meth:`Builder.set_stages`): base, bottom and back,
then the interior from the bottom up (runners, drawer sides, drawer bottom, drawer back, drawer front, one
drawer after the other; shelves; doors; the divider after the fronts below it), then the carcass sides, then
the top. The carcass sides go on late: a hand holding a drawer side from above spans the gap to the carcass
side. Until then the interior hangs on the back and the bottom (shelves, divider and runners reach the back;
the fronts rest on the bottom board's front edge or on one another). The back stops a few millimetres below the
sides' top, so that once the top is off the carcass sides, not the back, are the highest parts (a planner
taking the highest parts out first then finds this order directly).

The part count stays within 20: drawers are drawn first, then the base, divider, doors and shelves within
what is left.
"""

from __future__ import annotations

import numpy as np

from perception.synth.builder import Builder
from perception.synth.legs import Leg, PlacedLeg
from perception.synth.sampling import chance, choice, integer, uniform

__all__ = ["build_cabinet", "DRAWER_SIDE_GAP_M", "DRAWER_BACK_ROOM_M"]

MAX_PARTS = 20
DRAWER_SIDE_GAP_M = 0.022  # least gap between a drawer side and the carcass side (a fingertip and clearance)
DRAWER_BACK_ROOM_M = 0.105  # least gap between a drawer's back and the carcass back (half the palm's length)
_DRAWER_RAISE = (0.03, 0.035)  # drawer bottom's underside above the lower edges of the drawer sides
_DRAWER_BACK_ABOVE = 0.022  # least height of a drawer's back above the drawer bottom
_SHELF_SETBACK = (0.0, 0.015)
_TOP_OVERHANG_FRONT = (0.02, 0.03)  # overlay top beyond the fronts' front faces
_TOP_OVERHANG_SIDE = (0.02, 0.035)  # overlay top beyond the sides' outer faces
_GRIP_GAP = (0.034, 0.04)  # under an inset top or the divider: from a front's top edge to the board's underside
_PLINTH_RECESS = (0.025, 0.05)  # front kick board behind the carcass front
_BACK_RECESS = (0.025, 0.04)  # an inset back panel in front of the sides' rear edges
# sized for the Panda cell (scenes/cell.toml): the flat boards of a larger cabinet do not all fit the kitting
# ring within the arm's reach (planning/kitting.py checks the area first)
MAX_WIDTH_M, MAX_DEPTH_M, MAX_HEIGHT_M = 0.44, 0.34, 0.46
_MIN_REGION = 0.08  # interior height of a door / shelf region next to drawers
_FRONT_FLOOR_GAP = 0.015  # least height of the fronts' lower edges above the floor
_DOOR_FINGER_ROOM = 0.025  # shelves' top faces at least this far below the doors' top edge


def build_cabinet(rng: np.random.Generator, b: Builder) -> dict:
    """Add a cabinet's parts and joints to ``b``; return the variant record."""
    # --- structure and part budget ------------------------------------------------------------------------
    n_drawers = int(choice(rng, (0, 1, 2), (0.3, 0.35, 0.35)))
    budget = MAX_PARTS - 5 - 5 * n_drawers - 2 * max(0, n_drawers - 1)  # carcass, drawers, runners
    base_options = [("none", 0)] + [
        (k, n) for k, n in (("plinth", 2), ("plinth", 4), ("feet", 4)) if n <= budget
    ]
    base, base_parts = choice(rng, base_options, [1.0] * len(base_options))
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
    drawer_position = ("full" if not divider else choice(rng, ("top", "bottom"))) if n_drawers else "none"
    # an overlay back covers the sides' rear edges: only where no front covers their front edges (see the notes)
    back = choice(rng, ("inset", "overlay")) if n_drawers + n_doors == 0 else "inset"

    # --- dimensions ---------------------------------------------------------------------------------------
    t = uniform(rng, 0.01, 0.02)  # carcass boards
    t_back = uniform(rng, 0.006, 0.01)
    back_recess = uniform(rng, *_BACK_RECESS) if back == "inset" else 0.0
    front_t = uniform(rng, 0.01, 0.018)  # doors and drawer fronts
    overhang_side = uniform(rng, *_TOP_OVERHANG_SIDE) if top == "overlay" else 0.0
    overhang_front = front_t + uniform(rng, *_TOP_OVERHANG_FRONT) if top == "overlay" else 0.0
    grip = uniform(rng, *_GRIP_GAP) if top == "inset" else 0.0
    # a front below the divider stops a finger-pull gap short of it (the divider is held at its front edge,
    # through that gap); the front above the divider rests on its front edge
    div_grip = uniform(rng, *_GRIP_GAP) if divider and (drawer_position == "bottom" or n_doors) else 0.0
    # no deeper than wide: horizontal boards are held at their front edges (see the module notes)
    depth_lo = 0.28 if n_drawers else 0.2
    width = uniform(rng, max(0.25, depth_lo / 0.9 + 2 * t), MAX_WIDTH_M - 2 * overhang_side)
    depth = uniform(rng, depth_lo, min(MAX_DEPTH_M, 0.9 * (width - 2 * t)))
    base_h = uniform(rng, 0.02, 0.06) if base != "none" else 0.0
    raise_h = uniform(rng, 0.01, 0.05) if base == "none" and chance(rng, 0.35) else 0.0
    bottom_lo = base_h + raise_h  # underside of the bottom board

    # drawer boxes: side gap, board thicknesses, raised bottom, runners, clearance above each box
    side_gap = uniform(rng, DRAWER_SIDE_GAP_M, DRAWER_SIDE_GAP_M + 0.008)
    d_t = uniform(rng, 0.006, 0.012)
    d_bottom_t = uniform(rng, 0.006, 0.01)
    d_raise = uniform(rng, *_DRAWER_RAISE)
    runner_h = uniform(rng, 0.01, 0.015)
    clear = uniform(rng, 0.006, 0.012)
    # above the top-most box: below the top front's top edge (where a finger-pull gap cuts the front short)
    top_clear = max(clear, (div_grip if drawer_position == "bottom" else grip) + 0.003)
    box_min = d_raise + d_bottom_t + _DRAWER_BACK_ABOVE
    stack = (n_drawers - 1) * (clear + runner_h) + top_clear if n_drawers else 0.0  # band height less the boxes
    if n_drawers:
        min_interior = n_drawers * box_min + stack + (t + _MIN_REGION if divider else 0.0)
    else:
        min_interior = 0.1
    fixed = bottom_lo + 2 * t  # up to the bottom board's top face, and the top board
    lowest = max(0.25, fixed + min_interior + 0.01)
    height = uniform(rng, lowest, max(lowest, MAX_HEIGHT_M))

    z0 = base_h  # sides' lower ends
    side_h = height - base_h - (t if top == "overlay" else 0.0)
    z_side_top = z0 + side_h
    inner_w = width - 2 * t
    y_front = -0.5 * depth
    y_back = 0.5 * depth - back_recess  # the back panel's rear face (an overlay back's front face)
    y_back_limit = y_back - t_back if back == "inset" else y_back  # rear edge of the boards inside
    inner_d = y_back_limit - y_front
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
    back_h = side_h - uniform(rng, 0.002, 0.004)  # a little below the sides' top (see the module notes)
    if back == "inset":
        b.add_box(
            "back", (inner_w, t_back, back_h), (0.0, y_back - 0.5 * t_back, z0 + 0.5 * back_h), "carcass"
        )
    else:
        b.add_box(
            "back", (width, t_back, back_h), (0.0, 0.5 * depth + 0.5 * t_back, z0 + 0.5 * back_h), "carcass"
        )
    for board in ("top", "bottom", "back"):
        b.join(board, "side_left")
        b.join(board, "side_right")
    if top == "inset":  # the inset top's rear edge against the back; an overlay top clears it by a few mm
        b.join("top", "back")
    b.join("bottom", "back")

    # --- interior layout ----------------------------------------------------------------------------------
    interior = zi1 - zi0
    box_h = band_lo = 0.0
    region_lo, region_hi = zi0, zi1
    div_lo = div_mid = 0.0
    if n_drawers:
        if divider:
            box_max = (interior - t - _MIN_REGION - stack) / n_drawers
            box_h = uniform(rng, box_min, min(0.1, box_max))
            band = n_drawers * box_h + stack
            if drawer_position == "bottom":
                band_lo = zi0
                div_lo = zi0 + band
                region_lo, region_hi = div_lo + t, zi1
            else:
                div_lo = zi1 - band - t
                band_lo = div_lo + t
                region_lo, region_hi = zi0, div_lo
            b.add_box("divider", board_size, (0.0, y_board, div_lo + 0.5 * t), "shelves")
            b.join("divider", "side_left")
            b.join("divider", "side_right")
            b.join("divider", "back")
            div_mid = div_lo + 0.5 * t
        else:
            band_lo = zi0
            box_h = (interior - stack) / n_drawers

    # --- front faces: overlay fronts cover the carcass from its lower edge up to the sides' top ------------
    # (under an inset top they stop a finger-pull gap below it); ``gap`` between neighbouring fronts
    gap = uniform(rng, 0.002, 0.004)
    # boundaries between fronts; each front keeps 0.5 * gap from them, and clears the floor (by more than a planner
    # takes for contact: a front standing on the floor would hold up the drawer box behind it)
    front_lo = max(bottom_lo, _FRONT_FLOOR_GAP) - 0.5 * gap
    front_hi = z_side_top if top == "overlay" else zi1 - grip + 0.5 * gap
    edge = uniform(rng, 0.0, 0.4) * t  # how far the fronts stop short of the outer side faces
    if n_drawers and divider:
        below = (front_lo, div_lo - div_grip + 0.5 * gap if div_grip else div_mid)
        drawer_front = below if drawer_position == "bottom" else (div_mid, front_hi)
        region_front = (div_mid, front_hi) if drawer_position == "bottom" else below
    else:
        drawer_front = region_front = (front_lo, front_hi)

    # --- shelves and doors --------------------------------------------------------------------------------
    n_shelves = 0
    if region:
        shelf_t = uniform(rng, 0.008, t)
        # behind the doors' top edge (held from above) a fingertip needs room: shelves stay lower
        shelf_hi = min(region_hi, region_front[1] - 0.5 * gap - _DOOR_FINGER_ROOM) if n_doors else region_hi
        span = shelf_hi - region_lo
        n_shelves = max(0, min(n_shelves_wanted, int((span - 0.04) // (0.04 + shelf_t))))
        setback = uniform(rng, *_SHELF_SETBACK)
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
        outer = inner_w - 2 * side_gap  # drawer box width
        inner = outer - 2 * d_t
        # no deeper than its bottom is wide (the bottom is held at its front edge), clear of the carcass back
        box_d = min(inner_d * uniform(rng, 0.6, 0.95), inner_d - DRAWER_BACK_ROOM_M, 0.9 * inner)
        y_box = y_front + 0.5 * box_d
        runner_w = side_gap + 0.5 * d_t  # from the carcass side to the middle of the drawer side above it
        pitch = box_h + clear + runner_h
        for i in range(n_drawers):  # i = 0 is the lowest drawer; drawer 1 is the top one
            floor = band_lo + i * pitch  # lower edges of the drawer sides
            name = f"drawer_{n_drawers - i}"
            module = name
            f_lo = drawer_front[0] if i == 0 else floor - runner_h
            f_hi = drawer_front[1] if i == n_drawers - 1 else floor + pitch - runner_h
            front_h = f_hi - f_lo - gap
            b.add_box(f"{name}_front", (width - 2 * edge, front_t, front_h),
                      (0.0, y_front - 0.5 * front_t, 0.5 * (f_lo + f_hi)), module)  # fmt: skip
            for lr, sx in (("left", -1.0), ("right", 1.0)):
                b.add_box(f"{name}_side_{lr}", (d_t, box_d, box_h),
                          (sx * (0.5 * outer - 0.5 * d_t), y_box, floor + 0.5 * box_h), module)  # fmt: skip
            bottom_z = floor + d_raise
            b.add_box(f"{name}_bottom", (inner, box_d, d_bottom_t), (0.0, y_box, bottom_z + 0.5 * d_bottom_t), module)
            back_lo = bottom_z + d_bottom_t
            back_h = floor + box_h - back_lo
            b.add_box(f"{name}_back", (inner, d_t, back_h),
                      (0.0, y_front + box_d - 0.5 * d_t, back_lo + 0.5 * back_h), module)  # fmt: skip
            overlap = min(f_hi - 0.5 * gap, floor + box_h) - max(f_lo + 0.5 * gap, floor)
            if overlap < 0.01:
                raise RuntimeError(f"{name}: front and box overlap only {overlap:.4f} m in height")
            for lr in ("left", "right"):
                b.join(f"{name}_side_{lr}", f"{name}_front")
                b.join(f"{name}_side_{lr}", f"{name}_bottom")
                b.join(f"{name}_side_{lr}", f"{name}_back")
                b.join(f"{name}_front", f"side_{lr}")
            b.join(f"{name}_bottom", f"{name}_front")
            b.join(f"{name}_bottom", f"{name}_back")
            if i == 0:  # the lowest drawer stands on the bottom board or the divider
                below = "bottom" if drawer_position in ("bottom", "full") else "divider"
                for lr in ("left", "right"):
                    b.join(f"{name}_side_{lr}", below)
            else:  # the others on runners fastened to the carcass sides
                for lr, sx in (("left", -1.0), ("right", 1.0)):
                    runner = f"{name}_runner_{lr}"
                    b.add_box(runner, (runner_w, inner_d, runner_h),
                              (sx * (0.5 * inner_w - 0.5 * runner_w), y_board, floor - 0.5 * runner_h),
                              "carcass")  # fmt: skip
                    b.join(runner, f"side_{lr}")
                    b.join(runner, "back")
                    b.join(runner, f"{name}_side_{lr}")

    # --- base ---------------------------------------------------------------------------------------------
    if base == "plinth":
        kick_t = uniform(rng, 0.01, 0.02)
        side_in = uniform(rng, 0.0, 0.5) * t
        recess_front = uniform(rng, *_PLINTH_RECESS)
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

    # --- designed assembly order (the mixed level keeps merges consistent with it) -----------------------
    def drawer_stages(i: int) -> list[list[str]]:
        name = f"drawer_{n_drawers - i}"
        out = [[f"{name}_runner_left", f"{name}_runner_right"]] if i else []
        out += [[f"{name}_side_left", f"{name}_side_right"], [f"{name}_bottom"], [f"{name}_back"]]
        return out + [[f"{name}_front"]]

    shelves = [[f"shelf_{i + 1}"] for i in range(n_shelves)]
    doors = [[n for n in ("door", "door_left", "door_right") if b.has(n)]]
    drawers = [stage for i in range(n_drawers) for stage in drawer_stages(i)]
    if drawer_position == "top":  # the doors are held at their top edge from above, before the divider
        interior = shelves + doors + [["divider"]] + drawers
    elif drawer_position == "bottom":
        interior = drawers + [["divider"]] + shelves + doors
    else:
        interior = drawers + shelves + doors
    base_names = [p.name for p in b.parts if p.module == "base"]
    carcass = [["back"], ["bottom"]] if raise_h > 0.0 else [["bottom"], ["back"]]  # a raised bottom hangs on the back
    order = [base_names, *carcass, *interior, ["side_left", "side_right"], ["top"]]
    b.set_stages(order, max_span=4)  # no group spanning more: a closed box has no free edge to hold it by

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
