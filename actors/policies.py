"""Grasp policies: the :class:`Policy` protocol, two scripted baselines, and :func:`make_policy`.

A policy maps an observation to one action of the contract in ``actors.grasp``:
``act(obs, openings, rng) -> ((i, j, k, s), score)`` with cell (i, j) of the scene grid, rotation
k of R, opening index s into ``openings`` and a score in [0, 1] (the predicted success
probability; scripted policies return 0.5). A learned policy (common.policy) implements the same
method.

- ``random``: uniform over the valid cells, rotations and openings. As in the paper's code, the
  valid cells are those of the action square (``sim.action_half_extent`` around the grid centre,
  the paper's valid bounds) that some camera observed -- not only cells showing an object.
- ``heuristic``: a scripted top-down grasp. Cells higher than ``min_height`` that are observed and
  not obstacle form blobs (8-connected); one blob of at least ``min_cells`` cells is picked at
  random, the grasp goes to its centroid, closing across the blob's minor axis (PCA of the cell
  centres), with the largest opening. With no blob it falls back to a random action.

Usage::

    policy = make_policy("heuristic", cfg)
    action, score = policy.act(obs, openings=(0.5, 0.75, 1.0), rng=np.random.default_rng(0))
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from scipy import ndimage

from common.config import Config
from common.geometry import cell_to_world, grid_centre, world_to_cell
from common.observation import Observation

POLICY_NAMES = ("random", "heuristic")
"""Policies :func:`make_policy` builds."""
SCRIPTED_SCORE = 0.5
"""Score scripted policies report for their actions."""


@runtime_checkable
class Policy(Protocol):
    """Chooses one grasp per observation."""

    name: str
    """Short name, used in logs and summaries."""

    def act(
        self, obs: Observation, openings: tuple[float, ...], rng: np.random.Generator
    ) -> tuple[tuple[int, int, int, int], float]:
        """Action (i, j, k, s) and its score in [0, 1] for ``obs`` given the candidate ``openings``."""
        ...


def _check_inputs(obs: Observation, openings: tuple[float, ...], shape: tuple[int, int]) -> None:
    assert obs.heightmap.shape == shape, (obs.heightmap.shape, shape)
    if len(openings) == 0:
        raise ValueError("openings: expected at least one candidate opening")


class RandomPolicy:
    """Uniform over observed cells of the action square, rotations and openings."""

    name = "random"

    def __init__(self, cfg: Config) -> None:
        grid = cfg.scene_grid
        self.shape = grid.shape[:2]
        self.rotations = cfg.model.rotations
        centre = grid_centre(grid)
        xy = cell_to_world(grid, *np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij"))
        # (X, Y) bool: cells inside the action square
        self.region = np.all(np.abs(xy - centre) <= cfg.sim.action_half_extent, axis=-1)

    def act(self, obs, openings, rng):
        _check_inputs(obs, openings, self.shape)
        cells = np.flatnonzero(obs.valid & self.region)
        if cells.size == 0:
            cells = np.flatnonzero(self.region)
        i, j = np.unravel_index(int(rng.choice(cells)), self.shape)
        k = int(rng.integers(self.rotations))
        s = int(rng.integers(len(openings)))
        return (int(i), int(j), k, s), SCRIPTED_SCORE


class HeuristicPolicy:
    """Centroid of a random object blob, closing across its minor axis, widest opening."""

    name = "heuristic"

    def __init__(self, cfg: Config, min_height: float = 0.008, min_cells: int = 4) -> None:
        """``min_height``: cells higher than this (m) count as object; ``min_cells``: smallest blob."""
        self.grid = cfg.scene_grid
        self.shape = self.grid.shape[:2]
        self.rotations = cfg.model.rotations
        self.min_height = float(min_height)
        self.min_cells = int(min_cells)
        self._fallback = RandomPolicy(cfg)

    def blobs(self, obs: Observation) -> tuple[np.ndarray, list[int]]:
        """Labelled (X, Y) int32 blob map and the labels of blobs with at least ``min_cells`` cells."""
        obstacle_cells = obs.obstacle.max(axis=2) > 0.5
        mask = (obs.heightmap > self.min_height) & obs.valid & ~obstacle_cells
        labels, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        return labels, [b for b in range(1, n + 1) if sizes[b] >= self.min_cells]

    def act(self, obs, openings, rng):
        _check_inputs(obs, openings, self.shape)
        labels, keep = self.blobs(obs)
        if not keep:
            return self._fallback.act(obs, openings, rng)
        blob = keep[int(rng.integers(len(keep)))]
        cells = np.argwhere(labels == blob)
        xy = cell_to_world(self.grid, cells[:, 0], cells[:, 1])
        centroid = xy.mean(axis=0)
        evals, evecs = np.linalg.eigh(np.cov((xy - centroid).T))
        minor = evecs[:, int(np.argmin(evals))]
        theta = float(np.arctan2(minor[1], minor[0])) % np.pi
        step = 2.0 * np.pi / self.rotations
        k = int(np.round(theta / step)) % self.rotations
        i, j = world_to_cell(self.grid, centroid[0], centroid[1])
        i = int(np.clip(i, 0, self.shape[0] - 1))
        j = int(np.clip(j, 0, self.shape[1] - 1))
        s = int(np.argmax(openings))
        return (i, j, k, s), SCRIPTED_SCORE


def make_policy(name: str, cfg: Config, **kwargs) -> Policy:
    """The policy called ``name`` (one of :data:`POLICY_NAMES`); raises ValueError (one line) otherwise.

    ``kwargs`` reach the policy's constructor; learned policies (``checkpoint:PATH`` with a
    ``mode``) are added here by the module that provides them.
    """
    if name == "random":
        return RandomPolicy(cfg, **kwargs)
    if name == "heuristic":
        return HeuristicPolicy(cfg, **kwargs)
    if name.startswith("checkpoint:"):
        # kwargs: mode (fix-config | fix-gripper | adagrasp), grippers [(key, encoding)], epsilon, device
        from common.policy import LearnedPolicy

        try:
            return LearnedPolicy.from_checkpoint(name[len("checkpoint:") :], cfg, **kwargs)
        except ValueError as e:
            raise ValueError(f"--policy {name}: {e}") from None
    raise ValueError(f"--policy {name}: unknown policy (known: {', '.join(POLICY_NAMES)})")
