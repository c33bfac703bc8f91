"""A replay shard: the only writer of one Zarr v3 group holding a FIFO ring of trials.

Layout and decoding rules: replay/schema.py and docs/REPLAY_FORMAT.md. The group opens with
plain ``zarr.open_group(path, mode="r")``.

Commit protocol (why a crash never exposes a half-written trial): the ring has ``capacity + 1``
slots for ``capacity`` visible trials, so trial ``n`` goes to slot ``n % (capacity + 1)``, whose
previous trial was already evicted by the commit before. The shard writes the gripper-table row
(if the key is new), the volumes and the columns of trial ``n``, and only then one commit
``[max(first, n + 1 - capacity), n + 1]`` that both exposes trial ``n`` and evicts the oldest.
Chunks are written to a temporary file and renamed, so a chunk is either old or new, never torn.
A reader that reads a trial and then sees ``commit[0]`` still at or below it has read a
consistent trial.

Gripper-table rows are reference-counted by the visible trials that use them (counts are
rebuilt from the trial columns on open, never stored), so eviction frees a row only when no
visible trial refers to it.

Usage (in-process; as a Ray actor see replay.client.start_remote_shards)::

    shard = ReplayShard("runs/x/replay/shard_000", cfg)       # creates or reopens
    n = shard.insert(trial)                                   # trial number in this shard
    idx = shard.index()                                       # ids, labels, scores of readable trials
    data = shard.read(idx["trial_id"][:8])                    # int8 codes for a batch
    shard.update_scores(data["trial_id"], new_scores)
    reader = ReplayShard(path, read_only=True)                # inspector / export / other process
"""

from __future__ import annotations

import fcntl
import heapq
import os
import re
import shutil
import time
import typing
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import google_crc32c
import numpy as np
import zarr
from numcodecs import VLenUTF8, Zstd
from zarr.codecs import Crc32cCodec, ZstdCodec

from common.config import Config, to_dict
from common.observation import Observation, TrialMeta
from replay.sampler import BufferPool
from replay.schema import (
    ATTR_KEY,
    COLUMN_NAMES,
    HEIGHTMAP_STEP,
    OBSTACLE_LEVELS,
    ROOT_KIND,
    SCHEMA_VERSION,
    SHARD_KIND,
    SHARD_NAME,
    SHARD_NAME_PATTERN,
    TABLE_COLUMN_NAMES,
    ArraySpec,
    EncodedTrial,
    ReplayCorruptError,
    ReplayError,
    ReplayInputError,
    ReplaySchemaError,
    array_specs,
    decode_surface,
    decode_unit,
    encode_trial,
    max_errors,
    meta_from_json,
)


class ReplayCorruptWarning(UserWarning):
    """A trial was found unreadable and is skipped (one line: path, array, slot, trial)."""


@dataclass
class StoredTrial:
    """One trial as read back from a shard (volumes decoded to float32)."""

    trial_id: int
    """Insertion number within the shard."""
    observation: Observation
    """Decoded observation (within the quantisation error of the inserted one)."""
    gripper_key: str
    """Key of the gripper encoding."""
    gripper_encoding: np.ndarray
    """(2, gX, gY, gZ) float32 gripper TSDF/truncation at the executed opening (0) and closed (1)."""
    action: tuple[int, int, int, int]
    """(i, j, k, s)."""
    label: bool
    """Grasp success."""
    score: float
    """Stored score (refreshed by the learner)."""
    meta: TrialMeta
    """Metadata, exactly as inserted."""
    insert_time: float
    """UNIX time (s) of the commit."""


def _chunk_error(e: BaseException) -> str:
    """First line of an exception, prefixed by its type."""
    text = str(e).splitlines()[0] if str(e) else ""
    return f"{type(e).__name__}: {text}"[:200]


