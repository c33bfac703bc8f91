"""Policies on synthetic observations, episodes, and the rollout CLI end to end."""

import json

import numpy as np
import pytest

from actors.grasp import run_episode
from actors.policies import HeuristicPolicy, Policy, RandomPolicy, make_policy
from actors.rollout import cli, episode_seed
from actors.simulation import Simulation
from common.geometry import cell_to_world, rotation_angle
from common.gripper import get_gripper
from common.observation import Observation

GRIPPER = "parallel_jaw-0"


def _observation(cfg, heightmap, obstacle_cells=None) -> Observation:
    shape = cfg.scene_grid.shape
    obstacle = np.zeros(shape, dtype=np.float32)
    if obstacle_cells is not None:
        obstacle[obstacle_cells, 0] = 1.0
    return Observation(
        tsdf=np.ones(shape, dtype=np.float32),
        obstacle=obstacle,
        heightmap=heightmap.astype(np.float32),
        valid=np.ones(shape[:2], dtype=bool),
    ).validate()


def _bar(cfg, centre, yaw, length=0.1, width=0.03, height=0.05):
    """Heightmap (X, Y) of a bar seen from above."""
    xs, ys = np.meshgrid(np.arange(cfg.scene_grid.shape[0]), np.arange(cfg.scene_grid.shape[1]), indexing="ij")
    xy = cell_to_world(cfg.scene_grid, xs, ys) - centre
    along = xy @ np.array([np.cos(yaw), np.sin(yaw)])
    across = xy @ np.array([-np.sin(yaw), np.cos(yaw)])
    return np.where((np.abs(along) <= length / 2) & (np.abs(across) <= width / 2), height, 0.0)


@pytest.mark.parametrize("yaw_k", [0, 3, 5])
def test_heuristic_grasps_a_bar_across_its_width(default_cfg, yaw_k):
    cfg = default_cfg
    r = cfg.model.rotations
    bar_yaw = rotation_angle(yaw_k, r)
    centre = np.array([0.03, -0.05])
    obs = _observation(cfg, _bar(cfg, centre, bar_yaw))
    policy = make_policy("heuristic", cfg)
    assert isinstance(policy, Policy)
    (i, j, k, s), score = policy.act(obs, (0.5, 1.0, 0.75), np.random.default_rng(0))
    np.testing.assert_allclose(cell_to_world(cfg.scene_grid, i, j), centre, atol=cfg.scene_grid.voxel_size)
    closing = rotation_angle(k, r)
    assert abs(np.cos(closing - bar_yaw)) < 0.2, "the jaws close across the bar, not along it"
    assert s == 1 and score == 0.5


def test_heuristic_ignores_obstacles_and_falls_back_to_random(default_cfg):
    cfg = default_cfg
    hm = _bar(cfg, np.array([0.0, 0.0]), 0.0)
    obstacle_cells = hm > 0
    policy = HeuristicPolicy(cfg)
    obs = _observation(cfg, hm, obstacle_cells)
    labels, keep = policy.blobs(obs)
    assert keep == []
    (i, j, k, s), _ = policy.act(obs, (1.0,), np.random.default_rng(0))
    assert 0 <= i < hm.shape[0] and 0 <= j < hm.shape[1] and s == 0


def test_random_policy_covers_the_action_square(default_cfg):
    cfg = default_cfg
    obs = _observation(cfg, np.zeros(cfg.scene_grid.shape[:2]))
    obs.valid[:, :10] = False
    policy = RandomPolicy(cfg)
    rng = np.random.default_rng(0)
    actions = np.array([policy.act(obs, (0.5, 0.75, 1.0), rng)[0] for _ in range(3000)])
    xy = cell_to_world(cfg.scene_grid, actions[:, 0], actions[:, 1])
    assert np.all(np.abs(xy) <= cfg.sim.action_half_extent + 1e-9)
    assert np.all(actions[:, 1] >= 10), "only observed cells"
    assert set(actions[:, 2]) == set(range(cfg.model.rotations))
    assert set(actions[:, 3]) == {0, 1, 2}


def test_unknown_policy_is_one_line(default_cfg):
    with pytest.raises(ValueError) as info:
        make_policy("telepathy", default_cfg)
    assert "\n" not in str(info.value) and "telepathy" in str(info.value)


def test_multi_episode_ends_when_empty_or_after_max_attempts(default_cfg):
    cfg = default_cfg
    with Simulation(cfg, seed=0) as sim:
        gripper = sim.load_gripper(get_gripper(GRIPPER), 1.0)
        policy = make_policy("heuristic", cfg)
        results = list(run_episode(sim, gripper, policy, (1.0,), "multi", "train", seed=episode_seed(0, 0)))
        assert 1 <= len(results) <= cfg.sim.multi_max_attempts
        assert [r.step for r in results] == list(range(len(results)))
        assert len(results) == cfg.sim.multi_max_attempts or not sim.targets
        lifted = sum(len(r.outcome.lifted_targets) for r in results)
        assert len(sim.targets) <= cfg.sim.multi_objects - lifted
        assert all(r.trial_s > 0 for r in results)


