"""Simulation: rendering geometry, scenes per kind, reproducibility, and bad input."""

import numpy as np
import pybullet
import pytest

from actors.objects import ObjectModel, ObjectSetError
from actors.simulation import Simulation, SimulationError
from common.config import ConfigError, load_config
from common.gripper import get_gripper


def _one_line(e: BaseException) -> str:
    msg = str(e)
    assert msg and "\n" not in msg, repr(msg)
    return msg


def test_tinyrenderer_matches_pinhole_model(default_cfg):
    """Every pixel whose ray hits the top of a box shows the box, and no other pixel does."""
    with Simulation(default_cfg, seed=0) as sim:
        (K, T), = sim.cameras
        size, centre = np.array([0.043, 0.0371, 0.05]), np.array([0.0031, -0.0022, 0.025])
        body = sim.add_box(size, centre)
        depths, segs = sim.render()
        top = centre[2] + size[2] / 2
        v, u = np.mgrid[0 : K.height, 0 : K.width]
        d = T.translation[2] - top
        rays = np.stack([(u - K.cx) / K.fx * d, (v - K.cy) / K.fy * d, np.full(u.shape, d)], axis=-1)
        hit = T.apply(rays)
        rel = np.abs(hit[..., :2] - centre[:2]) - size[:2] / 2
        inside = np.all(rel < 0, axis=-1)
        clear = np.min(np.abs(rel), axis=-1) * K.fx / d > 0.01  # pixel centre not on an edge
        assert inside.sum() > 50
        np.testing.assert_array_equal((segs[0] == body)[clear], inside[clear])
        np.testing.assert_allclose(depths[0][inside], d, atol=1e-4)
        assert np.all(depths[0][segs[0] == sim.table] > d)


def test_oblique_depth_back_projects_onto_the_box(default_cfg):
    """Ring cameras: pixels of the box top back-project to its top face (metric depth along z_cam)."""
    cfg = default_cfg
    cfg.sim.cameras = 3
    with Simulation(cfg, seed=0) as sim:
        size, centre = np.array([0.06, 0.06, 0.04]), np.array([0.01, 0.02, 0.02])
        body = sim.add_box(size, centre)
        depths, segs = sim.render()
        for (K, T), depth, seg in zip(sim.cameras, depths, segs):
            v, u = np.nonzero(seg == body)
            z = depth[v, u]
            pts = T.apply(np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], axis=-1))
            inside = np.all(np.abs(pts - centre) <= size / 2 + 1e-3, axis=-1)
            assert inside.mean() > 0.99
            assert np.any(np.abs(pts[:, 2] - size[2]) < 1e-3), "the top face is seen"


@pytest.mark.parametrize("kind", ["single", "multi", "obstacle"])
def test_scene_smoke(default_cfg, kind):
    cfg = default_cfg
    with Simulation(cfg, seed=3) as sim:
        sim.reset_scene(kind, "train")
        n_t = {"single": 1, "multi": cfg.sim.multi_objects, "obstacle": cfg.sim.obstacle_targets}[kind]
        n_o = cfg.sim.obstacle_obstacles if kind == "obstacle" else 0
        assert len(sim.targets) == n_t and len(sim.obstacles) == n_o
        assert len(sim.object_ids()) == n_t + n_o and all("/" in n for n in sim.object_ids())
        before = np.array([sim.body_position(b) for b in sim.objects])
        sim.step(60)
        moved = np.linalg.norm(np.array([sim.body_position(b) for b in sim.objects]) - before, axis=1)
        assert moved.max() < 0.002, f"the scene is at rest after reset_scene (moved {moved.max()} m in 0.25 s)"
        for body in sim.objects:
            centre = sim.body_position(body)
            assert np.all(np.abs(centre[:2] - sim.centre[:2]) <= cfg.sim.fence_half_extent)
            assert sim.body_top(body) <= cfg.scene_grid.z_range[1]
            near_table = pybullet.getClosestPoints(body, sim.table, 0.05, physicsClientId=sim.client)
            assert all(c[8] > -0.005 for c in near_table), "no object sinks into the table"
        assert sim.body_position(sim.fence)[2] < -cfg.sim.fence_height, "the fence is lowered after the drop"
        obs = sim.observe()
        shape = cfg.scene_grid.shape
        assert shape == (96, 96, 32)
        assert obs.tsdf.shape == shape and obs.tsdf.dtype == np.float32
        assert obs.obstacle.shape == shape and obs.obstacle.dtype == np.float32
        assert obs.heightmap.shape == shape[:2] and obs.heightmap.dtype == np.float32
        assert obs.valid.shape == shape[:2] and obs.valid.dtype == np.bool_
        assert obs.valid.mean() > 0.95
        assert obs.heightmap.max() > 0.01 and np.median(obs.heightmap) < 0.002
        assert (obs.obstacle.max() > 0.5) == (kind == "obstacle")


