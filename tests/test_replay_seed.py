"""Seeding a new run's replay from an earlier one (replay.seed_from): the trials arrive as
stored, the newest first up to capacity, a mismatched or corrupt source is named in one line,
and the run's own counters (trials, rate limiter, max_trials) leave the seeded trials out."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr

from common.config import ConfigError, load_config
from learner.loop import LearnerProcess, total_inserted
from learner.run import cli, parse_args, resolve
from replay.client import ReplayClient, open_local_shards
from replay.schema import ATTR_KEY, ReplayError, ReplaySchemaError
from replay.inspect import summarize
from replay.seed import SEED_CLIENT, STAGING_SUFFIX, seed_replay
from replay.shard import ReplayShard
from replay.synthetic import numbered_trial
from replay.synthetic import small_config as tiny_cfg
from tests.test_learner import SMALL

def _source(path: Path, cfg, n: int) -> list[ReplayShard]:
    """A replay at ``path`` holding trials 0..n-1 (episode_id = i; every third with obstacles)."""
    shards = open_local_shards(path, cfg)
    client = ReplayClient(shards, cfg, seed=0)
    for i in range(n):
        t = numbered_trial(cfg, i, n_objects=2, n_obstacles=1 if i % 3 == 0 else 0)
        t.label = bool(i % 2)
        client.insert(t.validate())
    client.flush()
    return shards


def _by_episode(shards: list[ReplayShard]) -> dict[int, object]:
    """Every visible trial's stored record, keyed by its episode id."""
    out = {}
    for s in shards:
        for t in s.visible_ids():
            rec = s.encoded(int(t), (0, 0))
            out[json.loads(rec.meta_json)["episode_id"]] = rec
    return out


def _digest(path: Path) -> dict[str, str]:
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


def test_seeded_replay_holds_the_source_trials_as_stored(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=1)
    source = _source(tmp_path / "old" / "replay", cfg, 7)
    before = _by_episode(source)
    for s in source:
        s.close()
    cfg.replay.shards = 2
    report = seed_replay(tmp_path / "old", tmp_path / "new" / "replay", cfg)  # a run directory is enough
    assert report["trials"] == report["available"] == 7 and report["skipped"] == 0
    assert report["seeded_from"] == str((tmp_path / "old" / "replay").resolve())
    assert not (tmp_path / "new" / ("replay" + STAGING_SUFFIX)).exists()
    shards = open_local_shards(tmp_path / "new" / "replay", cfg)
    after = _by_episode(shards)
    assert after.keys() == before.keys()
    for ep, old in before.items():
        new = after[ep]
        for name in ("tsdf", "surface", "gripper"):
            assert np.array_equal(getattr(new, name), getattr(old, name)), (ep, name)
        assert (new.obstacle is None) == (old.obstacle is None)
        if old.obstacle is not None:
            assert np.array_equal(new.obstacle, old.obstacle)
        assert (new.action, new.label, new.score, new.meta_json, new.gripper_key) == (
            old.action, old.label, old.score, old.meta_json, old.gripper_key)
    tokens = np.concatenate([s.column("insert_token", s.visible_ids()) for s in shards])
    assert (tokens[:, 0] == SEED_CLIENT).all()
    assert [s.stats()["seeded"] for s in shards] == [4, 3], "round-robin, oldest first"
    root = zarr.open_group(str(tmp_path / "new" / "replay"), mode="r").attrs[ATTR_KEY]
    assert root["seeded_trials"] == 7 and root["seeded_from"] == report["seeded_from"]
    client = ReplayClient(shards, cfg, seed=1)
    assert total_inserted(client) == 0, "seeded trials are not this run's trials"
    assert client.run_marks() == {"episode_ends": {}, "policy_version": -1}, "the source run's episode numbers do not number this run's"
    client.insert(numbered_trial(cfg, 100).validate())
    client.flush()
    assert total_inserted(client) == 1 and client.size() == 8
    assert client.run_marks()["episode_ends"] == {0: 101}
    for s in shards:
        s.close()


