"""Rigid transforms named by their frames, and scene-grid index <-> world conversions.

Convention: ``T_a_b`` maps points expressed in frame b into frame a, so
``T_world_tcp = T_world_body * T_body_tcp`` and ``p_world = T_world_tcp.apply(p_tcp)``.
World frame: z up, table top at z = 0, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.config import SceneGridConfig


@dataclass(frozen=True)
class Transform:
    """A rigid transform: rotation (3, 3) float64 and translation (3,) float64 in metres."""

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation, dtype=np.float64)
        assert r.shape == (3, 3), f"rotation must be (3, 3), got {r.shape}"
        assert t.shape == (3,), f"translation must be (3,), got {t.shape}"
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @staticmethod
    def identity() -> "Transform":
        return Transform(np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(m: np.ndarray) -> "Transform":
        """From a (4, 4) homogeneous matrix."""
        m = np.asarray(m, dtype=np.float64)
        assert m.shape == (4, 4), f"expected (4, 4), got {m.shape}"
        return Transform(m[:3, :3], m[:3, 3])

    @staticmethod
    def from_quat(quat_xyzw, translation) -> "Transform":
        """From a PyBullet-style quaternion (x, y, z, w) and a translation (3,) in metres."""
        x, y, z, w = np.asarray(quat_xyzw, dtype=np.float64) / np.linalg.norm(quat_xyzw)
        r = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        return Transform(r, translation)

    @staticmethod
    def from_yaw(yaw: float, translation=(0.0, 0.0, 0.0)) -> "Transform":
        """Rotation by ``yaw`` radians about +z, then translation (3,) in metres."""
        c, s = np.cos(yaw), np.sin(yaw)
        return Transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), translation)

    def as_matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    def as_quat(self) -> np.ndarray:
        """Rotation as a quaternion (x, y, z, w), float64."""
        r = self.rotation
        tr = np.trace(r)
        if tr > 0:
            s = np.sqrt(tr + 1.0) * 2
            q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
        elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
            s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
            q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
        elif r[1, 1] > r[2, 2]:
            s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
            q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
        else:
            s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
            q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
        q = np.asarray(q)
        return q / np.linalg.norm(q)

    def inverse(self) -> "Transform":
        rt = self.rotation.T
        return Transform(rt, -rt @ self.translation)

    def __mul__(self, other: "Transform") -> "Transform":
        return Transform(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points (..., 3) metres from the source frame into the target frame."""
        points = np.asarray(points, dtype=np.float64)
        assert points.shape[-1] == 3, f"points must end in 3, got {points.shape}"
        return points @ self.rotation.T + self.translation


def rotation_angle(k: int, rotations: int) -> float:
    """Yaw (rad) of rotation index k of R: theta_k = 2 pi k / R."""
    return 2.0 * np.pi * k / rotations


def grid_centre(grid: SceneGridConfig) -> np.ndarray:
    """(2,) float64 world (x, y) in metres of the scene grid's centre (the action and fence squares'
    centre)."""
    return np.array([np.mean(grid.x_range), np.mean(grid.y_range)])


def cell_to_world(grid: SceneGridConfig, i, j) -> np.ndarray:
    """World (x, y) in metres of the centre of scene cell (i, j); returns (..., 2) float64.

    Index i runs along world x, j along world y.
    """
    i = np.asarray(i, dtype=np.float64)
    j = np.asarray(j, dtype=np.float64)
    x = grid.x_range[0] + (i + 0.5) * grid.voxel_size
    y = grid.y_range[0] + (j + 0.5) * grid.voxel_size
    return np.stack([x, y], axis=-1)


def world_to_cell(grid: SceneGridConfig, x, y) -> np.ndarray:
    """Scene cell (i, j) int64 (..., 2) containing world (x, y) metres; may fall outside the grid."""
    i = np.floor((np.asarray(x, dtype=np.float64) - grid.x_range[0]) / grid.voxel_size)
    j = np.floor((np.asarray(y, dtype=np.float64) - grid.y_range[0]) / grid.voxel_size)
    return np.stack([i, j], axis=-1).astype(np.int64)


def voxel_centers(origin, voxel_size: float, shape) -> np.ndarray:
    """World coordinates (X, Y, Z, 3) float64 metres of the voxel centres of a grid whose
    corner (voxel (0, 0, 0)'s lower corner) sits at ``origin``."""
    axes = [origin[d] + (np.arange(shape[d]) + 0.5) * voxel_size for d in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
