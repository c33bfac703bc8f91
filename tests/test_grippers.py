"""Gripper specs, the PyBullet gripper, the procedural families and the real grippers."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np
import pybullet as p
import pybullet_data
import pytest
import yaml

from actors.bullet_gripper import BulletGripper, lift_test
from common.geometry import Transform
from common.gripper import (
    GripperModel,
    GripperSpecError,
    check_kinematics,
    get_gripper,
    joint_positions,
    list_grippers,
    load_spec,
    posed_meshes,
    registered_spec_paths,
)
from common.gripper_procedural import FAMILY_NAMES, generate, sample_params

REAL = ("wsg_50", "panda_hand", "pr2_gripper", "xarm_gripper", "g1_three_finger")


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    """Generated URDFs go to one temporary cache per test session, never the user's cache."""
    monkeypatch.setenv("ADAGRASP_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))


@pytest.fixture
def client():
    c = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=c)
    yield c
    p.disconnect(physicsClientId=c)


# ------------------------------------------------------------------ physics sanity


def _cube_trials(seeds) -> list[bool]:
    spec = get_gripper("parallel_jaw-0")
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        off = tuple(rng.uniform(-0.008, 0.008, 2))
        out.append(lift_test(spec, 1.0, "box", 0.04, offset=off, yaw=float(rng.uniform(-0.3, 0.3))).success)
    return out


def test_parallel_jaw_lifts_centred_cube_9_of_10():
    ok = _cube_trials(range(10))
    assert sum(ok) >= 9, ok


# ------------------------------------------------------------------ BulletGripper API


def test_reset_and_move_track_the_tcp(client):
    g = BulletGripper(client, get_gripper("parallel_jaw-1"), scale=1.1)
    T = Transform.from_yaw(0.7, (0.1, -0.05, 0.3))
    g.reset(T, 0.5)
    assert np.allclose(g.tcp_pose().translation, T.translation, atol=1e-6)
    assert np.allclose(g.tcp_pose().rotation, T.rotation, atol=1e-6)
    T2 = Transform.from_yaw(-0.4, (0.0, 0.02, 0.2))
    for _ in range(240):
        g.move_tcp(T2)
        g.step()
        p.stepSimulation(physicsClientId=client)
    assert np.allclose(g.tcp_pose().translation, T2.translation, atol=2e-3)
    assert np.allclose(g.tcp_pose().rotation, T2.rotation, atol=1e-2)
    g.remove()


def test_opening_targets_move_fingers_and_couplings_follow(client):
    spec = get_gripper("parallel_jaw-2")
    g = BulletGripper(client, spec, 1.0)
    g.reset(Transform.from_yaw(0.0, (0, 0, 0.5)), 1.0)
    wide = g.finger_aperture()
    assert wide == pytest.approx(GripperModel(spec).aperture(1.0), abs=1e-3)
    g.set_opening_target(0.3)
    for _ in range(240):
        g.step()
        p.stepSimulation(physicsClientId=client)
    q = g.joint_state()
    expected = joint_positions(spec, 0.3)
    for name, v in expected.items():
        assert q[name] == pytest.approx(v, abs=2e-3), name
    assert g.finger_aperture() == pytest.approx(GripperModel(spec).aperture(0.3), abs=2e-3)
    assert g.finger_aperture() < wide
    assert not g.in_contact()
    g.remove()


def test_declared_target_coupling_keeps_closing_when_driver_is_blocked(client):
    """Under-actuated distal links follow the driver's target, not its blocked position."""
    spec = get_gripper("underactuated-0")
    assert any(c.mode == "target" for c in spec.couplings)
    g = BulletGripper(client, spec, 1.0)
    g.reset(Transform.from_yaw(0.0, (0, 0, 0.5)), 1.0)
    drive = spec.drive_joints[0].name
    idx = [i for i in range(p.getNumJoints(g.body_id, physicsClientId=client))
           if p.getJointInfo(g.body_id, i, physicsClientId=client)[1].decode() == drive][0]
    g.close()
    p.setJointMotorControl2(g.body_id, idx, p.VELOCITY_CONTROL, targetVelocity=0, force=1e4, physicsClientId=client)
    for _ in range(240):
        g.step()
        p.stepSimulation(physicsClientId=client)
    q = g.joint_state()
    closed, opened = joint_positions(spec, 0.0), joint_positions(spec, 1.0)
    assert q[drive] == pytest.approx(opened[drive], abs=0.02)
    for c in spec.couplings:
        if c.mode == "target":
            assert q[c.joint] == pytest.approx(closed[c.joint], abs=0.05), c.joint
        elif c.driver == drive:
            assert q[c.joint] == pytest.approx(opened[c.joint], abs=0.05), c.joint
    g.remove()


def test_coupling_error_is_the_largest_deviation_from_the_mimic_relation(client):
    """Joints set by hand off their mimic relation: the error is the largest deviation."""
    spec = get_gripper("xarm_gripper")
    g = BulletGripper(client, spec, 1.0)
    g.reset(Transform.from_yaw(0.0, (0, 0, 0.5)), 0.5)
    assert g.coupling_error() < 1e-9, "reset puts every joint on its kinematics"
    drive = spec.drive_joints[0].name
    q = g.joint_state()
    shifts = (0.05, -0.2, 0.1, 0.0, 0.03)
    for c, shift in zip(spec.couplings, shifts):
        p.resetJointState(g.body_id, g._joint[c.joint], q[c.joint] + shift, physicsClientId=client)
    p.resetJointState(g.body_id, g._joint[drive], q[drive] + 0.01, physicsClientId=client)
    deviations = [abs(s - 0.01 * c.multiplier) for c, s in zip(spec.couplings, shifts)]
    assert g.coupling_error() == pytest.approx(max(deviations), abs=1e-9)
    g.remove()


