"""Crash safety and concurrent readers, with real writer processes.

A writer subprocess inserts deterministic synthetic trials (trial of episode e is built from
``default_rng(e)``), so the parent can rebuild every trial and check what it reads back.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from replay.schema import ReplayError, max_errors
from replay.shard import ReplayCorruptWarning, ReplayShard, check_shards, ensure_root, find_shards
from replay.synthetic import numbered_trial as make_trial
from replay.synthetic import small_config as tiny_cfg

REPO = Path(__file__).resolve().parents[1]


def episode_trial(cfg, e: int):
    """The writer's trial of episode ``e``: every third one carries obstacles."""
    with_obstacle = e % 3 == 0
    return make_trial(cfg, e, n_objects=1 + with_obstacle, n_obstacles=2 * with_obstacle)


WRITER = r"""
import sys, time
from replay.shard import ReplayShard
from replay.synthetic import small_config as tiny_cfg
from tests.test_replay_crash import episode_trial

path = sys.argv[1]
capacity, start, count, stall_at = (int(v) for v in sys.argv[2:6])
cfg = tiny_cfg(capacity=capacity, chunk=4)
shard = ReplayShard(path, cfg)
real_commit = shard._write_commit

def commit(first, end):
    if end == stall_at and shard._end == stall_at - 1:
        print("DATA_WRITTEN", end - 1, flush=True)   # every chunk of the trial is on disk, commit not yet
        time.sleep(600)
    real_commit(first, end)

shard._write_commit = commit
print("OPEN", shard._end, flush=True)
e = start
while count < 0 or e < start + count:
    n = shard.insert(episode_trial(cfg, e))
    print("COMMITTED", n, e, flush=True)
    e += 1
"""