def shard_capacity(total: int, num_shards: int) -> int:
    """Per-shard ring size: ceil(total / num_shards)."""
    return -(-int(total) // int(num_shards))


def shard_path(root: str | Path, index: int) -> Path:
    """Path of shard ``index``'s group under a replay root."""
    return Path(root) / SHARD_NAME.format(index=index)


def shard_attributes(cfg: Config, shard_index: int, num_shards: int) -> dict:
    """The schema attributes a shard created from ``cfg`` stores under ``ATTR_KEY`` (all but
    its creation time): shapes, capacity, quantisation, the grids and the action's meaning."""
    rc = cfg.replay
    capacity = shard_capacity(rc.capacity, num_shards)
    slots = capacity + 1
    table_rows = capacity + 1  # every visible trial may hold its own gripper-table row
    specs = array_specs(
        slots, table_rows, cfg.scene_grid.shape, tuple(cfg.gripper_grid.shape), rc.chunk_trials, rc.tsdf_levels
    )
    scene_grid = to_dict(cfg.scene_grid)
    scene_grid["truncation"] = cfg.scene_grid.truncation
    gripper_grid = to_dict(cfg.gripper_grid)
    gripper_grid["truncation"] = cfg.gripper_grid.truncation
    return {
        "kind": SHARD_KIND,
        "schema_version": SCHEMA_VERSION,
        "shard_index": shard_index,
        "num_shards": num_shards,
        "capacity": capacity,
        "slots": slots,
        "table_rows": table_rows,
        "chunk_trials": min(rc.chunk_trials, slots),
        "scene_shape": list(cfg.scene_grid.shape),
        "gripper_shape": list(cfg.gripper_grid.shape),
        "tsdf_levels": rc.tsdf_levels,
        "obstacle_levels": OBSTACLE_LEVELS,
        "heightmap_step_m": HEIGHTMAP_STEP,
        "max_abs_error": max_errors(rc.tsdf_levels),
        "rotations": cfg.model.rotations,
        "grasp_depth_m": cfg.sim.grasp_depth,
        "scene_grid": scene_grid,
        "gripper_grid": gripper_grid,
        "visibility": "trial t is visible iff commit[0] <= t < commit[1] and trial_id[t % slots] == t",
        "arrays": {
            s.name: {"shape": list(s.shape), "chunks": list(s.chunks), "dtype": s.dtype, "units": s.units}
            for s in specs
        },
    }


CONFIG_ATTRIBUTES = (
    "capacity", "scene_shape", "gripper_shape", "tsdf_levels", "num_shards", "shard_index",
    "rotations", "grasp_depth_m", "scene_grid", "gripper_grid",
)
"""Shard attributes an existing shard must share with the config it is opened with: a trial
stored under other grids, rotations or grasp depth would mean something else to the run."""


def attribute_difference(key: str, have, want) -> tuple[str, object, object] | None:
    """The first (dotted key, stored value, wanted value) where two attribute values differ."""
    if isinstance(have, dict) and isinstance(want, dict):
        for k in sorted(set(have) | set(want)):
            found = attribute_difference(f"{key}.{k}", have.get(k), want.get(k))
            if found:
                return found
        return None
    return None if have == want else (key, have, want)


def read_kind(path: str | Path) -> dict | None:
    """The replay attributes of the Zarr group at ``path``, or None if it is not a replay group."""
    p = Path(path)
    if not (p / "zarr.json").is_file():
        return None
    try:
        g = zarr.open_group(str(p), mode="r")
    except Exception as e:  # noqa: BLE001 - any unreadable group is reported as one line
        raise ReplaySchemaError(f"{p}/zarr.json: unreadable group metadata ({_chunk_error(e)})") from None
    attrs = g.attrs.get(ATTR_KEY)
    return dict(attrs) if isinstance(attrs, dict) else None


def find_shards(path: str | Path) -> list[Path]:
    """Shard groups at ``path``: the group itself if it is a shard, else the shards of a replay root."""
    p = Path(path)
    if not p.exists():
        raise ReplaySchemaError(f"{p}: no such file or folder")
    attrs = read_kind(p)
    if attrs is None:
        raise ReplaySchemaError(f"{p}: attributes.{ATTR_KEY}: not a replay root or shard group")
    version = attrs.get("schema_version")
    if version != SCHEMA_VERSION:
        raise ReplaySchemaError(
            f"{p}: attributes.{ATTR_KEY}.schema_version: expected {SCHEMA_VERSION}, got {version!r}"
        )
    if attrs.get("kind") == SHARD_KIND:
        return [p]
    shards = []
    for child in sorted(p.iterdir()):
        if child.name.startswith("."):
            continue  # a shard being created (see ReplayShard._create), or another hidden folder
        _refuse_damaged_shard(child)
        a = read_kind(child) if child.is_dir() else None
        if a is not None and a.get("kind") == SHARD_KIND:
            shards.append(child)
    return shards


def ensure_root(root: str | Path, num_shards: int) -> Path:
    """Create (or check, :func:`check_root`) the replay root group that holds ``num_shards`` shard groups."""
    p = Path(root)
    if check_root(p, num_shards):
        return p
    p.mkdir(parents=True, exist_ok=True)
    zarr.create_group(
        str(p),
        attributes={ATTR_KEY: {"kind": ROOT_KIND, "schema_version": SCHEMA_VERSION, "num_shards": num_shards}},
    )
    return p


def check_root(root: str | Path, num_shards: int) -> bool:
    """Whether a replay root group of ``num_shards`` shards exists at ``root``; writes nothing.

    Raises :class:`ReplaySchemaError` in one line naming the file and the field when ``root``
    holds unreadable group metadata, a group that is not a replay root, another schema version
    or another shard count.
    """
    p = Path(root)
    attrs = read_kind(p)
    if attrs is None:
        if (p / "zarr.json").exists():
            raise ReplaySchemaError(f"{p}: attributes.{ATTR_KEY}: existing group is not a replay root")
        return False
    if attrs.get("schema_version") != SCHEMA_VERSION:
        raise ReplaySchemaError(
            f"{p}: attributes.{ATTR_KEY}.schema_version: expected {SCHEMA_VERSION}, got {attrs.get('schema_version')!r}"
        )
    if attrs.get("kind") != ROOT_KIND or attrs.get("num_shards") != num_shards:
        raise ReplaySchemaError(
            f"{p}: attributes.{ATTR_KEY}.num_shards: replay root has {attrs.get('num_shards')!r} shards, "
            f"config asks for {num_shards}"
        )
    return True


def _check_attributes(path: Path, attrs: dict) -> None:
    """One line naming the attribute when a shard's schema attributes that readers compute with are
    missing or of the wrong type (a hand-edited zarr.json), before any of them is used."""
    def refuse(key: str, want: str) -> typing.NoReturn:
        got = f"got {attrs[key]!r:.60}" if key in attrs else "missing"
        raise ReplaySchemaError(f"{path}: attributes.{ATTR_KEY}.{key}: expected {want}, {got}")

    def count(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v >= 0

    for key in ("capacity", "slots", "table_rows", "chunk_trials", "tsdf_levels", "shard_index", "rotations"):
        if not count(attrs.get(key)):
            refuse(key, "a non-negative integer")
    for key in ("scene_shape", "gripper_shape"):
        v = attrs.get(key)
        if not (isinstance(v, list) and len(v) == 3 and all(count(x) and x > 0 for x in v)):
            refuse(key, "three positive integers")
    for key in ("scene_grid", "gripper_grid"):
        v = attrs.get(key)
        size = v.get("voxel_size") if isinstance(v, dict) else None
        if isinstance(size, bool) or not isinstance(size, (int, float)) or not size > 0:
            refuse(key, "a grid with a positive voxel_size")


def _refuse_damaged_shard(path: Path) -> None:
    """One line when ``path`` is a shard's folder (shard_NNN) that holds files but no zarr.json: its
    trials cannot be read, and a new shard cannot be created over them."""
    if re.fullmatch(SHARD_NAME_PATTERN, path.name) and path.is_dir() and not (path / "zarr.json").is_file():
        held = sum(1 for f in path.rglob("*") if f.is_file())
        if held:
            raise ReplaySchemaError(
                f"{path}/zarr.json: missing, but the shard folder holds {held} files (damaged; move it away to "
                "start that shard empty)"
            )


def check_shards(root: str | Path, cfg: Config) -> None:
    """Check the replay root (:func:`check_root`), then open the shards that exist under ``root``
    read-only with ``cfg`` and close them.

    A root that is unreadable or holds another shard count, or a config the stored trials cannot
    take (other rotations, grids, quantisation or capacity), raises :class:`ReplaySchemaError` in
    one line naming the file or shard and the field, with nothing written. Call it in the process
    that starts a run, before shards are placed in Ray actors, where the same error would reach
    the user as actor tracebacks. Missing shards are skipped (the run creates them); corrupt-chunk
    warnings are left to the run's own open.
    """
    n = cfg.replay.shards
    check_root(root, n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReplayCorruptWarning)
        for k in range(n):
            _refuse_damaged_shard(shard_path(root, k))
            if (shard_path(root, k) / "zarr.json").is_file():
                ReplayShard(shard_path(root, k), cfg, shard_index=k, num_shards=n, read_only=True).close()


class _ChunkIO:
    """Reads and writes whole chunks of one array straight from and to their files.

    Zarr-python spends ~1.5 ms of CPU per chunk in its asynchronous machinery, whatever the
    chunk's size; an insert touches ~15 chunks. When the array's codec chain is exactly the one
    this schema creates (``bytes`` little-endian or ``vlen-utf8``, then ``zstd``, then ``crc32c``)
    chunks are encoded here with the same codecs (numcodecs Zstd, google-crc32c) in ~0.1 ms, and
    written like zarr's local store does: to a ``*.partial`` file, then renamed over the chunk,
    so a chunk is always old or new, never torn. The bytes are what zarr writes (tests read them
    back with plain zarr). For any other chain every call goes through zarr.

    Reads decode a chunk once, into its final buffer; errors come back as one-line strings
    (missing file, checksum, decode) so the caller can name the trial.
    """

    def __init__(self, arr: zarr.Array, array_dir: Path) -> None:
        self.arr = arr
        self.dir = array_dir
        meta = arr.metadata.to_dict()
        codecs = meta["codecs"]
        self.string = meta["data_type"] == "string"
        first = "vlen-utf8" if self.string else "bytes"
        little = self.string or codecs[0].get("configuration", {}).get("endian", "little") == "little"
        self.direct = [c["name"] for c in codecs] == [first, "zstd", "crc32c"] and little and (
            array_dir / "zarr.json"
        ).is_file()
        zstd_conf = codecs[1].get("configuration", {}) if len(codecs) > 1 else {}
        self._zstd = Zstd(level=int(zstd_conf.get("level", 0)), checksum=bool(zstd_conf.get("checksum", False)))
        self._vlen = VLenUTF8()
        self.rows = int(arr.chunks[0])
        self.inner = tuple(arr.chunks[1:])
        self.dtype = None if self.string else np.dtype(meta["data_type"]).newbyteorder("<")
        self.zeros = (0,) * (len(arr.shape) - 1)

    def key(self, chunk: int) -> str:
        return self.arr.metadata.encode_chunk_key((chunk,) + self.zeros)

    def read(self, index: int, out: np.ndarray | None = None) -> np.ndarray | str:
        """Entry ``index`` of a one-entry-per-chunk array, shape chunks[1:] (into ``out`` if given), or an error."""
        if not self.direct:
            try:
                out = self.arr[index]
            except Exception as e:  # noqa: BLE001
                return _chunk_error(e)
            # chunks are only read where the trial stored one, and never consist of fill values only
            return "chunk missing (fill value)" if (out == self.arr.fill_value).all() else out
        key = self.key(index)
        try:
            raw = (self.dir / key).read_bytes()
        except FileNotFoundError:
            return f"chunk file {key} missing"
        except OSError as e:
            return _chunk_error(e)
        if len(raw) < 4 or np.uint32(google_crc32c.value(raw[:-4])).tobytes() != raw[-4:]:
            return f"chunk file {key}: checksum mismatch"
        if out is None:
            out = np.empty(self.inner, self.dtype)
        try:
            self._zstd.decode(raw[:-4], out=out)
        except Exception as e:  # noqa: BLE001
            return f"chunk file {key}: {_chunk_error(e)}"
        return out

    def write(self, chunk: int, data: np.ndarray) -> None:
        """Replace chunk ``chunk`` (entries chunk*rows ...) with ``data`` (up to ``rows`` entries; an edge
        chunk is padded with the fill value, as zarr stores it)."""
        c0 = chunk * self.rows
        if not self.direct:
            self.arr[c0:c0 + len(data)] = data
            return
        if len(data) < self.rows:
            dtype = object if self.string else self.dtype
            pad = np.full((self.rows - len(data),) + self.inner, self.arr.fill_value, dtype=dtype)
            data = np.concatenate([np.asarray(data, dtype=pad.dtype), pad])
        if self.string:
            payload = self._vlen.encode(np.asarray(data, dtype=object))
        else:
            payload = np.ascontiguousarray(data, dtype=self.dtype).tobytes()
        body = self._zstd.encode(payload)
        path = self.dir / self.key(chunk)
        tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex}.partial")
        with open(tmp, "wb") as f:
            f.write(body)
            f.write(np.uint32(google_crc32c.value(body)).tobytes())
        os.replace(tmp, path)

    def delete(self, chunk: int) -> None:
        """Remove a chunk: it reads as the fill value again."""
        if not self.direct:
            c0 = chunk * self.rows
            self.arr[c0:c0 + self.rows] = np.full((self.rows,) + self.inner, self.arr.fill_value)
            return
        (self.dir / self.key(chunk)).unlink(missing_ok=True)


class ReplayShard:
    """The only writer of one Zarr group: a FIFO of ``capacity`` trials (a ring of ``capacity + 1``
    slots) plus a gripper table.

    ``read_only=True`` opens an existing shard for reading (any process, while a writer appends);
    :meth:`refresh` picks up new commits. Not thread-safe: one caller at a time (a Ray actor
    serialises its calls).
    """

    def __init__(
        self,
        path: str | Path,
        cfg: Config | None = None,
        *,
        shard_index: int = 0,
        num_shards: int = 1,
        read_only: bool = False,
    ) -> None:
        self.path = Path(path)
        self.read_only = read_only
        self._lock_fd: int | None = None
        exists = (self.path / "zarr.json").is_file()
        if not exists:
            if read_only:
                raise ReplaySchemaError(f"{self.path}: zarr.json: no replay shard here")
            if cfg is None:
                raise ReplaySchemaError(f"{self.path}: cannot create a shard without a config")
            self._create(cfg, shard_index, num_shards)
        self._open(cfg, shard_index, num_shards)

    # ----------------------------------------------------------------------------------
    # Creation and opening
    # ----------------------------------------------------------------------------------

    def _create(self, cfg: Config, shard_index: int, num_shards: int) -> None:
        rc = cfg.replay
        attrs = {**shard_attributes(cfg, shard_index, num_shards), "created": time.time()}
        specs = array_specs(
            attrs["slots"], attrs["table_rows"], cfg.scene_grid.shape, tuple(cfg.gripper_grid.shape),
            rc.chunk_trials, rc.tsdf_levels,
        )
        # Built beside its place under a hidden name and renamed into place when complete: a crash
        # during creation leaves no half-made shard that a restart or --resume could not open.
        self.path.parent.mkdir(parents=True, exist_ok=True)
        staging = self.path.with_name(f".{self.path.name}.creating-{os.getpid()}")
        if staging.exists():
            shutil.rmtree(staging)
        group = zarr.create_group(str(staging))
        compressors = [ZstdCodec(level=rc.compression_level), Crc32cCodec()]
        for spec in specs:
            group.create_array(
                spec.name,
                shape=spec.shape,
                chunks=spec.chunks,
                dtype=str if spec.dtype == "string" else spec.dtype,
                fill_value=spec.fill,
                compressors=compressors,
                attributes=spec.attributes(),
                # "c.17.0.0.0": one flat folder of chunk files per array, no folder chain per trial
                chunk_key_encoding={"name": "default", "separator": "."},
            )
        group["commit"][:] = np.array([0, 0], np.int64)
        group.attrs[ATTR_KEY] = attrs
        try:
            os.rename(staging, self.path)
        except OSError as e:
            shutil.rmtree(staging, ignore_errors=True)
            raise ReplaySchemaError(f"{self.path}: cannot create a shard here ({e.strerror})") from None

    def _open(self, cfg: Config | None, shard_index: int, num_shards: int) -> None:
        p = self.path
        try:
            group = zarr.open_group(str(p), mode="r" if self.read_only else "r+")
        except Exception as e:  # noqa: BLE001
            raise ReplaySchemaError(f"{p}/zarr.json: cannot open group ({_chunk_error(e)})") from None
        attrs = group.attrs.get(ATTR_KEY)
        if not isinstance(attrs, dict):
            raise ReplaySchemaError(
                f"{p}: attributes.{ATTR_KEY}: missing (not a replay shard, or creation was cut off)"
            )
        version = attrs.get("schema_version")
        if version != SCHEMA_VERSION:
            raise ReplaySchemaError(
                f"{p}: attributes.{ATTR_KEY}.schema_version: expected {SCHEMA_VERSION}, got {version!r}"
            )
        if attrs.get("kind") != SHARD_KIND:
            raise ReplaySchemaError(
                f"{p}: attributes.{ATTR_KEY}.kind: expected {SHARD_KIND!r}, got {attrs.get('kind')!r}"
            )
        _check_attributes(p, attrs)
        self.attrs = dict(attrs)
        self.capacity = int(attrs["capacity"])
        self.slots = int(attrs["slots"])
        self.table_rows = int(attrs["table_rows"])
        self.chunk_trials = int(attrs["chunk_trials"])
        self.levels = int(attrs["tsdf_levels"])
        self.scene_shape = tuple(int(v) for v in attrs["scene_shape"])
        self.gripper_shape = tuple(int(v) for v in attrs["gripper_shape"])
        self.shard_index = int(attrs["shard_index"])
        self.seeded_trials = int(attrs.get("seeded_trials", 0))
        """Trials copied in from an earlier replay before the run began (trial numbers
        0..seeded_trials-1; replay.seed); 0 for a shard that started empty."""
        if cfg is not None:
            want = shard_attributes(cfg, shard_index, num_shards)
            for key in CONFIG_ATTRIBUTES:
                found = attribute_difference(key, attrs.get(key), want[key])
                if found:
                    name, stored, given = found
                    raise ReplaySchemaError(
                        f"{p}: attributes.{ATTR_KEY}.{name}: stored {stored!r}, config gives {given!r}"
                    )
        if self.slots != self.capacity + 1:
            raise ReplaySchemaError(f"{p}: attributes.{ATTR_KEY}.slots: expected capacity + 1, got {self.slots}")
        specs = array_specs(
            self.slots, self.table_rows, self.scene_shape, self.gripper_shape, self.chunk_trials, self.levels
        )
        self._specs = {s.name: s for s in specs}
        self._arrays: dict[str, zarr.Array] = {}
        for spec in specs:
            self._arrays[spec.name] = self._check_array(group, spec)
        self._io = {s.name: _ChunkIO(self._arrays[s.name], p / s.name) for s in specs}
        if not self.read_only:
            self._take_lock()
            self._remove_partial_files()
        self._staging = BufferPool(max_buffers=64)
        self._problems: list[str] = []
        self._corrupt: dict[int, str] = {}
        self._corrupt_skipped = 0
        self._duplicates = 0
        self._inserts = 0
        self._load_state()

    def _check_array(self, group: zarr.Group, spec: ArraySpec) -> zarr.Array:
        p = self.path
        try:
            arr = group[spec.name]
        except KeyError:
            raise ReplaySchemaError(f"{p}/{spec.name}: array missing") from None
        except Exception as e:  # noqa: BLE001
            raise ReplaySchemaError(f"{p}/{spec.name}/zarr.json: unreadable ({_chunk_error(e)})") from None
        if not isinstance(arr, zarr.Array):
            raise ReplaySchemaError(f"{p}/{spec.name}: expected an array, found a group")
        dtype = arr.metadata.to_dict()["data_type"]
        if dtype != spec.dtype:
            raise ReplaySchemaError(f"{p}/{spec.name}: data_type: expected {spec.dtype}, got {dtype}")
        if tuple(arr.shape) != spec.shape:
            raise ReplaySchemaError(f"{p}/{spec.name}: shape: expected {spec.shape}, got {tuple(arr.shape)}")
        if tuple(arr.chunks) != spec.chunks:
            raise ReplaySchemaError(f"{p}/{spec.name}: chunks: expected {spec.chunks}, got {tuple(arr.chunks)}")
        return arr

    def _take_lock(self) -> None:
        """Advisory exclusive lock on the group's zarr.json: one writer per shard, released on exit or crash."""
        fd = os.open(self.path / "zarr.json", os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise ReplayError(f"{self.path}: another process is writing this shard") from None
        self._lock_fd = fd

    def _remove_partial_files(self) -> None:
        """Temporary files of writes cut off by a crash (never visible to zarr) are removed.

        Zarr writes them next to their target: in the group folder or an array folder (flat chunk keys).
        """
        for folder in [self.path] + [self.path / name for name in self._specs]:
            with os.scandir(folder) as entries:
                for entry in entries:
                    if entry.name.endswith(".partial") and entry.is_file():
                        os.unlink(entry.path)

    def close(self) -> None:
        """Release the writer lock. The shard object must not be used afterwards."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> "ReplayShard":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_lock_fd", None) is not None:
            os.close(self._lock_fd)

    # ----------------------------------------------------------------------------------
    # State in memory
    # ----------------------------------------------------------------------------------

    def _problem(self, message: str) -> None:
        """Record and warn about an unreadable chunk or lost trial, once per message."""
        if message not in self._problems:
            self._problems.append(message)
            warnings.warn(message, ReplayCorruptWarning, stacklevel=3)

    def _read_commit(self) -> tuple[int, int]:
        try:
            first, end = (int(v) for v in self._arrays["commit"][:])
        except Exception as e:  # noqa: BLE001
            raise ReplayCorruptError(f"{self.path}/commit: unreadable ({_chunk_error(e)})") from None
        if first < 0 or end < first or end - first > self.capacity:
            raise ReplayCorruptError(f"{self.path}/commit: invalid value [{first}, {end}) (missing chunk?)")
        return first, end

    def _load_column(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Whole column in memory, and a bool mask of entries whose chunk could not be read."""
        arr, spec = self._arrays[name], self._specs[name]
        bad = np.zeros(spec.shape[0], bool)
        try:
            data = arr[:]
        except Exception:  # noqa: BLE001 - fall back to chunk by chunk to isolate the bad ones
            if spec.dtype == "string":
                data = np.full(spec.shape, spec.fill, dtype=object)
            else:
                data = np.full(spec.shape, spec.fill, dtype=spec.dtype)
            step = spec.chunks[0]
            for c0 in range(0, spec.shape[0], step):
                c1 = min(c0 + step, spec.shape[0])
                try:
                    data[c0:c1] = arr[c0:c1]
                except Exception as e:  # noqa: BLE001
                    bad[c0:c1] = True
                    self._unreadable_chunks.add((name, c0 // step))
                    self._problem(
                        f"{self.path}/{name}: chunk of slots {c0}..{c1 - 1} unreadable ({_chunk_error(e)}); "
                        f"those trials are skipped"
                    )
        if spec.dtype == "string":
            data = np.asarray(data, dtype=object)
        return data, bad

    def _load_state(self) -> None:
        c = self.slots
        self._unreadable_chunks: set[tuple[str, int]] = set()
        """(column, chunk) pairs that could not be read when the columns were loaded."""
        try:
            self._first, self._end = self._read_commit()
            damaged_commit = None
        except ReplayCorruptError as e:
            damaged_commit = str(e)
        self._col: dict[str, np.ndarray] = {}
        bad = np.zeros(c, bool)
        for name in COLUMN_NAMES:
            data, b = self._load_column(name)
            self._col[name] = data
            bad |= b
        self._table: dict[str, np.ndarray] = {}
        bad_rows = np.zeros(self.table_rows, bool)
        for name in TABLE_COLUMN_NAMES:
            data, b = self._load_column(name)
            self._table[name] = data
            bad_rows |= b
        if damaged_commit is not None:
            self._recover_commit(damaged_commit, bad)
        elif self.read_only:
            # a live writer may have evicted trials while the columns were read: those are gone, not lost
            self._follow_evictions()
        self._lost = np.zeros(c, bool)
        ids = np.arange(self._first, self._end, dtype=np.int64)
        slots = ids % c
        col = self._col
        checks = {
            "trial_id": col["trial_id"][slots] == ids,
            "action": (col["action"][slots] >= 0).all(1),
            "label": col["label"][slots] <= 1,
            "score": np.isfinite(col["score"][slots]),
            "insert_time": np.isfinite(col["insert_time"][slots]),
            "meta": np.array([bool(m) for m in col["meta"][slots]], bool),
            "gripper_row": (col["gripper_row"][slots] >= 0) & (col["gripper_row"][slots] < self.table_rows),
            "obstacle_voxels": col["obstacle_voxels"][slots] >= 0,
        }
        self._lost[slots[bad[slots]]] = True
        for name, ok in checks.items():
            newly = ~ok & ~self._lost[slots]
            if newly.any():
                self._problem(
                    f"{self.path}/{name}: {int(newly.sum())} visible trial(s) with missing values "
                    f"(first: trial {int(ids[newly][0])}); they are skipped"
                )
            self._lost[slots[~ok]] = True
        rows = col["gripper_row"][slots]
        row_ok = np.zeros(len(slots), bool)
        in_range = (rows >= 0) & (rows < self.table_rows)
        row_ok[in_range] = ~bad_rows[rows[in_range]] & np.array(
            [bool(k) for k in self._table["gripper_table_key"][rows[in_range]]], bool
        )
        lost_by_row = ~row_ok & ~self._lost[slots]
        if lost_by_row.any():
            self._problem(
                f"{self.path}/gripper_table_key: {int(lost_by_row.sum())} visible trial(s) refer to an unreadable or "
                f"empty gripper-table row; they are skipped"
            )
        self._lost[slots[~row_ok]] = True
        # Reference counts, key -> row map and free rows, from the readable visible trials.
        self._refcount = np.zeros(self.table_rows, np.int64)
        self._slot_row = np.full(c, -1, np.int64)
        self._row_of: dict[tuple[str, int], int] = {}
        self._rows_read: set[int] = set()
        """Rows of _row_of whose chunk this writer has written or read back: a row found in the
        table at open is read once before an insert reuses it (a damaged one is not reused)."""
        self._tokens: dict[tuple[int, int], int] = {}
        for t, s in zip(ids.tolist(), slots.tolist()):
            if self._lost[s]:
                continue
            r = int(col["gripper_row"][s])
            self._refcount[r] += 1
            self._slot_row[s] = r
            key = (str(self._table["gripper_table_key"][r]), int(self._table["gripper_table_opening"][r]))
            self._row_of.setdefault(key, r)
            tok = tuple(int(v) for v in col["insert_token"][s])
            self._tokens[tok] = t
        self._free_rows = [r for r in range(self.table_rows) if self._refcount[r] == 0]
        heapq.heapify(self._free_rows)

    def refresh(self) -> None:
        """Re-read the commit and columns (readers following a live writer)."""
        self._load_state()

    # ----------------------------------------------------------------------------------
    # Writing
    # ----------------------------------------------------------------------------------

    def _require_writer(self) -> None:
        if self.read_only or self._lock_fd is None:
            raise ReplayError(f"{self.path}: shard is open read-only")

    def _write_commit(self, first: int, end: int) -> None:
        self._io["commit"].write(0, np.array([first, end], np.int64))
        self._first, self._end = first, end

    def _column_write(self, name: str, index: int, table: bool = False) -> None:
        """Write the whole chunk of column ``name`` that holds entry ``index``, from memory."""
        io = self._io[name]
        chunk = index // io.rows
        if (name, chunk) in self._unreadable_chunks:
            self._keep_unreadable_chunk(name, chunk)
        io.write(chunk, (self._table if table else self._col)[name][chunk * io.rows:(chunk + 1) * io.rows])

    def _recover_commit(self, damage: str, bad: np.ndarray) -> None:
        """The commit chunk is unreadable or missing (e.g. a power loss after its rename, nothing
        being fsynced): the visible range is rebuilt from the trial_id column. The newest trial
        number found there is left out, since its insert may have stopped before its commit (its
        other columns may still be the previous trial's); the ``capacity`` trials before it are
        complete, as the ring keeps ``capacity + 1`` slots. A writer keeps the damaged file aside
        (like a column chunk's) and writes the recovered commit; a reader uses it in memory."""
        ids = self._col["trial_id"][~bad]
        newest = int(ids.max()) if ids.size else -1
        end = max(newest, 0)
        first = max(0, end - self.capacity)
        self._first, self._end = first, end
        self._problem(f"{damage}; recovered [{first}, {end}) from the trial_id column"
                      + (f" (trial {newest}, the newest stored, left out)" if newest >= 0 else ""))
        if not self.read_only:
            self._keep_unreadable_chunk("commit", 0)
            self._write_commit(first, end)

    def _keep_unreadable_chunk(self, name: str, chunk: int) -> None:
        """Before the first write over a column chunk that could not be read at open (it is rewritten
        whole, from memory, where its trials are fill values), its file is renamed aside, so that
        no stored byte is lost: ``<chunk key>.unreadable-<UNIX time>``, in the array's folder."""
        self._unreadable_chunks.discard((name, chunk))
        path = self._io[name].dir / self._io[name].key(chunk)
        if path.is_file():
            aside = path.with_name(f"{path.name}.unreadable-{int(time.time())}")
            os.replace(path, aside)
            self._problem(f"{path}: unreadable chunk kept as {aside.name} before it is rewritten")

    def _check_record(self, rec: EncodedTrial) -> None:
        x, y, z = self.scene_shape
        w = rec.where
        if rec.levels != self.levels:
            raise ReplayInputError(f"{w}: levels: encoded with {rec.levels}, shard {self.path} stores {self.levels}")
        if rec.tsdf.shape != (x, y, z) or rec.tsdf.dtype != np.int8:
            raise ReplayInputError(
                f"{w}: observation.tsdf: shape {rec.tsdf.shape}, shard {self.path} stores {(x, y, z)}"
            )
        if rec.obstacle is not None and (rec.obstacle.shape != (x, y, z) or rec.obstacle.dtype != np.int8):
            raise ReplayInputError(f"{w}: observation.obstacle: shape {rec.obstacle.shape}, expected {(x, y, z)}")
        if rec.surface.shape != (2, x, y) or rec.surface.dtype != np.int16:
            raise ReplayInputError(f"{w}: observation.heightmap: shape {rec.surface.shape[1:]}, expected {(x, y)}")
        if rec.gripper.shape != (2,) + self.gripper_shape or rec.gripper.dtype != np.int8:
            raise ReplayInputError(
                f"{w}: gripper_encoding: shape {rec.gripper.shape[1:]}, shard {self.path} stores {self.gripper_shape}"
            )
        i, j, k, s = rec.action
        if not (0 <= i < x and 0 <= j < y and s >= 0):
            raise ReplayInputError(f"{w}: action: {rec.action} outside the scene grid {(x, y)}")
        rotations = int(self.attrs["rotations"])
        if not 0 <= k < rotations:
            raise ReplayInputError(f"{w}: action: rotation {k} outside the shard's {rotations} rotations")

    def insert(self, trial) -> int:
        """Quantise and store a :class:`common.observation.Trial`; returns its trial number in this shard."""
        token = (-1, self._end)
        return self.insert_encoded(encode_trial(trial, self.levels, token))

    def insert_encoded(self, rec: EncodedTrial) -> int:
        """Store an encoded trial (see replay.schema.encode_trial); returns its trial number.

        A repeated token (a retried request) returns the trial number of the first insert.
        """
        self._require_writer()
        self._check_record(rec)
        if rec.token in self._tokens and rec.token[0] >= 0:
            self._duplicates += 1
            return self._tokens[rec.token]
        n = self._end
        slot = n % self.slots  # its previous trial, n - capacity - 1, is no longer visible
        key = (rec.gripper_key, int(rec.action[3]))
        row = self._row_of.get(key)
        if row is not None and row not in self._rows_read:
            res = self._io["gripper_table"].read(row)
            if isinstance(res, str):  # its visible trials are lost with it; this one gets a fresh row
                for t in self.visible_ids().tolist():
                    if self._slot_row[t % self.slots] == row:
                        self._mark_corrupt("gripper_table", t, row, res)
                row = None
            else:
                self._rows_read.add(row)
        new_row = row is None
        if new_row:
            row = heapq.heappop(self._free_rows)
        col = self._col
        col["trial_id"][slot] = n
        col["obstacle_voxels"][slot] = rec.obstacle_voxels
        col["insert_time"][slot] = time.time()
        col["insert_token"][slot] = rec.token
        col["action"][slot] = rec.action
        col["gripper_row"][slot] = row
        col["label"][slot] = int(rec.label)
        col["score"][slot] = rec.score
        col["meta"][slot] = rec.meta_json
        io = self._io
        try:
            if new_row:
                self._table["gripper_table_key"][row] = key[0]
                self._table["gripper_table_opening"][row] = key[1]
                io["gripper_table"].write(row, rec.gripper[None])
                for name in TABLE_COLUMN_NAMES:
                    self._column_write(name, row, table=True)
            io["tsdf"].write(slot, rec.tsdf[None])
            if rec.obstacle is not None:
                io["obstacle"].write(slot, rec.obstacle[None])
            else:  # a chunk left by the slot's previous trial, or by a write cut off before its commit
                io["obstacle"].delete(slot)
            io["surface"].write(slot, rec.surface[None])
            for name in COLUMN_NAMES:
                self._column_write(name, slot)
            first = max(self._first, n + 1 - self.capacity)
            evicted = range(self._first, first)
            self._write_commit(first, n + 1)  # the last write: the trial is committed once it lands
        except Exception as e:  # noqa: BLE001 - nothing is committed; report one line
            if new_row:
                heapq.heappush(self._free_rows, row)
            raise ReplayError(f"{self.path}: writing trial {n} failed ({_chunk_error(e)}); nothing committed") from None
        # count the new trial's use of its row before the evicted trials release theirs: when it
        # reuses the row of its only evicted user, that row must not go back to the free list
        self._refcount[row] += 1
        self._slot_row[slot] = row
        for e in evicted:
            self._release_slot(e % self.slots, e)
        if new_row:
            self._row_of[key] = row
            self._rows_read.add(row)
        self._tokens[rec.token] = n
        self._lost[slot] = False
        self._inserts += 1
        return n

    def _release_slot(self, slot: int, trial: int) -> None:
        """Bookkeeping after ``trial`` (in ``slot``) was evicted by a written commit."""
        self._corrupt.pop(trial, None)
        row = int(self._slot_row[slot])
        self._slot_row[slot] = -1
        if row >= 0:
            self._refcount[row] -= 1
            if self._refcount[row] == 0:
                key = (str(self._table["gripper_table_key"][row]), int(self._table["gripper_table_opening"][row]))
                if self._row_of.get(key) == row:
                    del self._row_of[key]
                heapq.heappush(self._free_rows, row)
        tok = tuple(int(v) for v in self._col["insert_token"][slot])
        if self._tokens.get(tok) == trial:
            del self._tokens[tok]

    def update_scores(self, trial_ids, scores) -> int:
        """Write refreshed scores of visible trials; ids evicted meanwhile are ignored. Returns how many."""
        self._require_writer()
        ids = np.asarray(trial_ids, dtype=np.int64).reshape(-1)
        sc = np.asarray(scores, dtype=np.float64).reshape(-1)
        if ids.shape != sc.shape:
            raise ReplayInputError(f"{self.path}: update_scores: {ids.shape[0]} ids but {sc.shape[0]} scores")
        bad = ~(np.isfinite(sc) & (sc >= 0) & (sc <= 1))
        if bad.any():
            raise ReplayInputError(
                f"{self.path}: update_scores.scores: expected probabilities in [0, 1], got {float(sc[bad][0])!r} "
                f"for trial {int(ids[bad][0])}"
            )
        live = self._live_mask(ids)
        slots = ids[live] % self.slots
        if not len(slots):
            return 0
        self._col["score"][slots] = sc[live]
        step = self._io["score"].rows
        try:
            for head in sorted({int(s) // step * step for s in slots}):
                self._column_write("score", head)
        except OSError as e:
            raise ReplayError(f"{self.path}/score: write failed ({_chunk_error(e)})") from None
        return int(live.sum())

    # ----------------------------------------------------------------------------------
    # Reading
    # ----------------------------------------------------------------------------------

    def _live_mask(self, ids: np.ndarray) -> np.ndarray:
        """Which trial ids are visible, intact and not known to be corrupt."""
        slots = ids % self.slots
        ok = (ids >= self._first) & (ids < self._end) & (self._col["trial_id"][slots] == ids) & ~self._lost[slots]
        if self._corrupt:
            ok &= ~np.isin(ids, np.fromiter(self._corrupt, np.int64))
        return ok

    def visible_ids(self) -> np.ndarray:
        """(n,) int64 trial numbers that are visible and readable, oldest first."""
        ids = np.arange(self._first, self._end, dtype=np.int64)
        return ids[self._live_mask(ids)]

    def __len__(self) -> int:
        return int(len(self.visible_ids()))

    def size(self) -> int:
        """Number of readable visible trials."""
        return len(self)

    def index(self) -> dict[str, np.ndarray]:
        """What a sampler needs: trial_id (n,) int64, label (n,) bool, score (n,) float32."""
        ids = self.visible_ids()
        slots = ids % self.slots
        return {
            "trial_id": ids,
            "label": self._col["label"][slots] == 1,
            "score": self._col["score"][slots].astype(np.float32),
        }

    def column(self, name: str, trial_ids) -> np.ndarray:
        """Values of a per-trial column (see COLUMN_NAMES) for the given visible trials."""
        ids = np.asarray(trial_ids, np.int64)
        return self._col[name][ids % self.slots]

    def _evicted_meanwhile(self, trial: int) -> bool:
        """A reader following a live writer: whether ``trial`` was evicted since the commit was
        read (its chunks may then be gone or rewritten: not damage). Always False for the writer."""
        if not self.read_only:
            return False
        self._follow_evictions()
        return trial < self._first

    def _follow_evictions(self) -> None:
        """A reader: take the writer's newer ``commit[0]`` (trials evicted since the columns were
        loaded), but not its end: trials committed since then are read by :meth:`refresh`, since
        the columns in memory may hold a slot's trial that was not yet committed (a writer
        mid-insert, or one that crashed before its commit, whose slot a later trial fills)."""
        self._first = max(self._first, self._read_commit()[0])

    def _mark_corrupt(self, name: str, trial: int, index: int, err: str) -> str:
        """Remember an unreadable trial (warned once); returns the one-line description. An
        unreadable gripper-table row is not reused: the next trial of its gripper writes a new row."""
        if name == "gripper_table":
            for key in [k for k, r in self._row_of.items() if r == index]:
                del self._row_of[key]
            self._rows_read.discard(index)
        line = f"{self.path}/{name}: chunk {index} of trial {trial} unreadable ({err})"
        if trial not in self._corrupt:
            self._corrupt[trial] = line
            self._problem(f"{line}; trial skipped")
        return line

    def read(self, trial_ids) -> dict[str, Any]:
        """Quantised batch data of the given trials, in the given order, skipping unreadable ones.

        Returns trial_id (n,) int64; tsdf: list of n (X, Y, Z) int8 codes; obstacle: list of n
        (X, Y, Z) int8 codes or None (no obstacle voxel); gripper: list of n (2, gX, gY, gZ) int8
        codes; action (n, 4) int64; label (n,) bool; score (n,) float32; missing: requested ids
        that were evicted or are corrupt (counted, warned once). Code arrays may be reused by
        the shard once the caller drops them.
        """
        ids = np.asarray(trial_ids, dtype=np.int64).reshape(-1)
        live = self._live_mask(ids)
        ids_live = ids[live]
        slots = ids_live % self.slots
        rows = self._col["gripper_row"][slots].astype(np.int64)
        n_obstacle = self._col["obstacle_voxels"][slots]
        n = len(ids_live)
        keep = np.ones(n, bool)
        tsdfs: list = [None] * n
        obstacles: list = [None] * n
        grippers: list = [None] * n
        shape = self.scene_shape
        for b in range(n):
            t, s = int(ids_live[b]), int(slots[b])
            reads = [("tsdf", s, tsdfs, self._staging.take(shape, np.int8))]
            if n_obstacle[b] > 0:
                reads.append(("obstacle", s, obstacles, self._staging.take(shape, np.int8)))
            reads.append(("gripper_table", int(rows[b]), grippers, None))
            for name, index, dest, out in reads:
                res = self._io[name].read(index, out=out)
                if isinstance(res, str):
                    if not self._evicted_meanwhile(t):
                        self._mark_corrupt(name, t, index, res)
                    keep[b] = False
                    break
                dest[b] = res
        if self.read_only:
            self._follow_evictions()
            keep &= ids_live >= self._first
        self._corrupt_skipped += int((~keep).sum())
        sel = np.flatnonzero(keep)
        col = self._col
        out_slots = slots[sel]
        missing = [int(t) for t in ids[~live]] + [int(t) for t in ids_live[~keep]]
        return {
            "trial_id": ids_live[sel],
            "tsdf": [tsdfs[b] for b in sel],
            "obstacle": [obstacles[b] for b in sel],
            "gripper": [grippers[b] for b in sel],
            "action": col["action"][out_slots].astype(np.int64),
            "label": col["label"][out_slots] == 1,
            "score": col["score"][out_slots].astype(np.float32),
            "missing": missing,
        }

    def encoded(self, trial_id: int, token: tuple[int, int]) -> EncodedTrial:
        """One complete trial as stored (codes, not decoded), to be inserted elsewhere under
        ``token``; ReplayError if not visible, ReplayCorruptError if unreadable."""
        t = int(trial_id)
        if t in self._corrupt:
            raise ReplayCorruptError(self._corrupt[t])
        if not self._live_mask(np.array([t]))[0]:
            raise ReplayError(f"{self.path}: trial {t}: not visible (visible: {self._first}..{self._end - 1})")
        slot = t % self.slots
        row = int(self._col["gripper_row"][slot])
        n_obstacle = int(self._col["obstacle_voxels"][slot])
        evicted = f"{self.path}: trial {t}: evicted by the writer while it was read"
        results = {}
        for name, index in self._volume_chunks(slot):
            res = self._io[name].read(index)
            if isinstance(res, str):
                if self._evicted_meanwhile(t):
                    raise ReplayError(evicted)
                raise ReplayCorruptError(self._mark_corrupt(name, t, index, res))
            results[name] = res
        if self._evicted_meanwhile(t):
            raise ReplayError(evicted)
        col = self._col
        return EncodedTrial(
            tsdf=results["tsdf"],
            obstacle=results.get("obstacle"),
            obstacle_voxels=n_obstacle,
            surface=results["surface"],
            gripper_key=str(self._table["gripper_table_key"][row]),
            gripper=results["gripper_table"],
            action=tuple(int(v) for v in col["action"][slot]),
            label=bool(col["label"][slot] == 1),
            score=float(col["score"][slot]),
            meta_json=str(col["meta"][slot]),
            token=(int(token[0]), int(token[1])),
            levels=self.levels,
            where=f"{self.path}: trial {t}",
        )

    def _volume_chunks(self, slot: int) -> list[tuple[str, int]]:
        """(array, chunk index) of every volume chunk of the trial in ``slot``: tsdf, surface,
        obstacle where it has one, and its gripper-table row last."""
        chunks = [("tsdf", slot), ("surface", slot)]
        if int(self._col["obstacle_voxels"][slot]) > 0:
            chunks.append(("obstacle", slot))
        return chunks + [("gripper_table", int(self._col["gripper_row"][slot]))]

    def verify(self) -> int:
        """Read every visible trial's volume chunks (checksum, decompression; a gripper-table row
        once for all its trials); an unreadable one is marked corrupt like a failed sample read
        (warned once, counted in stats, no longer visible). Returns how many were found."""
        found = 0
        rows: dict[int, str | None] = {}  # row -> error, None when readable
        for t in self.visible_ids().tolist():
            error = None
            for name, index in self._volume_chunks(t % self.slots):
                if name == "gripper_table":
                    if index not in rows:
                        res = self._io[name].read(index)
                        rows[index] = res if isinstance(res, str) else None
                    res = rows[index]
                else:
                    res = self._io[name].read(index)
                if isinstance(res, str):
                    error = name, index, res
                    break
            if error is not None and not self._evicted_meanwhile(t):
                name, index, res = error
                self._mark_corrupt(name, t, index, res)
                found += 1
        return found

    def get_trial(self, trial_id: int) -> StoredTrial:
        """One complete trial, decoded; ReplayError if not visible, ReplayCorruptError if unreadable."""
        t = int(trial_id)
        rec = self.encoded(t, (-1, t))
        slot = t % self.slots
        if rec.obstacle is not None:
            obstacle = decode_unit(rec.obstacle, OBSTACLE_LEVELS)
        else:
            obstacle = np.zeros(self.scene_shape, np.float32)
        heightmap, valid = decode_surface(rec.surface)
        obs = Observation(
            tsdf=decode_unit(rec.tsdf, self.levels), obstacle=obstacle, heightmap=heightmap, valid=valid
        ).validate()
        return StoredTrial(
            trial_id=t,
            observation=obs,
            gripper_key=rec.gripper_key,
            gripper_encoding=decode_unit(rec.gripper, self.levels),
            action=rec.action,
            label=rec.label,
            score=rec.score,
            meta=meta_from_json(rec.meta_json),
            insert_time=float(self._col["insert_time"][slot]),
        )

    # ----------------------------------------------------------------------------------
    # Introspection
    # ----------------------------------------------------------------------------------

    def info(self) -> dict:
        """The shard's schema attributes (shapes, quantisation, grids, capacity)."""
        return dict(self.attrs)

    def stats(self) -> dict:
        """Counters: commit range, seeded, visible, successes, failures, lost, corrupt, duplicates,
        table rows in use."""
        idx = self.index()
        ids = np.arange(self._first, self._end)
        return {
            "shard": self.shard_index,
            "path": str(self.path),
            "capacity": self.capacity,
            "first": self._first,
            "end": self._end,
            "seeded": self.seeded_trials,
            "visible": int(len(idx["trial_id"])),
            "successes": int(idx["label"].sum()),
            "failures": int((~idx["label"]).sum()),
            "lost": int(self._lost[ids % self.slots].sum()) if len(ids) else 0,
            "corrupt": len(self._corrupt),
            "corrupt_skipped": self._corrupt_skipped,
            "duplicates_skipped": self._duplicates,
            "table_rows_used": int((self._refcount > 0).sum()),
            "problems": list(self._problems),
        }

    def run_marks(self) -> dict:
        """Where a resumed run's numbers must start when trials were committed after its last
        checkpoint, from this run's visible trials (trials a new replay was seeded with are left
        out): ``episode_ends`` {actor id: one past its largest episode number} and
        ``policy_version``, the largest weights version a trial was collected with (-1: none)."""
        ids = self.visible_ids()
        ends: dict[int, int] = {}
        version = -1
        for text in self._col["meta"][ids[ids >= self.seeded_trials] % self.slots]:
            meta = meta_from_json(str(text))
            ends[meta.actor_id] = max(ends.get(meta.actor_id, 0), meta.episode_id + 1)
            version = max(version, meta.policy_version)
        return {"episode_ends": ends, "policy_version": version}

    def problems(self) -> list[str]:
        """One line per unreadable chunk or lost trial found so far."""
        return list(self._problems)


def disk_usage(path: str | Path) -> tuple[int, int]:
    """(apparent bytes of all files, allocated bytes of all files and folders) under ``path``."""
    apparent = allocated = 0
    for root, _, files in os.walk(path):
        allocated += os.stat(root).st_blocks * 512
        for f in files:
            st = os.stat(os.path.join(root, f))
            apparent += st.st_size
            allocated += st.st_blocks * 512
    return apparent, allocated


__all__ = [
    "ReplayShard",
    "ReplayCorruptWarning",
    "StoredTrial",
    "disk_usage",
    "check_root",
    "ensure_root",
    "find_shards",
    "shard_capacity",
    "shard_path",
    "read_kind",
]