@pytest.mark.parametrize("name", ["wsg_50", "panda_hand"])
def test_prismatic_mimic_stays_rigid_while_holding(name):
    """The gear on a prismatic finger pair keeps the fingers on their kinematics under the grip."""
    r = lift_test(get_gripper(name), 1.0, "box", 0.04)
    assert r.success and r.coupling_error_held < 1e-3, r


@pytest.mark.parametrize("name", ["pr2_gripper", "revolute-1"])
def test_revolute_mimic_stays_rigid_while_holding_an_off_centre_box(name):
    """A box 1 cm off the TCP axis: one finger meets it first and pushes it to the centre; the gear
    keeps both revolute fingers on their kinematics. With PyBullet's default 50 solver iterations
    it gives way (and gave way by about 0.5 rad on the earlier free-floating base)."""
    r = lift_test(get_gripper(name), 1.0, "box", 0.04, offset=(0.01, 0.0))
    assert r.success and r.coupling_error_held < 0.02, r
    weak = lift_test(get_gripper(name), 1.0, "box", 0.04, offset=(0.01, 0.0), solver_iterations=50)
    assert weak.coupling_error_held > 0.02, "the bound cannot tell a yielding gear from a rigid one"


def test_virtual_arm_tracks_tcp_targets_and_rejects_tilt(client):
    """reset puts the TCP exactly on the target; move_tcp's motors follow a new position and a yaw
    past pi along the short way; a tilted target is refused."""
    spec = get_gripper("pr2_gripper")
    g = BulletGripper(client, spec, 1.0)
    target = Transform.from_yaw(0.4, (0.1, -0.2, 0.5))
    g.reset(target, 1.0)
    got = g.tcp_pose()
    assert np.allclose(got.translation, target.translation, atol=1e-9)
    assert np.allclose(got.rotation, target.rotation, atol=1e-9)
    st = p.getLinkState(g.body_id, g._link[spec.cut_link], computeForwardKinematics=True, physicsClientId=client)
    want = target * spec.T_base_tcp(1.0).inverse()
    assert np.allclose(st[4], want.translation, atol=1e-7), "the hand's base sits at T_world_tcp * T_tcp_base"
    assert np.allclose(Transform.from_quat(st[5], st[4]).rotation, want.rotation, atol=1e-6)
    for yaw in np.linspace(0.4, 3.6, 9):
        for _ in range(24):
            g.move_tcp(Transform.from_yaw(float(yaw), (0.15, -0.1, 0.4)))
            g.step()
            p.stepSimulation(physicsClientId=client)
    for _ in range(120):
        g.step()
        p.stepSimulation(physicsClientId=client)
    end = Transform.from_yaw(3.6, (0.15, -0.1, 0.4))
    got = g.tcp_pose()
    assert np.allclose(got.translation, end.translation, atol=2e-3), got.translation
    assert np.allclose(got.rotation, end.rotation, atol=2e-3)
    tilted = Transform(Transform.from_yaw(0.0).rotation @ np.array([[1, 0, 0], [0, 0.99, -0.141], [0, 0.141, 0.99]]),
                       (0.0, 0.0, 0.5))
    with pytest.raises(ValueError, match="tilts"):
        g.move_tcp(tilted)
    g.remove()


def test_in_contact_sees_the_table_and_honours_exclude(client):
    plane = p.loadURDF(str(Path(pybullet_data.getDataPath()) / "plane.urdf"), physicsClientId=client)
    g = BulletGripper(client, get_gripper("parallel_jaw-0"), 1.0)
    g.reset(Transform.from_yaw(0.0, (0, 0, 0.3)), 1.0)
    p.stepSimulation(physicsClientId=client)
    assert not g.in_contact()
    g.reset(Transform.from_yaw(0.0, (0, 0, 0.005)), 1.0)
    for _ in range(5):
        g.step()
        p.stepSimulation(physicsClientId=client)
    assert g.in_contact()
    assert not g.in_contact(exclude=(plane,))
    g.remove()
    assert p.getNumBodies(physicsClientId=client) == 1


# ------------------------------------------------------------------ library


@pytest.mark.parametrize("family", FAMILY_NAMES)
def test_procedural_families_are_deterministic_and_monotonic(family):
    assert sample_params(family, 5) == sample_params(family, 5)
    assert sample_params(family, 5) != sample_params(family, 6)
    a, b = generate(family, 5), generate(family, 5)
    assert a.spec.urdf == b.spec.urdf and a.spec.name == f"{family}-5"
    for scale in (0.8, 1.2):
        ap = check_kinematics(a.spec, scale)
        assert ap[-1] > ap[0] + 0.005 * scale
    assert a.spec.description.startswith(family)


@pytest.mark.parametrize("name", REAL)
def test_real_grippers_load_open_close_monotonically(name):
    spec = get_gripper(name)
    assert spec.split == "test"
    assert spec.license
    for scale in (0.8, 1.0, 1.2):
        ap = check_kinematics(spec, scale)
        assert ap[-1] > 0.03 * scale, ap
    mesh = posed_meshes(spec, 1.0, 1.0)
    lo, hi = mesh.bounds
    assert lo[2] < 0.0 < hi[2], "fingers must reach below the TCP and the hand rise above it"


