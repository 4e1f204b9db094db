"""Rigid poses: the project's one convention for positions and rotations.

Convention (used everywhere inside the project):

- Quaternions are unit quaternions written **w first**: ``quat_wxyz = (w, x, y, z)``, with ``w >= 0`` after
  normalisation so that each rotation has one written form.
- A :class:`Pose` named ``a_from_b`` (Drake's ``X_AB``) maps coordinates in frame ``b`` to frame ``a``:
  ``p_a = a_from_b.apply(p_b) = R @ p_b + position``. Composition reads left to right:
  ``world_from_part = world_from_table @ table_from_part``.
- Positions are metres unless a name says otherwise (for example ``_norm`` for the perception module's
  normalised units).

Conversions to other libraries happen only at their edges, through the functions at the end of this module:
PyBullet (x-first quaternions), python-fcl (w-first, ``fcl.Transform``), scipy (x-first).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Pose",
    "AXIS_ROTATIONS",
    "quat_normalize",
    "quat_multiply",
    "quat_conjugate",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_angle_rad",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
]

_UNIT_TOLERANCE = 1e-3


def _axis_rotations() -> np.ndarray:
    """(24, 3, 3): the proper rotations that map the coordinate axes onto themselves (signed permutations, det +1)."""
    matrices = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[list(order), range(3)] = signs
            if np.linalg.det(matrix) > 0:
                matrices.append(matrix)
    return np.array(matrices)


AXIS_ROTATIONS = _axis_rotations()


def quat_normalize(quat_wxyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """Return ``quat_wxyz`` scaled to unit norm with ``w >= 0``. Raises ``ValueError`` on a zero or NaN input."""
    q = np.asarray(quat_wxyz, dtype=np.float64).reshape(4)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"quaternion {q.tolist()} cannot be normalised (zero or not finite)")
    q = q / norm
    return -q if q[0] < 0 else q


def quat_conjugate(quat_wxyz: np.ndarray) -> np.ndarray:
    """Inverse rotation of a unit quaternion (w first)."""
    q = np.asarray(quat_wxyz, dtype=np.float64)
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_multiply(q1_wxyz: np.ndarray, q2_wxyz: np.ndarray) -> np.ndarray:
    """Hamilton product ``q1 * q2`` (w first): the rotation ``q2`` followed by ``q1``."""
    w1, x1, y1, z1 = np.asarray(q1_wxyz, dtype=np.float64)
    w2, x2, y2, z2 = np.asarray(q2_wxyz, dtype=np.float64)
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def quat_to_matrix(quat_wxyz: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of a quaternion (w first; normalised here)."""
    w, x, y, z = quat_normalize(quat_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w first, ``w >= 0``) of a (3, 3) rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"rotation matrix must have shape (3, 3), got {m.shape}")
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return quat_normalize(q)


def quat_angle_rad(q1_wxyz: np.ndarray, q2_wxyz: np.ndarray) -> float:
    """Angle in radians, in [0, pi], of the rotation taking ``q1`` to ``q2``."""
    dot = abs(float(np.dot(quat_normalize(q1_wxyz), quat_normalize(q2_wxyz))))
    return 2.0 * float(np.arccos(min(1.0, dot)))