def test_seed_keeps_the_newest_trials_up_to_capacity(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=1)
    for s in _source(tmp_path / "old", cfg, 12):
        s.close()
    small = tiny_cfg(capacity=6, shards=2)
    report = seed_replay(tmp_path / "old", tmp_path / "new", small)
    assert report["trials"] == 6 and report["available"] == 12
    shards = open_local_shards(tmp_path / "new", small)
    assert sorted(_by_episode(shards)) == list(range(6, 12))
    for s in shards:
        s.close()


def test_newest_across_source_shards_into_uneven_shards_with_shared_gripper_rows(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=2)
    source = open_local_shards(tmp_path / "old", cfg)
    for i in range(10):  # one gripper at three openings: trials share gripper-table rows
        source[i % 2].insert(numbered_trial(cfg, i, scale=1.0, openings=(0.6, 0.8, 1.0)))
    before = _by_episode(source)
    for sh in source:
        sh.close()
    three = tiny_cfg(capacity=7, shards=3)  # 3 slots per shard
    report = seed_replay(tmp_path / "old", tmp_path / "new", three)
    assert report["trials"] == 7 and report["available"] == 10
    shards = open_local_shards(tmp_path / "new", three)
    after = _by_episode(shards)
    assert sorted(after) == list(range(3, 10)), "the newest by commit time, across both source shards"
    for ep, new in after.items():
        assert np.array_equal(new.gripper, before[ep].gripper) and new.action == before[ep].action
        assert np.array_equal(new.tsdf, before[ep].tsdf)
    assert [sh.stats()["seeded"] for sh in shards] == [3, 2, 2]
    assert all(sh.stats()["table_rows_used"] <= min(3, sh.stats()["visible"]) for sh in shards)
    client = ReplayClient(shards[:1], three, seed=0)
    for i in range(4):  # the run's own trials push every seeded one out of shard 0
        client.insert(numbered_trial(three, 100 + i).validate())
    client.flush()
    assert total_inserted(client) == 4 and shards[0].stats()["visible"] == 3
    for sh in shards:
        sh.close()


def test_left_over_staging_folder_is_replaced(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=1)
    for sh in _source(tmp_path / "old", cfg, 3):
        sh.close()
    staging = tmp_path / "new" / ("replay" + STAGING_SUFFIX)
    staging.mkdir(parents=True)
    (staging / "half-written").write_text("a seeding cut off")
    assert seed_replay(tmp_path / "old", tmp_path / "new" / "replay", cfg)["trials"] == 3
    assert not staging.exists() and not (tmp_path / "new" / "replay" / "half-written").exists()


def test_mismatched_source_is_one_line_and_writes_nothing(tmp_path):
    coarse = tiny_cfg(capacity=16, shards=1, levels=63)
    for s in _source(tmp_path / "old", coarse, 3):
        s.close()
    before = _digest(tmp_path / "old")
    with pytest.raises(ReplaySchemaError) as e:
        seed_replay(tmp_path / "old", tmp_path / "new" / "replay", tiny_cfg(capacity=16, shards=2))
    line = str(e.value)
    assert "\n" not in line and "shard_000" in line and "tsdf_levels" in line and "63" in line, line
    assert not (tmp_path / "new" / "replay").exists()
    assert not (tmp_path / "new" / ("replay" + STAGING_SUFFIX)).exists()
    assert _digest(tmp_path / "old") == before, "the source is only read"
    with pytest.raises(ReplayError, match="no such file"):
        seed_replay(tmp_path / "missing", tmp_path / "new" / "replay", coarse)
    wider = tiny_cfg(capacity=16, shards=1, levels=63)
    wider.scene_grid.truncation_voxels = 3.0  # same shapes, another TSDF: the sub-field is named
    with pytest.raises(ReplaySchemaError, match=r"scene_grid\.truncation: source has 0\.04, .* gives 0\.024"):
        seed_replay(tmp_path / "old", tmp_path / "new" / "replay", wider)


def test_unreadable_source_trial_is_skipped_and_named(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=1)
    for s in _source(tmp_path / "old", cfg, 5):
        s.close()
    chunk = tmp_path / "old" / "shard_000" / "tsdf" / "c.2.0.0.0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    report = seed_replay(tmp_path / "old", tmp_path / "new", cfg)
    assert report["trials"] == 4 and report["skipped"] == 1
    assert "tsdf" in report["problems"][0] and "trial 2" in report["problems"][0]
    shards = open_local_shards(tmp_path / "new", cfg)
    assert sorted(_by_episode(shards)) == [0, 1, 3, 4]
    assert shards[0].stats()["seeded"] == 4
    for s in shards:
        s.close()


