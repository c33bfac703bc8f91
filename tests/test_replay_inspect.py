"""``python -m replay inspect|show|export`` on a replay root and on one shard."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from replay.client import ReplayClient, open_local_shards
from replay.inspect import cli, open_readers, trial_table
from replay.schema import max_errors
from replay.shard import ReplayShard
from replay.synthetic import numbered_trial as make_trial
from replay.synthetic import small_config as tiny_cfg

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def replay_root(tmp_path):
    cfg = tiny_cfg(capacity=16, shards=2)
    shards = open_local_shards(tmp_path / "replay", cfg)
    client = ReplayClient(shards, cfg, seed=0)
    trials = []
    for i in range(12):
        t = make_trial(
            cfg, i, label=i % 3 == 0, gripper=("wsg_50" if i < 4 else "parallel_jaw"),
            n_objects=1 if i % 2 else 5, n_obstacles=0, policy_version=i // 6,
        )
        trials.append(t)
        client.insert(t)
    for s in shards:
        s.close()
    return tmp_path / "replay", cfg, trials


def test_inspect_reports_counts_rates_bytes_and_schema(replay_root, tmp_path, capsys):
    root, cfg, trials = replay_root
    out = tmp_path / "summary.json"
    assert cli(["inspect", str(root), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    s = json.loads(out.read_text())
    assert s["trials"] == 12 and s["schema_version"] == 1 and len(s["shards"]) == 2
    assert s["success_rate"] == pytest.approx(4 / 12)
    assert s["by_gripper"]["wsg_50"]["trials"] == 4
    assert s["by_gripper"]["wsg_50"]["success_rate"] == pytest.approx(2 / 4)
    assert s["by_gripper"]["parallel_jaw"]["trials"] == 8
    assert s["by_scene"]["single"]["trials"] == 6 and s["by_scene"]["multi"]["trials"] == 6
    assert set(s["by_policy_version"]) == {"0", "1"} and s["by_object_set"]["synthetic"]["trials"] == 12
    assert s["bytes_on_disk"] > 0 and s["bytes_per_trial"] == pytest.approx(s["bytes_on_disk"] / 12)
    assert sum(b["trials"] for b in s["insert_rate"]["bins"]) == 12
    assert "success rate" in text and "by gripper" in text and "schema version 1" in text
    # one shard alone
    assert cli(["inspect", str(root / "shard_001")]) == 0
    assert "6 of capacity 8" in capsys.readouterr().out


def test_show_writes_a_png(replay_root, tmp_path, capsys):
    root, _, _ = replay_root
    png = tmp_path / "t.png"
    assert cli(["show", str(root), "--trial", "-1", "--out", str(png)]) == 0
    img = matplotlib.image.imread(png)
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 900


def test_export_matches_the_stored_trials(replay_root, tmp_path):
    root, cfg, trials = replay_root
    npz = tmp_path / "e.npz"
    assert cli(["export", str(root), "--trials", "2:7", "--out", str(npz)]) == 0
    data = np.load(npz)
    assert data["tsdf"].shape == (5,) + cfg.scene_grid.shape and data["tsdf"].dtype == np.float32
    by_episode = {t.meta.episode_id: t for t in trials}
    err = max_errors(cfg.replay.tsdf_levels)
    for b in range(5):
        meta = json.loads(str(data["meta_json"][b]))
        t = by_episode[meta["episode_id"]]
        assert tuple(data["action"][b]) == t.action and bool(data["label"][b]) == t.label
        assert np.abs(data["tsdf"][b] - t.observation.tsdf).max() <= err["tsdf"] + 1e-7
        assert str(data["gripper_key"][b]) == t.gripper_key
    assert list(data["position"]) == [2, 3, 4, 5, 6]
    assert (np.diff(data["insert_time"]) >= 0).all()


def test_export_leaves_out_an_unreadable_trial_with_one_warning(replay_root, tmp_path, capsys):
    """A damaged chunk costs its own trial only: the rest of the range is exported, and the
    position column says which trials came out."""
    root, cfg, trials = replay_root
    (root / "shard_000" / "tsdf" / "c.2.0.0.0").write_bytes(b"not a chunk")
    table = trial_table(open_readers(root))
    bad = int(np.flatnonzero((table["shard"] == 0) & (table["trial_id"] == 2))[0])
    npz = tmp_path / "e.npz"
    assert cli(["export", str(root), "--trials", "0:12", "--out", str(npz)]) == 0
    data = np.load(npz)
    assert list(data["position"]) == [p for p in range(12) if p != bad]
    by_episode = {t.meta.episode_id: t for t in trials}
    for b, meta in enumerate(data["meta_json"]):
        t = by_episode[json.loads(str(meta))["episode_id"]]
        assert tuple(data["action"][b]) == t.action and str(data["gripper_key"][b]) == t.gripper_key
    err = capsys.readouterr().err.strip().splitlines()
    assert [line for line in err if f"trial {bad} left out" in line], err
    assert all(line.startswith("warning: ") for line in err), err
    assert cli(["export", str(root), "--trials", f"{bad}:{bad + 1}", "--out", str(tmp_path / "none.npz")]) == 2
    assert "none of the 1 selected trials can be read" in capsys.readouterr().err
    assert not (tmp_path / "none.npz").exists()


def test_errors_are_one_line_with_exit_code_2(replay_root, tmp_path, capsys):
    root, _, _ = replay_root
    assert cli(["show", str(root), "--trial", "99", "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--trial 99" in err and "12 trials" in err
    assert cli(["inspect", str(tmp_path / "nowhere")]) == 2
    assert f"{tmp_path / 'nowhere'}: no such file or folder" in capsys.readouterr().err
    assert cli(["inspect", str(tmp_path)]) == 2
    assert "not a replay root or shard group" in capsys.readouterr().err
    assert cli(["export", str(root), "--trials", "5", "--out", str(tmp_path / "x.npz")]) == 2
    assert "expected A:B" in capsys.readouterr().err
    for command, out, needle in (("show", "x.txt", "expected a .png file"), ("export", "x", "expected a .npz file")):
        where = ["--trial", "0"] if command == "show" else ["--trials", "0:2"]
        assert cli([command, str(root), *where, "--out", str(tmp_path / out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and f"--out {tmp_path / out}: {needle}" in err, err
        assert not (tmp_path / out).exists() and not (tmp_path / f"{out}.npz").exists()


def test_module_entry_point(replay_root):
    root, _, _ = replay_root
    r = subprocess.run(
        [sys.executable, "-m", "replay", "inspect", str(root)], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    assert r.returncode == 0, r.stderr
    assert "trials            12" in r.stdout
    assert ReplayShard(root / "shard_000", read_only=True).size() == 6


def test_a_corrupt_chunk_is_one_warning_line_and_the_error_one_line(replay_root, tmp_path, capsys):
    """A damaged chunk reaches the user of `python -m replay` as one `warning:` line (not Python's
    two-line warning with the source line) and, where the trial is asked for, one `error:` line."""
    root, _, _ = replay_root
    for shard in ("shard_000", "shard_001"):  # the oldest trial is the first of one of them (the client's pick)
        (root / shard / "tsdf" / "c.0.0.0.0").write_bytes(b"not a chunk")
    assert cli(["show", str(root), "--trial", "0", "--out", str(tmp_path / "t.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and all(line.startswith(("warning: ", "error: ")) for line in err), err
    assert err[-1].startswith("error: ") and not any("shard.py" in line for line in err), err


def test_inspect_reads_every_chunk_and_lists_the_unreadable_trial(replay_root, tmp_path, capsys):
    """inspect finds a damaged volume chunk by itself (it does not wait for a sample to meet it):
    the trial is counted unreadable, named on a problem line, and left out of the rates."""
    root, _, _ = replay_root
    (root / "shard_000" / "tsdf" / "c.2.0.0.0").write_bytes(b"not a chunk")
    out = tmp_path / "summary.json"
    assert cli(["inspect", str(root), "--json", str(out)]) == 0
    captured = capsys.readouterr()
    s = json.loads(out.read_text())
    assert s["trials"] == 11 and s["shards"][0]["corrupt"] == 1 and s["shards"][1]["corrupt"] == 0
    assert any("tsdf: chunk 2 of trial 2 unreadable" in p for p in s["shards"][0]["problems"])
    assert "1 unreadable" in captured.out and "problem: " in captured.out
    assert all(line.startswith("warning: ") for line in captured.err.strip().splitlines())


def test_policy_versions_are_listed_in_numeric_order(tmp_path):
    cfg = tiny_cfg(capacity=4)
    shard = ReplayShard(tmp_path / "s", cfg)
    for i, version in enumerate((10, 2, 1)):
        shard.insert(make_trial(cfg, i, policy_version=version))
    shard.close()
    out = tmp_path / "summary.json"
    assert cli(["inspect", str(tmp_path / "s"), "--json", str(out)]) == 0
    assert list(json.loads(out.read_text())["by_policy_version"]) == ["1", "2", "10"]
