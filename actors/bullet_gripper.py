"""A gripper body in one PyBullet client, carried by a fixed-base virtual arm.

The arm is four motorised joints (prismatic x, y, z, then revolute yaw about world z) added
above the gripper's base link in a generated URDF (:func:`mounted_urdf`); its last frame is the
top-down TCP frame, so the joint targets are the TCP position and yaw. A stiff arm, unlike a
free-floating base held by a constraint, keeps PyBullet's gear constraints between revolute
finger joints rigid while the fingers squeeze an object, given enough constraint-solver
iterations in the client (``sim.solver_iterations``; :func:`lift_test` sets the same default).

Couplings (URDF ``<mimic>`` and declared ones; PyBullet ignores ``<mimic>``): a ``mimic``
coupling is a JOINT_GEAR constraint between the driver and the coupled joint (a rigid,
two-way linkage: a blocked follower also stops the driver); a ``measured`` coupling is a
per-step position target at the driver's measured position; a ``target`` coupling is a
per-step position target at the driver's commanded target (under-actuated and adaptive
fingers keep closing when the driver is blocked). Call :meth:`BulletGripper.step`
once before every ``stepSimulation``.

Call loop::

    g = BulletGripper(client, get_gripper("parallel_jaw-0"), scale=1.0)
    g.reset(T_world_tcp, opening=1.0)          # teleport, fingers at the opening
    while not g.in_contact() and ...:          # descend
        g.move_tcp(next_pose); g.step(); p.stepSimulation(physicsClientId=client)
    g.close()
    for _ in range(n): g.step(); p.stepSimulation(physicsClientId=client)
    g.move_tcp(lifted_pose) ...
    g.remove()

:func:`lift_test` runs that loop on a box or a cylinder in its own client (used by
``grippers check`` and the tests).
"""

from __future__ import annotations

import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as p

from common.config import SimConfig
from common.geometry import Transform
from common.gripper import (
    GripperModel,
    GripperSpec,
    GripperSpecError,
    aperture_from_points,
    joint_positions,
    scaled_urdf,
)


CLOSE_MAX_S = 2.0
"""Lift test: longest closing phase (s); it ends earlier once every joint has been still
(< 0.01 m/s or rad/s) for 0.1 s."""
GEAR_FORCE_FACTOR = 10.0
"""Maximum force of a gear (mimic) constraint, as a multiple of the spec's coupling force."""
GEAR_ERP = 1.0
"""Error reduction of a gear constraint: the whole position error is corrected every step."""
ARM_JOINTS = ("arm_x", "arm_y", "arm_z", "arm_yaw")
"""Joints of the virtual arm, world root to TCP frame: prismatic x, y, z (m), revolute yaw (rad)."""
ARM_REACH = 10.0
"""Metres: limit of each prismatic arm joint either side of the world origin."""
ARM_LINK_MASS = 0.05
"""Kilograms of each intermediate arm link (a small point-like inertia; no geometry)."""
_TILT_TOL = 1e-6
"""Largest |z_tcp . world z - 1| a TCP target may have: the arm only yaws."""