def test_trials_lost_in_the_source_columns_are_counted_and_named(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=1)  # 4 trials per column chunk
    for sh in _source(tmp_path / "old", cfg, 6):
        sh.close()
    meta = tmp_path / "old" / "shard_000" / "meta" / "c.1"  # slots 4..7
    meta.write_bytes(meta.read_bytes()[:-3] + b"xyz")
    report = seed_replay(tmp_path / "old", tmp_path / "new", cfg)
    assert report["trials"] == report["available"] == 4 and report["skipped"] == 2
    assert any("/meta" in line for line in report["problems"]), report["problems"]


def test_inspect_counts_seeded_trials_apart(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=1)
    for sh in _source(tmp_path / "old", cfg, 5):
        sh.close()
    seed_replay(tmp_path / "old", tmp_path / "new", cfg)
    shards = open_local_shards(tmp_path / "new", cfg)
    for i in range(3):
        shards[0].insert(numbered_trial(cfg, 50 + i, policy_version=1))
    shards[0].close()
    s = summarize(tmp_path / "new")
    assert s["trials"] == 8 and s["seeded_trials"] == 5
    assert {k: v["trials"] for k, v in s["by_policy_version"].items()} == {"0 (seeded)": 5, "1": 3}
    assert sum(b["trials"] for b in s["insert_rate"]["bins"]) == 3, "the copies are not an insert rate"


def test_learner_counts_only_the_runs_own_trials(tmp_path):
    cfg = load_config("tiny", overrides=SMALL)
    for s in _source(tmp_path / "old", cfg, 12):
        s.close()
    seed_replay(tmp_path / "old", tmp_path / "run" / "replay", cfg)
    shards = open_local_shards(tmp_path / "run" / "replay", cfg)
    torch.manual_seed(0)
    proc = LearnerProcess(cfg, shards, str(tmp_path / "run"), seed=0, torch_threads=1)
    assert proc.inserted() == 0
    assert proc.train(4)["ran"] == 0, "no step before the run's own min_replay trials, seeded ones aside"
    own = 11  # with min_replay 8 and 2 samples per insert: (11 - 8 + 1) * 2 = 8 samples, one step of 8
    assert proc.learner.limiter.allowed_steps(own, 0) == 1
    client = ReplayClient(shards, cfg, seed=1)
    for i in range(own):
        t = numbered_trial(cfg, 1000 + i, n_objects=2)
        t.label = bool(i % 2)
        client.insert(t.validate())
    client.flush()
    stats = proc.train(4)
    assert stats["inserted"] == own and stats["ran"] == 1, stats
    assert proc.replay.size() == 12 + own
    for s in shards:
        s.close()


