"""Procedural chairs: legs, a seat, a back between two posts, optional stretchers and arms.

Working frame: +z up, the seat's front edge towards -y, its back towards +y, "left" is -x. Every dimension
is drawn from a range; the structure is drawn from these choices (recorded in ``variant``):

- ``legs``: 3 or 4 legs (``leg_count``) of ``box``, ``round``, ``tapered`` or ``tapered_round`` section;
- ``seat``: ``slab`` (one board), ``frame_panel`` (four rails around a thinner panel, tops flush) or
  ``frame_slats`` (four rails with slats between the front and rear rails);
- ``back``: ``panel``, ``vertical_slats`` (optionally on a lower rail) or ``horizontal_slats`` between two
  posts, under a top rail that sits ``between`` the posts or ``over`` them;
- ``posts``: ``on_seat`` (two posts standing on the seat) or ``leg_extension`` (the rear legs run up to
  form the back, the seat's rear face against them);
- ``stretchers``: ``H``, ``box`` (``staggered`` or not) or ``none`` with four legs; ``T`` or ``none`` with
  three;
- ``arms``: 0 or 1 (an arm rest on a short post each side, its rear end against the back post).

Slats (seat slats, vertical and horizontal back slats) stand :data:`SLAT_GAP_M` or more apart, and as far from
the rails and posts beside them, so that a robot's fingertips fit between them: a slat can then be held with
its neighbours in place.
"""

from __future__ import annotations

import numpy as np

from perception.synth.builder import Builder
from perception.synth.legs import SECTIONS, Leg, PlacedLeg
from perception.synth.sampling import chance, choice, integer, uniform

__all__ = ["build_chair", "SLAT_GAP_M"]

MAX_PARTS = 20
SLAT_GAP_M = 0.022  # least gap between slats and to the rails or posts beside them: a fingertip with clearance
_SEAT_PARTS = {"slab": 1, "frame_panel": 5, "frame_slats": 4}
_STRETCHER_PARTS = {"H": 3, "box": 4, "T": 2, "none": 0}


def _count(n_legs, seat, posts, back, lower_rail, stretchers, arms, seat_slats, back_slats) -> int:
    n = n_legs + _SEAT_PARTS[seat] + (seat_slats if seat == "frame_slats" else 0)
    n += (2 if posts == "on_seat" else 0) + 1 + (1 if back == "panel" else back_slats) + int(lower_rail)
    return n + _STRETCHER_PARTS[stretchers] + 4 * int(arms)