def mounted_urdf(spec: GripperSpec, scale: float, visual_from_collision: bool = False) -> str:
    """URDF text of the scaled gripper (:func:`common.gripper.scaled_urdf`) with the virtual arm
    above its base link: world -> arm_x -> arm_y -> arm_z -> arm_yaw -> fixed joint at
    ``T_tcp_base`` -> the gripper's base. Built in memory; :class:`BulletGripper` writes it to a
    temporary file only while PyBullet parses it."""
    robot = scaled_urdf(spec, scale, visual_from_collision)
    T_tcp_base = spec.T_base_tcp(scale).inverse()
    rpy = _urdf_rpy(T_tcp_base.rotation)
    xyz = T_tcp_base.translation
    origin = {"xyz": " ".join(f"{v:.9g}" for v in xyz), "rpy": " ".join(f"{v:.9g}" for v in rpy)}
    children = {j.find("child").get("link") for j in robot.findall("joint")}
    roots = [link.get("name") for link in robot.findall("link") if link.get("name") not in children]
    if len(roots) != 1:
        raise GripperSpecError(
            f"{spec.spec_path}: the processed URDF of {spec.urdf.name} has root links {roots}, not one"
        )
    names = {link.get("name") for link in robot.findall("link")} | {j.get("name") for j in robot.findall("joint")}
    arm_links = ("arm_world",) + tuple(f"{j}_link" for j in ARM_JOINTS)
    clash = sorted(names & ({"arm_mount", *ARM_JOINTS, *arm_links}))
    if clash:
        raise GripperSpecError(f"{spec.spec_path}: URDF names {clash} clash with the virtual arm's")
    links, joints = [], []
    parent = "arm_world"
    axes = {"arm_x": "1 0 0", "arm_y": "0 1 0", "arm_z": "0 0 1", "arm_yaw": "0 0 1"}
    for name in arm_links:
        link = ET.Element("link", name=name)
        inertial = ET.SubElement(link, "inertial")
        ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
        ET.SubElement(inertial, "mass", value=f"{ARM_LINK_MASS}")
        ET.SubElement(inertial, "inertia", ixx="1e-5", iyy="1e-5", izz="1e-5", ixy="0", ixz="0", iyz="0")
        links.append(link)
    for name in ARM_JOINTS:
        child = f"{name}_link"
        kind = "continuous" if name == "arm_yaw" else "prismatic"
        joint = ET.Element("joint", name=name, type=kind)
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=child)
        ET.SubElement(joint, "origin", xyz="0 0 0", rpy="0 0 0")
        ET.SubElement(joint, "axis", xyz=axes[name])
        if kind == "prismatic":
            ET.SubElement(joint, "limit", lower=f"{-ARM_REACH}", upper=f"{ARM_REACH}", effort="1e9", velocity="1e3")
        joints.append(joint)
        parent = child
    mount = ET.Element("joint", name="arm_mount", type="fixed")
    ET.SubElement(mount, "parent", link=parent)
    ET.SubElement(mount, "child", link=roots[0])
    ET.SubElement(mount, "origin", **origin)
    for k, el in enumerate(links + joints + [mount]):
        robot.insert(k, el)
    ET.indent(robot)
    return ET.tostring(robot, encoding="unicode")


