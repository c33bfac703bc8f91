"""Synthetic trials with the shapes, dtypes and value ranges of simulated ones.

For replay tests and for developing against the record contract without physics. The scene is
a table with boxes, cylinders and spheres seen by one top-down camera: each column's surface
height comes from the objects' analytic shapes, and the TSDF is the vertical signed distance
to that surface, divided by the truncation and clipped to [-1, 1] (voxels more than the
truncation behind the surface read +1, as in common.tsdf). The gripper encoding is the
exact signed distance to a parallel-jaw hand (palm + two fingers) at each opening and closed.

Usage::

    rng = np.random.default_rng(0)
    trial = synthetic_trial(rng, cfg.scene_grid, cfg.gripper_grid, n_objects=5, episode_id=3)
    trial.validate()
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from common.config import Config, GripperGridConfig, SceneGridConfig, load_config
from common.geometry import voxel_centers
from common.observation import Observation, Trial, TrialMeta

SHAPES = ("box", "cylinder", "sphere")
"""Primitive kinds the synthetic scenes are built from."""


def _object_heights(rng: np.random.Generator, xy: np.ndarray, n: int, half_extent: float) -> list[np.ndarray]:
    """Top-surface height (X, Y) float32 metres of ``n`` random primitives; 0 outside each footprint."""
    tops = []
    for _ in range(n):
        kind = SHAPES[rng.integers(len(SHAPES))]
        centre = rng.uniform(-0.7 * half_extent, 0.7 * half_extent, size=2)
        d = xy - centre
        if kind == "box":
            yaw = rng.uniform(0, np.pi)
            c, s = np.cos(yaw), np.sin(yaw)
            u = np.abs(c * d[..., 0] + s * d[..., 1])
            v = np.abs(-s * d[..., 0] + c * d[..., 1])
            hx, hy = rng.uniform(0.01, 0.04, size=2)
            height = rng.uniform(0.02, 0.09)
            top = np.where((u <= hx) & (v <= hy), height, 0.0)
        elif kind == "cylinder":
            r = rng.uniform(0.012, 0.04)
            height = rng.uniform(0.02, 0.1)
            top = np.where(np.hypot(d[..., 0], d[..., 1]) <= r, height, 0.0)
        else:
            r = rng.uniform(0.015, 0.04)
            rho2 = (d**2).sum(-1)
            top = np.where(rho2 <= r * r, r + np.sqrt(np.maximum(r * r - rho2, 0.0)), 0.0)
        tops.append(top.astype(np.float32))
    return tops


def synthetic_observation(
    rng: np.random.Generator, grid: SceneGridConfig, n_objects: int, n_obstacles: int = 0
) -> Observation:
    """A tabletop observation with ``n_objects`` targets and ``n_obstacles`` obstacles."""
    shape = grid.shape
    centers = voxel_centers(grid.origin, grid.voxel_size, shape)
    xy = centers[:, :, 0, :2]
    half_extent = 0.5 * (grid.x_range[1] - grid.x_range[0])
    targets = _object_heights(rng, xy, n_objects, half_extent)
    obstacles = _object_heights(rng, xy, n_obstacles, half_extent)
    stack = np.stack(targets + obstacles + [np.zeros(shape[:2], np.float32)])
    heightmap = stack.max(0).astype(np.float32)
    top_is_obstacle = np.zeros(shape[:2], bool)
    if n_obstacles:
        top_is_obstacle = (np.argmax(stack, 0) >= n_objects) & (np.argmax(stack, 0) < n_objects + n_obstacles)
    z = centers[0, 0, :, 2]
    signed = (z[None, None, :] - heightmap[..., None]) / grid.truncation
    # like common.tsdf: voxels further than the truncation behind the surface are unobserved, read as +1
    tsdf = np.where(signed < -1.0, 1.0, np.clip(signed, -1.0, 1.0)).astype(np.float32)
    band = np.abs(signed) < 1.0
    obstacle = (band & top_is_obstacle[..., None]).astype(np.float32)
    valid = np.ones(shape[:2], bool)
    return Observation(tsdf=tsdf, obstacle=obstacle, heightmap=heightmap, valid=valid).validate()


def _box_sdf(points: np.ndarray, centre, half) -> np.ndarray:
    """Exact signed distance (metres) from points (..., 3) to an axis-aligned box."""
    q = np.abs(points - np.asarray(centre)) - np.asarray(half)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(q.max(-1), 0.0)
    return outside + inside


def synthetic_gripper_encoding(
    grid: GripperGridConfig, openings: tuple[float, ...], scale: float = 1.0, finger_width: float = 0.02
) -> np.ndarray:
    """(S, 2, gX, gY, gZ) float32 TSDF/truncation of a parallel-jaw hand at each opening and closed.

    TCP frame: origin at the grasp centre, fingers along -z, jaws closing along x.
    """
    gx, gy, gz = grid.shape
    origin = (-0.5 * gx * grid.voxel_size, -0.5 * gy * grid.voxel_size, -grid.tcp_height)
    pts = voxel_centers(origin, grid.voxel_size, grid.shape)
    finger_len, thick, palm_h = 0.05 * scale, 0.008 * scale, 0.015 * scale
    max_half_gap = 0.04 * scale

    def hand(gap: float) -> np.ndarray:
        palm_half = (max_half_gap + thick, finger_width * scale, palm_h / 2)
        palm = _box_sdf(pts, (0.0, 0.0, finger_len + palm_h / 2), palm_half)
        finger_half = (thick / 2, finger_width * scale / 2, finger_len / 2)
        fingers = [
            _box_sdf(pts, (sx * (gap + thick / 2), 0.0, finger_len / 2), finger_half)
            for sx in (-1.0, 1.0)
        ]
        d = np.minimum(palm, np.minimum(*fingers))
        return np.clip(d / grid.truncation, -1.0, 1.0).astype(np.float32)

    closed = hand(0.0)
    enc = np.stack([np.stack([hand(o * max_half_gap), closed]) for o in openings])
    assert enc.shape == (len(openings), 2, gx, gy, gz)
    return enc


def synthetic_trial(
    rng: np.random.Generator,
    scene_grid: SceneGridConfig,
    gripper_grid: GripperGridConfig,
    n_objects: int = 1,
    n_obstacles: int = 0,
    *,
    episode_id: int = 0,
    step: int = 0,
    actor_id: int = 0,
    label: bool | None = None,
    score: float | None = None,
    gripper: str = "synthetic_parallel",
    scale: float | None = None,
    openings: tuple[float, ...] | None = None,
    encoding: np.ndarray | None = None,
    rotations: int = 16,
    policy_version: int = 0,
    wall_time: float | None = None,
) -> Trial:
    """A complete, valid Trial; pass ``encoding`` to reuse a precomputed (S, 2, gX, gY, gZ) table."""
    obs = synthetic_observation(rng, scene_grid, n_objects, n_obstacles)
    scale = float(rng.uniform(0.8, 1.2)) if scale is None else float(scale)
    if openings is None:
        openings = tuple(float(o) for o in np.sort(rng.uniform(0.5, 1.0, size=5)))
    if encoding is None:
        encoding = synthetic_gripper_encoding(gripper_grid, openings, scale)
    x, y, _ = scene_grid.shape
    action = (
        int(rng.integers(x)), int(rng.integers(y)), int(rng.integers(rotations)), int(rng.integers(len(openings)))
    )
    scene = "single" if n_objects == 1 and not n_obstacles else ("obstacle" if n_obstacles else "multi")
    meta = TrialMeta(
        episode_id=episode_id,
        step=step,
        scene=scene,
        object_set="synthetic",
        object_ids=tuple(
            f"synthetic/{SHAPES[int(i)]}_{int(i)}" for i in rng.integers(0, 3, size=n_objects + n_obstacles)
        ),
        gripper=gripper,
        gripper_scale=scale,
        openings=tuple(openings),
        cameras=1,
        actor_id=actor_id,
        policy_version=policy_version,
        seed=int(rng.integers(2**31)),
        wall_time=float(rng.uniform(1.7e9, 1.8e9)) if wall_time is None else wall_time,
    )
    key = f"{gripper}|{scale!r}|{','.join(repr(o) for o in openings)}"
    return Trial(
        observation=obs,
        gripper_key=key,
        gripper_encoding=encoding,
        action=action,
        label=bool(rng.random() < 0.5) if label is None else bool(label),
        score=float(rng.random()) if score is None else float(score),
        meta=meta,
    ).validate()


def small_config(capacity: int = 16, shards: int = 1, chunk: int = 4, levels: int = 127) -> Config:
    """The default config on a 48 x 48 x 16 scene grid and a 16 x 16 x 8 gripper grid (8 mm voxels):
    the code paths of paper scale at a fraction of the cost, for tests."""
    return load_config(
        "default",
        overrides=[
            "scene_grid.voxel_size=0.008",
            "gripper_grid.shape=[16, 16, 8]",
            f"replay.capacity={capacity}",
            f"replay.shards={shards}",
            f"replay.chunk_trials={chunk}",
            f"replay.tsdf_levels={levels}",
        ],
    )


def numbered_trial(cfg: Config, i: int, rng: np.random.Generator | None = None, **kw) -> Trial:
    """Trial number ``i``, rebuilt identically from ``default_rng(i)`` unless ``rng`` is given."""
    rng = np.random.default_rng(i) if rng is None else rng
    kw.setdefault("episode_id", i)
    n_objects = kw.pop("n_objects", 1)
    n_obstacles = kw.pop("n_obstacles", 0)
    return synthetic_trial(rng, cfg.scene_grid, cfg.gripper_grid, n_objects, n_obstacles, **kw)


def random_actions(
    batch: int, grid_xy: tuple[int, int], rotations: int, margin: int, generator: torch.Generator
) -> torch.Tensor:
    """(batch, 4) int64 actions (i, j, k, s): cells (i, j) uniform over the scene grid
    ``grid_xy`` = (X, Y) at least ``margin`` cells from its edge, rotation k uniform in
    [0, rotations), opening index s = 0; drawn from ``generator`` in the order i, j, k."""
    X, Y = grid_xy
    assert 0 <= margin and 2 * margin < min(X, Y), (margin, grid_xy)
    return torch.stack(
        [
            torch.randint(margin, X - margin, (batch,), generator=generator),
            torch.randint(margin, Y - margin, (batch,), generator=generator),
            torch.randint(rotations, (batch,), generator=generator),
            torch.zeros(batch, dtype=torch.int64),
        ],
        dim=1,
    )


class FixedBatchReplay:
    """The part of the replay client a :class:`learner.learner.Learner` calls, serving one fixed
    batch: for learner tests and benchmarks that leave replay reads out.

    scene (B, 2, X, Y, Z) float32, gripper (B, 2, gX, gY, gZ) float32, action (B, 4) int64
    (i, j, k, s), label (B,) float32 (1 = success), all on the CPU as the client returns them.
    ``sample(B)`` returns that batch every time (with ``index`` (B, 2) int64 = (0, b) and
    ``score`` zeros); ``update_scores`` keeps every call's scores in ``scores``.
    """

    def __init__(self, scene: torch.Tensor, gripper: torch.Tensor, action: torch.Tensor, label: torch.Tensor):
        b = scene.shape[0]
        assert scene.dim() == 5 and gripper.dim() == 5 and gripper.shape[0] == b, (scene.shape, gripper.shape)
        assert action.shape == (b, 4) and label.shape == (b,), (action.shape, label.shape)
        self.batch = SimpleNamespace(
            scene=scene,
            gripper=gripper,
            action=action,
            label=label,
            score=torch.zeros(b),
            index=torch.stack([torch.zeros(b, dtype=torch.int64), torch.arange(b)], dim=1),
        )
        self.scores: list[np.ndarray] = []

    def sample(self, batch_size: int) -> SimpleNamespace:
        fixed = self.batch.scene.shape[0]
        assert batch_size == fixed, f"sample: batch {batch_size}, fixed batch {fixed}"
        return self.batch

    def update_scores(self, index, scores) -> None:
        assert len(index) == len(scores), (len(index), len(scores))
        self.scores.append(np.asarray(scores))
