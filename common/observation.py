"""Records passed between simulation, policy, replay and learner.

These are the contracts between the parts; each field's docstring gives shape, dtype,
units and frame. Producers call ``validate()`` before handing a record over.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Observation:
    """One fused top-down observation of the scene on the scene grid (DESIGN.md section 3).

    Axis 0 of every volume runs along world x, axis 1 along world y, axis 2 along world z;
    voxel (0, 0, 0) has its lower corner at the scene grid's origin.
    """

    tsdf: np.ndarray
    """(X, Y, Z) float32, truncated signed distance / truncation in [-1, 1]; > 0 free space."""
    obstacle: np.ndarray
    """(X, Y, Z) float32 in [0, 1], 1 where the surface within the truncation band is an obstacle."""
    heightmap: np.ndarray
    """(X, Y) float32 metres above the table, world frame; 0 where only the table was seen."""
    valid: np.ndarray
    """(X, Y) bool, True where some camera observed the column."""

    def validate(self) -> "Observation":
        t = self.tsdf
        assert t.dtype == np.float32 and t.ndim == 3, (
            f"observation.tsdf: {t.shape} {t.dtype}, expected (X, Y, Z) float32"
        )
        x, y, z = t.shape
        for name, want, dtype in (
            ("obstacle", (x, y, z), np.float32), ("heightmap", (x, y), np.float32), ("valid", (x, y), np.bool_)
        ):
            a = getattr(self, name)
            assert a.shape == want and a.dtype == dtype, (
                f"observation.{name}: {a.shape} {a.dtype}, expected {want} {np.dtype(dtype)}"
            )
        return self


@dataclass
class TrialMeta:
    """Metadata of one grasp trial; every field is stored exactly in the replay."""

    episode_id: int
    """Episode index, unique per actor (actor_id, episode_id) identifies an episode."""
    step: int
    """Attempt index within the episode, from 0."""
    scene: str
    """Scene kind: single | multi | obstacle."""
    object_set: str
    """Name of the object set the scene's objects came from."""
    object_ids: tuple[str, ...]
    """Identifiers of the objects in the scene (set-qualified names)."""
    gripper: str
    """Gripper name as registered in the gripper library."""
    gripper_scale: float
    """Global scale of the gripper."""
    openings: tuple[float, ...]
    """Candidate initial openings of this episode, in [0, 1]; action.s indexes this tuple."""
    cameras: int
    """Number of cameras fused into the observation."""
    actor_id: int
    """Actor that collected the trial."""
    policy_version: int
    """Version of the weights that chose the action (-1 for scripted policies)."""
    seed: int
    """Seed of the episode's scene generator."""
    wall_time: float
    """UNIX time (s) when the trial finished."""


@dataclass
class Trial:
    """One grasp attempt, as pushed by an actor to the replay.

    The gripper encoding is referenced by ``gripper_key``; the replay stores the encoding once
    per key in its gripper table, never per trial.
    """

    observation: Observation
    """The observation the action was chosen from."""
    gripper_key: str
    """Key of the gripper encoding: gripper name, scale and openings (see common.gripper_encoding)."""
    gripper_encoding: np.ndarray
    """(S, 2, gX, gY, gZ) float32 TSDF/truncation of the gripper at each opening (channel 0) and closed
    (channel 1), in the TCP frame at yaw 0, on the gripper grid."""
    action: tuple[int, int, int, int]
    """(i, j, k, s): scene cell along x and y, rotation index (theta = 2 pi k / R), opening index."""
    label: bool
    """True if exactly one target ended above the lift height and no obstacle was lifted."""
    score: float
    """Predicted success probability of the executed action (0.5 for scripted policies)."""
    meta: TrialMeta
    """Bookkeeping metadata."""
    extra: dict = field(default_factory=dict)
    """Free-form diagnostics (not stored by the replay)."""

    def validate(self) -> "Trial":
        self.observation.validate()
        enc = self.gripper_encoding
        assert enc.ndim == 5 and enc.shape[1] == 2 and enc.dtype == np.float32, (
            f"gripper_encoding: {enc.shape} {enc.dtype}, expected (S, 2, gX, gY, gZ) float32"
        )
        assert enc.shape[0] == len(self.meta.openings), (
            f"gripper_encoding: {enc.shape[0]} openings, meta.openings has {len(self.meta.openings)}"
        )
        i, j, k, s = self.action
        x, y, _ = self.observation.tsdf.shape
        assert 0 <= i < x and 0 <= j < y and k >= 0 and 0 <= s < enc.shape[0], (
            f"action: {tuple(self.action)} outside (i < {x}, j < {y}, k >= 0, s < {enc.shape[0]})"
        )
        return self