def test_mimic_is_read_automatically():
    spec = get_gripper("panda_hand")
    (c,) = spec.couplings
    assert (c.joint, c.driver, c.multiplier, c.from_mimic) == ("panda_finger_joint2", "panda_finger_joint1", 1.0, True)
    xarm = get_gripper("xarm_gripper")
    assert len(xarm.couplings) == 5 and all(c.from_mimic for c in xarm.couplings)


@pytest.mark.parametrize("name", REAL)
def test_real_grippers_lift_a_box(name):
    assert lift_test(get_gripper(name), 1.0, "box", 0.04).success


def test_inertia_from_collision_of_an_offset_box():
    import xml.etree.ElementTree as ET

    from common.gripper_formats import inertia_from_collision

    robot = ET.fromstring(
        '<robot name="r"><link name="a"><inertial><mass value="2.0"/>'
        '<inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial>'
        '<collision><origin xyz="0.1 0 0.05"/><geometry><box size="0.1 0.2 0.3"/></geometry></collision>'
        "</link><link name=\"massless\"/></robot>"
    )
    assert inertia_from_collision(robot) == ["a"]
    inertial = robot.find("link/inertial")
    assert np.allclose([float(v) for v in inertial.find("origin").get("xyz").split()], [0.1, 0.0, 0.05])
    got = {k: float(v) for k, v in inertial.find("inertia").attrib.items()}
    m, (a, b, c) = 2.0, (0.1, 0.2, 0.3)  # solid box about its centre: m / 12 * (sum of the other two sides squared)
    assert got["ixx"] == pytest.approx(m / 12 * (b * b + c * c), rel=1e-6)
    assert got["iyy"] == pytest.approx(m / 12 * (a * a + c * c), rel=1e-6)
    assert got["izz"] == pytest.approx(m / 12 * (a * a + b * b), rel=1e-6)
    assert abs(got["ixy"]) < 1e-12 and float(inertial.find("mass").get("value")) == 2.0


@pytest.mark.slow
@pytest.mark.parametrize("name", REAL)
def test_real_grippers_pass_the_full_check(name):
    from actors.gripper_cli import check_gripper

    report = check_gripper(get_gripper(name))
    assert report.passed, report.reasons


def test_list_grippers_filters():
    test = list_grippers(split="test")
    assert {s.name for s in test} == set(REAL)
    three = list_grippers(family="3-finger")
    assert three and all(s.family == "3-finger" for s in three)
    train = list_grippers(split="train")
    assert len(train) >= 32 and {s.params["generator"] for s in train} == set(FAMILY_NAMES)


def test_tcp_estimated_when_spec_leaves_it_out(tmp_path):
    spec = get_gripper("parallel_jaw-3")
    data = yaml.safe_load(spec.spec_path.read_text())
    del data["tcp"]
    data["source"] = str(spec.source)
    f = tmp_path / "no_tcp.yaml"
    f.write_text(yaml.safe_dump(data))
    est = load_spec(f)
    assert est.tcp_estimated and not spec.tcp_estimated
    assert np.allclose(est.approach_axis, spec.approach_axis, atol=0.01)
    assert abs(abs(est.closing_axis[0]) - 1.0) < 0.01
    assert np.allclose(est.tcp_position, spec.tcp_position, atol=0.01)


# ------------------------------------------------------------------ bad input


def _write(tmp_path: Path, data: dict, name: str = "bad.yaml") -> Path:
    f = tmp_path / name
    f.write_text(yaml.safe_dump(data))
    return f


def _base(tmp_path: Path) -> dict:
    spec = get_gripper("parallel_jaw-0")
    data = yaml.safe_load(spec.spec_path.read_text())
    data["source"] = str(spec.source)
    return data


def _one_line(e: pytest.ExceptionInfo, *parts: str) -> None:
    msg = str(e.value)
    assert "\n" not in msg
    for part in parts:
        assert part in msg, msg


@pytest.mark.parametrize("override", [
    {"couplings": [{"joint": "finger_right_joint", "driver": "finger_left_joint", "multiplier": 0.5, "mode": "target"}]},
    {"couplings": [{"joint": "finger_right_joint", "driver": "finger_left_joint", "multiplier": 0.5,
                    "offset": 0.004, "mode": "mimic"}]},
    {"drive_joints": [{"name": "finger_left_joint", "open": 0.03, "closed": 0.0},
                      {"name": "finger_right_joint", "open": 0.012, "closed": 0.0}], "couplings": []},
], ids=["target-half", "mimic-half-offset", "second-drive"])
def test_a_spec_that_overrides_a_urdf_mimic_poses_the_model_as_pybullet_does(tmp_path, client, override):
    """The parallel jaw's URDF ``<mimic>``s its right finger to the left one. A spec that couples
    the right finger otherwise, or drives it, must pose the kinematic model (what the gripper
    encoding and the reach see) where PyBullet puts the fingers, not where the file's ``<mimic>`` would."""
    data = _base(tmp_path)
    assert "<mimic joint=\"finger_left_joint\"" in Path(data["source"]).read_text()
    data.update(override)
    spec = load_spec(_write(tmp_path, data, "override.yaml"))
    assert "<mimic" not in spec.urdf.read_text()
    g = BulletGripper(client, spec, 1.2)
    model = GripperModel(spec, 1.2)
    for opening in (1.0, 0.4):
        g.reset(Transform.from_yaw(0.3, (0.1, 0, 0.5)), opening)
        T_tcp_world = g.tcp_pose().inverse()
        poses = model.link_poses(opening)
        for link in ("finger_left", "finger_right"):
            st = p.getLinkState(g.body_id, g._link[link], computeForwardKinematics=True, physicsClientId=client)
            sim = (T_tcp_world * Transform.from_quat(st[5], st[4])).as_matrix()
            np.testing.assert_allclose(poses[link], sim, atol=1e-5, err_msg=f"{link} at opening {opening}")
    q = joint_positions(spec, 1.0, 1.2)
    assert abs(q["finger_right_joint"]) != pytest.approx(abs(q["finger_left_joint"]), abs=1e-3)
    g.remove()


