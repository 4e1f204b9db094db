"""Closed-form inverse kinematics of the Franka Panda's TCP, one solution set per value of joint 7.

Pure geometry in numpy, no simulator. The Panda has seven joints, so a TCP pose leaves one degree of freedom: with
joint 7 given, the rest follow in closed form (the decomposition of He and Liu, "Analytical inverse kinematics for
Franka Emika Panda", 2021), up to eight solutions per value of joint 7:

- joint 7 and the TCP pose give the wrist point (joint 6's origin, where joint 5's and joint 6's axes meet) and
  link 6's orientation;
- the wrist's distance from the shoulder (joint 2's origin) gives joint 4 (two branches);
- the upper arm turns about the shoulder-wrist line (the elbow's swivel) until joint 5's axis is square to joint
  6's, as the arm's build requires (two branches), which fixes link 3's orientation;
- link 3's orientation is a z-y-z turn by joints 1, 2 and 3 (two branches), and what is left of link 6's is a y-z
  turn by joints 5 and 6.

Frames are the URDF's (``franka_panda/panda.urdf`` in pybullet_data): ``base_from_*`` in the arm's base frame,
metres and radians. :data:`LINK7_FROM_TCP` is the fixed transform from link 7 to the TCP between the fingertips
(``panda_grasptarget``).
"""

from __future__ import annotations

import numpy as np

SHOULDER_HEIGHT_M = 0.333  # joint 1's origin above the base; joint 2's origin is the same point
UPPER_ARM_M = 0.316  # joint 2 to joint 3 along link 3's axis
ELBOW_OFFSET_M = 0.0825  # the elbow's offset, out along link 3 and back along link 4
FOREARM_M = 0.384  # elbow to the wrist
WRIST_OFFSET_M = 0.088  # joint 6's origin to joint 7's, along link 6's x axis
FLANGE_M = 0.107  # joint 7's origin to the flange (link 8)
HAND_ROTATION_RAD = -np.pi / 4  # the hand's turn about the flange's z axis
HAND_TCP_M = 0.105  # the hand's origin to the TCP between the fingertips


