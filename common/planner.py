"""Grasp planning from raw depth images: the inference API for real robots.

Depth images (metres along each camera's optical axis; 0, NaN or inf = no return) with pinhole
intrinsics (OpenCV camera frame: x right, y down, z forward) and world-from-camera poses are
fused into the scene TSDF (``common.tsdf``), every candidate gripper is encoded from its URDF
spec (``common.gripper_encoding``, cached), the network scores every gripper, opening, rotation
and cell, and the best ``top_k`` valid grasps come back in the world frame.

The world frame is the one the model was trained in: z up, table top at z = 0, the workspace
``scene_grid.x_range`` x ``y_range`` x ``z_range`` (centred on the origin by default); the camera
poses must be expressed in it. A grasp's position is the pose the simulator executes for its cell:
clipped to the square of half-size ``sim.fence_half_extent`` (a cell near the edge of the valid
square is grasped at the fence, as in training) and raised so the closing fingers stay
``sim.table_clearance`` above the table.

Usage::

    planner = GraspPlanner.from_checkpoint("runs/r1/checkpoints/latest.pt")
    grasps = planner.plan([depth], [K], [T_world_cam], grippers=["wsg_50", ("panda_hand", 1.1)])
    best = grasps[0]    # PlannedGrasp: position (3,) m, yaw rad, opening, gripper index/name, score
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from common.calibration import Calibration, CalibrationError
from common.camera import Intrinsics
from common.config import Config
from common.geometry import Transform
from common.gripper import GripperModel, GripperSpec, get_gripper
from common.gripper_encoding import GripperEncoder, gripper_key, spec_tag
from common.network import AdaGraspNet
from common.observation import Observation
from common.policy import action_region, grasp_pose, valid_cells
from common.tsdf import fuse_observation


class PlannerError(ValueError):
    """Bad planner input; the message is one line naming the argument."""


@dataclass(frozen=True)
class PlannedGrasp:
    """One ranked grasp in the world frame."""

    position: np.ndarray
    """(3,) float64 TCP position, world frame, metres: the pose the simulator executes for the action
    (:func:`common.policy.grasp_pose`: x, y clipped to the fence square; z = surface height -
    sim.grasp_depth, raised so that the closing fingertips stay sim.table_clearance above the table)."""
    yaw: float
    """Gripper yaw about +z, radians: its closing axis (TCP x) turned from world x towards y."""
    opening: float
    """Initial opening in [0, 1]."""
    gripper: int
    """Index into the ``grippers`` argument of :meth:`GraspPlanner.plan`."""
    gripper_name: str
    """Name of that gripper."""
    score: float
    """Predicted success probability."""
    action: tuple[int, int, int, int, int]
    """(i, j, k, s, g) on the model's grids."""


def _as_camera(intrinsics, depth: np.ndarray, n: int) -> Intrinsics:
    if isinstance(intrinsics, Intrinsics):
        if intrinsics.shape != depth.shape:
            raise PlannerError(f"intrinsics[{n}]: image {intrinsics.shape} but depths[{n}] is {depth.shape}")
        return intrinsics
    K = np.asarray(intrinsics, dtype=np.float64)
    if K.shape != (3, 3):
        raise PlannerError(f"intrinsics[{n}]: expected common.camera.Intrinsics or a (3, 3) matrix, got shape {K.shape}")
    h, w = depth.shape
    return Intrinsics(width=w, height=h, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])


def _as_pose(pose, n: int) -> Transform:
    if isinstance(pose, Transform):
        return pose
    m = np.asarray(pose, dtype=np.float64)
    if m.shape != (4, 4):
        raise PlannerError(f"camera_poses[{n}]: expected a Transform or a (4, 4) world-from-camera matrix, got {m.shape}")
    return Transform.from_matrix(m)


