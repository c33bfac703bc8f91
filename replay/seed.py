"""A new run's replay seeded with the trials of an earlier replay (``replay.seed_from``).

The newest readable trials of the source (a run directory or its ``replay`` folder), up to the
new replay's capacity, are copied as stored (the int8 codes, no second quantisation) into the
new run's shards, oldest first, round-robin. Their action, label, score, obstacle count and
metadata are kept exactly (the score, the source learner's prediction, sets a copy's sampling
priority until the new learner draws and re-scores it); their trial numbers and gripper-table
rows are the new shard's, their ``insert_time`` is the time of the copy and their insert
token's client id is :data:`SEED_CLIENT`. Each shard records how many trials it was seeded with
(``seeded_trials``, trial numbers ``0 .. seeded_trials - 1``), and the root records the source
(``seeded_from``) and the total; :func:`learner.loop.total_inserted` leaves seeded trials out,
so the run's trial count, epsilon schedule, rate limiter and ``run.max_trials`` count only
the trials its own actors collect, while the learner samples from both from its first step.

The copy is built in ``RUN/replay.seeding`` and renamed to ``RUN/replay`` when complete, so
a cut-off seeding leaves no replay behind (the folder is removed by the next attempt). A start
stopped after that rename but before its ``config.yaml`` was written leaves a complete seeded
replay that no trial of the run has reached yet; seeding it again from the same source reuses
it (``reused`` in the report) instead of refusing the run directory; if the config now gives
other grids, quantisation, rotations, grasp depth or capacity than it was made with, it is
refused with one line naming the shard and the attribute and left untouched. A source whose
grids, quantisation, rotations or grasp depth differ from the new run's is refused with one
line naming the source shard and the attribute, before anything is written. The source is
only read, and may be a run that is still writing it.

Usage::

    report = seed_replay("runs/earlier", run_dir / "replay", cfg)
    report["trials"], report["skipped"]
"""

from __future__ import annotations

import shutil
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import zarr

from common.config import Config
from replay.inspect import open_readers, trial_table
from replay.schema import ATTR_KEY, ReplayError, ReplaySchemaError
from replay.shard import (
    CONFIG_ATTRIBUTES,
    ReplayCorruptWarning,
    ReplayShard,
    attribute_difference,
    ensure_root,
    read_kind,
    shard_attributes,
    shard_path,
)

SEED_CLIENT = -2
"""Client id in the insert token of a copied trial (actors use ids >= 0, a plain insert -1)."""

MATCHING_ATTRIBUTES = (
    "scene_shape", "gripper_shape", "tsdf_levels", "rotations", "grasp_depth_m", "scene_grid", "gripper_grid",
)
"""Shard attributes a source must share with the new run for its trials to mean the same there."""

STAGING_SUFFIX = ".seeding"
"""The copy is built in ``<replay>.seeding`` and renamed when complete."""

PROGRESS_EVERY_S = 5.0
"""Seconds between ``progress`` calls while copying."""


def source_root(source: str | Path) -> Path:
    """The replay folder of ``source``: ``source/replay`` when ``source`` is a run directory."""
    p = Path(source)
    if (p / "replay" / "zarr.json").is_file() and not (p / "zarr.json").is_file():
        return p / "replay"
    if not p.exists():
        raise ReplayError(f"{p}: replay.seed_from: no such file or directory")
    return p


def _set_attributes(path: Path, **values) -> None:
    group = zarr.open_group(str(path), mode="r+")
    group.attrs[ATTR_KEY] = {**dict(group.attrs[ATTR_KEY]), **values}


def _check_matching(readers: list[ReplayShard], cfg: Config, keys: tuple[str, ...], holder: str,
                    advice: str) -> None:
    """Raise one line naming the first shard and attribute in ``keys`` whose stored value differs
    from what a shard created from ``cfg`` would store; ``holder`` names the stored side."""
    for r in readers:
        want = shard_attributes(cfg, r.shard_index, cfg.replay.shards)
        have = r.info()
        for key in keys:
            found = attribute_difference(key, have.get(key), want.get(key))
            if found:
                name, a, b = found
                raise ReplaySchemaError(
                    f"{r.path}: attributes.{ATTR_KEY}.{name}: {holder} has {a!r}, this run's config gives {b!r} "
                    f"(replay.seed_from{advice})"
                )