def _urdf_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF roll, pitch, yaw (rad) of a (3, 3) rotation, R = Rz(yaw) Ry(pitch) Rx(roll); exact
    near pitch +-pi/2 too (the PR2's approach axis is the base x axis, pitch exactly pi/2)."""
    cos_pitch = float(np.hypot(R[0, 0], R[1, 0]))
    pitch = float(np.arctan2(-R[2, 0], cos_pitch))
    if cos_pitch > 1e-9:
        return float(np.arctan2(R[2, 1], R[2, 2])), pitch, float(np.arctan2(R[1, 0], R[0, 0]))
    return float(np.arctan2(-R[1, 2], R[1, 1])), pitch, 0.0


class BulletGripper:
    """A gripper body in one PyBullet client, carried by a fixed-base virtual arm."""

    def __init__(self, client: int, spec: GripperSpec, scale: float = 1.0, visual_from_collision: bool = False) -> None:
        """``visual_from_collision`` renders the collision geometry (what the encoding sees)."""
        self.client, self.spec, self.scale = client, spec, float(scale)
        text = mounted_urdf(spec, self.scale, visual_from_collision)
        with tempfile.TemporaryDirectory(prefix="adagrasp-gripper-") as folder:
            urdf = Path(folder) / "gripper.urdf"
            urdf.write_text(text)
            try:
                self.body_id = p.loadURDF(str(urdf), [0, 0, 0], useFixedBase=True,
                                          flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client)
            except p.error:  # PyBullet raises rather than returning a negative id
                self.body_id = -1
        if self.body_id < 0:
            raise GripperSpecError(
                f"{spec.spec_path}: PyBullet could not load {spec.urdf.name} mounted at scale {scale}"
            )
        self._joint: dict[str, int] = {}
        self._link: dict[str, int] = {}
        for i in range(p.getNumJoints(self.body_id, physicsClientId=client)):
            info = p.getJointInfo(self.body_id, i, physicsClientId=client)
            self._joint[info[1].decode()] = i
            self._link[info[12].decode()] = i
        missing = [j for j in spec.joint_names if j not in self._joint]
        if missing:
            raise GripperSpecError(f"{spec.spec_path}: joints {missing} missing from the loaded body")
        self._arm = [self._joint[n] for n in ARM_JOINTS]
        self._tcp_link = self._link[f"{ARM_JOINTS[-1]}_link"]
        # no velocity damping (PyBullet's default 0.04 applies to the whole multibody, arm included)
        for link in range(-1, p.getNumJoints(self.body_id, physicsClientId=client)):
            p.changeDynamics(self.body_id, link, lateralFriction=spec.friction, spinningFriction=0.002,
                             rollingFriction=0.0, linearDamping=0.0, angularDamping=0.0, physicsClientId=client)
        self._drive = {d.name: d for d in spec.drive_joints}
        self._targets: dict[str, float] = {}
        self._gears: list[int] = []
        for c in spec.couplings:
            if c.mode == "mimic" and abs(c.multiplier) > 1e-9:
                j = self._joint[c.joint]
                p.setJointMotorControl2(self.body_id, j, p.VELOCITY_CONTROL, targetVelocity=0.0, force=0.0,
                                        physicsClientId=client)
                gear = p.createConstraint(self.body_id, self._joint[c.driver], self.body_id, j, p.JOINT_GEAR,
                                          [0, 0, 1], [0, 0, 0], [0, 0, 0], physicsClientId=client)
                offset, ratio = c.value(0.0, self.scale), c.ratio(self.scale)
                # PyBullet's gear holds q_driver + ratio * q_joint = target
                p.changeConstraint(gear, gearRatio=-1.0 / ratio, relativePositionTarget=-offset / ratio,
                                   maxForce=GEAR_FORCE_FACTOR * spec.coupling_force, erp=GEAR_ERP, physicsClientId=client)
                self._gears.append(gear)
        self._geared = {c.joint for c in spec.couplings if c.mode == "mimic" and abs(c.multiplier) > 1e-9}
        self._model: GripperModel | None = None
        self._reach: dict[float, float] = {}
        self.reset(Transform.from_yaw(0.0, (0.0, 0.0, 2.0)), 1.0)

    # ---------------------------------------------------------------- pose
    def _arm_targets(self, T_world_tcp: Transform, nearest: bool = True) -> list[float]:
        """Arm joint values (x, y, z in m, yaw in rad) that put the TCP at ``T_world_tcp``; the yaw
        is the branch nearest the arm's current yaw (``nearest``) or in (-pi, pi]. Raises if the
        TCP target tilts more than :data:`_TILT_TOL` allows (about 1.4 mrad; a smaller tilt is
        dropped: the arm only yaws)."""
        R = T_world_tcp.rotation
        if abs(R[2, 2] - 1.0) > _TILT_TOL:
            raise ValueError(f"TCP target tilts {np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))):.3g} deg; "
                             "the virtual arm only yaws about world z")
        yaw = float(np.arctan2(R[1, 0], R[0, 0]))
        if nearest:
            now = p.getJointState(self.body_id, self._arm[3], physicsClientId=self.client)[0]
            yaw += 2.0 * np.pi * round((now - yaw) / (2.0 * np.pi))
        x, y, z = (float(v) for v in T_world_tcp.translation)
        return [x, y, z, yaw]

    def reset(self, T_world_tcp: Transform, opening: float) -> None:
        """Teleport the arm so the TCP is at ``T_world_tcp``; joints set to ``opening`` and held there."""
        for j, q in zip(self._arm, self._arm_targets(T_world_tcp, nearest=False)):
            p.resetJointState(self.body_id, j, q, 0.0, physicsClientId=self.client)
        for name, q in joint_positions(self.spec, opening, self.scale).items():
            p.resetJointState(self.body_id, self._joint[name], q, 0.0, physicsClientId=self.client)
        self.move_tcp(T_world_tcp)
        self.set_opening_target(opening)

    def move_tcp(self, T_world_tcp: Transform, max_force: float | None = None) -> None:
        """New targets of the arm's joint motors (the TCP goes to ``T_world_tcp``) with at most
        ``max_force`` (N on x, y, z; N m on yaw; default the spec's ``base_force``); the caller steps the sim."""
        force = self.spec.base_force if max_force is None else float(max_force)
        for j, q in zip(self._arm, self._arm_targets(T_world_tcp)):
            p.setJointMotorControl2(self.body_id, j, p.POSITION_CONTROL, targetPosition=q, targetVelocity=0.0,
                                    force=force, physicsClientId=self.client)

    def tcp_pose(self) -> Transform:
        """Current ``T_world_tcp``."""
        st = p.getLinkState(self.body_id, self._tcp_link, computeForwardKinematics=True, physicsClientId=self.client)
        return Transform.from_quat(st[5], st[4])

    # ---------------------------------------------------------------- joints
    def set_opening_target(self, opening: float) -> None:
        """Motor targets of the drive joints for ``opening`` in [0, 1]; coupled joints follow in :meth:`step`."""
        q = joint_positions(self.spec, float(np.clip(opening, 0.0, 1.0)), self.scale)
        for name, d in self._drive.items():
            self._targets[name] = q[name]
            vel = self.spec.max_velocity * (self.scale if d.prismatic else 1.0)
            p.setJointMotorControl2(self.body_id, self._joint[name], p.POSITION_CONTROL, targetPosition=q[name],
                                    force=self.spec.force, maxVelocity=vel, physicsClientId=self.client)
        self.step()

    def close(self) -> None:
        """Drive to the closed state (opening 0) with the spec's force."""
        self.set_opening_target(0.0)

    def joint_state(self) -> dict[str, float]:
        """Measured position (m or rad) of every movable joint."""
        return {n: p.getJointState(self.body_id, self._joint[n], physicsClientId=self.client)[0]
                for n in self.spec.joint_names}

    def step(self) -> None:
        """Per-step coupling targets; call once before every ``stepSimulation``."""
        measured: dict[str, float] = {}
        targets = dict(self._targets)
        for c in self.spec.couplings:
            if c.joint in self._geared:
                continue
            src = c.driver
            if c.mode == "measured":
                if src not in measured:
                    measured[src] = p.getJointState(self.body_id, self._joint[src], physicsClientId=self.client)[0]
                base = measured[src]
            else:
                base = targets.get(src)
                if base is None:
                    base = p.getJointState(self.body_id, self._joint[src], physicsClientId=self.client)[0]
            q = c.value(base, self.scale)
            targets[c.joint] = q
            measured.setdefault(c.joint, q)
            p.setJointMotorControl2(self.body_id, self._joint[c.joint], p.POSITION_CONTROL, targetPosition=q,
                                    force=self.spec.coupling_force, physicsClientId=self.client)

    # ---------------------------------------------------------------- sensing
    def in_contact(self, exclude: tuple[int, ...] = ()) -> bool:
        """True if any link of the gripper touches another body not in ``exclude``."""
        for c in p.getContactPoints(bodyA=self.body_id, physicsClientId=self.client):
            if c[2] != self.body_id and c[2] not in exclude:
                return True
        return False

    def contact_bodies(self) -> set[int]:
        """Ids of the bodies the gripper touches now."""
        return {c[2] for c in p.getContactPoints(bodyA=self.body_id, physicsClientId=self.client) if c[2] != self.body_id}

    def coupling_error(self) -> float:
        """Largest |q_joint - Coupling.value(q_driver, scale)| (m or rad) over the ``mimic`` and
        ``measured`` couplings now (0 without them): how far the linkage is from its kinematics."""
        q = self.joint_state()
        err = 0.0
        for c in self.spec.couplings:
            if c.mode in ("mimic", "measured"):
                want = c.value(q[c.driver], self.scale)
                err = max(err, abs(q[c.joint] - want))
        return err

    def finger_aperture(self) -> float:
        """Metres between the finger pads: the diameter of the widest cylinder about the approach
        axis that no finger surface enters, from the fingertips up to ``aperture_band`` above the TCP
        (see :func:`common.gripper.aperture_from_points`)."""
        T_tcp_world = self.tcp_pose().inverse()
        pts = []
        for link, local in self.model().finger_samples().items():
            if link == self.spec.cut_link:
                continue
            st = p.getLinkState(self.body_id, self._link[link], computeForwardKinematics=True, physicsClientId=self.client)
            T = T_tcp_world * Transform.from_quat(st[5], st[4])
            pts.append(T.apply(local))
        return aperture_from_points(np.concatenate(pts), self.spec.aperture_band * self.scale)

    def model(self) -> GripperModel:
        """The gripper's kinematic model (TCP frame) at this scale, built once."""
        if self._model is None:
            self._model = GripperModel(self.spec, self.scale)
        return self._model

    def reach(self, opening: float) -> float:
        """Metres the fingers reach below the TCP at their lowest while closing from ``opening``
        (:meth:`GripperModel.sweep_depth` of the exact finger geometry), cached per opening."""
        key = round(float(opening), 6)
        if key not in self._reach:
            self._reach[key] = self.model().sweep_depth(max_opening=key)
        return self._reach[key]

    def remove(self) -> None:
        """Remove the gear constraints and the body from the client."""
        for gear in self._gears:
            p.removeConstraint(gear, physicsClientId=self.client)
        p.removeBody(self.body_id, physicsClientId=self.client)


# --------------------------------------------------------------------------------------
# lift test
# --------------------------------------------------------------------------------------


@dataclass
class LiftResult:
    """Outcome of one :func:`lift_test`."""

    success: bool
    """The object ended at least ``lift_min`` above where it started."""
    object_rise: float
    """Metres the object's centre rose."""
    contact_height: float
    """TCP height (m) where the descent stopped."""
    reason: str
    """Empty on success, else why it failed."""
    coupling_error_held: float
    """:meth:`BulletGripper.coupling_error` when closing on the object ended (m or rad)."""


def lift_test(spec: GripperSpec, scale: float = 1.0, shape: str = "box", size: float = 0.04,
              offset: tuple[float, float] = (0.0, 0.0), yaw: float = 0.0, mass: float = 0.1,
              friction: float = 1.0, time_step: float = SimConfig.time_step,
              solver_iterations: int = SimConfig.solver_iterations, lift_height: float = 0.2,
              lift_min: float = 0.1) -> LiftResult:
    """Top-down grasp of one object on a plane in a fresh DIRECT client; True if it is lifted.

    ``shape``: box (a cube of edge ``size``) or cylinder (diameter and height ``size``), placed at
    ``offset`` (m) from the TCP axis with ``yaw`` (rad). The gripper descends (opening 1, closing
    along world x) to the object's half height -- but no lower than the depth the fingers sweep
    while closing down to 0.8 x the object's size (:meth:`GripperModel.sweep_depth`) -- or first
    contact, closes until the joints are still, and lifts by ``lift_height``.
    """
    import pybullet_data

    client = p.connect(p.DIRECT)
    try:
        p.setGravity(0, 0, -9.81, physicsClientId=client)
        p.setPhysicsEngineParameter(fixedTimeStep=time_step, numSolverIterations=solver_iterations,
                                    physicsClientId=client)
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=client)
        plane = p.loadURDF("plane.urdf", physicsClientId=client)
        p.changeDynamics(plane, -1, lateralFriction=friction, physicsClientId=client)
        if shape == "box":
            col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[size / 2] * 3, physicsClientId=client)
        elif shape == "cylinder":
            col = p.createCollisionShape(p.GEOM_CYLINDER, radius=size / 2, height=size, physicsClientId=client)
        else:
            raise ValueError(f"shape must be box or cylinder, got {shape!r}")
        quat = p.getQuaternionFromEuler([0, 0, yaw])
        obj = p.createMultiBody(mass, col, basePosition=[offset[0], offset[1], size / 2], baseOrientation=quat,
                                physicsClientId=client)
        p.changeDynamics(obj, -1, lateralFriction=friction, rollingFriction=0.0, spinningFriction=0.001,
                         physicsClientId=client)
        for _ in range(20):
            p.stepSimulation(physicsClientId=client)
        z0 = p.getBasePositionAndOrientation(obj, physicsClientId=client)[0][2]

        g = BulletGripper(client, spec, scale)
        start = size + 0.12 * scale
        target = max(size / 2, GripperModel(spec, scale).sweep_depth(min_aperture=0.8 * size) + 0.002)
        g.reset(Transform.from_yaw(0.0, (0.0, 0.0, start)), 1.0)
        for _ in range(10):
            g.step()
            p.stepSimulation(physicsClientId=client)
        speed = 0.3 * time_step
        z = start
        for _ in range(int((start - target) / speed) + int(0.3 / time_step)):
            z = max(target, z - speed)
            g.move_tcp(Transform.from_yaw(0.0, (0.0, 0.0, z)))
            g.step()
            p.stepSimulation(physicsClientId=client)
            if g.in_contact() or g.tcp_pose().translation[2] < target + 1e-3:
                break
        contact_z = g.tcp_pose().translation[2]
        g.move_tcp(g.tcp_pose())
        g.close()
        joints = [g._joint[n] for n in spec.joint_names]
        still = 0
        for k in range(int(CLOSE_MAX_S / time_step)):
            g.step()
            p.stepSimulation(physicsClientId=client)
            vel = [s[1] for s in p.getJointStates(g.body_id, joints, physicsClientId=client)]
            still = still + 1 if max(abs(v) for v in vel) < 0.01 else 0
            if k * time_step > 0.3 and still * time_step >= 0.1:
                break
        held_error = g.coupling_error()
        T = g.tcp_pose()
        steps = int(1.0 / time_step)
        for k in range(1, steps + 1):
            g.move_tcp(Transform(T.rotation, T.translation + [0, 0, lift_height * k / steps]))
            g.step()
            p.stepSimulation(physicsClientId=client)
        for _ in range(int(0.3 / time_step)):
            g.step()
            p.stepSimulation(physicsClientId=client)
        rise = p.getBasePositionAndOrientation(obj, physicsClientId=client)[0][2] - z0
        ok = rise >= lift_min
        reason = "" if ok else f"{shape} rose only {rise:.3f} m (needs {lift_min} m)"
        return LiftResult(ok, float(rise), float(contact_z), reason, float(held_error))
    finally:
        p.disconnect(physicsClientId=client)
