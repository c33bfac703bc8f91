"""End to end: `python -m launcher` with real Ray actors, PyBullet, the network and the Zarr replay.

The 2-actor run is part of the default suite; the fault scenarios (kill -9 of an actor, of a
shard, and of the launcher followed by --resume) take minutes and are marked slow.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import zarr

from common.checkpoint import read_checkpoint
from common.config import load_config, save_config
from learner.run import cli, with_earlier_parts
from replay.client import ReplayClient, open_local_shards
from replay.schema import ATTR_KEY, SCHEMA_VERSION

ROOT = Path(__file__).resolve().parents[1]


def _launch(run_dir: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "launcher", "--actors", "2", "--config", "tiny", "--run-dir", str(run_dir), "--quiet", *extra]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


def _summary(output: str) -> dict:
    last = [ln for ln in output.splitlines() if ln.startswith("{")][-1]
    return json.loads(last)


def _committed(run_dir: Path) -> int:
    """Visible trials in the run's replay, read with plain zarr-backed shards."""
    cfg = load_config(run_dir / "config.yaml")
    shards = open_local_shards(run_dir / "replay", cfg, read_only=True)
    try:
        return ReplayClient(shards, cfg).size()
    finally:
        for s in shards:
            s.close()


def _progress_trials(run_dir: Path) -> int:
    path = run_dir / "progress.jsonl"
    if not path.is_file():
        return 0
    lines = path.read_text().splitlines()
    return json.loads(lines[-1])["trials"] if lines else 0


def _wait_for(predicate, timeout: float, what: str, proc: subprocess.Popen | None = None) -> None:
    t0 = time.time()
    while not predicate():
        if proc is not None and proc.poll() is not None:
            out = proc.stdout.read() if proc.stdout else ""
            raise AssertionError(f"launcher exited early while waiting for {what}:\n{out[-3000:]}")
        if time.time() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(1.0)


def test_two_actor_run_collects_trains_and_publishes(tmp_path):
    run_dir = tmp_path / "run"
    t0 = time.time()
    proc = _launch(run_dir, "--max-trials", "30", "--set", "learner.insert_lead=4")
    out, _ = proc.communicate(timeout=600)
    elapsed = time.time() - t0
    assert proc.returncode == 0, out[-3000:]
    summary = _summary(out)
    assert summary["trials"] >= 30
    assert summary["learner_steps"] > 0
    assert summary["weights_published"] >= 2
    assert summary["weights_published"] == summary["weights_version"]  # one version each, from 1, none lost
    # The actor side of the rate limiter: inserts never lead the learner's schedule by the
    # allowance plus one in-flight single-object episode per actor.
    cfg = load_config(run_dir / "config.yaml")
    lead = summary["trials"] - cfg.learner.min_replay - summary["learner_samples"] / cfg.learner.samples_per_insert
    assert lead < cfg.learner.insert_lead + 2, (lead, summary)
    assert _committed(run_dir) >= 30
    ckpt = read_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert ckpt.step == summary["learner_steps"] and ckpt.cfg.replay.shards == 2
    assert (run_dir / "config.yaml").is_file() and list((run_dir / "tb").iterdir())
    group = zarr.open_group(str(run_dir / "replay" / "shard_000"), mode="r")
    assert group.attrs[ATTR_KEY]["schema_version"] == SCHEMA_VERSION
    print(f"2-actor tiny run: {summary['trials']} trials in {elapsed:.1f} s")


FAILING_LEARNER = """
import learner.loop as loop

_train = loop.LearnerProcess.train


def train(self, max_steps, *args, **kwargs):
    if self.learner.stats.steps > 0:
        raise RuntimeError("learner failure for the test")
    return _train(self, max_steps, *args, **kwargs)


loop.LearnerProcess.train = train
"""
"""A sitecustomize for the launcher and every Ray process it starts: a learner whose chunk fails
once it has trained."""


