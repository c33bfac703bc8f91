"""GraspPlanner: raw depth -> ranked world-frame grasps; on analytic depth and on depth rendered by
the simulator, where the planned grasp is executed."""

import numpy as np
import pytest
import torch

from common.calibration import Calibration, GripperFit
from common.camera import top_down_camera
from common.checkpoint import save_checkpoint
from common.config import load_config
from common.gripper import get_gripper
from common.gripper_encoding import GripperEncoder, gripper_key, spec_tag
from common.network import build_model
from common.planner import GraspPlanner, PlannerError
from common.policy import grasp_pose, valid_cells

GRIPPER = "parallel_jaw-0"
SMALL = [
    "scene_grid.x_range=[-0.064, 0.064]",
    "scene_grid.y_range=[-0.064, 0.064]",
    "scene_grid.z_range=[0.0, 0.064]",
    "gripper_grid.shape=[16, 16, 8]",
    "sim.action_half_extent=0.056",
    "model.rotations=8",
]
"""A 32 x 32 x 16 scene grid at 4 mm, 8 rotations: the same pipeline, fast."""


@pytest.fixture(autouse=True)
def isolated(monkeypatch, tmp_path_factory):
    """Generated gripper files in a temporary cache; one torch thread (shared machine)."""
    monkeypatch.setenv("ADAGRASP_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def box_depth(cfg, height=0.6, box=((0.02, 0.06), (-0.03, 0.01), 0.05)):
    """A top-down camera and its depth image (H, W) float32 m of a box (x range, y range, top z) on the table."""
    K, T = top_down_camera(cfg.scene_grid, height, cfg.sim.image_pixels_per_voxel)
    (x0, x1), (y0, y1), top = box
    rays = K.pixel_rays()
    d_top = height - top
    pts = T.apply(rays * d_top)
    on_box = (pts[..., 0] >= x0) & (pts[..., 0] <= x1) & (pts[..., 1] >= y0) & (pts[..., 1] <= y1)
    depth = np.where(on_box, d_top, height).astype(np.float32)
    return K, T, depth


def planner_for(cfg):
    torch.manual_seed(0)
    return GraspPlanner(build_model(cfg), cfg, encoder=GripperEncoder(cfg.gripper_grid, disk=False))


def test_plan_ranks_valid_grasps_from_analytic_depth():
    cfg = load_config("default", SMALL)
    planner = planner_for(cfg)
    K, T, depth = box_depth(cfg)
    openings = (0.5, 1.0)
    grasps = planner.plan([depth], [K], [T], [GRIPPER, (GRIPPER, 1.2)], openings=openings, top_k=7)
    obs = planner.last_observation
    i, j = np.unravel_index(int(np.argmax(obs.heightmap)), obs.heightmap.shape)
    assert abs(float(obs.heightmap.max()) - 0.05) < 0.005
    assert 0.02 <= (i + 0.5) * 0.004 - 0.064 <= 0.06 and -0.03 <= (j + 0.5) * 0.004 - 0.064 <= 0.01
    assert len(grasps) == 7
    scores = [g.score for g in grasps]
    assert scores == sorted(scores, reverse=True)
    probs = planner.last_probs
    assert probs.shape == (2, 2, 8, 32, 32)
    mask = valid_cells(obs, cfg)
    assert scores[0] == pytest.approx(float(np.where(mask, probs, -1).max()))
    for g in grasps:
        i, j, k, s, gi = g.action
        assert mask[i, j] and g.gripper == gi and g.gripper_name == GRIPPER and g.opening == openings[s]
        reach = planner.reach(get_gripper(GRIPPER), (1.0, 1.2)[gi], openings[s])
        assert 0.005 < reach < 0.1
        position, yaw = grasp_pose(cfg, obs.heightmap, i, j, k, reach)
        np.testing.assert_allclose(g.position, position)
        assert g.yaw == yaw and g.score == pytest.approx(float(probs[gi, s, k, i, j]))
    # the same scores as the network on the fused observation
    enc = planner.encoder.encode(get_gripper(GRIPPER), 1.0, openings)
    direct = planner.model.predict(np.stack([obs.tsdf, obs.obstacle]), [enc]).numpy()
    np.testing.assert_allclose(direct[0], probs[0], atol=1e-6)
    # matrices instead of Intrinsics / Transform give the same plan
    again = planner.plan(depth, K.matrix(), T.as_matrix(), GRIPPER, openings=openings, top_k=3)
    order = np.argsort(-np.where(mask, probs[0], -1).ravel(), kind="stable")[:3]
    expected = []
    for o in order:
        s, k, i, j = (int(v) for v in np.unravel_index(o, probs[0].shape))
        expected.append((i, j, k, s, 0))
    assert [g.action for g in again] == expected
    spread = planner.plan([depth], [K], [T], [GRIPPER], openings=openings, top_k=5, min_separation=0.02)
    for a in range(len(spread)):
        for b in range(a):
            assert np.linalg.norm(spread[a].position[:2] - spread[b].position[:2]) >= 0.02


def test_reach_is_cached_per_spec_not_per_file():
    """Two specs of one processed URDF with other TCP axes reach differently; the cache keeps both."""
    import dataclasses

    cfg = load_config("default", SMALL)
    planner = planner_for(cfg)
    spec = get_gripper(GRIPPER)
    tilted = dataclasses.replace(spec, approach_axis=(0.0, 0.6, -0.8))
    assert tilted.urdf == spec.urdf
    first = planner.reach(spec, 1.0, 1.0)
    assert planner.reach(tilted, 1.0, 1.0) != pytest.approx(first, abs=1e-4)
    assert planner.reach(spec, 1.0, 1.0) == first


def test_bad_planner_input_is_one_line():
    cfg = load_config("default", SMALL)
    planner = planner_for(cfg)
    K, T, depth = box_depth(cfg)
    cases = [
        (dict(depths=[depth, depth], intrinsics=[K], camera_poses=[T]), "one per camera"),
        (dict(depths=[depth[:10]], intrinsics=[K], camera_poses=[T]), "intrinsics"),
        (dict(depths=[depth], intrinsics=[K], camera_poses=[np.eye(3)]), "camera_poses"),
        (dict(depths=[depth], intrinsics=[K], camera_poses=[T], grippers=[]), "grippers"),
        (dict(depths=[depth], intrinsics=[K], camera_poses=[T], openings=(1.5,)), "openings"),
        (dict(depths=[depth], intrinsics=[K], camera_poses=[T], top_k=0), "top_k"),
        (dict(depths=[(depth * 1000).astype(np.uint16)], intrinsics=[K], camera_poses=[T]),
         r"depths\[0\]: expected float metres, got dtype uint16"),
        (dict(depths=[np.zeros_like(depth)], intrinsics=[K], camera_poses=[T]), "observe no cell"),
        (dict(depths=[depth], intrinsics=[K], camera_poses=[T.as_matrix() @ np.diag([1.0, -1.0, -1.0, 1.0])]),
         "observe no cell of the action region"),
    ]
    for kwargs, needle in cases:
        kwargs.setdefault("grippers", [GRIPPER])
        with pytest.raises(PlannerError, match=needle) as e:
            planner.plan(**kwargs)
        assert "\n" not in str(e.value)


def test_planned_grasp_executes_in_the_simulator(tmp_path):
    """Depth rendered by the simulator (default grid; 4 rotations to keep it short) -> plan with a
    checkpointed (untrained) model -> the best grasp runs through the simulator's grasp primitive
    at the planned pose."""
    from actors.grasp import execute_grasp
    from actors.simulation import Simulation

    default_cfg = load_config("default", ["model.rotations=4"])
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / "model.pt", build_model(default_cfg), default_cfg)
    planner = GraspPlanner.from_checkpoint(path)
    spec = get_gripper(GRIPPER)
    openings = (1.0,)
    with Simulation(default_cfg, seed=3) as sim:
        gripper = sim.load_gripper(spec, 1.0)
        sim.reset_scene("single", seed=3)
        sim.park_gripper()
        depths, _ = sim.render()
        grasps = planner.plan(depths, [k for k, _ in sim.cameras], [t for _, t in sim.cameras], [spec], openings, top_k=3)
        obs = sim.observe()
        np.testing.assert_allclose(planner.last_observation.tsdf, obs.tsdf)
        best = grasps[0]
        i, j, k, s, _ = best.action
        outcome = execute_grasp(sim, gripper, (i, j, k, s), openings, obs.heightmap)
    # the planned pose is the executed one: clipped to the fence square, raised for the fingers' reach
    np.testing.assert_allclose(outcome.grasp_position, best.position, atol=1e-12)
    assert best.position[2] >= default_cfg.sim.table_clearance + planner.reach(spec, 1.0, 1.0) - 1e-12
    assert outcome.yaw == pytest.approx(best.yaw) and outcome.opening == best.opening
    assert outcome.steps > 0
    assert planner.encoder.encode(spec, 1.0, openings).shape == (1, 2, 32, 32, 16)
    assert gripper_key(spec_tag(spec), 1.0, openings) in {k for k, *_ in planner.model._kernels}


