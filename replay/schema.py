"""On-disk schema of a replay shard (one Zarr v3 group), quantisation, and the encoded trial record.

Every array of a shard, its shape, dtype, chunking, fill value, units and decoding rule is
listed once here (:func:`array_specs`); the shard creates its group from this table, checks an
existing group against it, and writes the same table into the group's attributes. The human
description lives in docs/REPLAY_FORMAT.md.

Flow of one trial::

    rec = encode_trial(trial, levels=127, token=(client_id, seq))   # in the actor's process
    shard.insert_encoded(rec)                                        # in the shard's process
    tsdf = decode_unit(rec.tsdf, levels)                             # back to float32

Errors are one line naming the path (or record) and the field: ReplaySchemaError for a group
that does not match this schema, ReplayCorruptError for a chunk that cannot be decoded,
ReplayInputError for a trial that cannot be stored.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass

import numpy as np

from common.observation import Trial, TrialMeta

SCHEMA_VERSION = 1
"""Version of the layout below; bumped on any change a reader must know about."""

ATTR_KEY = "adagrasp_replay"
"""Group attribute holding the schema description (shard and root groups)."""

SHARD_KIND = "shard"
ROOT_KIND = "root"

SHARD_NAME = "shard_{index:03d}"
"""Name of shard k's group under a replay root."""
SHARD_NAME_PATTERN = r"shard_\d{3,}"
"""Regular expression every name SHARD_NAME gives matches (and no hidden staging name)."""

OBSTACLE_LEVELS = 127
"""Stored obstacle code = round(obstacle * 127), int8 in [0, 127]; max error 1/254."""

HEIGHTMAP_STEP = 5e-5
"""Heightmap unit in metres: stored int16 = round(height / 5e-5); max error 2.5e-5 m, range +-1.638 m."""

INT8_MISSING = -128
"""Fill value of int8 volumes; never produced by the quantiser, so a missing chunk is detected."""
INT16_MISSING = -32768
"""Fill value of the int16 surface array; never produced by the quantiser."""
UINT8_MISSING = 255
"""Fill value of the uint8 label; never produced by the writer."""

RANGE_SLACK = 1e-3
"""Inputs may exceed their documented range by this much (float rounding) before they are rejected."""


class ReplayError(RuntimeError):
    """Base class of replay errors; every message is one line naming the path or record and the field."""


class ReplaySchemaError(ReplayError):
    """A group is not a replay shard of this schema version, or does not match the configuration."""


class ReplayCorruptError(ReplayError):
    """A chunk of a shard cannot be read or decoded."""


class ReplayInputError(ReplayError, ValueError):
    """A trial or request cannot be stored (wrong shape, value out of range, non-finite)."""


class ReplayEmptyError(ReplayError):
    """No readable trial to sample from."""


# --------------------------------------------------------------------------------------
# Array table
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ArraySpec:
    """One array of a shard group."""

    name: str
    shape: tuple[int, ...]
    chunks: tuple[int, ...]
    dtype: str
    fill: object
    units: str
    description: str
    per_trial_chunk: bool = False
    """True when one chunk holds exactly one trial (volumes): corruption stays within that trial."""

    def attributes(self) -> dict:
        return {"units": self.units, "description": self.description}