def _rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(angles: np.ndarray) -> np.ndarray:
    """(..., 3, 3) turns about z by ``angles`` (...)."""
    c, s = np.cos(angles), np.sin(angles)
    out = np.zeros(np.shape(angles) + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, -s, s, c, 1.0
    return out


def _transform(rotation: np.ndarray, position=(0.0, 0.0, 0.0)) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, position
    return out


LINK7_FROM_TCP = (_transform(np.eye(3), (0.0, 0.0, FLANGE_M)) @ _transform(_rot_z(HAND_ROTATION_RAD))
                  @ _transform(np.eye(3), (0.0, 0.0, HAND_TCP_M)))
# each joint's origin in its parent link's frame (the URDF's <origin>), then the joint turns about its own z
_PARENT_FROM_JOINT = (
    _transform(np.eye(3), (0.0, 0.0, SHOULDER_HEIGHT_M)),
    _transform(_rot_x(-np.pi / 2)),
    _transform(_rot_x(np.pi / 2), (0.0, -UPPER_ARM_M, 0.0)),
    _transform(_rot_x(np.pi / 2), (ELBOW_OFFSET_M, 0.0, 0.0)),
    _transform(_rot_x(-np.pi / 2), (-ELBOW_OFFSET_M, FOREARM_M, 0.0)),
    _transform(_rot_x(np.pi / 2)),
    _transform(_rot_x(np.pi / 2), (WRIST_OFFSET_M, 0.0, 0.0)),
)


def forward_tcp(q: np.ndarray) -> np.ndarray:
    """``base_from_tcp`` (..., 4, 4) at arm configurations ``q`` (..., 7)."""
    q = np.asarray(q, dtype=np.float64)
    cos, sin = np.cos(q), np.sin(q)
    turns = np.zeros(q.shape + (4, 4))  # (..., 7, 4, 4): each joint's turn about its z
    turns[..., 0, 0], turns[..., 0, 1], turns[..., 1, 0], turns[..., 1, 1] = cos, -sin, sin, cos
    turns[..., 2, 2] = turns[..., 3, 3] = 1.0
    out = _PARENT_FROM_JOINT[0] @ turns[..., 0, :, :]
    for joint in range(1, 7):
        out = out @ _PARENT_FROM_JOINT[joint] @ turns[..., joint, :, :]
    return out @ LINK7_FROM_TCP


def _unit(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def _frame(direction: np.ndarray) -> np.ndarray:
    """(..., 3, 3) orthonormal frames whose first column is the unit ``direction`` (..., 3)."""
    helper = np.where(np.abs(direction[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    second = _unit(np.cross(direction, helper))
    return np.stack([direction, second, np.cross(direction, second)], axis=-1)


def _wrap(angles: np.ndarray) -> np.ndarray:
    return (angles + np.pi) % (2.0 * np.pi) - np.pi


def ik_solutions(base_from_tcp: np.ndarray, q7_values: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 tolerance_m: float = 1e-5, tolerance_rotation: float = 1e-5) -> np.ndarray:
    """(K, 7): every arm configuration within the joint limits [``lower``, ``upper``] (7,) that places the TCP at
    ``base_from_tcp`` (4, 4) with joint 7 at one of ``q7_values`` (radians), up to eight for each, in their order;
    each confirmed by forward kinematics to ``tolerance_m`` and ``tolerance_rotation`` (the largest difference
    between the rotation matrices' entries)."""
    q7 = np.asarray(q7_values, dtype=np.float64).reshape(-1)
    q7 = q7[(q7 >= lower[6]) & (q7 <= upper[6])]
    if q7.size == 0:
        return np.zeros((0, 7))
    base_from_link7 = np.asarray(base_from_tcp, dtype=np.float64) @ np.linalg.inv(LINK7_FROM_TCP)
    rotation7, wrist7 = base_from_link7[:3, :3], base_from_link7[:3, 3]
    # link 6: link 7 = link 6 @ Rx(pi/2) Rz(q7), joint 7 WRIST_OFFSET_M along link 6's x from the wrist point
    rotation6 = rotation7 @ _rot_z(-q7) @ _rot_x(-np.pi / 2)  # (K, 3, 3)
    wrist = wrist7 - WRIST_OFFSET_M * rotation6[:, :, 0]  # (K, 3)
    shoulder_to_wrist = wrist - np.array([0.0, 0.0, SHOULDER_HEIGHT_M])
    distance = np.linalg.norm(shoulder_to_wrist, axis=-1)
    # in link 3's frame, shoulder to wrist is v(q4) = (a, 0, d3) + Rx(pi/2) Rz(q4) (-a, d5, 0), whose squared
    # length is k0 + kc cos q4 + ks sin q4
    a, d3, d5 = ELBOW_OFFSET_M, UPPER_ARM_M, FOREARM_M
    k0, kc, ks = 2 * a * a + d3 * d3 + d5 * d5, 2 * d3 * d5 - 2 * a * a, -2 * a * (d3 + d5)
    amplitude, phase = np.hypot(kc, ks), np.arctan2(ks, kc)
    ratio = (distance ** 2 - k0) / amplitude
    reachable = np.abs(ratio) <= 1.0
    spread = np.arccos(np.clip(ratio, -1.0, 1.0))
    q4 = _wrap(np.stack([phase + spread, phase - spread], axis=-1))  # (K, 2)
    c4, s4 = np.cos(q4), np.sin(q4)
    v = np.stack([a - a * c4 - d5 * s4, np.zeros_like(q4), d3 + d5 * c4 - a * s4], axis=-1)  # (K, 2, 3)
    w_unit = _unit(shoulder_to_wrist)[:, None, :].repeat(2, axis=1)  # (K, 2, 3)
    # link 3 = Rot(w, psi) @ R0 with R0 taking v's direction to w's; joint 5's axis (link 3 @ M e_y, with
    # M = Rx(pi/2) Rz(q4)) must be square to joint 6's (link 6's z)
    r0 = _frame(w_unit) @ np.swapaxes(_frame(_unit(v)), -1, -2)  # (K, 2, 3, 3)
    m = np.zeros(q4.shape + (3, 3))
    m[..., 0, 0], m[..., 0, 1], m[..., 1, 2], m[..., 2, 0], m[..., 2, 1] = c4, -s4, -1.0, s4, c4
    axis5 = np.einsum("...ij,...j->...i", r0, m[..., :, 1])
    axis6 = rotation6[:, None, :, 2].repeat(2, axis=1)
    along = np.einsum("...i,...i", w_unit, axis5) * np.einsum("...i,...i", w_unit, axis6)
    coef_a = np.einsum("...i,...i", axis5, axis6) - along
    coef_b = np.einsum("...i,...i", np.cross(w_unit, axis5), axis6)
    norm = np.hypot(coef_a, coef_b)
    ratio5 = -along / np.maximum(norm, 1e-12)
    reachable = reachable[:, None] & (np.abs(ratio5) <= 1.0) & (norm > 1e-12)
    spread5 = np.arccos(np.clip(ratio5, -1.0, 1.0))
    psi = np.stack([np.arctan2(coef_b, coef_a) + spread5, np.arctan2(coef_b, coef_a) - spread5], axis=-1)  # (K,2,2)
    cos_psi, sin_psi = np.cos(psi)[..., None, None], np.sin(psi)[..., None, None]
    wx = np.zeros(w_unit.shape + (3,))
    wx[..., 0, 1], wx[..., 0, 2], wx[..., 1, 2] = -w_unit[..., 2], w_unit[..., 1], -w_unit[..., 0]
    wx -= np.swapaxes(wx, -1, -2)
    outer = w_unit[..., :, None] * w_unit[..., None, :]
    turn = (cos_psi * np.eye(3) + sin_psi * wx[:, :, None] + (1 - cos_psi) * outer[:, :, None])  # (K, 2, 2, 3, 3)
    rotation3 = turn @ r0[:, :, None]
    # link 3 = Rz(q1) Ry(q2) Rz(q3); two branches, q2 > 0 and q2 < 0
    sin2 = np.hypot(rotation3[..., 0, 2], rotation3[..., 1, 2])
    q2 = np.arctan2(sin2, rotation3[..., 2, 2])
    q1 = np.arctan2(rotation3[..., 1, 2], rotation3[..., 0, 2])
    q3 = np.arctan2(rotation3[..., 2, 1], -rotation3[..., 2, 0])
    q123 = np.stack([np.stack([q1, q2, q3], -1), np.stack([_wrap(q1 + np.pi), -q2, _wrap(q3 + np.pi)], -1)], -2)
    # what is left of link 6 is Ry(q5) Rz(q6)
    rest = np.swapaxes(rotation3 @ m[:, :, None], -1, -2) @ rotation6[:, None, None]  # (K, 2, 2, 3, 3)
    q5 = np.arctan2(rest[..., 0, 2], rest[..., 2, 2])
    q6 = np.arctan2(rest[..., 1, 0], rest[..., 1, 1])
    q6 = np.where(q6 < lower[5], q6 + 2.0 * np.pi, q6)
    shape = q123.shape[:-1]  # (K, 2, 2, 2)
    solutions = np.concatenate([
        q123,
        np.broadcast_to(q4[:, :, None, None, None], shape + (1,)),
        np.broadcast_to(q5[..., None, None], shape + (1,)),
        np.broadcast_to(q6[..., None, None], shape + (1,)),
        np.broadcast_to(q7[:, None, None, None, None], shape + (1,)),
    ], axis=-1)
    keep = np.broadcast_to(reachable[..., None, None], shape)
    solutions = solutions[keep & np.all((solutions >= lower) & (solutions <= upper), axis=-1)]
    if len(solutions) == 0:
        return solutions.reshape(0, 7)
    reached = forward_tcp(solutions)
    position_error = np.linalg.norm(reached[:, :3, 3] - base_from_tcp[:3, 3], axis=-1)
    rotation_error = np.abs(reached[:, :3, :3] - base_from_tcp[:3, :3]).max(axis=(-1, -2))
    return solutions[(position_error <= tolerance_m) & (rotation_error <= tolerance_rotation)]