def test_planner_ranks_with_a_calibration():
    cfg = load_config("default", SMALL)
    planner = planner_for(cfg)
    K, T, depth = box_depth(cfg)
    grippers = [GRIPPER, "three_finger-1"]
    raw = planner.plan([depth], [K], [T], grippers, openings=(0.5, 1.0), top_k=1)[0]
    raw_probs = planner.last_probs
    fits = {name: GripperFit(-30.0 if g == raw.gripper else 0.0, 10, 5, 0.5) for g, name in enumerate(grippers)}
    cal = Calibration(fits, 2.0, "cal.json")
    best = planner.plan([depth], [K], [T], grippers, openings=(0.5, 1.0), top_k=1, calibration=cal)[0]
    assert best.gripper == 1 - raw.gripper
    mask = valid_cells(planner.last_observation, cfg)
    other = np.where(mask, raw_probs[best.gripper], -1.0)
    s, k, i, j = (int(v) for v in np.unravel_index(np.argmax(other), other.shape))
    assert best.action == (i, j, k, s, best.gripper)
    with pytest.raises(PlannerError, match="calibration: cal.json: episode_results: no trials of gripper wsg_50"):
        planner.plan([depth], [K], [T], [GRIPPER, "wsg_50"], openings=(0.5, 1.0), calibration=cal)