def test_rollout_cli_end_to_end(tmp_path, capsys):
    out = tmp_path / "summary.json"
    png = tmp_path / "png"
    argv = [
        "--scene", "single", "--objects", "train", "--gripper", GRIPPER, "--policy", "heuristic",
        "--episodes", "2", "--seed", "0", "--cameras", "1", "--json", str(out), "--png", str(png),
    ]
    assert cli(argv) == 0
    summary = json.loads(out.read_text())
    assert set(summary) == {
        "scene", "objects", "gripper", "policy", "episodes", "trials", "successes", "success_rate", "median_trial_s"
    }
    assert summary["scene"] == "single" and summary["episodes"] == 2 and summary["trials"] == 2
    assert summary["success_rate"] == summary["successes"] / 2
    assert 0 < summary["median_trial_s"] < 10
    assert sorted(p.name for p in png.iterdir()) == ["trial_000.png", "trial_001.png"]
    assert "rollout:" in capsys.readouterr().out


def test_rollout_through_the_launcher(tmp_path):
    import launcher

    out = tmp_path / "s.json"
    argv = ["rollout", "--scene", "obstacle", "--gripper", GRIPPER, "--policy", "random", "--episodes", "1",
            "--cameras", "2", "--json", str(out)]
    assert launcher.main(argv) == 0
    summary = json.loads(out.read_text())
    assert summary["scene"] == "obstacle" and 1 <= summary["trials"] <= 5


@pytest.mark.slow
def test_rollout_with_a_checkpoint_policy(tmp_path):
    """The --policy checkpoint:PATH --mode hook runs a (here untrained, small) network end to end
    (4-30 s on a shared 2-core machine, hence slow)."""
    from common.checkpoint import save_checkpoint
    from common.config import load_config
    from common.network import build_model

    small = ["model.channels=4", "model.rotations=4", "grippers.eval_openings=[0.75,1.0]"]
    cfg = load_config("default", small)
    ckpt = save_checkpoint(tmp_path / "m.pt", build_model(cfg), cfg)
    out = tmp_path / "s.json"
    argv = ["--gripper", GRIPPER, "--policy", f"checkpoint:{ckpt}", "--mode", "fix-config", "--episodes", "1",
            "--json", str(out), "--png", str(tmp_path / "png")] + [a for kv in small for a in ("--set", kv)]
    assert cli(argv) == 0
    summary = json.loads(out.read_text())
    assert summary["policy"] == "learned-fix-config" and summary["trials"] == 1
    pictures = sorted(p.name for p in (tmp_path / "png").iterdir())
    assert pictures == ["trial_000.png", "trial_000_grasp.png", "trial_000_scores.png"]
    assert all((tmp_path / "png" / p).stat().st_size > 5000 for p in pictures)


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--objects", "no_such_set"], "no_such_set"),
        (["--policy", "telepathy"], "telepathy"),
        (["--set", "sim.tcp_speed=-1"], "sim.tcp_speed"),
        (["--gripper", "no_such_gripper"], "no_such_gripper"),
        (["--policy", "random", "--mode", "adagrasp"], "--mode"),
        (["--policy", "checkpoint:/no/such/model.pt"], "/no/such/model.pt"),
        (["--png", "{tmp}/s.json"], "s.json: exists and is not a folder"),
        (["--scale", "-1"], "--scale: expected a value in [0.05, 20], got -1.0"),
        (["--cameras", "9"], "--cameras: sim.cameras: expected a value in [1, 4], got 9"),
        (["--json", "{tmp}/s.json/inside.json"], "s.json/inside.json:"),
    ],
)
def test_rollout_bad_input_is_one_line(tmp_path, capsys, extra, needle):
    out = tmp_path / "s.json"
    if any("{tmp}" in e for e in extra):  # a file where a folder is wanted
        out.write_text("mine")
        extra = [e.format(tmp=tmp_path) for e in extra]
    argv = ["--gripper", GRIPPER, "--episodes", "1", "--json", str(out)] + extra
    assert cli(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert not out.exists() or out.read_text() == "mine", "nothing is written on bad input"


def test_json_over_the_checkpoint_it_reads_is_refused_in_one_line(tmp_path, capsys):
    """--json naming the checkpoint of --policy checkpoint:PATH would replace the weights with the
    summary: refused before any episode, the file unchanged."""
    from common.checkpoint import save_checkpoint
    from common.config import load_config
    from common.network import build_model

    small = ["model.channels=4", "model.rotations=4", "grippers.eval_openings=[0.75,1.0]"]
    cfg = load_config("default", small)
    ckpt = save_checkpoint(tmp_path / "m.pt", build_model(cfg), cfg)
    before = ckpt.read_bytes()
    argv = ["--gripper", GRIPPER, "--policy", f"checkpoint:{ckpt}", "--mode", "fix-config", "--episodes", "1",
            "--json", str(ckpt)] + [a for kv in small for a in ("--set", kv)]
    assert cli(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"--json {ckpt}: is one of this command's input files" in err, err
    assert ckpt.read_bytes() == before