def test_mount_rpy_round_trips_near_pitch_90_degrees():
    """The arm's fixed-joint rpy rebuilds its rotation, also within mrad of pitch +-pi/2 (an
    approach axis near the base x axis), where Euler angles from a quaternion lose precision."""
    from actors.bullet_gripper import _urdf_rpy

    rng = np.random.default_rng(0)
    for k in range(300):
        yaw, roll = rng.uniform(-3.1, 3.1, 2)
        pitch = rng.uniform(-1.5, 1.5) if k % 2 else math.copysign(math.pi / 2, rng.normal()) + rng.normal() * 1e-3
        R = np.array(p.getMatrixFromQuaternion(p.getQuaternionFromEuler([roll, pitch, yaw]))).reshape(3, 3)
        back = np.array(p.getMatrixFromQuaternion(p.getQuaternionFromEuler(_urdf_rpy(R)))).reshape(3, 3)
        assert np.abs(back - R).max() < 1e-6, (roll, pitch, yaw)


def test_link_named_like_the_virtual_arm_is_refused(tmp_path, client):
    """A hand whose URDF already uses one of the arm's names gets one line naming the spec."""
    data = _base(tmp_path)
    urdf = tmp_path / "clash.urdf"
    urdf.write_text(Path(data["source"]).read_text().replace('"palm"', '"arm_world"'))
    data["source"], data["cut_link"] = str(urdf), "arm_world"
    f = _write(tmp_path, data, "clash.yaml")
    with pytest.raises(GripperSpecError) as e:
        BulletGripper(client, load_spec(f), 1.0)
    _one_line(e, "clash.yaml", "arm_world", "virtual arm")


def test_a_urdf_pybullet_cannot_load_is_one_line_naming_the_spec(tmp_path, client, monkeypatch):
    """PyBullet raises (rather than returning a negative id) when it cannot load the mounted URDF:
    one line naming the spec, which `grippers check` reports as a reason instead of a traceback."""
    from actors import bullet_gripper
    from actors.gripper_cli import check_gripper

    def refuse(*args, **kwargs):
        raise p.error("Cannot load URDF file.")

    monkeypatch.setattr(bullet_gripper.p, "loadURDF", refuse)
    spec = get_gripper("parallel_jaw-0")
    with pytest.raises(GripperSpecError) as e:
        BulletGripper(client, spec, 1.0)
    _one_line(e, str(spec.spec_path), "PyBullet could not load")
    report = check_gripper(spec)
    assert not report.passed and any("PyBullet could not load" in r for r in report.reasons), report.reasons


def test_a_closed_chain_in_the_urdf_is_one_line(tmp_path):
    """A joint whose child is already in the tree (here the palm again) made the subtree walk loop
    for ever; URDF describes trees."""
    data = _base(tmp_path)
    urdf = tmp_path / "loop.urdf"
    loop = '<joint name="back" type="fixed"><parent link="finger_left"/><child link="palm"/></joint></robot>'
    urdf.write_text(Path(data["source"]).read_text().replace("</robot>", loop))
    data["source"] = str(urdf)
    f = _write(tmp_path, data, "loop.yaml")
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "'back'", "reached twice")


@pytest.mark.parametrize("field, change", [
    ("drive_joints[0].name", lambda d: d["drive_joints"][0].update(name=["finger_left_joint"])),
    ("couplings[0].driver", lambda d: d.update(couplings=[{"joint": "finger_right_joint", "driver": ["x"]}])),
])
def test_a_list_where_a_joint_name_belongs_is_one_line(tmp_path, field, change):
    data = _base(tmp_path)
    change(data)
    f = _write(tmp_path, data)
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), field, "expected a joint name")


