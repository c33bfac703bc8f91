"""Learned policy: valid-action mask, epsilon-greedy selection, the three modes, poses,
the Policy protocol, ``make_policy("checkpoint:PATH")``, score-map pictures."""

import math

import numpy as np
import pytest
import torch

from actors.policies import Policy, make_policy
from common.calibration import apply_shifts
from common.checkpoint import save_checkpoint
from common.config import load_config
from common.geometry import cell_to_world
from common.network import build_model
from common.observation import Observation
from common.policy import LearnedPolicy, PolicyError, action_region, grasp_pose, select, valid_cells
from common.viz import grasp_image, save_png, score_maps_image, shown_rotations

SMALL = [
    "scene_grid.x_range=[-0.064, 0.064]",
    "scene_grid.y_range=[-0.064, 0.064]",
    "scene_grid.z_range=[0.0, 0.064]",
    "gripper_grid.shape=[16, 16, 8]",
    "sim.action_half_extent=0.048",
    "model.rotations=8",
    "model.min_surface_height=0.0",
]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def small(*overrides):
    cfg = load_config("default", SMALL + list(overrides))
    torch.manual_seed(0)
    return cfg, build_model(cfg).eval()


def observation(cfg, seed=0) -> Observation:
    """A few boxes; the left quarter of the grid unobserved."""
    rng = np.random.default_rng(seed)
    X, Y, Z = cfg.scene_grid.shape
    v = cfg.scene_grid.voxel_size
    cells = np.zeros((X, Y), dtype=np.int64)
    for _ in range(3):
        i, j = rng.integers(4, X - 8, size=2)
        cells[i : i + 4, j : j + 3] = rng.integers(3, Z - 4)
    z = np.arange(Z)[None, None, :]
    tsdf = np.clip((z - cells[:, :, None]) / 3.0, -1, 1).astype(np.float32)
    valid = np.ones((X, Y), dtype=bool)
    valid[: X // 4] = False
    return Observation(tsdf, np.zeros_like(tsdf), (cells * v).astype(np.float32), valid).validate()


def gripper(cfg, s, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand((s, 2, *cfg.gripper_grid.shape), generator=gen) * 2 - 1).numpy()


def test_valid_mask_is_the_observed_action_square():
    cfg, _ = small()
    obs = observation(cfg)
    region = action_region(cfg)
    xy = cell_to_world(cfg.scene_grid, *np.nonzero(region))
    assert np.all(np.abs(xy) <= 0.048 + 1e-9) and region.sum() == 24 * 24
    mask = valid_cells(obs, cfg)
    np.testing.assert_array_equal(mask, region & obs.valid)
    cfg_h, _ = small("model.min_surface_height=0.005")
    np.testing.assert_array_equal(valid_cells(obs, cfg_h), region & obs.valid & (obs.heightmap > 0.005))
    blind = Observation(obs.tsdf, obs.obstacle, obs.heightmap, np.zeros_like(obs.valid))
    np.testing.assert_array_equal(valid_cells(blind, cfg), region)


def test_select_greedy_and_proportional():
    rng = np.random.default_rng(0)
    probs = np.zeros((2, 3, 4, 4))
    probs[1, 2, 0, 0] = 0.99  # masked out below
    probs[0, 1, 2, 3] = 0.6
    probs[1, 0, 3, 1] = 0.3
    probs[0, 0, 1, 1] = 0.1
    mask = np.ones((4, 4), dtype=bool)
    mask[0, 0] = False
    idx, score, explored = select(probs, mask, 0.0, rng)
    assert idx == (0, 1, 2, 3) and score == 0.6 and not explored
    counts = {}
    for _ in range(4000):
        idx, _, explored = select(probs, mask, 1.0, rng)
        assert explored
        counts[idx] = counts.get(idx, 0) + 1
    assert set(counts) == {(0, 1, 2, 3), (1, 0, 3, 1), (0, 0, 1, 1)}
    assert counts[(0, 1, 2, 3)] / 4000 == pytest.approx(0.6, abs=0.03)
    assert counts[(1, 0, 3, 1)] / 4000 == pytest.approx(0.3, abs=0.03)


@pytest.mark.parametrize("mode", ["fix-gripper", "fix-config", "adagrasp"])
def test_modes_pick_the_best_valid_action(mode):
    cfg, model = small()
    obs = observation(cfg, 1)
    openings = (0.5, 0.75, 1.0)
    grippers = [("a", gripper(cfg, 3, 1))] + ([("b", gripper(cfg, 3, 2))] if mode == "adagrasp" else [])
    policy = LearnedPolicy(model, cfg, grippers, mode=mode, epsilon=0.0)
    assert isinstance(policy, Policy)
    rng = np.random.default_rng(5)
    action, score = policy.act(obs, openings, rng)
    choice = policy.last_choice
    i, j, k, s, g = choice.action
    assert action == (i, j, k, s) and score == choice.score and not choice.explored
    mask = valid_cells(obs, cfg)
    assert mask[i, j]
    full = model.predict(np.stack([obs.tsdf, obs.obstacle]), [torch.from_numpy(e) for _, e in grippers]).numpy()
    if mode == "fix-config":
        assert policy.last_probs.shape == (1, 1, 8, 32, 32)
        best = np.where(mask, full[g, s], -1).max()
    else:
        best = np.where(mask, full, -1).max()
    assert score == pytest.approx(best, abs=1e-6) and full[g, s, k, i, j] == pytest.approx(score, abs=1e-6)
    if mode == "adagrasp":
        assert g == int(np.argmax(np.where(mask, full, -1).reshape(2, -1).max(axis=1)))
    position, yaw = grasp_pose(cfg, obs.heightmap, i, j, k)
    np.testing.assert_allclose(choice.position, position)
    np.testing.assert_allclose(position[:2], cell_to_world(cfg.scene_grid, i, j))
    assert position[2] == pytest.approx(max(float(obs.heightmap[i, j]) - cfg.sim.grasp_depth, 0.0))
    assert yaw == pytest.approx(2 * math.pi * k / 8) and choice.opening == openings[s]


def test_fix_config_draws_the_opening_uniformly():
    cfg, model = small()
    obs = observation(cfg, 2)
    openings = (0.5, 0.625, 0.75, 0.875, 1.0)
    policy = LearnedPolicy(model, cfg, [("a", gripper(cfg, 5))], mode="fix-config")
    rng = np.random.default_rng(0)
    drawn = [policy.act(obs, openings, rng)[0][3] for _ in range(40)]
    assert set(drawn) == set(range(5))


def test_pose_clips_to_the_table():
    cfg, _ = small()
    hm = np.zeros((32, 32), dtype=np.float32)
    hm[3, 4] = 0.02
    position, yaw = grasp_pose(cfg, hm, 3, 4, 2)
    assert position[2] == 0.0 and yaw == pytest.approx(math.pi / 2)
    # fingers that sweep 3 cm below the TCP while closing keep sim.table_clearance above the table
    raised, _ = grasp_pose(cfg, hm, 3, 4, 2, reach=0.03)
    assert raised[2] == pytest.approx(0.03 + cfg.sim.table_clearance) and np.array_equal(raised[:2], position[:2])
    # a cell beyond the fence square grasps at its edge
    cfg.sim.fence_half_extent = 0.02
    far, _ = grasp_pose(cfg, hm, 0, 0, 0)
    np.testing.assert_allclose(far[:2], [-0.02, -0.02])


def test_bad_policy_input_is_one_line():
    cfg, model = small()
    with pytest.raises(PolicyError, match="mode"):
        LearnedPolicy(model, cfg, mode="greedy")
    with pytest.raises(PolicyError, match="grippers"):
        LearnedPolicy(model, cfg, [("a", gripper(cfg, 2)), ("b", gripper(cfg, 2))], mode="fix-gripper")
    policy = LearnedPolicy(model, cfg, [("a", gripper(cfg, 2))])
    with pytest.raises(PolicyError, match="openings") as e:
        policy.act(observation(cfg), (0.5, 0.75, 1.0), np.random.default_rng(0))
    assert "\n" not in str(e.value)
    with pytest.raises(PolicyError, match="grippers"):
        LearnedPolicy(model, cfg).act(observation(cfg), (1.0,), np.random.default_rng(0))


def test_make_policy_from_checkpoint(tmp_path):
    cfg, model = small()
    path = save_checkpoint(tmp_path / "m.pt", model, cfg, step=3, version=2)
    policy = make_policy(f"checkpoint:{path}", cfg, mode="adagrasp", grippers=[("a", gripper(cfg, 2))], epsilon=0.1)
    assert isinstance(policy, LearnedPolicy) and policy.mode == "adagrasp" and policy.model.weights_version == 2
    action, score = policy.act(observation(cfg), (0.5, 1.0), np.random.default_rng(0))
    assert len(action) == 4 and 0.0 <= score <= 1.0
    other = load_config("default", SMALL[:3] + ["gripper_grid.shape=[32, 32, 16]", "model.rotations=8"])
    with pytest.raises(ValueError, match="gripper_grid") as e:
        make_policy(f"checkpoint:{path}", other)
    assert "\n" not in str(e.value) and f"checkpoint:{path}" in str(e.value)


def test_pictures(tmp_path):
    cfg, model = small()
    obs = observation(cfg, 3)
    enc = gripper(cfg, 2)
    policy = LearnedPolicy(model, cfg, [("a", enc)], mode="fix-gripper")
    choice = policy.choose(obs, (0.5, 1.0), np.random.default_rng(0))
    img = score_maps_image(policy.last_probs[0], obs.heightmap, cfg, (0.5, 1.0), mask=valid_cells(obs, cfg))
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8 and img.shape[0] > img.shape[1] * 0.5
    assert img.std() > 10  # not blank
    assert save_png(img, tmp_path / "maps.png").stat().st_size > 1000
    assert shown_rotations(choice.action[2], 8)[0] <= choice.action[2] and choice.action[2] in shown_rotations(choice.action[2], 8)
    g_img = grasp_image(obs.heightmap, cfg, choice, enc[choice.action[3]], title="test")
    assert g_img.dtype == np.uint8 and g_img.std() > 10
    # the footprint is drawn: the picture changes with the encoding
    empty = np.ones_like(enc[0])
    assert np.abs(grasp_image(obs.heightmap, cfg, choice, empty, title="test").astype(int) - g_img).sum() > 0


def test_policy_chooses_across_grippers_with_the_calibrated_scores():
    """A shift against the raw winner hands the choice to the other gripper, at that gripper's own
    best grasp; the reported score is the calibrated one."""
    cfg, model = small()
    obs = observation(cfg)
    openings = (0.5, 1.0)
    grippers = [("a", gripper(cfg, 2, 1)), ("b", gripper(cfg, 2, 2))]
    raw = LearnedPolicy(model, cfg, grippers, mode="adagrasp")
    first = raw.choose(obs, openings, np.random.default_rng(0))
    winner, loser = first.action[4], 1 - first.action[4]
    shifts = np.zeros(2)
    shifts[winner] = -30.0
    policy = LearnedPolicy(model, cfg, grippers, mode="adagrasp", score_shifts=shifts)
    choice = policy.choose(obs, openings, np.random.default_rng(0))
    assert choice.action[4] == loser
    alone = LearnedPolicy(model, cfg, [grippers[loser]], mode="fix-gripper").choose(obs, openings, np.random.default_rng(0))
    assert choice.action[:4] == alone.action[:4]
    assert choice.score == pytest.approx(alone.score, rel=1e-5)  # zero shift for the loser
    np.testing.assert_allclose(policy.last_probs, apply_shifts(raw.last_probs, shifts), atol=1e-7)
    with pytest.raises(PolicyError, match="score_shifts: expected one per gripper"):
        LearnedPolicy(model, cfg, grippers, mode="adagrasp", score_shifts=np.zeros(3)).choose(
            obs, openings, np.random.default_rng(0)
        )
