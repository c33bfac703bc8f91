"""Grasp primitive and label: physics sanity on a centred cube, and the label rules."""

import numpy as np
import pybullet
import pytest

from actors.grasp import (
    FAILURE_MODES,
    GraspOutcome,
    execute_grasp,
    grasp_pose,
    gripper_reach,
    label_scene,
    remove_finished,
)
from actors.simulation import Simulation
from common.config import load_config
from common.geometry import cell_to_world, world_to_cell
from common.gripper import get_gripper

GRIPPER = "parallel_jaw-0"
CUBE = 0.04


def _centred_cube_trial(seed: int):
    """A 4 cm cube with random yaw and a sub-cell offset at the grid centre; a grasp at a random
    rotation on its cell, widest opening. Returns the outcome."""
    cfg = load_config("default")
    rng = np.random.default_rng(seed)
    with Simulation(cfg, seed=seed) as sim:
        gripper = sim.load_gripper(get_gripper(GRIPPER), 1.0)
        i, j = world_to_cell(sim.grid, 0.0, 0.0)
        xy = cell_to_world(sim.grid, i, j) + rng.uniform(-0.002, 0.002, size=2)
        sim.add_box([CUBE] * 3, [xy[0], xy[1], CUBE / 2], yaw=rng.uniform(0, 2 * np.pi))
        sim.settle()
        obs = sim.observe()
        k = int(rng.integers(cfg.model.rotations))
        outcome = execute_grasp(sim, gripper, (int(i), int(j), k, 0), (1.0,), obs.heightmap)
        if outcome.success:
            assert not sim.objects, "a lifted cube is removed from the scene"
        return outcome, gripper_reach(sim, gripper, 1.0)


def test_parallel_jaw_lifts_centred_cube_10_seeds():
    """Physics sanity (about 3 s, so not marked slow)."""
    clearance = load_config("default").sim.table_clearance
    results = [_centred_cube_trial(seed) for seed in range(10)]
    successes = sum(o.success for o, _ in results)
    print(f"physics sanity: {successes}/10 centred cubes lifted")
    assert successes >= 9, [o for o, _ in results if not o.success]
    assert all(o.lifted_targets == ("primitive/box",) for o, _ in results if o.success)
    assert all(o.failure is None and o.held_after_close and not o.lost_on_lift for o, _ in results if o.success)
    for o, reach in results:
        # top 4 cm - grasp depth 5 cm is below the table: the grasp height is clipped so the
        # lowest point of the gripper stays `table_clearance` above the table
        assert o.grasp_position[2] == pytest.approx(reach + clearance)
        assert abs(o.stop_z - o.grasp_position[2]) < 0.002 or o.stopped_at_contact


@pytest.mark.parametrize("bar_yaw, good_k, bad_k", [(0.0, 0, 4), (np.pi / 4, 2, 6)])
def test_the_executed_yaw_turns_with_k_the_way_the_network_assumes(bar_yaw, good_k, bad_k):
    """A 2.5 x 10 cm bar (long side along y, then turned by ``bar_yaw``) is lifted when the jaws
    close across it and slips when they close along it: rotation k turns the gripper by
    +2 pi k / R about z, so a sign error in the executed yaw swaps k = 2 and k = 6 on the turned
    bar (a cube looks the same either way)."""
    cfg = load_config("default")
    outcomes = {}
    for k in (good_k, bad_k):
        with Simulation(cfg, seed=0) as sim:
            gripper = sim.load_gripper(get_gripper(GRIPPER), 1.0)
            i, j = world_to_cell(sim.grid, 0.0, 0.0)
            xy = cell_to_world(sim.grid, i, j)
            sim.add_box([0.025, 0.10, 0.04], [xy[0], xy[1], 0.02], yaw=bar_yaw)
            sim.settle()
            obs = sim.observe()
            outcomes[k] = execute_grasp(sim, gripper, (int(i), int(j), k, 0), (1.0,), obs.heightmap)
    assert outcomes[good_k].success and not outcomes[bad_k].success, outcomes