def test_launcher_seeds_a_new_run_once_and_records_the_source(tmp_path, capsys):
    cfg = load_config("tiny")
    for s in _source(tmp_path / "old" / "replay", cfg, 3):
        s.close()
    run = tmp_path / "run"
    args = ["--config", "tiny", "--run-dir", str(run), "--set", f"replay.seed_from={tmp_path / 'old'}"]
    resolved, _ = resolve(parse_args(args))
    assert resolved.replay.seed_from == str((tmp_path / "old" / "replay").resolve())
    assert load_config(run / "config.yaml").replay.seed_from == resolved.replay.seed_from
    assert "replay seeded with 3 of 3 trials" in capsys.readouterr().out
    resumed, _ = resolve(parse_args(["--resume", "--run-dir", str(run)]))
    assert resumed.replay.seed_from == resolved.replay.seed_from, "a resumed run keeps its replay, seeds nothing"
    with pytest.raises(ConfigError) as e:
        resolve(parse_args(["--resume", "--run-dir", str(run), "--set", f"replay.seed_from={tmp_path}"]))
    assert "\n" not in str(e.value) and "replay.seed_from" in str(e.value) and "config.yaml" in str(e.value)
    assert load_config(run / "config.yaml").replay.seed_from == resolved.replay.seed_from, "the record is kept"
    shards = open_local_shards(run / "replay", cfg)
    assert sum(s.stats()["end"] for s in shards) == 3
    for s in shards:
        s.close()
    rc = cli(["--actors", "0", "--config", "tiny", "--run-dir", str(tmp_path / "bad"),
              "--set", f"replay.seed_from={tmp_path / 'nothing'}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "replay.seed_from" in err[0] and "nothing" in err[0], err
    assert not (tmp_path / "bad" / "config.yaml").exists() and not (tmp_path / "bad" / "replay").exists()
    assert not (tmp_path / "bad").exists(), "a refused run leaves no run directory behind"


def test_start_cut_off_before_its_config_reuses_the_untouched_seeded_replay(tmp_path, capsys):
    cfg = load_config("tiny")
    for s in _source(tmp_path / "old" / "replay", cfg, 3):
        s.close()
    run = tmp_path / "run"
    assert not seed_replay(tmp_path / "old", run / "replay", cfg)["reused"]  # renamed; config.yaml never written
    before = _digest(run / "replay")
    args = ["--config", "tiny", "--run-dir", str(run), "--set", f"replay.seed_from={tmp_path / 'old'}"]
    resolved, _ = resolve(parse_args(args))
    assert "replay already seeded with 3 trials" in capsys.readouterr().out
    assert _digest(run / "replay") == before, "the seeded replay is used as it is"
    assert load_config(run / "config.yaml").replay.seed_from == str((tmp_path / "old" / "replay").resolve())
    other = tmp_path / "other"
    for s in _source(other / "replay", cfg, 2):
        s.close()
    assert not seed_replay(tmp_path / "old", tmp_path / "run2" / "replay", cfg)["reused"]
    with pytest.raises(ReplayError, match="already has a replay"):
        seed_replay(other, tmp_path / "run2" / "replay", cfg)  # seeded from another source
    shards = open_local_shards(tmp_path / "run2" / "replay", cfg)
    client = ReplayClient(shards, cfg, seed=0)
    client.insert(numbered_trial(cfg, 99, n_objects=1, n_obstacles=0).validate())
    client.flush()
    for s in shards:
        s.close()
    with pytest.raises(ReplayError, match="already has a replay"):
        seed_replay(tmp_path / "old", tmp_path / "run2" / "replay", cfg)  # a trial of its own arrived


def test_untouched_seeded_replay_made_with_another_config_is_refused_in_one_line(tmp_path, capsys):
    cfg = load_config("tiny")
    for s in _source(tmp_path / "old" / "replay", cfg, 3):
        s.close()
    run = tmp_path / "run"
    seed_replay(tmp_path / "old", run / "replay", cfg)  # a start cut off before its config.yaml
    before = _digest(run / "replay")
    other = load_config("tiny", overrides=["model.rotations=8"])
    with pytest.raises(ReplaySchemaError) as e:  # action rotation indices would mean other angles
        seed_replay(tmp_path / "old", run / "replay", other)
    line = str(e.value)
    assert "\n" not in line and "shard_000" in line and "rotations: the replay already seeded here has 16" in line
    assert "gives 8" in line and "replay.seed_from" in line and f"remove {run / 'replay'}" in line, line
    rc = cli(["--actors", "0", "--config", "tiny", "--run-dir", str(run),
              "--set", f"replay.seed_from={tmp_path / 'old'}", "--set", "replay.capacity=1000"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "capacity: the replay already seeded here has 1000" in err[0], err
    assert "gives 500" in err[0], err
    assert _digest(run / "replay") == before and not (run / "config.yaml").exists(), "nothing written, nothing lost"
    assert seed_replay(tmp_path / "old", run / "replay", cfg)["reused"], "with its own config it is still reused"


def test_seeding_reports_progress(tmp_path, monkeypatch):
    cfg = tiny_cfg(capacity=16, shards=2)
    for sh in _source(tmp_path / "old", cfg, 9):
        sh.close()
    monkeypatch.setattr("replay.seed.PROGRESS_EVERY_S", 0.0)
    calls = []
    report = seed_replay(tmp_path / "old", tmp_path / "new" / "replay", cfg, progress=lambda d, t: calls.append((d, t)))
    assert report["trials"] == 9
    assert calls == [(d, 9) for d in range(9)], calls