def test_an_ascii_stl_mesh_reaches_pybullet_as_its_shape(tmp_path, client):
    """PyBullet reads binary STL but loads an ASCII STL as a 2 mm box without an error: ASCII STL
    is converted to OBJ like other formats, binary STL is used as it is."""
    import xml.etree.ElementTree as ET

    import trimesh

    from common.gripper_formats import resolve_meshes

    box = trimesh.creation.box((0.02, 0.02, 0.05))
    (tmp_path / "ascii.stl").write_text(trimesh.exchange.stl.export_stl_ascii(box))
    (tmp_path / "binary.stl").write_bytes(trimesh.exchange.stl.export_stl(box))
    robot = ET.fromstring('<robot name="r"><link name="a"><collision><geometry><mesh filename="ascii.stl"/>'
                          '</geometry></collision><visual><geometry><mesh filename="binary.stl"/></geometry>'
                          '</visual></link></robot>')
    resolve_meshes(robot, tmp_path / "r.urdf", tmp_path / "cache")
    ascii_mesh, binary_mesh = (Path(m.get("filename")) for m in robot.iter("mesh"))
    assert ascii_mesh.suffix == ".obj" and ascii_mesh.parent == tmp_path / "cache"
    assert binary_mesh == tmp_path / "binary.stl"
    for mesh in (ascii_mesh, binary_mesh):
        shape = p.createCollisionShape(p.GEOM_MESH, fileName=str(mesh), physicsClientId=client)
        body = p.createMultiBody(0.0, shape, physicsClientId=client)
        lo, hi = p.getAABB(body, physicsClientId=client)
        assert np.allclose(np.subtract(hi, lo), (0.02, 0.02, 0.05), atol=0.006), (mesh, lo, hi)  # + AABB margin


def test_unknown_joint_names_file_and_field(tmp_path):
    data = _base(tmp_path)
    data["drive_joints"][0]["name"] = "no_such_joint"
    f = _write(tmp_path, data)
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "drive_joints[0].name", "no_such_joint")


def test_opening_that_does_not_move_fingers(tmp_path):
    data = _base(tmp_path)
    data["drive_joints"][0]["open"] = data["drive_joints"][0]["closed"] + 0.001
    f = _write(tmp_path, data)
    with pytest.raises(GripperSpecError) as e:
        check_kinematics(load_spec(f))
    _one_line(e, str(f), "drive_joints[0].open", "does not move the fingers")
    data["drive_joints"][0]["open"] = data["drive_joints"][0]["closed"]
    f = _write(tmp_path, data, "same.yaml")
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "drive_joints[0].open")


def test_broken_urdf(tmp_path):
    urdf = tmp_path / "broken.urdf"
    urdf.write_text("<robot name='x'><link name='a'></robot>")
    data = _base(tmp_path)
    data["source"] = str(urdf)
    f = _write(tmp_path, data)
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "source", "not valid XML")


_SDF = ("<sdf version='1.6'><model name='m'><link name='palm'><collision name='c'><geometry><box><size>0.1 0.1 0.1"
        "</size></box></geometry></collision></link><link name='f'><collision name='c'><geometry><box><size>0.01 0.01"
        " 0.05</size></box></geometry></collision></link><joint name='j' type='prismatic'><parent>palm</parent>"
        "<child>f</child><axis><xyz>1 0 0</xyz><limit><lower>0</lower><upper>0.05</upper></limit></axis></joint>"
        "</model></sdf>")
_MJCF = ("<mujoco model='m'><worldbody><body name='palm'><geom type='box' size='0.05 0.05 0.05'/><body name='f' "
         "pos='0 0 -0.05'><joint name='j' type='slide' axis='1 0 0' range='0 0.05'/><geom type='box' "
         "size='0.005 0.005 0.02'/></body></body></worldbody></mujoco>")


def _urdf_sub(pattern: str, replacement: str):
    """A change to the parallel jaw's URDF (the first match of ``pattern``)."""
    return lambda text: re.sub(pattern, replacement, text, count=1)


@pytest.mark.parametrize("suffix, bad, field", [
    ("urdf", _urdf_sub(r'lower="[^"]*"', 'lower="abc"'), "joint finger_left_joint: limit lower: expected a number, got 'abc'"),
    ("urdf", _urdf_sub(r'multiplier="[^"]*"', 'multiplier="one"'), "joint finger_right_joint: mimic multiplier: expected a number"),
    ("urdf", _urdf_sub(r'<mass value="[^"]*"', '<mass value="abc"'), "inertial mass: expected a number, got 'abc'"),
    ("sdf", _SDF.replace("<parent>palm</parent>", ""), "joint j: parent: missing"),
    ("sdf", _SDF.replace("<lower>0</lower>", "<lower>zero</lower>"), "joint j: limit lower: expected a number"),
    ("sdf", _SDF.replace("<box><size>0.01 0.01 0.05</size></box>", "<box/>"), "link f collision box size: missing"),
    ("sdf", _SDF.replace("<box><size>0.01 0.01 0.05</size></box>",
                         "<cylinder><radius>abc</radius><length>0.05</length></cylinder>"), "cylinder radius: expected a number"),
    ("xml", _MJCF.replace("0.05 0.05 0.05", "0.05 0.05 abc"), "body palm size: expected a number, got 'abc'"),
    ("xml", _MJCF.replace("type='box' size='0.005", "type='box' contype='no' size='0.005"), "body f contype"),
])
def test_a_malformed_number_or_element_in_the_source_is_one_line(tmp_path, suffix, bad, field):
    """A value of the robot file that is not a number, or a missing element, names the spec, the
    source file and the element in one line when the spec loads (not a ValueError from deep
    inside, nor a failure later in every actor)."""
    data = _base(tmp_path)
    if callable(bad):
        source = Path(data["source"]).read_text()
        text = bad(source)
        assert text != source
    else:
        text = bad
        data.update(cut_link="palm", drive_joints=[{"name": "j", "open": 0.03, "closed": 0.0}], couplings=[])
    src = tmp_path / f"broken.{suffix}"
    src.write_text(text)
    data["source"] = str(src)
    f = _write(tmp_path, data)
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), f"source: broken.{suffix}: ", field)