def test_grasp_pose_follows_action_contract(default_cfg):
    with Simulation(default_cfg, seed=0) as sim:
        hm = np.zeros(sim.grid.shape[:2], dtype=np.float32)
        hm[50, 40] = 0.08
        pos, yaw, opening = grasp_pose(sim, (50, 40, 4, 1), (0.5, 0.75), hm)
        np.testing.assert_allclose(pos[:2], cell_to_world(sim.grid, 50, 40))
        assert pos[2] == pytest.approx(0.08 - default_cfg.sim.grasp_depth)
        assert yaw == pytest.approx(2 * np.pi * 4 / default_cfg.model.rotations)
        assert opening == 0.75
        pos, _, _ = grasp_pose(sim, (0, 0, 0, 0), (1.0,), hm)
        assert pos[2] == 0.0, "the grasp height is clipped to the table"
        lim = default_cfg.sim.fence_half_extent
        assert np.all(np.abs(pos[:2]) <= lim + 1e-12), "the grasp centre is clipped to the fence square"
        with pytest.raises(ValueError, match="opening index"):
            grasp_pose(sim, (50, 40, 0, 2), (0.5, 0.75), hm)


def test_label_rules(default_cfg):
    """Exactly one lifted target and no lifted obstacle succeeds; anything else fails."""
    with Simulation(default_cfg, seed=0) as sim:
        t1 = sim.add_box([0.03] * 3, [0.05, 0.0, 0.015])
        t2 = sim.add_box([0.03] * 3, [-0.05, 0.0, 0.015])
        ob = sim.add_box([0.03] * 3, [0.0, 0.06, 0.015], role="obstacle")
        assert label_scene(sim) == (False, (), ())

        def lift(body):
            pybullet.resetBasePositionAndOrientation(body, [0.0, 0.0, 0.3], [0, 0, 0, 1], physicsClientId=sim.client)

        lift(t1)
        assert label_scene(sim) == (True, (t1,), ())
        lift(ob)
        assert label_scene(sim) == (False, (t1,), (ob,)), "a lifted obstacle fails the grasp"
        pybullet.resetBasePositionAndOrientation(ob, [0.0, 0.06, 0.015], [0, 0, 0, 1], physicsClientId=sim.client)
        lift(t2)
        assert label_scene(sim) == (False, (t1, t2), ()), "two lifted targets fail the grasp"


@pytest.mark.parametrize("bound", ["scene_grid", "fence"])
def test_targets_leave_at_the_configured_bound(default_cfg, bound):
    """A target between the fence square (grasps are clipped to it) and the scene grid's edge stays
    with sim.target_bound "scene_grid" and leaves with "fence" (the paper's rule); an obstacle there
    stays either way; anything beyond the scene grid leaves either way."""
    cfg = load_config("default", overrides=[f"sim.target_bound={bound}"])
    with Simulation(cfg, seed=0) as sim:
        between = sim.add_box([0.03] * 3, [0.165, 0.0, 0.015])
        corner = sim.add_box([0.03] * 3, [-0.14, 0.14, 0.015])
        inside = sim.add_box([0.03] * 3, [0.12, -0.12, 0.015])
        obstacle = sim.add_box([0.03] * 3, [0.0, -0.165, 0.015], role="obstacle")
        beyond = sim.add_box([0.03] * 3, [0.2, 0.0, 0.015])
        remove_finished(sim, ())
        gone = {between, corner} if bound == "fence" else set()
        assert set(sim.objects) == {between, corner, inside, obstacle} - gone, (bound, sim.objects)
        assert beyond not in sim.objects


def test_grasping_an_obstacle_fails(default_cfg):
    with Simulation(default_cfg, seed=0) as sim:
        gripper = sim.load_gripper(get_gripper(GRIPPER), 1.0)
        i, j = world_to_cell(sim.grid, 0.0, 0.0)
        xy = cell_to_world(sim.grid, i, j)
        sim.add_box([CUBE] * 3, [xy[0], xy[1], CUBE / 2], role="obstacle", name="primitive/obstacle")
        target = sim.add_box([CUBE] * 3, [0.08, 0.08, CUBE / 2])
        sim.settle()
        obs = sim.observe()
        assert obs.obstacle.max() > 0.5, "the obstacle shows in the obstacle channel"
        outcome = execute_grasp(sim, gripper, (int(i), int(j), 0, 0), (1.0,), obs.heightmap)
        assert outcome.lifted_obstacles == ("primitive/obstacle",)
        assert not outcome.success and outcome.failure == "extra_lift"
        assert list(sim.objects) == [target], "the lifted obstacle is removed, the target stays"