def _run_with_hook(tmp_path, hook_source: str, max_trials: int, *extra: str, **env_extra: str):
    """``python -m launcher --actors 2`` on the tiny config (periodic checkpoints an hour apart)
    with ``hook_source`` as the sitecustomize of the launcher and every Ray process; returns the
    completed process and the run directory."""
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(hook_source)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(hook), str(ROOT)]), **env_extra)
    run_dir = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "launcher", "--actors", "2", "--config", "tiny", "--run-dir", str(run_dir), "--quiet",
         "--max-trials", str(max_trials), "--set", "learner.checkpoint_minutes=60", *extra],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=900,
    )
    return proc, run_dir


def test_a_failing_learner_still_lets_the_actors_finish_and_writes_the_final_checkpoint(tmp_path):
    """A learner chunk that raises ends the run with that error, but first the actors finish
    their episodes and the learner writes the final checkpoint (the only one here: periodic
    checkpoints are an hour apart), which counts every committed trial."""
    proc, run_dir = _run_with_hook(tmp_path, FAILING_LEARNER, 200)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "learner failure for the test" in out, out[-3000:]
    assert "learner: last chunk failed (RayTaskError" in out, out[-3000:]
    ckpt = read_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert ckpt.step >= 1 and ckpt.extra["replay"]["inserted"] == _committed(run_dir) > 0


DIVERGING_LEARNER = """
import torch

import learner.learner as learner_module

_train = learner_module.Learner.train


def train(self, steps, max_seconds=None):
    if self.stats.steps >= 2:
        with torch.no_grad():
            next(self.model.parameters()).fill_(float("nan"))
    return _train(self, steps, max_seconds)


learner_module.Learner.train = train
"""
"""A sitecustomize for the launcher and every Ray process it starts: a learner whose weights turn
non-finite after two steps."""