def array_specs(
    slots: int,
    table_rows: int,
    scene_shape: tuple[int, int, int],
    gripper_shape: tuple[int, int, int],
    chunk_trials: int,
    levels: int,
) -> list[ArraySpec]:
    """The arrays of a shard with ``slots`` trial slots and ``table_rows`` gripper-table rows."""
    c, g, ct = slots, table_rows, min(chunk_trials, slots)
    x, y, z = scene_shape
    gx, gy, gz = gripper_shape
    return [
        ArraySpec("commit", (2,), (2,), "int64", -1, "trial number",
                  "[first, end): trials first..end-1 are visible; written once per insert, after its data"),
        ArraySpec("tsdf", (c, x, y, z), (1, x, y, z), "int8", INT8_MISSING, f"TSDF/truncation * {levels}",
                  f"scene TSDF on the scene grid (axes x, y, z, world frame); decode as value / {levels} "
                  f"(TSDF/truncation in [-1, 1], > 0 free space)", True),
        ArraySpec("obstacle", (c, x, y, z), (1, x, y, z), "int8", 0, f"obstacle * {OBSTACLE_LEVELS}",
                  f"obstacle channel on the scene grid; decode as value / {OBSTACLE_LEVELS} (in [0, 1]); a trial "
                  f"without obstacle voxels has no chunk (reads as 0, see obstacle_voxels)", True),
        ArraySpec("surface", (c, 2, x, y), (1, 2, x, y), "int16", INT16_MISSING,
                  f"channel 0: {HEIGHTMAP_STEP} m; channel 1: flag",
                  f"channel 0: heightmap (top-surface height above the table, world frame), decode as "
                  f"value * {HEIGHTMAP_STEP} m; channel 1: valid, 1 where some camera observed the column", True),
        ArraySpec("trial_id", (c,), (ct,), "int64", -1, "trial number",
                  "insertion number of the trial in this slot (slot = trial_id % slots); -1 if empty"),
        ArraySpec("insert_time", (c,), (ct,), "float64", math.nan, "s (UNIX time)",
                  "shard clock when the trial was committed"),
        ArraySpec("insert_token", (c, 2), (ct, 2), "int64", -1, "id",
                  "(client id, sequence number) of the insert request; makes retried inserts idempotent"),
        ArraySpec("obstacle_voxels", (c,), (ct,), "int32", -1, "voxels",
                  "number of non-zero obstacle codes of the trial (0: no obstacle chunk is stored)"),
        ArraySpec("action", (c, 4), (ct, 4), "int32", -1, "index",
                  "(i, j, k, s): scene cell along x and y, rotation index (theta = 2 pi k / R), opening index"),
        ArraySpec("gripper_row", (c,), (ct,), "int32", -1, "row",
                  "row of gripper_table holding the encoding of the executed opening"),
        ArraySpec("label", (c,), (ct,), "uint8", UINT8_MISSING, "flag", "1 = grasp succeeded, 0 = failed"),
        ArraySpec("score", (c,), (ct,), "float64", math.nan, "probability",
                  "predicted success of the executed action; refreshed by the learner"),
        ArraySpec("meta", (c,), (ct,), "string", "", "JSON",
                  "TrialMeta as a JSON object (episode_id, step, scene, object_set, object_ids, gripper, "
                  "gripper_scale, openings, cameras, actor_id, policy_version, seed, wall_time)"),
        ArraySpec("gripper_table", (g, 2, gx, gy, gz), (1, 2, gx, gy, gz), "int8", INT8_MISSING,
                  f"TSDF/truncation * {levels}",
                  f"gripper TSDF at the executed opening (channel 0) and closed (channel 1), TCP frame at yaw 0, "
                  f"on the gripper grid; decode as value / {levels}", True),
        ArraySpec("gripper_table_key", (g,), (ct,), "string", "", "key",
                  "gripper_key of the row (gripper name, scale and openings); '' = free row"),
        ArraySpec("gripper_table_opening", (g,), (ct,), "int32", -1, "index",
                  "opening index s of the row within its key's openings"),
    ]


COLUMN_NAMES = (
    "trial_id", "insert_time", "insert_token", "obstacle_voxels", "action", "gripper_row", "label", "score", "meta",
)
"""Per-trial columns chunked ``chunk_trials`` trials at a time; a shard keeps them in memory."""
TABLE_COLUMN_NAMES = ("gripper_table_key", "gripper_table_opening")


# --------------------------------------------------------------------------------------
# Quantisation
# --------------------------------------------------------------------------------------


def _check_range(name: str, x: np.ndarray, lo: float, hi: float, where: str) -> None:
    if not np.isfinite(x).all():
        raise ReplayInputError(f"{where}: {name}: contains NaN or inf")
    mn, mx = float(x.min()), float(x.max())
    if mn < lo - RANGE_SLACK or mx > hi + RANGE_SLACK:
        raise ReplayInputError(f"{where}: {name}: values [{mn:.4g}, {mx:.4g}] outside [{lo}, {hi}]")


def quantise_unit(x: np.ndarray, levels: int, lo: float = -1.0) -> np.ndarray:
    """int8 code of values in [lo, 1]: round(x * levels), clipped to [lo * levels, levels]."""
    q = np.multiply(x, np.float32(levels), dtype=np.float32)
    np.rint(q, out=q)
    np.clip(q, lo * levels, levels, out=q)
    return q.astype(np.int8)


def scene_scales(levels: int) -> np.ndarray:
    """(2,) float32 factors that turn TSDF codes (0) and obstacle codes (1) back into values."""
    return np.array([1.0 / levels, 1.0 / OBSTACLE_LEVELS], np.float32)


def decode_unit(codes: np.ndarray, levels: int) -> np.ndarray:
    """float32 values from int8 codes of :func:`quantise_unit`."""
    return codes.astype(np.float32) * np.float32(1.0 / levels)