def test_two_targets_in_one_grasp_fail(default_cfg):
    """Two 2.5 cm cubes side by side along x, pinched together: both rise, the label is a failure."""
    with Simulation(default_cfg, seed=0) as sim:
        gripper = sim.load_gripper(get_gripper(GRIPPER), 1.0)
        i, j = world_to_cell(sim.grid, 0.0, 0.0)
        x, y = cell_to_world(sim.grid, i, j)
        edge = 0.025
        sim.add_box([edge] * 3, [x - edge / 2 - 0.0005, y, edge / 2], name="primitive/left")
        sim.add_box([edge] * 3, [x + edge / 2 + 0.0005, y, edge / 2], name="primitive/right")
        sim.settle()
        obs = sim.observe()
        outcome = execute_grasp(sim, gripper, (int(i), int(j), 0, 0), (1.0,), obs.heightmap)
        assert sorted(outcome.lifted_targets) == ["primitive/left", "primitive/right"], outcome
        assert not outcome.success and outcome.failure == "extra_lift"
        assert not sim.objects


def test_missed_grasp_fails_fast(default_cfg):
    """A grasp on the empty table lifts nothing and ends its lift early."""
    with Simulation(default_cfg, seed=0) as sim:
        gripper = sim.load_gripper(get_gripper(GRIPPER), 1.0)
        target = sim.add_box([CUBE] * 3, [0.1, 0.1, CUBE / 2])
        sim.settle()
        obs = sim.observe()
        i, j = world_to_cell(sim.grid, -0.1, -0.1)
        outcome = execute_grasp(sim, gripper, (int(i), int(j), 3, 0), (1.0,), obs.heightmap)
        assert not outcome.success and outcome.lifted_targets == ()
        assert outcome.failure == "missed" and not outcome.held_after_close and outcome.lost_on_lift
        assert list(sim.objects) == [target]
        full_lift_steps = (default_cfg.sim.lift_to + default_cfg.sim.hold_s * default_cfg.sim.tcp_speed) / (
            default_cfg.sim.tcp_speed * default_cfg.sim.time_step
        )
        assert outcome.steps < full_lift_steps


def test_heavy_cube_slips_out_of_the_grasp(default_cfg):
    """The centred-cube grasp of the physics sanity test on a 20 kg cube, beyond what the jaws'
    friction holds: the fingers touch it when closing ends, then lose it on the lift."""
    with Simulation(default_cfg, seed=0) as sim:
        gripper = sim.load_gripper(get_gripper(GRIPPER), 1.0)
        i, j = world_to_cell(sim.grid, 0.0, 0.0)
        xy = cell_to_world(sim.grid, i, j)
        cube = sim.add_box([CUBE] * 3, [xy[0], xy[1], CUBE / 2])
        pybullet.changeDynamics(cube, -1, mass=20.0, physicsClientId=sim.client)
        sim.settle()
        obs = sim.observe()
        outcome = execute_grasp(sim, gripper, (int(i), int(j), 0, 0), (1.0,), obs.heightmap)
        assert not outcome.success
        assert outcome.held_after_close and outcome.lost_on_lift and outcome.failure == "slipped", outcome


def test_failure_modes_follow_the_primitive():
    """Each failure mode from the flags, in the primitive's order; a success has none."""
    base = dict(grasp_position=(0.0, 0.0, 0.0), yaw=0.0, opening=1.0, stop_z=0.0, stopped_at_contact=False, steps=1)

    def mode(success=False, targets=(), obstacles=(), held=True, lost=False):
        return GraspOutcome(success=success, lifted_targets=targets, lifted_obstacles=obstacles,
                            held_after_close=held, lost_on_lift=lost, **base).failure

    assert mode(success=True, targets=("a",)) is None
    assert mode(obstacles=("o",), targets=("a",)) == "extra_lift"
    assert mode(targets=("a", "b")) == "extra_lift"
    assert mode(held=False, lost=True) == "missed"
    assert mode(held=True, lost=True) == "slipped"
    assert mode(held=True, lost=False) == "dropped"
    assert set(FAILURE_MODES) == {"missed", "slipped", "dropped", "extra_lift"}