def test_settle_stops_at_rest_before_the_cap(default_cfg):
    with Simulation(default_cfg, seed=0) as sim:
        box = sim.add_box([0.04, 0.03, 0.02], [0.0, 0.0, 0.06], yaw=0.3)
        steps = sim.settle()
        cap = default_cfg.sim.settle_max_s / default_cfg.sim.time_step
        assert steps < cap / 4, steps
        assert sim.body_position(box)[2] == pytest.approx(0.01, abs=1e-3)
        lin, ang = pybullet.getBaseVelocity(box, physicsClientId=sim.client)
        assert np.linalg.norm(lin) < default_cfg.sim.settle_velocity and np.linalg.norm(ang) < 0.5
        assert sim.settle() <= 16, "a scene at rest settles in two checks"


def test_scene_is_reproducible_from_its_seed(default_cfg):
    def positions(sim):
        return np.array([sim.body_position(b) for b in sim.objects])

    with Simulation(default_cfg, seed=11) as a, Simulation(default_cfg, seed=99) as b:
        a.reset_scene("multi", "train", seed=5)
        b.reset_scene("multi", "train", seed=5)
        assert a.object_ids() == b.object_ids()
        np.testing.assert_allclose(positions(a), positions(b), atol=1e-9)
        b.reset_scene("multi", "train", seed=6)
        assert a.object_ids() != b.object_ids() or not np.allclose(positions(a), positions(b))


def test_reset_replaces_the_previous_scene(default_cfg):
    with Simulation(default_cfg, seed=0) as sim:
        sim.reset_scene("multi", "train")
        sim.reset_scene("single", "train")
        assert len(sim.objects) == 1
        assert pybullet.getNumBodies(physicsClientId=sim.client) == 3, "table, fence and one object"


def test_solver_iterations_reach_the_client_and_survive_a_reset(default_cfg):
    cfg = load_config("default", ["sim.solver_iterations=123"])
    with Simulation(cfg, seed=0) as sim:
        sim.reset_scene("single", "train")
        params = pybullet.getPhysicsEngineParameters(physicsClientId=sim.client)
        assert params["numSolverIterations"] == 123
        assert params["fixedTimeStep"] == pytest.approx(cfg.sim.time_step)
    with pytest.raises(ConfigError) as info:
        load_config("default", ["sim.solver_iterations=0"])
    assert "sim.solver_iterations" in _one_line(info.value)


def test_parked_gripper_is_not_seen(default_cfg):
    cfg = default_cfg
    cfg.sim.cameras = 4
    with Simulation(cfg, seed=0) as sim:
        gripper = sim.load_gripper(get_gripper("parallel_jaw-0"), 1.0)
        assert sim.load_gripper(get_gripper("parallel_jaw-0"), 1.0) is gripper, "same gripper and scale is reused"
        sim.reset_scene("single", "train")
        sim.observe()
        _, segs = sim.render()
        assert all(not np.any(s == gripper.body_id) for s in segs)


def test_unknown_object_set_fails_in_one_line(default_cfg):
    with Simulation(default_cfg, seed=0) as sim:
        with pytest.raises(ObjectSetError) as info:
            sim.reset_scene("single", "no_such_set")
        assert "no_such_set" in _one_line(info.value)