def _untouched_seeded_replay(root: Path, src: Path, cfg: Config) -> int | None:
    """The trial count of ``root`` when it is a complete replay seeded from ``src`` with
    ``cfg.replay.shards`` shards that holds nothing but its seeded trials; None otherwise.
    Such a replay made with other grids, rotations, grasp depth or capacity than ``cfg`` gives
    is refused with one line naming the shard and the attribute."""
    try:
        if (read_kind(root) or {}).get("seeded_from") != str(src):
            return None
        readers = open_readers(root)
    except (ReplayError, OSError):
        return None
    try:
        if len(readers) != cfg.replay.shards or any(r.stats()["end"] != r.seeded_trials for r in readers):
            return None
        _check_matching(readers, cfg, CONFIG_ATTRIBUTES, "the replay already seeded here",
                        f"; remove {root} to seed it again with this config")
        return sum(r.seeded_trials for r in readers)
    finally:
        for r in readers:
            r.close()


def seed_replay(source: str | Path, root: str | Path, cfg: Config,
                progress: Callable[[int, int], None] | None = None) -> dict:
    """Copy the newest readable trials of ``source`` into a new replay at ``root`` (must not
    exist, unless it is an untouched copy of the same source: see the module text) with
    ``cfg.replay``'s shards and capacity; ``progress(handled, to_copy)`` is called about every
    five seconds while copying. Returns ``seeded_from`` (absolute source path), ``trials``
    (copied), ``available`` (readable trials listed in the source), ``skipped`` (source trials
    lost: unreadable when the source was opened or copied, or evicted meanwhile by a run still
    writing the source; the copy is not topped up with older ones), ``problems`` (one line
    each) and ``reused`` (True when ``root`` was such an untouched copy, then ``available`` is
    its trial count and ``skipped`` 0)."""
    src = source_root(source).resolve()
    root = Path(root)
    if root.exists():
        kept = _untouched_seeded_replay(root, src, cfg)
        if kept is not None:
            return {"seeded_from": str(src), "trials": kept, "available": kept, "skipped": 0, "problems": [],
                    "reused": True}
        raise ReplayError(
            f"{root}: replay.seed_from: this run directory already has a replay (a new run seeds an empty "
            f"one); remove it or choose another --run-dir"
        )
    staging = root.with_name(root.name + STAGING_SUFFIX)
    n_shards = cfg.replay.shards
    shards: list[ReplayShard] = []
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ReplayCorruptWarning)  # reported in the summary instead
            try:
                readers = open_readers(src)
            except ReplaySchemaError as e:
                raise ReplaySchemaError(f"{e} (replay.seed_from)") from None
            _check_matching(readers, cfg, MATCHING_ATTRIBUTES, "source", "")
            lost = sum(r.stats()["lost"] for r in readers)
            problems = [line for r in readers for line in r.problems()]
            if staging.exists():
                shutil.rmtree(staging)  # left by a seeding that was cut off; never visible as a replay
            ensure_root(staging, n_shards)
            shards = [ReplayShard(shard_path(staging, k), cfg, shard_index=k, num_shards=n_shards)
                      for k in range(n_shards)]
            table = trial_table(readers)
            available = len(table["trial_id"])
            copied, failed = 0, 0
            first = max(0, available - cfg.replay.capacity)
            last_report = time.monotonic()
            for n in range(first, available):
                if progress is not None and time.monotonic() - last_report >= PROGRESS_EVERY_S:
                    progress(n - first, available - first)
                    last_report = time.monotonic()
                reader = readers[int(table["shard"][n])]
                try:
                    rec = reader.encoded(int(table["trial_id"][n]), (SEED_CLIENT, copied))
                except ReplayError as e:  # unreadable, or evicted by a live writer since it was listed
                    failed += 1
                    problems.append(str(e))
                    continue
                shards[copied % n_shards].insert_encoded(rec)
                copied += 1
        counts = [sh.stats()["end"] for sh in shards]
        for sh in shards:
            sh.close()
        for k, count in enumerate(counts):
            _set_attributes(shard_path(staging, k), seeded_trials=count)
        _set_attributes(staging, seeded_from=str(src), seeded_trials=copied)
        staging.rename(root)
    except BaseException as e:
        for sh in shards:
            sh.close()
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(e, OSError):
            raise ReplayError(f"{staging}: replay.seed_from: copying {src} failed ({type(e).__name__}: {e})") from None
        raise
    return {"seeded_from": str(src), "trials": copied, "available": available, "skipped": lost + failed,
            "problems": problems, "reused": False}