def _slider(name: str, y: float, z: float, axis: str, limits: tuple[float, float], mimic: str = "") -> str:
    """A prismatic joint from the palm to a small box link ``<name>_link`` (URDF text)."""
    return (f"<link name='{name}_link'><collision><geometry><box size='0.01 0.01 0.01'/></geometry></collision></link>"
            f"<joint name='{name}' type='prismatic'><parent link='palm'/><child link='{name}_link'/>"
            f"<origin xyz='0 {y} {z}'/><axis xyz='{axis}'/>"
            f"<limit lower='{limits[0]}' upper='{limits[1]}' effort='1' velocity='1'/>{mimic}</joint>")


def test_held_joints_and_their_mimic_followers_freeze_where_the_file_puts_them(tmp_path):
    """A joint frozen by ``hold_joints`` sits at its value; a ``<mimic>`` follower of it (and a
    follower of that follower) is frozen where its ``<mimic>`` puts it, not at 0, and a joint that
    is neither driven, coupled nor held sits at 0. A ``<mimic>`` on a fixed joint couples nothing."""
    urdf = tmp_path / "held.urdf"
    urdf.write_text(
        "<robot name='held'><link name='palm'><collision><geometry><box size='0.1 0.1 0.02'/></geometry></collision></link>"
        + _slider("a", 0.03, 0.0, "1 0 0", (-0.05, 0.05))
        + _slider("b", -0.03, 0.0, "1 0 0", (-0.05, 0.05), "<mimic joint='a' multiplier='2' offset='0.005'/>")
        + _slider("d", 0.0, 0.03, "1 0 0", (-0.05, 0.05), "<mimic joint='b' multiplier='1' offset='0.001'/>")
        + _slider("e", 0.0, 0.06, "1 0 0", (-0.05, 0.05))
        + _slider("c", 0.0, -0.03, "0 1 0", (0.0, 0.04))
        + _slider("p", 0.04, 0.03, "1 0 0", (-0.05, 0.05), "<mimic joint='q' multiplier='1' offset='0.002'/>")
        + _slider("q", -0.04, 0.03, "1 0 0", (-0.05, 0.05), "<mimic joint='p' multiplier='1' offset='0.002'/>")
        + _slider("x", 0.04, 0.06, "1 0 0", (-0.05, 0.05), "<mimic joint='p' multiplier='1' offset='0.01'/>")
        + "<link name='f_link'/><joint name='f' type='fixed'><parent link='palm'/><child link='f_link'/>"
          "<mimic joint='c' multiplier='1' offset='0'/></joint>"
        + "</robot>"
    )
    data = _base(tmp_path)
    data.update(source=str(urdf), cut_link="palm", drive_joints=[{"name": "c", "open": 0.04, "closed": 0.0}],
                couplings=[], hold_joints={"a": 0.01})
    spec = load_spec(_write(tmp_path, data, "held.yaml"))
    assert spec.joint_names == ("c",)
    poses = GripperModel(spec, 1.0, frame="base").link_poses(0.5)
    expected = {"a_link": (0.01, 0.03, 0.0), "b_link": (0.025, -0.03, 0.0), "d_link": (0.026, 0.0, 0.03),
                "e_link": (0.0, 0.0, 0.06), "c_link": (0.0, 0.02, -0.03),
                # a <mimic> cycle no drive enters stays at 0; a follower of it where its <mimic> says
                "p_link": (0.0, 0.04, 0.03), "q_link": (0.0, -0.04, 0.03), "x_link": (0.01, 0.04, 0.06)}
    for link, xyz in expected.items():
        np.testing.assert_allclose(poses[link][:3, 3], xyz, atol=1e-9, err_msg=link)
    # a drive joint is not held
    data["hold_joints"] = {"a": 0.01, "c": 0.02}
    f = _write(tmp_path, data, "held-drive.yaml")
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "hold_joints.c: the joint is driven")
    data["hold_joints"] = {"a": 0.01, "f": 0.02}
    f = _write(tmp_path, data, "held-fixed.yaml")
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "hold_joints.f: the joint is fixed")
    data["hold_joints"] = {"a": 0.01}
    # a declared coupling must follow a joint that moves
    data["couplings"] = [{"joint": "e", "driver": "a", "mode": "target"}]
    f = _write(tmp_path, data, "frozen-driver.yaml")
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "couplings[0].driver: joint 'a' is neither driven nor coupled")