def test_a_single_obstacle_mask_is_taken_like_a_single_depth_image():
    cfg = load_config("default", SMALL)
    planner = planner_for(cfg)
    K, T, depth = box_depth(cfg)
    mask = depth < depth.max()
    one = planner.observe(depth, K, T, obstacle_masks=mask)
    listed = planner.observe([depth], [K], [T], obstacle_masks=[mask])
    assert one.obstacle.any() and np.array_equal(one.obstacle, listed.obstacle)


def test_kernels_follow_the_grippers_geometry_not_its_name():
    """The model caches each gripper's kernels: a spec of another geometry under a name already
    planned with (an edited spec file, two files of one name) gets its own scores."""
    import dataclasses

    cfg = load_config("default", SMALL)
    planner = planner_for(cfg)
    K, T, depth = box_depth(cfg)
    other = get_gripper("three_finger-1")
    planner.plan(depth, K, T, GRIPPER, openings=(1.0,))
    first = planner.last_probs.copy()
    planner.plan(depth, K, T, dataclasses.replace(other, name=GRIPPER), openings=(1.0,))
    renamed = planner.last_probs.copy()
    fresh = planner_for(cfg)
    fresh.plan(depth, K, T, other, openings=(1.0,))
    assert not np.allclose(renamed, first)
    np.testing.assert_allclose(renamed, fresh.last_probs, atol=1e-6)