class GraspPlanner:
    """Ranks top-down grasps of candidate grippers from depth images with a trained model."""

    def __init__(self, model: AdaGraspNet, cfg: Config, encoder: GripperEncoder | None = None) -> None:
        """``model``: the network built from ``cfg`` with its weights; ``encoder``: a gripper encoder
        on ``cfg.gripper_grid`` (default: one with the shared disk cache)."""
        self.model = model.eval()
        self.cfg = cfg
        self.encoder = encoder or GripperEncoder(cfg.gripper_grid)
        self.last_observation: Observation | None = None
        """The fused observation of the last :meth:`plan` call."""
        self.last_probs: np.ndarray | None = None
        """(G, S, R, X, Y) float32 scores of the last :meth:`plan` call (float64 and calibrated if it
        was given a calibration)."""
        self._models: dict[tuple[GripperSpec, float], GripperModel] = {}
        self._reach: dict[tuple[GripperSpec, float, float], float] = {}
        """Metres the fingers sweep below the TCP, per (gripper spec, scale, opening)."""

    def reach(self, spec: GripperSpec, scale: float, opening: float) -> float:
        """How far (m) the fingers of ``spec`` at ``scale`` reach below the TCP at their lowest while
        closing from ``opening`` (:meth:`GripperModel.sweep_depth`, as the simulator raises its
        grasps by), cached per spec (every field of it), scale and opening."""
        key = (spec, float(scale), round(float(opening), 6))
        if key not in self._reach:
            if key[:2] not in self._models:
                self._models[key[:2]] = GripperModel(spec, scale)
            self._reach[key] = self._models[key[:2]].sweep_depth(max_opening=key[2])
        return self._reach[key]

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str | torch.device = "cpu") -> "GraspPlanner":
        """A planner with the model and config of checkpoint ``path``."""
        from common.checkpoint import load_checkpoint

        model, ckpt = load_checkpoint(path, device=device)
        return cls(model, ckpt.cfg)

    def _grippers(self, grippers) -> list[tuple[GripperSpec, float]]:
        out = []
        grippers = [grippers] if isinstance(grippers, (str, Path, GripperSpec)) else list(grippers)
        if not grippers:
            raise PlannerError("grippers: expected at least one gripper (name, spec path, GripperSpec or (gripper, scale))")
        for n, g in enumerate(grippers):
            scale = 1.0
            if isinstance(g, tuple):
                if len(g) != 2:
                    raise PlannerError(f"grippers[{n}]: expected (gripper, scale), got {g!r}")
                g, scale = g
            if isinstance(g, (str, Path)):
                g = get_gripper(str(g))
            if not isinstance(g, GripperSpec):
                raise PlannerError(f"grippers[{n}]: expected a name, a spec path or a GripperSpec, got {type(g).__name__}")
            if not float(scale) > 0:
                raise PlannerError(f"grippers[{n}]: scale must be positive, got {scale!r}")
            out.append((g, float(scale)))
        return out

    def observe(self, depths, intrinsics, camera_poses, obstacle_masks=None) -> Observation:
        """Fuse ``depths`` (per camera (H, W) float m) into an Observation on the model's scene grid."""
        depths = [depths] if isinstance(depths, np.ndarray) and depths.ndim == 2 else list(depths)
        intrinsics = [intrinsics] if isinstance(intrinsics, Intrinsics) or np.ndim(intrinsics) == 2 else list(intrinsics)
        camera_poses = [camera_poses] if isinstance(camera_poses, Transform) or np.ndim(camera_poses) == 2 else list(camera_poses)
        if not depths:
            raise PlannerError("depths: expected at least one depth image")
        if not len(depths) == len(intrinsics) == len(camera_poses):
            raise PlannerError(
                f"depths/intrinsics/camera_poses: one per camera expected, got {len(depths)}, {len(intrinsics)}, {len(camera_poses)}"
            )
        arrays = []
        for n, d in enumerate(depths):
            d = np.asarray(d)
            if not np.issubdtype(d.dtype, np.floating):  # e.g. uint16 millimetres, read as metres
                raise PlannerError(f"depths[{n}]: expected float metres, got dtype {d.dtype} (millimetres: depth / 1000.0)")
            d = d.astype(np.float32, copy=False)
            if d.ndim != 2:
                raise PlannerError(f"depths[{n}]: expected an (H, W) image in metres, got shape {d.shape}")
            arrays.append(d)
        cameras = [(_as_camera(k, d, n), _as_pose(t, n)) for n, (k, d, t) in enumerate(zip(intrinsics, arrays, camera_poses))]
        masks = None
        if obstacle_masks is not None:
            one = isinstance(obstacle_masks, np.ndarray) and obstacle_masks.ndim == 2
            masks = [np.asarray(m, dtype=bool) for m in ([obstacle_masks] if one else obstacle_masks)]
            if len(masks) != len(arrays) or any(m.shape != d.shape for m, d in zip(masks, arrays)):
                raise PlannerError("obstacle_masks: expected one (H, W) mask per depth image, of its shape")
        return fuse_observation(self.cfg.scene_grid, arrays, cameras, masks)

    def plan(
        self,
        depths,
        intrinsics,
        camera_poses,
        grippers,
        openings: tuple[float, ...] | None = None,
        obstacle_masks=None,
        top_k: int = 10,
        min_separation: float = 0.0,
        calibration: Calibration | None = None,
    ) -> list[PlannedGrasp]:
        """Ranked grasps, best first.

        depths: per camera (H, W) float32 m; intrinsics: per camera ``Intrinsics`` or (3, 3) K;
        camera_poses: per camera world-from-camera ``Transform`` or (4, 4) matrix; grippers: names,
        spec paths, ``GripperSpec`` or (gripper, scale) pairs; openings: candidate initial openings
        in [0, 1] (default ``grippers.eval_openings``); obstacle_masks: per camera (H, W) bool, True
        on objects not to be lifted. ``min_separation`` (m): skip grasps whose TCP lies closer
        than this to a better one already kept (0 keeps neighbouring cells). ``calibration``
        (``common.calibration``): map each gripper's scores through the logit shift fitted for its
        name (whatever its scale here) before ranking across grippers; it must cover every gripper
        and come from this planner's checkpoint (not checked here; ``evaluate --calibration`` does).
        """
        if int(top_k) < 1:
            raise PlannerError(f"top_k: expected a positive integer, got {top_k!r}")
        openings = tuple(float(o) for o in (self.cfg.grippers.eval_openings if openings is None else openings))
        if not openings or any(not 0.0 <= o <= 1.0 for o in openings):
            raise PlannerError(f"openings: expected values in [0, 1], got {openings}")
        specs = self._grippers(grippers)
        obs = self.observe(depths, intrinsics, camera_poses, obstacle_masks)
        region = action_region(self.cfg)
        if not (obs.valid & region).any():  # the policy would fall back to every cell
            raise PlannerError(
                "depths/camera_poses: the cameras observe no cell of the action region (empty depth images, or "
                "poses that are not world-from-camera in the OpenCV frame: x right, y down, z forward)"
            )
        encodings = [self.encoder.encode(spec, scale, openings) for spec, scale in specs]
        # the model's kernel cache is keyed by geometry, not name: an edited spec, or another spec
        # of the same name, gets kernels of its own
        keys = [gripper_key(spec_tag(spec), scale, openings) for spec, scale in specs]
        scene = torch.from_numpy(np.stack([obs.tsdf, obs.obstacle]))
        probs = self.model.predict(scene, [torch.from_numpy(e) for e in encodings], keys).cpu().numpy()
        if calibration is not None:
            try:
                probs = calibration.apply(probs, [spec.name for spec, _ in specs])
            except CalibrationError as e:
                raise PlannerError(f"calibration: {e}") from None
        self.last_observation, self.last_probs = obs, probs
        mask = valid_cells(obs, self.cfg, region)
        masked = np.where(mask, probs, -1.0).ravel()
        order = np.argsort(-masked, kind="stable")
        out: list[PlannedGrasp] = []
        for idx in order:
            if masked[idx] < 0 or len(out) >= top_k:
                break
            g, s, k, i, j = (int(v) for v in np.unravel_index(int(idx), probs.shape))
            spec, scale = specs[g]
            position, yaw = grasp_pose(self.cfg, obs.heightmap, i, j, k, self.reach(spec, scale, openings[s]))
            if min_separation > 0 and any(
                p.gripper == g and np.linalg.norm(p.position[:2] - position[:2]) < min_separation for p in out
            ):
                continue
            out.append(PlannedGrasp(position, yaw, openings[s], g, specs[g][0].name, float(probs[g, s, k, i, j]), (i, j, k, s, g)))
        return out