@pytest.mark.parametrize("mode", ["mimic", "target"])
def test_couplings_between_a_hinge_and_a_slider_scale_with_the_gripper(tmp_path, client, mode):
    """A slider following a hinge (m per rad) moves twice as far on a gripper at scale 2, and a
    hinge following that slider (rad per m) turns as far at any scale: a coupling's multiplier is
    given at scale 1, in the follower's unit per the driver's. PyBullet reaches those values too."""
    hinge = ("<link name='h_link'><collision><geometry><box size='0.01 0.01 0.01'/></geometry></collision></link>"
             "<joint name='h' type='revolute'><parent link='palm'/><child link='h_link'/><origin xyz='0 0 -0.03'/>"
             "<axis xyz='0 0 1'/><limit lower='0' upper='1' effort='1' velocity='1'/></joint>")
    urdf = tmp_path / "mixed.urdf"
    urdf.write_text(
        "<robot name='mixed'><link name='palm'><collision><geometry><box size='0.1 0.1 0.02'/></geometry></collision></link>"
        + hinge + _slider("s", 0.03, -0.03, "1 0 0", (-0.05, 0.05)) + _slider("r", -0.03, -0.03, "0 1 0", (-1.0, 1.0))
        + "</robot>"
    )
    urdf.write_text(urdf.read_text().replace("name='r' type='prismatic'", "name='r' type='revolute'").replace(
        "<axis xyz='0 1 0'/>", "<axis xyz='0 0 1'/>"))
    data = _base(tmp_path)
    data.update(source=str(urdf), cut_link="palm", drive_joints=[{"name": "h", "open": 1.0, "closed": 0.0}],
                couplings=[{"joint": "s", "driver": "h", "multiplier": 0.02, "offset": 0.001, "mode": mode},
                           {"joint": "r", "driver": "s", "multiplier": 10.0, "mode": mode}])
    spec = load_spec(_write(tmp_path, data, "mixed.yaml"))
    for scale in (1.0, 2.0):
        q = joint_positions(spec, 1.0, scale)
        assert q["s"] == pytest.approx(0.021 * scale) and q["r"] == pytest.approx(0.21), (scale, q)
    g = BulletGripper(client, spec, 2.0)
    g.reset(Transform.from_yaw(0.0, (0, 0, 0.5)), 1.0)
    g.set_opening_target(0.5)
    for _ in range(480):
        g.step()
        p.stepSimulation(physicsClientId=client)
    q, want = g.joint_state(), joint_positions(spec, 0.5, 2.0)
    assert want["s"] == pytest.approx(0.022) and want["r"] == pytest.approx(0.11)
    for name in ("h", "s", "r"):
        assert q[name] == pytest.approx(want[name], abs=2e-3 if name == "s" else 2e-2), (name, q, want)
    assert g.coupling_error() < (1e-3 if mode == "mimic" else np.inf)
    g.remove()


def test_missing_mesh_and_missing_source(tmp_path):
    urdf = tmp_path / "nomesh.urdf"
    urdf.write_text(
        "<robot name='x'><link name='palm'><collision><geometry><mesh filename='package://nowhere/m.stl'/>"
        "</geometry></collision></link><link name='f'/><joint name='j' type='prismatic'><parent link='palm'/>"
        "<child link='f'/><axis xyz='1 0 0'/><limit lower='0' upper='0.05' effort='1' velocity='1'/></joint></robot>"
    )
    data = _base(tmp_path)
    data.update(source=str(urdf), drive_joints=[{"name": "j", "open": 0.05, "closed": 0.0}], couplings=[])
    f = _write(tmp_path, data)
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "source", "m.stl")
    data["source"] = str(tmp_path / "missing.urdf")
    f = _write(tmp_path, data, "missing.yaml")
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), "source", "not found")


@pytest.mark.parametrize(
    "key,value,field",
    [
        ("family", "4-finger", "family"),
        ("split", "val", "split"),
        ("cut_link", "no_link", "cut_link"),
        ("friction", -1, "friction"),
        ("inertia", "guess", "inertia"),
        ("colour", "red", "colour"),
        ("tcp", {"position": [0, 0], "approach": [0, 0, 1]}, "tcp.position"),
    ],
)
def test_bad_fields_name_file_and_field(tmp_path, key, value, field):
    data = _base(tmp_path)
    data[key] = value
    f = _write(tmp_path, data)
    with pytest.raises(GripperSpecError) as e:
        load_spec(f)
    _one_line(e, str(f), field)


def test_unknown_gripper_name():
    with pytest.raises(GripperSpecError) as e:
        get_gripper("no_such_gripper")
    _one_line(e, "no_such_gripper", "unknown gripper")


def test_registry_files_are_named_after_their_gripper():
    for name, path in registered_spec_paths().items():
        assert yaml.safe_load(path.read_text())["name"] == name


def test_cache_goes_to_env_dir():
    spec = get_gripper("revolute-1")
    assert str(spec.urdf).startswith(os.environ["ADAGRASP_CACHE"])
    assert not str(spec.urdf).startswith(str(Path(__file__).parents[1] / "assets"))


def test_scale_scales_geometry():
    spec = get_gripper("three_finger-2")
    a = GripperModel(spec, 1.0).mesh(0.7).extents
    b = GripperModel(spec, 1.2).mesh(0.7).extents
    assert np.allclose(b, 1.2 * a, rtol=1e-6)
    assert math.isclose(GripperModel(spec, 1.2).aperture(1.0), 1.2 * GripperModel(spec, 1.0).aperture(1.0), rel_tol=1e-2)


# ------------------------------------------------------------------ CLI