def spawn_writer(path: Path, capacity: int, start: int, count: int, stall_at: int = -1) -> subprocess.Popen:
    code = WRITER
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen(
        [sys.executable, "-c", code, str(path), str(capacity), str(start), str(count), str(stall_at)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=str(REPO),
    )


def wait_for(proc: subprocess.Popen, prefix: str, timeout: float = 60.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith(prefix):
            return line
        if not line and proc.poll() is not None:
            raise AssertionError(f"writer exited ({proc.returncode}): {proc.stderr.read()}")
    raise AssertionError(f"writer never printed {prefix}")


def check_every_visible_trial(path: Path, cfg) -> list[int]:
    """Reopen read-only; every visible trial must be complete and equal to what was inserted."""
    err = max_errors(cfg.replay.tsdf_levels)
    reader = ReplayShard(path, read_only=True)
    assert reader.problems() == []
    episodes = []
    for t in reader.visible_ids():
        got = reader.get_trial(int(t))
        want = episode_trial(cfg, got.meta.episode_id)
        assert got.meta == want.meta and got.action == want.action and got.label == want.label
        assert got.gripper_key == want.gripper_key and got.score == want.score
        for name in ("tsdf", "obstacle"):
            assert np.abs(getattr(got.observation, name) - getattr(want.observation, name)).max() <= err[name] + 1e-7
        assert np.abs(got.observation.heightmap - want.observation.heightmap).max() <= err["heightmap_m"] + 1e-7
        assert np.array_equal(got.observation.valid, want.observation.valid)
        assert np.abs(got.gripper_encoding - want.gripper_encoding[want.action[3]]).max() <= err["tsdf"] + 1e-7
        episodes.append(got.meta.episode_id)
    return episodes


def test_kill9_between_data_and_commit_hides_the_half_written_trial(tmp_path):
    cfg = tiny_cfg(capacity=6, chunk=4)
    path = tmp_path / "s"
    # trial 8 goes to slot 8 % 7 = 1 (ring of 6 + 1 slots), over trial 1; killed after its data, before its commit
    proc = spawn_writer(path, 6, 0, -1, stall_at=9)
    wait_for(proc, "DATA_WRITTEN 8")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(30)
    episodes = check_every_visible_trial(path, cfg)
    assert episodes == [2, 3, 4, 5, 6, 7]  # trial 8 never became visible, trial 2 was not evicted
    # the next writer reuses the slot and goes on
    proc = spawn_writer(path, 6, 100, 3)
    assert wait_for(proc, "OPEN").split()[1] == "8"
    proc.wait(60)
    assert proc.returncode == 0, proc.stderr.read()
    assert check_every_visible_trial(path, cfg) == [5, 6, 7, 100, 101, 102]


def test_kill9_at_random_moments_never_exposes_a_partial_trial(tmp_path):
    cfg = tiny_cfg(capacity=10, chunk=4)
    path = tmp_path / "s"
    rng = np.random.default_rng(0)
    start = 0
    committed_before = 0
    for _ in range(3):
        proc = spawn_writer(path, 10, start, -1)
        wait_for(proc, "OPEN")
        last = None
        deadline = time.monotonic() + float(rng.uniform(0.3, 1.0))
        while time.monotonic() < deadline:
            last = wait_for(proc, "COMMITTED")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        n_last, e_last = (int(v) for v in last.split()[1:])
        episodes = check_every_visible_trial(path, cfg)
        assert episodes, "nothing visible after the kill"
        # everything reported committed is visible (up to the ring size), in order
        assert episodes[-1] >= e_last and episodes == list(range(episodes[0], episodes[-1] + 1))
        assert ReplayShard(path, read_only=True)._end >= max(n_last + 1, committed_before)
        committed_before = n_last + 1
        start = episodes[-1] + 1
    ReplayShard(path, cfg).close()  # a writer removes left-over temporary files of cut-off writes
    assert not list(path.rglob("*.partial"))


def test_reader_opens_while_writer_appends(tmp_path):
    cfg = tiny_cfg(capacity=8, chunk=4)
    path = tmp_path / "s"
    proc = spawn_writer(path, 8, 0, -1)
    try:
        wait_for(proc, "COMMITTED")
        err = max_errors(cfg.replay.tsdf_levels)
        seen: set[int] = set()
        evicted_during_read = 0
        deadline = time.monotonic() + 4.0
        reader = None
        fresh = True
        while time.monotonic() < deadline:
            if fresh:
                reader = ReplayShard(path, read_only=True)
            else:
                reader.refresh()
            fresh = not fresh
            for t in reader.visible_ids():
                try:
                    got = reader.get_trial(int(t))
                except ReplayError as e:
                    assert "evicted by the writer" in str(e) or "not visible" in str(e)
                    evicted_during_read += 1
                    continue
                want = episode_trial(cfg, got.meta.episode_id)
                assert got.trial_id == got.meta.episode_id  # one writer from episode 0: trial n is episode n
                assert np.abs(got.observation.tsdf - want.observation.tsdf).max() <= err["tsdf"] + 1e-7
                assert got.action == want.action
                seen.add(got.trial_id)
            data = reader.read(reader.visible_ids())
            for t, codes in zip(data["trial_id"], data["tsdf"]):
                want = episode_trial(cfg, int(t))
                assert np.abs(codes / cfg.replay.tsdf_levels - want.observation.tsdf).max() <= err["tsdf"] + 1e-7
        assert len(seen) > 8, "the reader saw the writer move on"
        assert reader.problems() == []
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    print(json.dumps({"trials_checked": len(seen), "evicted_during_read": evicted_during_read}))



class _Crash(Exception):
    """Stands for the process dying at that point."""


def test_a_crash_while_a_shard_is_created_leaves_nothing_a_restart_cannot_open(tmp_path, monkeypatch):
    """A shard is built under a hidden name and renamed into place when complete: a crash part way
    (at its third array, or at the rename) leaves no folder at the shard's place, the replay root
    lists no half-made shard, and the next start creates it and stores trials."""
    cfg = tiny_cfg()
    root = ensure_root(tmp_path / "replay", 1)
    path = root / "shard_000"
    real_create_array = zarr.Group.create_array

    def third_array_crashes(self, *args, **kwargs):
        if len(list(self.array_keys())) == 2:
            raise _Crash
        return real_create_array(self, *args, **kwargs)

    def rename_crashes(*args):
        raise _Crash

    for target, crash in (("zarr.Group.create_array", third_array_crashes), ("replay.shard.os.rename", rename_crashes)):
        with monkeypatch.context() as m:
            m.setattr(target, crash)
            with pytest.raises(_Crash):
                ReplayShard(path, cfg)
        assert not path.exists() and find_shards(root) == [], target
    shard = ReplayShard(path, cfg)
    shard.insert(make_trial(cfg, 0))
    shard.close()
    assert find_shards(root) == [path] and len(ReplayShard(path, read_only=True)) == 1


def test_a_shard_folder_that_lost_its_zarr_json_is_one_line_for_readers_and_resume(tmp_path):
    """A shard_NNN folder holding chunk files but no zarr.json is refused in one line by the replay
    listing (which skipped it, dropping its trials without a word) and by the resume check (where
    creating a shard over it failed), and nothing is written."""
    cfg = tiny_cfg(shards=2)
    root = ensure_root(tmp_path / "replay", 2)
    for k in range(2):
        shard = ReplayShard(root / f"shard_00{k}", cfg, shard_index=k, num_shards=2)
        shard.insert(make_trial(cfg, k))
        shard.close()
    (root / "shard_001" / "zarr.json").unlink()
    before = sorted(p for p in root.rglob("*"))
    for call in (lambda: find_shards(root), lambda: check_shards(root, cfg)):
        with pytest.raises(ReplayError) as e:
            call()
        line = str(e.value)
        want = f"{root / 'shard_001'}/zarr.json: missing, but the shard folder holds"
        assert "\n" not in line and line.startswith(want), line
    assert sorted(p for p in root.rglob("*")) == before


@pytest.mark.parametrize("failing", ["surface", "commit"])
def test_a_failed_write_loses_only_that_trial_and_the_shard_goes_on(tmp_path, failing):
    """A chunk write that fails (a full disk), of the trial's data or of its commit, refuses that
    one insert; the trials before it and the ones inserted after it, in reused slots with and
    without obstacles, read back as they were written, in this process and in a fresh reader,
    with no problem reported. (A failed commit once kept the new trial's gripper-table row off
    the free list, and the next insert of a new gripper found none.)"""
    cfg = tiny_cfg(capacity=3, chunk=2)
    shard = ReplayShard(tmp_path / "s", cfg)
    trials = {}
    for e in range(4):
        trials[e] = make_trial(cfg, e, n_objects=2, n_obstacles=2 if e % 2 else 0)
        shard.insert(trials[e])
    real = shard._io[failing].write

    def full_disk(chunk, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    shard._io[failing].write = full_disk
    with pytest.raises(ReplayError, match="nothing committed"):
        shard.insert(make_trial(cfg, 99, n_objects=2, n_obstacles=2))
    shard._io[failing].write = real
    for e in range(4, 9):
        trials[e] = make_trial(cfg, e, n_objects=2, n_obstacles=2 if e % 2 else 0)
        shard.insert(trials[e])
    for reader in (shard, ReplayShard(tmp_path / "s", read_only=True)):
        for t in reader.visible_ids():
            got = reader.get_trial(int(t))
            want = trials[got.meta.episode_id]
            assert np.abs(got.observation.obstacle - want.observation.obstacle).max() <= 1 / 254 + 1e-6, t
            assert np.abs(got.gripper_encoding - want.gripper_encoding[want.action[3]]).max() <= 1 / 254 + 1e-6
        assert reader.problems() == []


class _Died(BaseException):
    """A writer process ending between its data and its commit (not an error the shard handles)."""


def test_a_reader_never_takes_a_trial_it_loaded_before_its_commit(tmp_path):
    """A writer dies after writing trial 3's data and columns, before its commit; a reader opens
    (commit [0, 3), but trial 3's columns are in its memory); a restarted writer commits another
    trial as number 3. The reader's reads follow evictions only: trial 3 stays out of its index
    until refresh(), which then shows the trial the writer committed, never a mix of the two."""
    cfg = tiny_cfg(capacity=4, chunk=4)
    path = tmp_path / "shard"
    writer = ReplayShard(path, cfg)
    for i in range(3):
        writer.insert(make_trial(cfg, i, label=False))

    def died(first, end):
        raise _Died

    writer._write_commit = died
    with pytest.raises(_Died):
        writer.insert(make_trial(cfg, 100, label=True, gripper="gripper_x"))
    writer.close()
    reader = ReplayShard(path, read_only=True)
    assert reader.visible_ids().tolist() == [0, 1, 2]
    writer = ReplayShard(path, cfg)
    assert writer.insert(make_trial(cfg, 200, label=False, gripper="gripper_y")) == 3
    reader.read([0])
    assert reader.visible_ids().tolist() == [0, 1, 2]
    assert reader.read([3])["missing"] == [3]
    reader.refresh()
    mine, theirs = reader.get_trial(3), writer.get_trial(3)
    assert mine.gripper_key == theirs.gripper_key and mine.label == theirs.label is False
    assert np.array_equal(mine.action, theirs.action)
    writer.close()
    reader.close()


@pytest.mark.parametrize("damage", ["checksum", "missing"])
def test_a_damaged_commit_is_rebuilt_from_the_trial_ids_and_its_bytes_kept(tmp_path, damage):
    """A commit chunk that is unreadable or gone (a power loss after its rename: nothing is
    fsynced) made the whole shard unopenable. The visible range is rebuilt from the trial_id
    column without the newest trial (its insert may have stopped before its commit); a reader
    uses it in memory, a writer keeps the damaged file aside, writes the commit and goes on."""
    cfg = tiny_cfg(capacity=4, chunk=4)
    path = tmp_path / "shard"
    with ReplayShard(path, cfg) as writer:
        for i in range(7):
            writer.insert(make_trial(cfg, i))
    commit = path / "commit" / "c.0"
    damaged = commit.read_bytes()[:-2] + b"xx"
    if damage == "checksum":
        commit.write_bytes(damaged)
    else:
        commit.unlink()
    with pytest.warns(ReplayCorruptWarning, match=r"commit: .*; recovered \[2, 6\) from the trial_id column "
                                                  r"\(trial 6, the newest stored, left out\)"):
        reader = ReplayShard(path, read_only=True)
    assert reader.visible_ids().tolist() == [2, 3, 4, 5]
    reader.close()
    with pytest.warns(ReplayCorruptWarning) as warned:
        writer = ReplayShard(path, cfg)
    lines = [str(w.message) for w in warned]
    assert any("recovered [2, 6)" in line for line in lines), lines
    assert any("kept as c.0.unreadable-" in line for line in lines) == (damage == "checksum"), lines
    assert writer.visible_ids().tolist() == [2, 3, 4, 5]
    assert writer.insert(make_trial(cfg, 6)) == 6
    assert writer.get_trial(5).label == make_trial(cfg, 5).label
    writer.close()
    kept = list((path / "commit").glob("c.0.unreadable-*"))
    assert (len(kept), kept and kept[0].read_bytes()) == ((1, damaged) if damage == "checksum" else (0, []))
    with ReplayShard(path, cfg) as reopened:
        assert reopened.visible_ids().tolist() == [3, 4, 5, 6] and reopened.problems() == []