def test_a_run_whose_learner_diverges_ends_with_one_line_and_keeps_finite_weights(tmp_path):
    """With Ray actors, a learner chunk that diverges ends the run: rc 2, the divergence as the
    last stderr line and the summary's error, and no checkpoint with non-finite weights."""
    proc, run_dir = _run_with_hook(tmp_path, DIVERGING_LEARNER, 200)
    out = proc.stdout + proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode == 2 and "training diverged" in last and "it wrote no checkpoint" in last, out[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert "training diverged" in summary["error"] and summary["trials"] < 200, summary
    assert not (run_dir / "checkpoints" / "latest.pt").exists(), "the only checkpoint would hold NaN weights"


LOST_LEARNER = """
import os

import learner.loop as loop

_train = loop.LearnerProcess.train


def train(self, max_steps, *args, **kwargs):
    import ray

    if self.learner.stats.steps >= 3 and not ray.get_runtime_context().was_current_actor_reconstructed:
        with open(os.environ["LOST_LEARNER_VERSION"], "w") as f:
            f.write(str(self.learner.stats.version))
        os._exit(1)
    return _train(self, max_steps, *args, **kwargs)


loop.LearnerProcess.train = train
"""
"""A sitecustomize for the launcher and every Ray process it starts: the learner's first process
dies (as if killed) once it has trained, writing the weights version it had published."""


def _policy_versions(run_dir: Path) -> list[int]:
    cfg = load_config(run_dir / "config.yaml")
    shards = open_local_shards(run_dir / "replay", cfg, read_only=True)
    try:
        return [s.get_trial(int(t)).meta.policy_version for s in shards for t in s.visible_ids()]
    finally:
        for s in shards:
            s.close()


def test_a_lost_learner_process_restarts_and_the_actors_take_its_new_weights(tmp_path):
    """The learner's process dies with no checkpoint written yet: Ray restarts it, it starts again
    from the initial weights, and the run goes on to its limit; the actors take the restarted
    learner's weights (their numbering: test_learner's after_version test) and the final
    checkpoint counts every committed trial."""
    lost = tmp_path / "lost_version"
    proc, run_dir = _run_with_hook(tmp_path, LOST_LEARNER, 60, "--set", "learner.insert_lead=4",
                                   LOST_LEARNER_VERSION=str(lost))
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "learner: process lost (" in out and lost.is_file(), out[-3000:]
    summary = _summary(proc.stdout)
    assert summary["learner_restarts"] == 1 and summary["trials"] >= 60, summary
    before = int(lost.read_text())
    assert max(_policy_versions(run_dir)) > before, "the actors never took the restarted learner's weights"
    ckpt = read_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert ckpt.version > before and ckpt.extra["replay"]["inserted"] == _committed(run_dir)


def test_a_mistyped_command_is_one_line_naming_the_commands(capsys):
    """A misspelt command was read as the train command's (or an evaluation's) arguments."""
    from actors.evaluate import cli as evaluate_cli
    from launcher import main

    assert main(["evalute", "table", "x.json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["launcher: error: 'evalute': not a command (one of train, rollout, grippers, evaluate; none = train)"]
    assert evaluate_cli(["tabel", "x.json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evaluate: error: 'tabel': not a command (one of table, compare"), err


def test_bad_config_value_is_one_line(tmp_path, capsys):
    rc = cli(["--actors", "0", "--config", "tiny", "--set", "learner.lr=fast", "--run-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "learner.lr" in err[0]


@pytest.mark.parametrize("override, field", [
    ("grippers.train_grippers=nosuch", "grippers.train_grippers: nosuch: unknown gripper"),
    ("sim.objects=nosuch", "sim.objects: object set 'nosuch': unknown"),
    ("model.feature_cell=0.024", "scene_grid.voxel_size: model.feature_cell / voxel_size must be a power of 2"),
    ("sim.fence_half_extent=0.01", "sim.drop_half_extent: 0.1 m must be below sim.fence_half_extent 0.01 m"),
    ("sim.camera_height=-1", "sim.camera_height: -1.0 m must exceed the grid top"),
    ("sim.image_pixels_per_voxel=0", "sim.image_pixels_per_voxel: expected > 0, got 0.0"),
    ("learner.min_replay=5000", "learner.min_replay: 5000 trials before training, but the replay holds at most "
                                "replay.capacity 2000"),
    pytest.param("learner.device=cuda", "learner.device: cuda, but torch",
                 marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")),
])
def test_a_name_or_network_the_run_cannot_use_is_one_line_and_starts_nothing(tmp_path, capsys, override, field):
    """An unknown training gripper or object set, or grids the network's widths cannot encode, is
    refused before RUN/config.yaml is written (else every actor fails and the corrected command
    finds the folder taken)."""
    run_dir = tmp_path / "r"
    rc = cli(["--actors", "0", "--config", "tiny", "--set", override, "--run-dir", str(run_dir)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "tiny.yaml with --set: " in err[0] and field in err[0], err
    assert not run_dir.exists()


def test_init_weights_of_another_network_is_one_line_and_starts_nothing(tmp_path, capsys):
    run_dir = tmp_path / "r"
    shipped = "model:adagrasp-single-2core-95min-arm"  # default widths; the tiny config's are narrower
    rc = cli(["--actors", "0", "--config", "tiny", "--set", f"learner.init_weights={shipped}", "--run-dir", str(run_dir)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "learner.init_weights" in err[0] and "model.scene_widths" in err[0] and "checkpoint.pt" in err[0]
    assert not run_dir.exists(), "a refused run leaves no run directory behind"


def test_resume_requires_existing_run(tmp_path, capsys):
    rc = cli(["--resume", "--run-dir", str(tmp_path / "nothing")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "config.yaml" in err


def test_resume_refuses_a_config_file_and_an_empty_run_config(tmp_path, capsys):
    """--resume runs with RUN/config.yaml: another --config would be ignored, and an empty
    RUN/config.yaml would resume with the defaults; both are one line, and nothing is written."""
    run_dir = tmp_path / "r"
    run_dir.mkdir()
    save_config(load_config("tiny"), run_dir / "config.yaml")
    before = (run_dir / "config.yaml").read_bytes()
    rc = cli(["--resume", "--run-dir", str(run_dir), "--config", "paper"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: --config paper:") and "--set" in err[0], err
    assert (run_dir / "config.yaml").read_bytes() == before and sorted(os.listdir(run_dir)) == ["config.yaml"]
    (run_dir / "config.yaml").write_text("\n")
    rc = cli(["--resume", "--run-dir", str(run_dir)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "config.yaml: empty" in err[0], err
    assert sorted(os.listdir(run_dir)) == ["config.yaml"]


@pytest.mark.parametrize("flag, value, key", [
    ("--max-trials", "-5", "run.max_trials"),
    ("--max-minutes", "-1", "run.max_minutes"),
    ("--shards", "0", "replay.shards"),
])
def test_a_limit_flag_out_of_range_is_one_line_and_leaves_the_run_as_it_was(tmp_path, capsys, flag, value, key):
    """--max-trials, --max-minutes and --shards are checked like their config keys before anything
    is written: a resumed run's config.yaml keeps its values (a -5 written there would refuse every
    later resume), and a new run leaves no folder."""
    run_dir = tmp_path / "r"
    run_dir.mkdir()
    save_config(load_config("tiny"), run_dir / "config.yaml")
    before = (run_dir / "config.yaml").read_bytes()
    for argv in (["--resume", "--run-dir", str(run_dir)], ["--config", "tiny", "--run-dir", str(tmp_path / "new")]):
        rc = cli([*argv, "--actors", "0", flag, value])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith(f"error: {flag}: {key}: expected a value in"), err
    assert (run_dir / "config.yaml").read_bytes() == before and sorted(os.listdir(run_dir)) == ["config.yaml"]
    assert not (tmp_path / "new").exists()


def test_resumed_run_summary_keeps_the_earlier_parts(tmp_path, capsys):
    path = tmp_path / "summary.json"
    first = {"trials": 10, "episodes": 3, "weights_published": 2}
    assert with_earlier_parts(path, first) == first, "a new run has no earlier parts"
    path.write_text(json.dumps(first))
    second = with_earlier_parts(path, {"trials": 25, "episodes": 4, "weights_published": 1})
    assert second == {"trials": 25, "episodes": 4, "weights_published": 1, "earlier_parts": [first]}
    path.write_text(json.dumps(second))
    third = with_earlier_parts(path, {"trials": 30, "episodes": 1})
    assert third["earlier_parts"] == [first, {"trials": 25, "episodes": 4, "weights_published": 1}]
    path.write_text('{"trials": 3')  # a summary cut short
    assert with_earlier_parts(path, {"trials": 31}) == {"trials": 31}
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "unreadable" in err[0], err
    aside = list(tmp_path.glob("summary.unreadable-*.json"))
    assert len(aside) == 1 and aside[0].read_text() == '{"trials": 3', "the unreadable file is kept, not overwritten"
    assert not path.exists()


def _ray_worker_pids(name: str) -> list[int]:
    out = subprocess.run(["ps", "-eo", "pid,args"], capture_output=True, text=True).stdout
    return [int(line.split()[0]) for line in out.splitlines() if f"ray::{name}" in line]


@pytest.mark.slow
def test_actor_kill_is_restarted_and_run_continues(tmp_path):
    run_dir = tmp_path / "run"
    proc = _launch(run_dir, "--max-trials", "60")
    try:
        _wait_for(lambda: _progress_trials(run_dir) >= 10 and _ray_worker_pids("ActorProcess"), 400, "10 trials", proc)
        before = _progress_trials(run_dir)
        victim = _ray_worker_pids("ActorProcess")[0]
        os.kill(victim, signal.SIGKILL)
        out, _ = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, out[-3000:]
    summary = _summary(out)
    assert summary["actor_restarts"] >= 1
    assert summary["trials"] >= 60 > before
    assert _committed(run_dir) >= 60  # every visible trial is complete, or reading it would fail


@pytest.mark.slow
def test_shard_kill_keeps_committed_trials(tmp_path):
    run_dir = tmp_path / "run"
    proc = _launch(run_dir, "--max-trials", "50")
    try:
        _wait_for(lambda: _progress_trials(run_dir) >= 10 and _ray_worker_pids("ReplayShard"), 400, "10 trials", proc)
        committed_before = _progress_trials(run_dir)
        os.kill(_ray_worker_pids("ReplayShard")[0], signal.SIGKILL)
        out, _ = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, out[-3000:]
    assert _committed(run_dir) >= max(50, committed_before)


@pytest.mark.slow
def test_launcher_kill_then_resume(tmp_path):
    run_dir = tmp_path / "run"
    proc = _launch(run_dir, "--max-trials", "1000", "--set", "learner.checkpoint_minutes=0.2")
    try:
        _wait_for(lambda: (run_dir / "checkpoints" / "latest.pt").is_file() and _progress_trials(run_dir) >= 15,
                  600, "a checkpoint and 15 trials", proc)
        os.killpg(proc.pid, signal.SIGKILL)  # the launcher and every Ray process it started
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    subprocess.run(["ray", "stop", "--force"], capture_output=True)
    committed = _committed(run_dir)
    step_before = read_checkpoint(run_dir / "checkpoints" / "latest.pt").step
    assert committed >= 15
    resumed = subprocess.run(
        [sys.executable, "-m", "launcher", "--resume", "--run-dir", str(run_dir), "--actors", "2",
         "--max-trials", str(committed + 10), "--quiet"],
        cwd=ROOT, capture_output=True, text=True, timeout=900,
    )
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    summary = _summary(resumed.stdout)
    assert summary["trials"] >= committed + 10
    assert _committed(run_dir) >= committed + 10
    assert read_checkpoint(run_dir / "checkpoints" / "latest.pt").step >= step_before
    assert "earlier_parts" not in summary, "the killed part wrote no summary"
    again = subprocess.run(
        [sys.executable, "-m", "launcher", "--resume", "--run-dir", str(run_dir), "--actors", "2",
         "--max-trials", str(summary["trials"] + 5), "--quiet"],
        cwd=ROOT, capture_output=True, text=True, timeout=900,
    )
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    written = json.loads((run_dir / "summary.json").read_text())
    assert written["earlier_parts"] == [summary] and written["trials"] >= summary["trials"] + 5


@pytest.mark.parametrize("argv, message", [
    (["--actors", "-1"], "--actors: expected 0 (everything in this process) or more, got -1"),
    (["--actors", "0", "--address", "auto"], "--address auto: --actors 0 runs everything in this process"),
])
def test_actor_counts_the_run_cannot_use_are_one_line(tmp_path, capsys, argv, message):
    """A negative count started Ray, the shards and the learner with no actor to collect trials;
    --address with --actors 0 was silently ignored (the run stayed in this process)."""
    run_dir = tmp_path / "r"
    rc = cli([*argv, "--config", "tiny", "--run-dir", str(run_dir)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err
    assert not run_dir.exists()


def test_the_run_directory_is_absolute_and_ray_address_counts_as_a_cluster(tmp_path, monkeypatch):
    """Ray workers (learner, shards) need not share the driver's working directory, so a relative
    --run-dir (or the default runs/<time>) is made absolute. RAY_ADDRESS in the environment (ray job
    submit) is the cluster the run joins, like --address: the learner's device is the cluster's."""
    from common.runtime import cluster_address
    from learner.run import parse_args, resolve

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert cluster_address(None) is None and cluster_address("auto") == "auto"
    _, run_dir = resolve(parse_args(["--config", "tiny", "--run-dir", "rel"]))
    assert run_dir == tmp_path / "rel" and run_dir.is_absolute()
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    assert cluster_address(None) == "10.0.0.1:6379"
    cfg, _ = resolve(parse_args(["--config", "tiny", "--run-dir", "gpu", "--set", "learner.device=cuda"]))
    assert cfg.learner.device == "cuda"