def test_cli_list_json(capsys):
    from actors.gripper_cli import cli

    assert cli(["list", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    test_rows = [r for r in rows if r["split"] == "test"]
    assert {r["name"] for r in test_rows} == set(REAL)
    families = {r["description"].split()[0] for r in rows if r["split"] == "train"}
    assert families == set(FAMILY_NAMES)
    for r in rows:
        assert r["aperture_max_m"] > r["aperture_min_m"] and r["drive_joints"] >= 1


def test_cli_check_passes_and_writes_png_and_json(tmp_path, capsys):
    from actors.gripper_cli import cli

    rc = cli(["check", "parallel_jaw-0", "--out", str(tmp_path), "--json", str(tmp_path / "r.json")])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "PASS" in out
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["passed"] and report["lift"]["box"]["success"] and report["lift"]["cylinder"]["success"]
    assert np.all(np.diff(report["apertures_sim"]) > -1e-3)
    assert (tmp_path / "parallel_jaw-0_encoding.png").stat().st_size > 10_000
    held = report["lift"]["box"]["coupling_error_held"] + report["lift"]["cylinder"]["coupling_error_held"]
    assert len(held) == 6 and report["coupling_error_held"] == pytest.approx(max(held), abs=1e-4)
    assert "holding the lift-test objects" in out


def test_cli_check_bad_spec_is_one_line(tmp_path, capsys):
    from actors.gripper_cli import cli

    data = _base(tmp_path)
    data["couplings"] = [{"joint": "finger_right_joint", "driver": "ghost_joint"}]
    f = _write(tmp_path, data)
    assert cli(["check", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(f) in err and "couplings[0].driver" in err


def test_cli_check_reports_fingers_that_do_not_move(tmp_path, capsys):
    from actors.gripper_cli import cli

    data = _base(tmp_path)
    data["drive_joints"][0]["open"] = data["drive_joints"][0]["closed"] + 0.001
    f = _write(tmp_path, data)
    assert cli(["check", str(f)]) == 1
    out = capsys.readouterr().out
    assert "FAIL" in out and "drive_joints[0].open" in out and "does not move the fingers" in out


def test_cli_generate_reports_pass_rate(capsys):
    from actors.gripper_cli import cli

    assert cli(["generate", "--count", "8", "--no-physics", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["generated"] == 8 and 0 <= summary["pass_rate"] <= 1
    assert set(summary["per_family"]) == set(FAMILY_NAMES)


def test_cli_generate_writes_the_passed_seeds_as_a_pool_section(tmp_path, capsys):
    from actors.gripper_cli import cli

    out, pool = tmp_path / "gen.json", tmp_path / "pool.yaml"
    assert cli(["generate", "--count", "8", "--start", "4", "--no-physics", "--quiet",
                "--json", str(out), "--pool-yaml", str(pool)]) == 0
    results = json.loads(out.read_text())["grippers"]
    passed = {r["name"] for r in results if r["passed"]}
    section = yaml.safe_load(pool.read_text())["pool"]
    assert {f"{fam}-{seed}" for fam, seeds in section.items() for seed in seeds} == passed
    assert all(seeds == sorted(seeds) for seeds in section.values())
    assert {r["name"] for r in results} == {f"{f}-{s}" for f in FAMILY_NAMES for s in (1, 2)}


def test_cli_generate_and_check_refuse_bad_counts_and_unwritable_outputs_before_the_run(tmp_path, capsys):
    """Outputs are written after the whole run: one that cannot be written (its folder is a file),
    a --count below 1 and a --start below 0 are one line before any gripper is checked; an output
    in a folder that does not exist yet is written, the folder made."""
    from actors.gripper_cli import cli

    taken = tmp_path / "file"
    taken.write_text("mine")
    for argv, needle in (
        (["generate", "--count", "0"], "--count 0: expected >= 1"),
        (["generate", "--start", "-1"], "--start -1: expected >= 0"),
        (["generate", "--count", "1", "--json", str(taken / "g.json")], f"--json {taken / 'g.json'}: {taken}"),
        (["generate", "--count", "1", "--pool-yaml", str(taken / "p.yaml")], f"--pool-yaml {taken / 'p.yaml'}"),
        (["check", "wsg_50", "--json", str(taken / "c.json")], f"--json {taken / 'c.json'}"),
    ):
        assert cli(argv) == 2
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and needle in err[0] and not captured.out, (argv, err)
    assert taken.read_text() == "mine"
    out = tmp_path / "new" / "deeper" / "gen.json"
    assert cli(["generate", "--count", "1", "--no-physics", "--quiet", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["summary"]["generated"] == 1


def test_pool_catalogue_holds_the_training_catalogue_and_valid_names():
    from common.gripper_procedural import catalog_names

    pool, train = catalog_names("pool"), catalog_names("train")
    assert len(pool) == len(set(pool)) and len(pool) > 4 * len(train)
    assert set(train) <= set(pool)
    families = {n.rsplit("-", 1)[0] for n in pool}
    assert families == set(FAMILY_NAMES)
    assert all(0 <= int(n.rsplit("-", 1)[1]) < 128 for n in pool)
    spec = get_gripper(pool[-1])
    assert spec.split == "train" and spec.name == pool[-1]
    with pytest.raises(ValueError, match="catalog section"):
        catalog_names("test")


def test_train_grippers_pool_selects_every_pool_gripper():
    from actors.grasp_actor import split_grippers
    from common.config import load_config
    from common.gripper_procedural import catalog_names

    two, multi = split_grippers(load_config("default", ["grippers.train_grippers=pool"]))
    assert {s.name for s in two + multi} == set(catalog_names("pool"))
    assert all(s.family == "2-finger" for s in two) and all(s.family != "2-finger" for s in multi)
    assert all(s.split == "train" for s in two + multi) and len(two) > 32 and len(multi) > 32


@pytest.mark.slow
def test_parallel_jaw_lifts_across_scales_and_seeds():
    spec = get_gripper("parallel_jaw-0")
    ok = [lift_test(spec, s, "box", 0.04, offset=(0.005 * (i % 3 - 1), 0.004), yaw=0.2 * i).success
          for i, s in enumerate((0.8, 0.9, 1.0, 1.1, 1.2))]
    assert all(ok), ok