def quat_wxyz_to_xyzw(quat_wxyz: Sequence[float]) -> tuple[float, float, float, float]:
    """PyBullet/scipy edge: w-first to x-first."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    return (x, y, z, w)


def quat_xyzw_to_wxyz(quat_xyzw: Sequence[float]) -> np.ndarray:
    """PyBullet/scipy edge: x-first to w-first."""
    x, y, z, w = (float(v) for v in quat_xyzw)
    return np.array([w, x, y, z])


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``a_from_b``: ``p_a = R(quat_wxyz) @ p_b + position``.

    position: (3,) float64, metres unless the variable name says otherwise.
    quat_wxyz: (4,) float64, unit quaternion, w first, w >= 0.
    """

    position: np.ndarray
    quat_wxyz: np.ndarray
    _rotation: np.ndarray = field(init=False, repr=False, compare=False)
    _key: tuple | None = field(init=False, repr=False, compare=False, default=None)

    def __post_init__(self) -> None:
        position = np.asarray(self.position, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(position)):
            raise ValueError(f"pose position {position.tolist()} is not finite")
        object.__setattr__(self, "position", position)
        object.__setattr__(self, "quat_wxyz", quat_normalize(self.quat_wxyz))
        rotation = quat_to_matrix(self.quat_wxyz)
        rotation.flags.writeable = False
        object.__setattr__(self, "_rotation", rotation)  # computed once: poses are immutable

    # --- construction -------------------------------------------------------------------------------------
    @staticmethod
    def identity() -> Pose:
        return Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))

    @staticmethod
    def from_matrix(matrix: np.ndarray) -> Pose:
        """From a (4, 4) homogeneous transform. The rotation block must be a rotation (orthonormal, det +1)."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"pose matrix must have shape (4, 4), got {m.shape}")
        rotation = m[:3, :3]
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
            raise ValueError("pose matrix rotation block is not a proper rotation")
        return Pose(m[:3, 3], matrix_to_quat(rotation))

    @staticmethod
    def from_rotation(rotation: np.ndarray, position: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0)) -> Pose:
        return Pose(np.asarray(position, dtype=np.float64), matrix_to_quat(rotation))

    @staticmethod
    def from_checked_quat(position: Sequence[float], quat_wxyz: Sequence[float], tolerance: float = 1e-3) -> Pose:
        """Like the constructor, but refuses a quaternion whose norm differs from 1 by more than ``tolerance``
        (user input should be unit already; a silent renormalisation would hide a malformed file)."""
        q = np.asarray(quat_wxyz, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)):
            raise ValueError(f"quaternion {list(quat_wxyz)} must be 4 finite numbers (w, x, y, z)")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > tolerance:
            raise ValueError(f"quaternion {q.tolist()} has norm {norm:.6f}, not 1 (tolerance {tolerance})")
        return Pose(np.asarray(position, dtype=np.float64), q)

    def key(self) -> tuple:
        """The pose as a hashable tuple: position and quaternion rounded to 1e-9 (computed once: planners look
        the same pose up hundreds of thousands of times)."""
        if self._key is None:
            object.__setattr__(self, "_key", (tuple(np.round(self.position, 9).tolist()),
                                              tuple(np.round(self.quat_wxyz, 9).tolist())))
        return self._key

    # --- algebra ------------------------------------------------------------------------------------------
    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation matrix (read-only)."""
        return self._rotation

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous transform."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.position
        return m

    def __matmul__(self, other: Pose) -> Pose:
        """``a_from_b @ b_from_c -> a_from_c``."""
        if not isinstance(other, Pose):
            return NotImplemented
        return Pose(
            self.rotation @ other.position + self.position,
            quat_multiply(self.quat_wxyz, other.quat_wxyz),
        )

    def inverse(self) -> Pose:
        """``a_from_b.inverse() -> b_from_a``."""
        rotation_t = self.rotation.T
        return Pose(-rotation_t @ self.position, quat_conjugate(self.quat_wxyz))

    def apply(self, points_b: np.ndarray) -> np.ndarray:
        """Map points (3,) or (N, 3) from frame b to frame a."""
        pts = np.asarray(points_b, dtype=np.float64)
        return pts @ self.rotation.T + self.position

    def distance(self, other: Pose) -> tuple[float, float]:
        """(translation distance in the position unit, rotation angle in radians) between two poses."""
        return float(np.linalg.norm(self.position - other.position)), quat_angle_rad(self.quat_wxyz, other.quat_wxyz)

    def is_close(self, other: Pose, atol_position: float = 1e-9, atol_angle_rad: float = 1e-7) -> bool:
        dp, da = self.distance(other)
        return dp <= atol_position and da <= atol_angle_rad

    # --- library edges -------------------------------------------------------------------------------------
    def to_pybullet(self) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """(position, quaternion x-first) as PyBullet takes them."""
        return tuple(float(v) for v in self.position), quat_wxyz_to_xyzw(self.quat_wxyz)

    @staticmethod
    def from_pybullet(position: Sequence[float], quat_xyzw: Sequence[float]) -> Pose:
        """From PyBullet's (position, quaternion x-first)."""
        return Pose(np.asarray(position, dtype=np.float64), quat_xyzw_to_wxyz(quat_xyzw))

    def to_fcl(self):
        """An ``fcl.Transform`` (python-fcl takes quaternions w first)."""
        import fcl

        return fcl.Transform(self.quat_wxyz.copy(), self.position.copy())

    @staticmethod
    def from_fcl(transform) -> Pose:
        return Pose(np.asarray(transform.getTranslation()), np.asarray(transform.getQuatRotation()))

    def to_dict(self) -> dict:
        """The assembly-folder JSON form: ``{"position": [x, y, z], "quat_wxyz": [w, x, y, z]}``."""
        return {
            "position": [round(float(v), 9) for v in self.position],
            "quat_wxyz": [round(float(v), 9) for v in self.quat_wxyz],
        }

    def __repr__(self) -> str:
        p = ", ".join(f"{v:.4f}" for v in self.position)
        q = ", ".join(f"{v:.4f}" for v in self.quat_wxyz)
        return f"Pose(position=[{p}], quat_wxyz=[{q}])"
