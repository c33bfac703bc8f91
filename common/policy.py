"""Learned grasp policies: valid-action mask, epsilon-greedy selection, world poses.

A :class:`LearnedPolicy` scores every (opening, rotation, cell) of its grippers with the
network and picks one action ``(i, j, k, s, g)``: scene cell (i along x, j along y), rotation k
(yaw theta_k = 2 pi k / R about +z), opening index s, gripper index g. Modes:

- ``fix-config``: one opening drawn uniformly from the candidates (at evaluation the paper's
  list, ``grippers.eval_openings``); the best cell and rotation for it (only that opening is scored);
- ``fix-gripper``: one gripper; the best opening, rotation and cell;
- ``adagrasp``: several grippers; the best gripper, opening, rotation and cell.

With ``score_shifts`` (``common.calibration``) each gripper's scores are calibrated before the
choice; within one gripper the order of its grasps does not change.

Valid actions (the paper's mask): cells inside the square of half-size ``sim.action_half_extent``
around the grid centre that some camera observed (``obs.valid``), at every rotation and opening;
with ``model.min_surface_height`` > 0 only cells higher than that count. If no cell passes, the
whole square is valid (an empty scene still gets an action, as the random policy does).

Exploration (epsilon-greedy as in the paper): with probability ``epsilon`` the action is drawn
with probability proportional to its predicted success probability over the valid actions,
otherwise it is the valid argmax. The pose of an action (:func:`grasp_pose`): TCP (x, y) at the
cell centre (``common.geometry.cell_to_world``) clipped to the square of half-size
``sim.fence_half_extent``, z = heightmap at the cell minus ``sim.grasp_depth``, clipped to the
table and, where the gripper is known (the simulator, the planner), raised for its fingers' reach;
yaw theta_k.

Call loop::

    policy = LearnedPolicy(model, cfg, [(key, encoding)], mode="fix-gripper", epsilon=0.3)
    action, score = policy.act(obs, openings, rng)       # actors.policies.Policy: (i, j, k, s), score
    choice = policy.last_choice                          # GraspChoice: g, world pose, score
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from common.calibration import apply_shifts
from common.config import Config
from common.geometry import cell_to_world, grid_centre, rotation_angle
from common.network import AdaGraspNet
from common.observation import Observation

MODES = ("fix-config", "fix-gripper", "adagrasp")
"""Selection modes of a learned policy."""


class PolicyError(ValueError):
    """Bad policy input (mode, grippers, openings, checkpoint); one line naming the field."""


@dataclass(frozen=True)
class GraspChoice:
    """One chosen grasp."""

    action: tuple[int, int, int, int, int]
    """(i, j, k, s, g): cell along x and y, rotation index, opening index, gripper index."""
    position: np.ndarray
    """(3,) float64 TCP position in the world frame, metres (:func:`grasp_pose` without the reach:
    the simulator raises z further when the closing fingers would come nearer the table)."""
    yaw: float
    """Gripper yaw theta_k about +z, radians."""
    opening: float
    """Initial opening in [0, 1] (``openings[s]``)."""
    score: float
    """Predicted success probability of the action."""
    explored: bool
    """True if the action came from the exploratory (proportional) branch."""


def action_region(cfg: Config) -> np.ndarray:
    """(X, Y) bool: cells whose centre lies within ``sim.action_half_extent`` of the grid centre."""
    grid = cfg.scene_grid
    X, Y, _ = grid.shape
    xy = cell_to_world(grid, *np.meshgrid(np.arange(X), np.arange(Y), indexing="ij"))
    centre = grid_centre(grid)
    return np.all(np.abs(xy - centre) <= cfg.sim.action_half_extent + 1e-9, axis=-1)


def valid_cells(obs: Observation, cfg: Config, region: np.ndarray | None = None) -> np.ndarray:
    """(X, Y) bool valid-action mask of ``obs`` (see the module docstring)."""
    region = action_region(cfg) if region is None else region
    mask = region & obs.valid
    if cfg.model.min_surface_height > 0:
        mask &= obs.heightmap > cfg.model.min_surface_height
    return mask if mask.any() else region.copy()


def grasp_pose(
    cfg: Config, heightmap: np.ndarray, i: int, j: int, k: int, reach: float | None = None
) -> tuple[np.ndarray, float]:
    """TCP position (3,) float64 world metres and yaw (rad) of a grasp at cell (i, j), rotation k:
    the pose the simulator executes. The centre is clipped to the fence square
    (``sim.fence_half_extent``; the paper clips to its workspace bounds); z is the cell's surface
    ``sim.grasp_depth`` deep, not below the table, and, given ``reach`` (m the fingers sweep below
    the TCP while closing from the opening, :meth:`GripperModel.sweep_depth`), high enough that
    the fingertips stay ``sim.table_clearance`` above the table.

    heightmap: (X, Y) float32 metres above the table (the observation's).
    """
    grid = cfg.scene_grid
    centre = grid_centre(grid)
    lim = cfg.sim.fence_half_extent
    xy = np.clip(cell_to_world(grid, i, j), centre - lim, centre + lim)
    z = max(float(heightmap[i, j]) - cfg.sim.grasp_depth, grid.z_range[0])
    if reach is not None:
        z = max(z, grid.z_range[0] + reach + cfg.sim.table_clearance)
    return np.array([xy[0], xy[1], z]), rotation_angle(int(k), cfg.model.rotations)


def select(
    probs: np.ndarray, mask: np.ndarray, epsilon: float, rng: np.random.Generator
) -> tuple[tuple[int, ...], float, bool]:
    """Epsilon-greedy choice over ``probs`` (..., X, Y) float restricted to cells where ``mask``
    (X, Y) bool is True: with probability ``epsilon`` an index drawn proportionally to ``probs``,
    else the argmax. Returns (index tuple into probs, its probability, explored)."""
    assert probs.shape[-2:] == mask.shape and mask.any(), (probs.shape, mask.shape)
    masked = np.where(mask, probs, 0.0).astype(np.float64)
    flat = masked.ravel()
    explored = bool(rng.random() < epsilon)
    total = flat.sum()
    if explored and total > 0:
        idx = int(rng.choice(flat.size, p=flat / total))
    elif explored:
        cells = np.flatnonzero(np.broadcast_to(mask, probs.shape).ravel())
        idx = int(rng.choice(cells))
    else:
        idx = int(np.argmax(np.where(np.broadcast_to(mask, probs.shape), masked, -1.0).ravel()))
    index = tuple(int(v) for v in np.unravel_index(idx, probs.shape))
    return index, float(probs[index]), explored


class LearnedPolicy:
    """A network-driven policy implementing ``actors.policies.Policy`` (``act``), plus ``choose``."""

    def __init__(
        self,
        model: AdaGraspNet,
        cfg: Config,
        grippers: list[tuple[str, np.ndarray]] | None = None,
        mode: str = "fix-gripper",
        epsilon: float = 0.0,
        score_shifts: np.ndarray | None = None,
    ) -> None:
        """``grippers``: (key, encoding (S, 2, gX, gY, gZ) float32) per candidate gripper, S =
        len(openings) passed to ``act``; may be set later with :meth:`set_grippers`.
        ``score_shifts``: (G,) float logits added to each gripper's score logits before choosing
        (``common.calibration``; None: the network's scores as they are)."""
        if mode not in MODES:
            raise PolicyError(f"mode: expected one of {list(MODES)}, got {mode!r}")
        if not 0.0 <= epsilon <= 1.0:
            raise PolicyError(f"epsilon: expected a value in [0, 1], got {epsilon!r}")
        self.model = model.eval() if model.training else model
        self.cfg = cfg
        self.mode = mode
        self.epsilon = float(epsilon)
        self.name = f"learned-{mode}"
        self.region = action_region(cfg)
        self.grippers: list[tuple[str, np.ndarray]] = []
        self.last_choice: GraspChoice | None = None
        self.last_probs: np.ndarray | None = None
        """(G, S, R, X, Y) float32 scores of the last call (only the drawn opening for fix-config);
        float64 and calibrated when ``score_shifts`` is set."""
        self.score_shifts = None if score_shifts is None else np.asarray(score_shifts, dtype=np.float64)
        """(G,) float64 logit shift per gripper (in the order of ``grippers``), or None."""
        if grippers is not None:
            self.set_grippers(grippers)

    def set_grippers(self, grippers: list[tuple[str, np.ndarray]]) -> None:
        """Candidate grippers: (key, encoding (S, 2, gX, gY, gZ) float32) each; with ``score_shifts``
        set, as many as it has shifts."""
        if not grippers:
            raise PolicyError("grippers: expected at least one (key, encoding) pair")
        if self.score_shifts is not None and self.score_shifts.shape != (len(grippers),):
            raise PolicyError(
                f"score_shifts: expected one per gripper ({len(grippers)}), got shape {self.score_shifts.shape}"
            )
        if self.mode != "adagrasp" and len(grippers) != 1:
            raise PolicyError(f"grippers: mode {self.mode} takes one gripper, got {len(grippers)}")
        for n, (key, enc) in enumerate(grippers):
            enc = np.asarray(enc)
            shape = tuple(self.model.gripper_shape)
            if enc.dtype != np.float32 or enc.ndim != 5 or enc.shape[1] != 2 or enc.shape[2:] != shape:
                raise PolicyError(f"grippers[{n}] ({key}): expected (S, 2, {shape}) float32, got {enc.shape} {enc.dtype}")
        self.grippers = [(str(k), np.asarray(e)) for k, e in grippers]

    def scores(self, obs: Observation, openings: tuple[float, ...], s_only: int | None = None) -> np.ndarray:
        """(G, S, R, X, Y) float32 success probabilities; with ``s_only`` just that opening (S = 1)."""
        if not self.grippers:
            raise PolicyError("grippers: none set; pass them to the constructor or set_grippers")
        for key, enc in self.grippers:
            if enc.shape[0] != len(openings):
                raise PolicyError(f"openings: {len(openings)} candidates but gripper {key} has {enc.shape[0]} encodings")
        scene = np.stack([obs.tsdf, obs.obstacle])
        encs = [enc if s_only is None else enc[s_only : s_only + 1] for _, enc in self.grippers]
        keys = [key if s_only is None else f"{key}#{s_only}" for key, _ in self.grippers]
        return self.model.predict(torch.from_numpy(scene), [torch.from_numpy(e) for e in encs], keys).cpu().numpy()

    def choose(self, obs: Observation, openings: tuple[float, ...], rng: np.random.Generator) -> GraspChoice:
        """The action for ``obs`` with its world pose and score."""
        obs.validate()
        if len(openings) == 0:
            raise PolicyError("openings: expected at least one candidate opening")
        mask = valid_cells(obs, self.cfg, self.region)
        if self.mode == "fix-config":
            s_fixed = int(rng.integers(len(openings)))
            probs = self.scores(obs, openings, s_only=s_fixed)
            if self.score_shifts is not None:
                probs = self._calibrated(probs)
            (g, _, k, i, j), score, explored = select(probs, mask, self.epsilon, rng)
            s = s_fixed
        else:
            probs = self.scores(obs, openings)
            if self.score_shifts is not None:
                probs = self._calibrated(probs)
            (g, s, k, i, j), score, explored = select(probs, mask, self.epsilon, rng)
        self.last_probs = probs
        position, yaw = grasp_pose(self.cfg, obs.heightmap, i, j, k)
        choice = GraspChoice((i, j, k, s, g), position, yaw, float(openings[s]), score, explored)
        self.last_choice = choice
        return choice

    def _calibrated(self, probs: np.ndarray) -> np.ndarray:
        if self.score_shifts.shape != (len(self.grippers),):
            raise PolicyError(
                f"score_shifts: expected one per gripper ({len(self.grippers)}), got shape {self.score_shifts.shape}"
            )
        return apply_shifts(probs, self.score_shifts)

    def act(self, obs: Observation, openings: tuple[float, ...], rng: np.random.Generator):
        """``actors.policies.Policy``: ((i, j, k, s), score); the gripper index is in ``last_choice``."""
        choice = self.choose(obs, openings, rng)
        return choice.action[:4], choice.score

    @classmethod
    def from_checkpoint(
        cls,
        path: str | Path,
        cfg: Config | None = None,
        grippers: list[tuple[str, np.ndarray]] | None = None,
        mode: str = "fix-gripper",
        epsilon: float = 0.0,
        device: str = "cpu",
        score_shifts: np.ndarray | None = None,
    ) -> "LearnedPolicy":
        """A policy running the model of checkpoint ``path``. With ``cfg`` given (the run's), its
        grids must match the checkpoint's; the policy uses ``cfg`` for the action square and poses."""
        from common.checkpoint import load_checkpoint

        model, ckpt = load_checkpoint(path, device=device)
        if cfg is None:
            cfg = ckpt.cfg
        for section in ("scene_grid", "gripper_grid"):
            mine, theirs = getattr(cfg, section), getattr(ckpt.cfg, section)
            if mine != theirs:
                raise PolicyError(f"{path}: {section}: the checkpoint's grid {theirs} differs from the run's {mine}")
        if cfg.model.rotations != ckpt.cfg.model.rotations:
            raise PolicyError(f"{path}: model.rotations: checkpoint {ckpt.cfg.model.rotations}, run {cfg.model.rotations}")
        return cls(model, cfg, grippers, mode=mode, epsilon=epsilon, score_shifts=score_shifts)
