"""What a simulated assembly measured (:func:`cell.simulate.simulate_program`): where each part ended against its
target, the unplanned contacts, joint limit violations and failed grasps; as plain JSON
(:meth:`SimulationResult.summary`) and as one line of words (:meth:`SimulationResult.failure_words`).

Frames and units: poses in the world frame (+z up, metres); times on the program's clock (seconds, 0 when it
starts).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from planning.pose import Pose


@dataclass(frozen=True)
class PartResult:
    """Where one part ended (world frame). ``position_error_m``: distance of its centre from the target's (metres);
    ``rotation_error_deg``: smallest rotation to the target over the part's symmetries (degrees).
    ``grasp_offset_m`` / ``grasp_offset_deg``: how far the part lay from its planned grasp, relative to the hand,
    when the fingers closed on it (metres at the TCP, degrees; None if never grasped); ``grasp_seated``: whether it
    was held at the planned grasp (offset within :attr:`cell.simulate.SimSettings.grasp_seat_m`, ``grasp_seat_deg`` and
    ``grasp_square_deg``) rather than where it lay; ``gripped_at_s``: when the grip last took hold of it (program
    clock, seconds; None if never)."""

    name: str
    world_from_final: Pose
    position_error_m: float
    rotation_error_deg: float
    within_tolerance: bool
    grasped: bool  # the hand held it at some point
    fastened_to: tuple[str, ...]  # what it was fastened to at release ("fixture" for the world)
    settle_motion_m: float  # how far its centre moved while settling at the start
    moved_after_release_m: float | None  # how far its centre moved from its release to the end (None: never released)
    grasp_offset_m: float | None = None
    grasp_offset_deg: float | None = None
    grasp_seated: bool = False
    gripped_at_s: float | None = None

    def to_json(self) -> dict:
        return {"name": self.name, "world_from_final": self.world_from_final.to_dict(),
                "position_error_m": self.position_error_m, "rotation_error_deg": self.rotation_error_deg,
                "within_tolerance": self.within_tolerance, "grasped": self.grasped,
                "fastened_to": list(self.fastened_to), "settle_motion_m": self.settle_motion_m,
                "moved_after_release_m": self.moved_after_release_m, "grasp_offset_m": self.grasp_offset_m,
                "grasp_offset_deg": self.grasp_offset_deg, "grasp_seated": self.grasp_seated,
                "gripped_at_s": self.gripped_at_s}


@dataclass(frozen=True)
class ContactEvent:
    """An unplanned contact between ``body_a`` and ``body_b`` (robot links are named ``robot/<link>``) from
    ``start_s`` to ``end_s`` (seconds on the program's clock: 0 when it starts, negative while the world settles
    before it), first seen during program step ``step``; ``depth_m``: the deepest penetration seen (metres, 0 for
    touching)."""

    start_s: float
    end_s: float
    step: str
    body_a: str
    body_b: str
    depth_m: float


@dataclass(frozen=True)
class LimitEvent:
    """The simulated arm beyond a joint limit (times on the program's clock, as :class:`ContactEvent`):
    ``quantity`` "position" (rad) or "velocity" (rad/s); ``peak`` the farthest value reached, ``limit`` the bound
    it crossed (signed like ``peak``)."""

    start_s: float
    end_s: float
    step: str
    joint: str
    quantity: str
    peak: float
    limit: float


@dataclass(frozen=True)
class GraspFailure:
    """The gripper step ``step`` ended at ``time_s`` (program clock) without both fingers touching ``part``;
    ``fingers_touching`` names those that did."""

    part: str
    step: str
    time_s: float
    fingers_touching: tuple[str, ...]


@dataclass
class SimulationResult:
    parts: list[PartResult]
    contacts: list[ContactEvent]
    limit_violations: list[LimitEvent]
    grasp_failures: list[GraspFailure]
    frames: list[np.ndarray]  # (H, W, 3) uint8 RGB every ``record_every_s`` from the program's start, and at the end
    rate_hz: float
    simulated_s: float  # the program plus both settling times
    wall_s: float
    final_arm_q: tuple[float, ...]  # rad
    final_opening_m: float  # between the fingers
    unsettled: list[str] = field(default_factory=list)  # parts that moved while settling at the start
    # pairs of parts whose bodies overlap at their targets: (part, part, deepest penetration in metres)
    overlaps_at_target: list[tuple[str, str, float]] = field(default_factory=list)

    @property
    def success(self) -> bool:
        return (all(p.within_tolerance for p in self.parts) and not self.contacts and not self.limit_violations
                and not self.grasp_failures)

    def summary(self) -> dict:
        """Everything measured, as plain JSON types."""
        return {"success": self.success, "rate_hz": self.rate_hz, "simulated_s": self.simulated_s,
                "wall_s": self.wall_s, "parts": [p.to_json() for p in self.parts],
                "grasp_failures": [asdict(g) | {"fingers_touching": list(g.fingers_touching)}
                                   for g in self.grasp_failures],
                "unplanned_contacts": [asdict(c) for c in self.contacts],
                "limit_violations": [asdict(v) for v in self.limit_violations],
                "unsettled_parts": list(self.unsettled),
                "overlaps_at_target": [{"part_a": a, "part_b": b, "depth_m": depth}
                                       for a, b, depth in self.overlaps_at_target]}

    def failure_words(self) -> str:
        """One line saying what went wrong (empty on success)."""
        words = []
        off = [p for p in self.parts if not p.within_tolerance]
        if off:
            words.append(f"{len(off)} part(s) off target (" + ", ".join(
                f"{p.name}: {p.position_error_m * 1000:.1f} mm, {p.rotation_error_deg:.1f} deg" for p in off[:3])
                + (", ..." if len(off) > 3 else "") + ")")
        for g in self.grasp_failures[:3]:
            touching = " and ".join(g.fingers_touching) or "no finger"
            words.append(f"grasp of {g.part} failed at '{g.step}' (t = {g.time_s:.2f} s; {touching} touched it)")
        if self.contacts:
            c = self.contacts[0]
            words.append(f"{len(self.contacts)} unplanned contact(s), first {c.body_a} against {c.body_b} at "
                         f"t = {c.start_s:.2f} s during '{c.step}'")
        if self.limit_violations:
            v = self.limit_violations[0]
            words.append(f"{len(self.limit_violations)} joint limit violation(s), first {v.joint} {v.quantity} "
                         f"{v.peak:.3f} beyond {v.limit:.3f} at t = {v.start_s:.2f} s during '{v.step}'")
        return "; ".join(words)