def test_unknown_scene_kind_fails_in_one_line(default_cfg):
    with Simulation(default_cfg, seed=0) as sim:
        with pytest.raises(SimulationError) as info:
            sim.reset_scene("pile", "train")
        assert "pile" in _one_line(info.value)


def _with_models(sim, models):
    sim._object_sets["custom"] = models


def _model(name: str, urdf) -> ObjectModel:
    return ObjectModel(name=f"procedural/{name}", urdf=urdf, scale=1.0, source="procedural", split="train")


def test_missing_urdf_fails_in_one_line(default_cfg, tmp_path):
    """A URDF removed after its set was listed (e.g. a cleared cache) fails the reset cleanly."""
    ghost = tmp_path / "ghost.urdf"
    ghost.write_text("<robot/>")
    model = _model("ghost", ghost)
    ghost.unlink()
    with Simulation(default_cfg, seed=0) as sim:
        _with_models(sim, [model])
        with pytest.raises(ObjectSetError) as info:
            sim.reset_scene("single", "custom")
        assert str(ghost) in _one_line(info.value) and "not found" in str(info.value)
        assert not sim.objects
        assert sim.body_position(sim.fence)[2] < 0, "the fence is lowered again"


def test_broken_mesh_and_broken_urdf_fail_in_one_line(default_cfg, tmp_path):
    (tmp_path / "nan.obj").write_text("v nan nan nan\nv nan nan nan\nv nan nan nan\nf 1 2 3\n")
    link = (
        '<robot name="nan"><link name="l"><inertial><mass value="0.1"/>'
        '<inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>'
        '<collision><geometry><mesh filename="nan.obj"/></geometry></collision></link></robot>'
    )
    (tmp_path / "nan.urdf").write_text(link)
    (tmp_path / "garbage.urdf").write_text("<robot><link")
    with Simulation(default_cfg, seed=0) as sim:
        for name, what, error in (("nan", "broken mesh", SimulationError), ("garbage", "cannot load", ObjectSetError)):
            urdf = tmp_path / f"{name}.urdf"
            _with_models(sim, [_model(name, urdf)])
            with pytest.raises(error) as info:
                sim.reset_scene("single", "custom")
            msg = _one_line(info.value)
            assert str(urdf) in msg and what in msg
            assert pybullet.getNumBodies(physicsClientId=sim.client) == 2, "nothing is left behind"


def test_bad_config_value_fails_in_one_line(default_cfg):
    with pytest.raises(ConfigError) as info:
        load_config("default", ["sim.tcp_speed=-1"])
    assert "sim.tcp_speed" in _one_line(info.value)
    cfg = load_config("default", ["sim.lift_to=0.15"])
    with pytest.raises(ConfigError) as info:
        Simulation(cfg, seed=0)
    assert "sim.lift_to" in _one_line(info.value)


def test_a_world_that_fails_to_build_leaves_no_client_connected(default_cfg, monkeypatch):
    """An error while the world is built (the constructor never returns, so no close() of its
    owner can run) disconnects the physics client it had connected."""
    clients = []

    def failing(self):
        clients.append(self.client)
        raise RuntimeError("world build failure for the test")

    monkeypatch.setattr(Simulation, "_build_world", failing)
    with pytest.raises(RuntimeError, match="world build failure"):
        Simulation(default_cfg, seed=0)
    assert len(clients) == 1 and clients[0] >= 0 and not pybullet.isConnected(physicsClientId=clients[0])


def test_a_gripper_is_reused_only_for_the_same_spec_and_scale(default_cfg):
    """load_gripper keeps the loaded gripper for an equal spec (a fresh get_gripper of the same
    file) at the same scale; another spec under the same name is another gripper."""
    import dataclasses

    spec = get_gripper("parallel_jaw-0")
    with Simulation(default_cfg, seed=0) as sim:
        first = sim.load_gripper(spec, 1.0)
        assert sim.load_gripper(get_gripper("parallel_jaw-0"), 1.0) is first
        renamed = dataclasses.replace(get_gripper("three_finger-1"), name=spec.name)
        other = sim.load_gripper(renamed, 1.0)
        assert other is not first and other.spec is renamed
        assert sim.load_gripper(renamed, 1.1) is not other