def build_chair(rng: np.random.Generator, b: Builder) -> dict:
    """Add a chair's parts and joints to ``b``; return the variant record."""
    # --- structure ----------------------------------------------------------------------------------------
    n_legs = 3 if chance(rng, 0.2) else 4
    section = choice(rng, SECTIONS)
    seat = choice(rng, ("slab", "frame_panel", "frame_slats"))
    back = choice(rng, ("panel", "vertical_slats", "horizontal_slats"))
    extension = n_legs == 4 and seat == "slab" and section in ("box", "round") and chance(rng, 0.8)
    posts = "leg_extension" if extension else "on_seat"
    stretchers = choice(rng, ("H", "box", "none")) if n_legs == 4 else choice(rng, ("T", "none"))
    arms = chance(rng, 0.35)
    top_rail = choice(rng, ("between", "over"))
    lower_rail = back == "vertical_slats" and (extension or chance(rng, 0.4))

    min_back_slats = {"panel": 0, "vertical_slats": 2, "horizontal_slats": 1}[back]
    # keep the part count within the cap at the smallest slat counts: drop the optional extras first
    while _count(n_legs, seat, posts, back, lower_rail, stretchers, arms, 3, min_back_slats) > MAX_PARTS:
        if arms:
            arms = False
        elif lower_rail and not extension:
            lower_rail = False
        elif stretchers == "box":
            stretchers = "H"
        else:
            stretchers = "none"
    budget = MAX_PARTS - _count(n_legs, seat, posts, back, lower_rail, stretchers, arms, 0, 0)

    # --- overall proportions ------------------------------------------------------------------------------
    height = uniform(rng, 0.40, 0.60)
    seat_top = height * uniform(rng, 0.45, 0.55)
    width = uniform(rng, 0.22, 0.36)
    depth = uniform(rng, 0.20, min(0.34, 1.15 * width))

    leg_top = uniform(rng, 0.018, 0.032) if section.startswith("tapered") else uniform(rng, 0.014, 0.032)
    leg_bottom = max(0.011, leg_top * uniform(rng, 0.55, 0.8)) if section.startswith("tapered") else leg_top

    if seat == "slab":
        seat_thickness = uniform(rng, 0.012, 0.03)
        rail_width = rail_height = panel_thickness = 0.0
        leg_inset = uniform(rng, 0.0, 0.08) * min(width, depth)
    else:
        rail_width = uniform(rng, 0.016, 0.03)
        rail_height = uniform(rng, 0.018, 0.035)
        panel_thickness = uniform(rng, 0.006, min(0.014, rail_height - 0.004))
        seat_thickness = rail_height
        leg_inset = uniform(rng, 0.0, 0.5) * rail_width
    leg_length = seat_top - seat_thickness
    leg = Leg(section, leg_top, leg_bottom, leg_length)

    # --- back posts -------------------------------------------------------------------------------------
    rail_h = uniform(rng, 0.02, min(0.05, 0.3 * (height - seat_top)))  # top rail height
    drop = uniform(rng, 0.0, 0.3) * rail_h if top_rail == "between" and chance(rng, 0.5) else 0.0
    post_top = height - rail_h if top_rail == "over" else height
    x_leg = 0.5 * width - leg_inset - 0.5 * leg_top
    y_front = -0.5 * depth + leg_inset + 0.5 * leg_top
    if extension:
        post_section, post_w = section, leg_top
        x_post, y_post = x_leg, 0.5 * depth + 0.5 * leg_top
        y_rear = y_post
        rear_leg = Leg(section, leg_top, leg_top, post_top)
    else:
        post_section = "round" if section in ("round", "tapered_round") and chance(rng, 0.75) else "box"
        post_w = uniform(rng, 0.014, 0.028)
        if seat == "slab":
            x_post = 0.5 * width - uniform(rng, 0.0, 0.06) * width - 0.5 * post_w
            y_post = 0.5 * depth - uniform(rng, 0.0, 0.04) * depth - 0.5 * post_w
        else:  # the post's centre stands over the side and rear rails
            x_post = 0.5 * width - max(0.5 * post_w, rail_width * uniform(rng, 0.3, 0.7))
            y_post = 0.5 * depth - max(0.5 * post_w, rail_width * uniform(rng, 0.3, 0.7))
        y_rear = 0.5 * depth - leg_inset - 0.5 * leg_top
        rear_leg = leg
    post = Leg(post_section, post_w, post_w, post_top - seat_top)
    inner_width = 2.0 * (x_post - 0.5 * post_w)  # between the posts' inner faces (tangent planes if round)

    # --- seat -------------------------------------------------------------------------------------------
    seat_z = seat_top - 0.5 * seat_thickness
    # seat slats are held from above across their width: room for a fingertip between them
    seat_slat_w = uniform(rng, 0.02, min(0.05, (width - 2 * rail_width - 4 * SLAT_GAP_M) / 3))

    def seat_part_under(x: float, y: float) -> str:
        """The seat part whose top face is under the point (x, y) (rails first)."""
        if seat == "slab":
            return "seat"
        if y <= -0.5 * depth + rail_width:
            return "seat_rail_front"
        if y >= 0.5 * depth - rail_width:
            return "seat_rail_rear"
        if abs(x) >= 0.5 * width - rail_width:
            return "seat_rail_left" if x < 0 else "seat_rail_right"
        raise RuntimeError("point is not over a seat rail")

    # --- slat counts within the part budget and the geometry ----------------------------------------------
    seat_slats = 0
    if seat == "frame_slats":
        free = width - 2 * rail_width
        geom = int((free - SLAT_GAP_M + 1e-9) // (seat_slat_w + SLAT_GAP_M))
        seat_slats = integer(rng, 3, min(6, geom, budget - min_back_slats))
    back_slats = 0
    zone_lo = seat_top
    zone_hi = post_top - drop - (0.0 if top_rail == "over" else rail_h)
    zone = zone_hi - zone_lo
    slat_w = uniform(rng, 0.015, max(0.015, min(0.04, (inner_width - 3 * SLAT_GAP_M) / 2)))
    slat_t = uniform(rng, 0.006, min(0.014, 0.8 * post_w))
    if back == "vertical_slats":
        geom = int((inner_width - SLAT_GAP_M + 1e-9) // (slat_w + SLAT_GAP_M))
        back_slats = integer(rng, 2, min(6, geom, budget - seat_slats))
    elif back == "horizontal_slats":
        margin_top = uniform(rng, SLAT_GAP_M, 0.035)
        margin_bottom = uniform(rng, SLAT_GAP_M, max(SLAT_GAP_M, 0.3 * zone))
        slat_h = uniform(rng, 0.015, 0.035)
        avail = zone - margin_top - margin_bottom
        geom = int((avail + SLAT_GAP_M + 1e-9) // (slat_h + SLAT_GAP_M))
        back_slats = integer(rng, 1, min(4, geom, budget - seat_slats))

    # --- legs ---------------------------------------------------------------------------------------------
    placed: dict[str, PlacedLeg] = {}
    if n_legs == 4:
        placed["leg_front_left"] = PlacedLeg(leg, -x_leg, y_front, 0.0)
        placed["leg_front_right"] = PlacedLeg(leg, x_leg, y_front, 0.0)
    else:
        placed["leg_front"] = PlacedLeg(leg, 0.0, y_front, 0.0)
    placed["leg_rear_left"] = PlacedLeg(rear_leg, -x_leg, y_rear, 0.0)
    placed["leg_rear_right"] = PlacedLeg(rear_leg, x_leg, y_rear, 0.0)
    for name, pl in placed.items():
        b.add_leg(name, pl, "base" if not (extension and "rear" in name) else "back")

    # --- seat parts ---------------------------------------------------------------------------------------
    if seat == "slab":
        b.add_box("seat", (width, depth, seat_thickness), (0.0, 0.0, seat_z), "seat")
        for name in placed:
            b.join(name, "seat")
    else:
        long_rail = (width, rail_width, rail_height)
        short_rail = (rail_width, depth - 2 * rail_width, rail_height)
        b.add_box("seat_rail_front", long_rail, (0.0, -0.5 * depth + 0.5 * rail_width, seat_z), "seat")
        b.add_box("seat_rail_rear", long_rail, (0.0, 0.5 * depth - 0.5 * rail_width, seat_z), "seat")
        for side, sx in (("left", -1.0), ("right", 1.0)):
            name = f"seat_rail_{side}"
            b.add_box(name, short_rail, (sx * (0.5 * width - 0.5 * rail_width), 0.0, seat_z), "seat")
            b.join(name, "seat_rail_front")
            b.join(name, "seat_rail_rear")
        panel_z = seat_top - 0.5 * panel_thickness
        free_w, free_d = width - 2 * rail_width, depth - 2 * rail_width
        if seat == "frame_panel":
            b.add_box("seat_panel", (free_w, free_d, panel_thickness), (0.0, 0.0, panel_z), "seat")
            for rail in ("front", "rear", "left", "right"):
                b.join("seat_panel", f"seat_rail_{rail}")
        else:
            gap = (free_w - seat_slats * seat_slat_w) / (seat_slats + 1)
            for i in range(seat_slats):
                x = -0.5 * free_w + gap + 0.5 * seat_slat_w + i * (seat_slat_w + gap)
                name = f"seat_slat_{i + 1}"
                b.add_box(name, (seat_slat_w, free_d, panel_thickness), (x, 0.0, panel_z), "seat")
                b.join(name, "seat_rail_front")
                b.join(name, "seat_rail_rear")
        for name in placed:
            b.join(name, "seat_rail_front" if "front" in name else "seat_rail_rear")

    # --- back -------------------------------------------------------------------------------------------
    if extension:
        post_names = ("leg_rear_left", "leg_rear_right")
    else:
        post_names = ("back_post_left", "back_post_right")
        for name, sx in zip(post_names, (-1.0, 1.0)):
            b.add_leg(name, PlacedLeg(post, sx * x_post, y_post, seat_top), "back")
            b.join(name, seat_part_under(sx * x_post, y_post))
    rail_depth = post_w * uniform(rng, 0.5, 1.0)
    if top_rail == "between":
        b.add_box(
            "back_top_rail",
            (inner_width, rail_depth, rail_h),
            (0.0, y_post, height - drop - 0.5 * rail_h),
            "back",
        )
    else:
        overhang = uniform(rng, 0.0, 0.02)
        over_depth = uniform(rng, max(post_w, 0.012), post_w + 0.02)
        over_len = 2.0 * (x_post + 0.5 * post_w + overhang)
        b.add_box(
            "back_top_rail", (over_len, over_depth, rail_h), (0.0, y_post, height - 0.5 * rail_h), "back"
        )
    for name in post_names:
        b.join("back_top_rail", name)

    def on_seat(name: str, x: float) -> None:
        if not extension:
            b.join(name, seat_part_under(x, y_post))

    if back == "panel":
        panel_t = uniform(rng, 0.006, min(0.014, 0.8 * post_w))
        lift = 0.0 if chance(rng, 0.4) else uniform(rng, 0.05, 0.35) * zone
        panel_h = zone - lift
        b.add_box(
            "back_panel", (inner_width, panel_t, panel_h), (0.0, y_post, zone_hi - 0.5 * panel_h), "back"
        )
        b.join("back_panel", "back_top_rail")
        for name in post_names:
            b.join("back_panel", name)
        if lift == 0.0:
            on_seat("back_panel", 0.0)
    elif back == "vertical_slats":
        slat_lo = zone_lo
        if lower_rail:
            low_h = uniform(rng, 0.015, 0.03)
            on_seat_rail = not extension and chance(rng, 0.3)
            low_lo = zone_lo if on_seat_rail else zone_lo + uniform(rng, 0.03, 0.25) * zone
            b.add_box(
                "back_lower_rail",
                (inner_width, rail_depth, low_h),
                (0.0, y_post, low_lo + 0.5 * low_h),
                "back",
            )
            for name in post_names:
                b.join("back_lower_rail", name)
            if on_seat_rail:
                on_seat("back_lower_rail", 0.0)
            slat_lo = low_lo + low_h
        slat_len = zone_hi - slat_lo
        gap = (inner_width - back_slats * slat_w) / (back_slats + 1)
        for i in range(back_slats):
            x = -0.5 * inner_width + gap + 0.5 * slat_w + i * (slat_w + gap)
            name = f"back_slat_{i + 1}"
            b.add_box(name, (slat_w, slat_t, slat_len), (x, y_post, slat_lo + 0.5 * slat_len), "back")
            b.join(name, "back_top_rail")
            if lower_rail:
                b.join(name, "back_lower_rail")
            else:
                on_seat(name, x)
    else:
        lo = zone_lo + margin_bottom
        step = (avail - slat_h) / (back_slats - 1) if back_slats > 1 else 0.0
        for i in range(back_slats):
            z = lo + i * step if back_slats > 1 else zone_hi - margin_top - slat_h
            name = f"back_slat_{i + 1}"
            b.add_box(name, (inner_width, slat_t, slat_h), (0.0, y_post, z + 0.5 * slat_h), "back")
            for post_name in post_names:
                b.join(name, post_name)

    # --- stretchers -------------------------------------------------------------------------------------
    staggered = False
    if stretchers != "none":
        st_w = uniform(rng, 0.55, 0.8) * leg.min_width
        st_h = uniform(rng, 0.01, 0.022)
        z_a = uniform(rng, 0.15, 0.45) * leg_length
        lo_a, hi_a = z_a - 0.5 * st_h, z_a + 0.5 * st_h
        fl = placed["leg_front_left"] if n_legs == 4 else placed["leg_front"]
        rl = placed["leg_rear_left"]
        if stretchers in ("H", "box"):
            staggered = stretchers == "box" and chance(rng, 0.5)
            z_b = z_a
            if staggered:
                z_b += (1 if z_a < 0.3 * leg_length else -1) * uniform(rng, 1.3, 2.5) * st_h
                z_b = min(max(z_b, 0.08 * leg_length + st_h), 0.7 * leg_length)
            lo_b, hi_b = z_b - 0.5 * st_h, z_b + 0.5 * st_h
            y0, y1 = fl.y + fl.reach(lo_b, hi_b), rl.y - rl.reach(lo_b, hi_b)
            for side, sx in (("left", -1.0), ("right", 1.0)):
                name = f"stretcher_{side}"
                b.add_box(name, (st_w, y1 - y0, st_h), (sx * x_leg, 0.5 * (y0 + y1), z_b), "base")
                b.join(name, f"leg_front_{side}")
                b.join(name, f"leg_rear_{side}")
            if stretchers == "H":
                y_mid = 0.5 * (y0 + y1) + uniform(rng, -0.2, 0.2) * (y1 - y0)
                b.add_box(
                    "stretcher_middle", (2 * (x_leg - 0.5 * st_w), st_w, st_h), (0.0, y_mid, z_b), "base"
                )
                b.join("stretcher_middle", "stretcher_left")
                b.join("stretcher_middle", "stretcher_right")
            else:
                for end, pl in (("front", fl), ("rear", rl)):
                    name = f"stretcher_{end}"
                    length = 2 * (x_leg - pl.reach(lo_a, hi_a))
                    b.add_box(name, (length, st_w, st_h), (0.0, pl.y, z_a), "base")
                    b.join(name, f"leg_{end}_left")
                    b.join(name, f"leg_{end}_right")
        else:  # T: rear stretcher between the rear legs, centre stretcher from the front leg to it
            length = 2 * (x_leg - rl.reach(lo_a, hi_a))
            b.add_box("stretcher_rear", (length, st_w, st_h), (0.0, rl.y, z_a), "base")
            b.join("stretcher_rear", "leg_rear_left")
            b.join("stretcher_rear", "leg_rear_right")
            y0, y1 = fl.y + fl.reach(lo_a, hi_a), rl.y - 0.5 * st_w
            b.add_box("stretcher_centre", (st_w, y1 - y0, st_h), (0.0, 0.5 * (y0 + y1), z_a), "base")
            b.join("stretcher_centre", "leg_front")
            b.join("stretcher_centre", "stretcher_rear")

    # --- arms -------------------------------------------------------------------------------------------
    if arms:
        arm_post_w = uniform(rng, 0.012, min(0.022, post_w))
        arm_w = uniform(rng, max(arm_post_w, 0.018), 0.035)
        arm_t = uniform(rng, 0.012, 0.02)
        arm_top = zone_lo + uniform(rng, 0.35, 0.6) * zone
        y_back = y_post - 0.5 * post_w  # the back post's front face (tangent plane if round)
        y_tip = -0.5 * depth + uniform(rng, 0.0, 0.12) * depth
        y_arm_post = y_tip + uniform(rng, 0.5, 1.5) * arm_post_w
        arm_post = Leg(post_section, arm_post_w, arm_post_w, arm_top - arm_t - seat_top)
        for side, sx, post_name in (("left", -1.0, post_names[0]), ("right", 1.0, post_names[1])):
            rest, stand = f"arm_rest_{side}", f"arm_post_{side}"
            b.add_box(
                rest,
                (arm_w, y_back - y_tip, arm_t),
                (sx * x_post, 0.5 * (y_tip + y_back), arm_top - 0.5 * arm_t),
                f"arm_{side}",
            )
            b.add_leg(stand, PlacedLeg(arm_post, sx * x_post, y_arm_post, seat_top), f"arm_{side}")
            b.join(rest, stand)
            b.join(rest, post_name)
            b.join(stand, seat_part_under(sx * x_post, y_arm_post))

    # --- designed assembly order (the mixed level keeps merges consistent with it) -----------------------
    names = [p.name for p in b.parts]

    def named(*prefixes: str) -> list[str]:
        return [n for n in names if n.startswith(prefixes)]

    # a seat panel or slats go in before the last rail around them, a back panel or slats before the top rail
    b.set_stages(
        [
            named("leg_"),
            named("stretcher_"),
            ["seat"] if seat == "slab" else ["seat_rail_front", "seat_rail_rear", "seat_rail_left"],
            named("seat_panel", "seat_slat_"),
            named("seat_rail_right"),
            named("back_post_"),
            named("back_lower_rail"),
            named("back_panel", "back_slat_"),
            ["back_top_rail"],
            named("arm_"),
        ]
    )

    return {
        "legs": section,
        "leg_count": n_legs,
        "seat": seat,
        "back": back,
        "posts": posts,
        "top_rail": top_rail,
        "lower_rail": int(lower_rail),
        "stretchers": stretchers,
        "staggered": int(staggered),
        "arms": int(arms),
        "seat_slats": seat_slats,
        "back_slats": back_slats,
        "height": round(height, 4),
        "seat_height": round(seat_top, 4),
        "width": round(width, 4),
        "depth": round(depth, 4),
    }