def encode_surface(heightmap: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(2, X, Y) int16: heightmap in units of HEIGHTMAP_STEP metres (0) and the valid flag (1)."""
    out = np.empty((2,) + heightmap.shape, np.int16)
    out[0] = np.clip(np.rint(heightmap.astype(np.float64) / HEIGHTMAP_STEP), -32767, 32767)
    out[1] = valid
    return out


def decode_surface(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) float32 heightmap in metres and (X, Y) bool valid from (2, X, Y) int16 codes."""
    return (q[0].astype(np.float64) * HEIGHTMAP_STEP).astype(np.float32), q[1] == 1


def max_errors(levels: int) -> dict[str, float]:
    """Largest absolute round-trip error of each stored quantity (in its own units)."""
    return {
        "tsdf": 0.5 / levels,
        "obstacle": 0.5 / OBSTACLE_LEVELS,
        "gripper_tsdf": 0.5 / levels,
        "heightmap_m": 0.5 * HEIGHTMAP_STEP,
    }


# --------------------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------------------


def meta_to_json(meta: TrialMeta, where: str) -> str:
    """Exact JSON text of a TrialMeta (floats round-trip bit for bit); one-line error on a bad field."""
    out = {}
    for f in dataclasses.fields(TrialMeta):
        v = getattr(meta, f.name)
        tp = str(f.type)
        try:
            if tp == "int":
                if isinstance(v, (bool, np.bool_)) or int(v) != v:
                    raise TypeError
                out[f.name] = int(v)
            elif tp == "float":
                out[f.name] = float(v)
            elif tp == "str":
                if not isinstance(v, str):
                    raise TypeError
                out[f.name] = v
            elif tp == "tuple[str, ...]":
                if isinstance(v, str) or not all(isinstance(s, str) for s in v):
                    raise TypeError
                out[f.name] = list(v)
            elif tp == "tuple[float, ...]":
                out[f.name] = [float(s) for s in v]
            else:
                raise TypeError
        except (TypeError, ValueError):
            raise ReplayInputError(f"{where}: meta.{f.name}: expected {tp}, got {v!r}") from None
    return json.dumps(out, sort_keys=True, allow_nan=True)


def meta_from_json(text: str) -> TrialMeta:
    """TrialMeta from :func:`meta_to_json` output."""
    d = json.loads(text)
    d["object_ids"] = tuple(d["object_ids"])
    d["openings"] = tuple(d["openings"])
    return TrialMeta(**d)


# --------------------------------------------------------------------------------------
# Encoded trial: what travels from an actor to a shard
# --------------------------------------------------------------------------------------


@dataclass
class EncodedTrial:
    """A trial quantised for storage (about 4x smaller than the float record; cheap to ship)."""

    tsdf: np.ndarray
    """(X, Y, Z) int8 TSDF codes (round(tsdf * levels))."""
    obstacle: np.ndarray | None
    """(X, Y, Z) int8 obstacle codes (round(obstacle * 127)), None when every code is 0."""
    obstacle_voxels: int
    """Number of non-zero obstacle codes."""
    surface: np.ndarray
    """(2, X, Y) int16: heightmap codes (HEIGHTMAP_STEP metres) and valid flags (see encode_surface)."""
    gripper_key: str
    """Key of the gripper encoding (name, scale, openings)."""
    gripper: np.ndarray
    """(2, gX, gY, gZ) int8 gripper TSDF codes at the executed opening and closed."""
    action: tuple[int, int, int, int]
    """(i, j, k, s)."""
    label: bool
    """Grasp success."""
    score: float
    """Predicted success probability of the executed action."""
    meta_json: str
    """TrialMeta as JSON (:func:`meta_to_json`)."""
    token: tuple[int, int]
    """(client id, sequence number), unique per insert request."""
    levels: int
    """TSDF quantisation levels the codes were made with."""
    where: str
    """Short name of the trial for error messages (actor, episode, step)."""


def trial_name(meta: TrialMeta) -> str:
    return f"trial(actor {meta.actor_id}, episode {meta.episode_id}, step {meta.step})"


def encode_trial(trial: Trial, levels: int, token: tuple[int, int]) -> EncodedTrial:
    """Validate and quantise a Trial; raises ReplayInputError (one line) on bad input."""
    where = trial_name(trial.meta)
    try:
        trial.validate()
    except AssertionError as e:
        raise ReplayInputError(f"{where}: record does not match common.observation.Trial: {e}") from None
    obs = trial.observation
    _check_range("observation.tsdf", obs.tsdf, -1.0, 1.0, where)
    _check_range("observation.obstacle", obs.obstacle, 0.0, 1.0, where)
    lim = 32767 * HEIGHTMAP_STEP
    _check_range("observation.heightmap", obs.heightmap, -lim, lim, where)
    s = int(trial.action[3])
    row = trial.gripper_encoding[s]
    _check_range(f"gripper_encoding[{s}]", row, -1.0, 1.0, where)
    score = float(trial.score)
    if not 0.0 <= score <= 1.0:
        raise ReplayInputError(f"{where}: score: expected a probability in [0, 1], got {trial.score!r}")
    if not isinstance(trial.gripper_key, str) or not trial.gripper_key:
        raise ReplayInputError(f"{where}: gripper_key: expected a non-empty string, got {trial.gripper_key!r}")
    obstacle = quantise_unit(obs.obstacle, OBSTACLE_LEVELS, lo=0.0)
    n_obstacle = int(np.count_nonzero(obstacle))
    return EncodedTrial(
        tsdf=quantise_unit(obs.tsdf, levels),
        obstacle=obstacle if n_obstacle else None,
        obstacle_voxels=n_obstacle,
        surface=encode_surface(obs.heightmap, obs.valid),
        gripper_key=trial.gripper_key,
        gripper=quantise_unit(row, levels),
        action=tuple(int(a) for a in trial.action),
        label=bool(trial.label),
        score=score,
        meta_json=meta_to_json(trial.meta, where),
        token=(int(token[0]), int(token[1])),
        levels=int(levels),
        where=where,
    )
