"""The top-down grasp primitive, its label, and multi-step episodes.

Action contract: ``(i, j, k, s)`` = scene cell i along world x and j along world y (centre from
``common.geometry.cell_to_world``), rotation k of R = ``model.rotations`` with yaw
theta = 2 pi k / R about +z (the gripper's closing direction, TCP x, turned from world x by
theta), and index s into the episode's ``openings`` tuple.

Primitive (DESIGN.md section 3): the TCP goes above (x, y) at yaw theta with the chosen opening,
descends at ``sim.tcp_speed`` until the gripper first touches anything or the TCP reaches the
grasp height (top surface at (i, j) from the heightmap minus ``sim.grasp_depth``, clipped to the
table: the fingers' lowest point, open or closing, stays ``sim.table_clearance`` above it, so
fingertips are not dragged along the table while they close), closes fully until the fingers
have got moving and stopped again (or ``sim.close_max_s``), lifts to
``sim.lift_to`` and holds still for ``sim.hold_s``. The label is True when exactly one target's
base ends above ``sim.lift_height`` and no obstacle's does. Lifted objects are then removed, as
are objects that left the scene grid.

Cost is kept low without bending the physics: the descent starts just above the highest object
(not from a fixed home height), the TCP moves ``tcp_speed * time_step`` per physics step through
the force-limited motors of the gripper's virtual arm, closing ends as soon as the aperture stops
changing, and the lift ends early (a failure) when the gripper has left every object behind.

Call loop::

    for result in run_episode(sim, gripper, policy, openings, "multi", "train"):
        print(result.action, result.outcome.success)
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import pybullet

from actors.bullet_gripper import BulletGripper
from actors.simulation import Simulation
from common.geometry import Transform
from common.observation import Observation
from common.policy import grasp_pose as cell_grasp_pose

_CLOSE_STILL_STEPS = 6
"""Closing ends once no finger joint moved more than its threshold over this many steps."""
_CLOSE_STILL_M = 1e-4
"""Prismatic joint travel (m, at gripper scale 1) below which a finger counts as stopped."""
_CLOSE_STILL_RAD = 2e-3
"""Revolute joint travel (rad) below which a finger counts as stopped."""
_CLOSE_STARTED = 10.0
"""The stop test applies once some finger travelled this many times its threshold from where
closing began (or after ``_CLOSE_MIN_S``): fingers still speeding up from rest are not stopped."""
_CLOSE_MIN_S = 0.2
"""Simulated seconds after which the stop test applies even if no finger got moving (blocked)."""
_ARRIVE_TOL = 0.001
"""The TCP has arrived at the grasp height when it is this close (m)."""
_ARRIVE_MAX_S = 0.25
"""Simulated seconds the descent may take beyond its nominal duration to arrive."""
_LIFT_EMPTY_RISE = 0.05
"""After the TCP's target rose this far (m; the TCP trails it) with the gripper touching no
object, the lift ends as a failure."""
FAILURE_MODES = ("missed", "slipped", "dropped", "extra_lift")
"""What went wrong in a failed grasp (:attr:`GraspOutcome.failure`), in the order of the primitive:
``missed``: the closed fingers touched no object (none between them, or it was pushed out while
closing); ``slipped``: they held an object but the lift left every object behind; ``dropped``:
the gripper still touched an object at the end of the lift, but no target ended above the lift
height; ``extra_lift``: an obstacle, or more than one target, ended above it."""


@dataclass(frozen=True)
class GraspOutcome:
    """What one grasp did."""

    success: bool
    """Exactly one target ended above ``sim.lift_height`` and no obstacle did."""
    lifted_targets: tuple[str, ...]
    """Names of the targets that ended above the lift height."""
    lifted_obstacles: tuple[str, ...]
    """Names of the obstacles that ended above the lift height."""
    grasp_position: tuple[float, float, float]
    """Commanded grasp TCP position (x, y, z), world frame, metres (z after the table clip)."""
    yaw: float
    """Grasp yaw theta about +z, radians."""
    opening: float
    """Initial opening in [0, 1]."""
    stop_z: float
    """TCP height (m) where the descent ended."""
    stopped_at_contact: bool
    """The descent ended on contact before the grasp height."""
    steps: int
    """Physics steps taken by the primitive."""
    held_after_close: bool
    """The gripper touched an object when closing ended."""
    lost_on_lift: bool
    """The lift ended early: the TCP's target rose ``_LIFT_EMPTY_RISE`` with the gripper
    touching no object."""

    @property
    def failure(self) -> str | None:
        """None for a success, else one of :data:`FAILURE_MODES`."""
        if self.success:
            return None
        if self.lifted_obstacles or len(self.lifted_targets) > 1:
            return "extra_lift"
        if not self.held_after_close:
            return "missed"
        return "slipped" if self.lost_on_lift else "dropped"


@dataclass(frozen=True)
class TrialResult:
    """One attempt of an episode, as produced by :func:`run_episode`."""

    step: int
    """Attempt index within the episode, from 0."""
    observation: Observation
    """The observation the action was chosen from."""
    action: tuple[int, int, int, int]
    """(i, j, k, s), see the module docstring."""
    score: float
    """The policy's score of the action."""
    outcome: GraspOutcome
    """What the grasp did."""
    object_ids: tuple[str, ...]
    """Names of the objects in the scene when the action was chosen."""
    trial_s: float
    """Wall time (s) of the attempt: observation, policy, grasp and label (the scene reset of the
    episode is added to its first attempt)."""


def grasp_pose(
    sim: Simulation, action, openings, heightmap: np.ndarray, reach: float | None = None
) -> tuple[np.ndarray, float, float]:
    """Grasp TCP position (3,) float64 world metres, yaw (rad) and opening of ``action`` after
    checking it (:func:`common.policy.grasp_pose`, which the planner and the policy report too:
    the centre clipped to the fence square, z raised for ``reach`` when given).

    ``heightmap``: (X, Y) float32 metres above the table (the observation's).
    """
    grid = sim.grid
    i, j, k, s = (int(a) for a in action)
    shape = grid.shape[:2]
    assert heightmap.shape == shape and heightmap.dtype == np.float32, (heightmap.shape, heightmap.dtype)
    if not (0 <= i < shape[0] and 0 <= j < shape[1]):
        raise ValueError(f"action: cell ({i}, {j}) outside the scene grid {shape}")
    if not 0 <= k < sim.cfg.model.rotations:
        raise ValueError(f"action: rotation {k} outside [0, {sim.cfg.model.rotations})")
    if not 0 <= s < len(openings):
        raise ValueError(f"action: opening index {s} outside the {len(openings)} openings")
    position, yaw = cell_grasp_pose(sim.cfg, heightmap, i, j, k, reach)
    return position, yaw, float(openings[s])


def gripper_reach(sim: Simulation, gripper: BulletGripper, opening: float) -> float:
    """How far (m) the fingers reach below the TCP at their lowest while they close from
    ``opening``: swept over the openings from ``opening`` to closed on the exact finger geometry
    (PyBullet's bounds of a turned link are those of its turned local box, centimetres too low for
    linkage fingers, which would hold the fingers above short objects)."""
    return gripper.reach(opening)


def _still_thresholds(gripper: BulletGripper) -> tuple[list[str], np.ndarray]:
    """Movable joint names and, per joint, the travel below which it counts as stopped."""
    spec = gripper.spec
    prismatic = {d.name: d.prismatic for d in spec.drive_joints} | {c.joint: c.prismatic for c in spec.couplings}
    names = list(spec.joint_names)
    still = np.array([_CLOSE_STILL_M * gripper.scale if prismatic[n] else _CLOSE_STILL_RAD for n in names])
    return names, still


def _advance(sim: Simulation, gripper: BulletGripper) -> None:
    gripper.step()
    pybullet.stepSimulation(physicsClientId=sim.client)


def label_scene(sim: Simulation) -> tuple[bool, tuple[int, ...], tuple[int, ...]]:
    """(success, lifted target bodies, lifted obstacle bodies) from the current object heights."""
    h = sim.cfg.sim.lift_height
    lifted_t = tuple(b for b in sim.targets if sim.body_position(b)[2] > h)
    lifted_o = tuple(b for b in sim.obstacles if sim.body_position(b)[2] > h)
    return (len(lifted_t) == 1 and not lifted_o), lifted_t, lifted_o


def remove_finished(sim: Simulation, lifted) -> None:
    """Remove the lifted bodies, every object whose centre left the scene grid (x, y) and, with
    ``sim.target_bound`` "fence", every target whose centre left the fence square (x, y) that
    grasp centres are clipped to."""
    grid = sim.grid
    gone = set(lifted)
    lim = sim.cfg.sim.fence_half_extent if sim.cfg.sim.target_bound == "fence" else None
    targets = set(sim.targets)
    for b in list(sim.objects):
        x, y, _ = sim.body_position(b)
        if not (grid.x_range[0] <= x <= grid.x_range[1] and grid.y_range[0] <= y <= grid.y_range[1]):
            gone.add(b)
        elif lim is not None and b in targets and max(abs(x - sim.centre[0]), abs(y - sim.centre[1])) > lim:
            gone.add(b)
    sim.remove_objects(sorted(gone))


def execute_grasp(sim: Simulation, gripper: BulletGripper, action, openings, heightmap: np.ndarray) -> GraspOutcome:
    """Run the grasp primitive for ``action`` (see the module docstring), label it, remove what
    was lifted and park the gripper. ``openings``: the episode's candidate openings in [0, 1]."""
    cfg = sim.cfg.sim
    dt = cfg.time_step
    _, _, opening = grasp_pose(sim, action, openings, heightmap)
    reach = gripper_reach(sim, gripper, opening)
    position, yaw, _ = grasp_pose(sim, action, openings, heightmap, reach)
    objects = set(sim.objects)
    steps = 0

    start_z = max(sim.scene_top(), position[2] - reach) + reach + cfg.approach_clearance
    rot = Transform.from_yaw(yaw).rotation
    gripper.reset(Transform(rot, np.array([position[0], position[1], start_z])), opening)

    # descend until first contact or the grasp height; the arm's motors trail a moving
    # target (by about 2 cm at 0.5 m/s), so the descent ends when the TCP itself arrives
    dz = cfg.tcp_speed * dt
    z = start_z
    stopped_at_contact = False
    for _ in range(int(math.ceil((start_z - position[2]) / dz + _ARRIVE_MAX_S / dt))):
        z = max(position[2], z - dz)
        gripper.move_tcp(Transform(rot, np.array([position[0], position[1], z])), cfg.tcp_max_force)
        _advance(sim, gripper)
        steps += 1
        if gripper.in_contact():
            stopped_at_contact = True
            break
        if z == position[2] and gripper.tcp_pose().translation[2] - position[2] < _ARRIVE_TOL:
            break
    hold = Transform(rot, gripper.tcp_pose().translation)
    stop_z = float(hold.translation[2])
    gripper.move_tcp(hold, cfg.tcp_max_force)

    # close until the fingers stop
    gripper.close()
    joints, still = _still_thresholds(gripper)
    q0 = gripper.joint_state()
    history: list[np.ndarray] = [np.array([q0[n] for n in joints])]
    started = False
    for k in range(1, int(math.ceil(cfg.close_max_s / dt)) + 1):
        _advance(sim, gripper)
        steps += 1
        q = gripper.joint_state()
        history.append(np.array([q[n] for n in joints]))
        started = started or bool(np.any(np.abs(history[-1] - history[0]) > _CLOSE_STARTED * still))
        if (started or k * dt >= _CLOSE_MIN_S) and len(history) > _CLOSE_STILL_STEPS and np.all(
            np.abs(history[-1] - history[-1 - _CLOSE_STILL_STEPS]) < still
        ):
            break
    held = bool(gripper.contact_bodies() & objects)

    # lift; end early once the gripper has left every object behind
    z = stop_z
    empty = False
    while z < cfg.lift_to:
        z = min(cfg.lift_to, z + dz)
        gripper.move_tcp(Transform(rot, np.array([hold.translation[0], hold.translation[1], z])), cfg.tcp_max_force)
        _advance(sim, gripper)
        steps += 1
        if z - stop_z > _LIFT_EMPTY_RISE and not (gripper.contact_bodies() & objects):
            empty = True
            break
    if not empty:
        for _ in range(int(round(cfg.hold_s / dt))):
            _advance(sim, gripper)
            steps += 1

    success, lifted_t, lifted_o = label_scene(sim)
    object_names = {b: o.name for b, o in sim.objects.items()}
    remove_finished(sim, lifted_t + lifted_o)
    sim.park_gripper()
    return GraspOutcome(
        success=success,
        lifted_targets=tuple(object_names[b] for b in lifted_t),
        lifted_obstacles=tuple(object_names[b] for b in lifted_o),
        grasp_position=(float(position[0]), float(position[1]), float(position[2])),
        yaw=float(yaw),
        opening=opening,
        stop_z=stop_z,
        stopped_at_contact=stopped_at_contact,
        steps=steps,
        held_after_close=held,
        lost_on_lift=empty,
    )


def max_attempts(sim: Simulation, kind: str) -> int:
    """Grasp attempts of one episode of scene ``kind``."""
    cfg = sim.cfg.sim
    return {"single": 1, "multi": cfg.multi_max_attempts, "obstacle": cfg.obstacle_max_attempts}[kind]


def run_episode(
    sim: Simulation,
    gripper: BulletGripper,
    policy,
    openings: tuple[float, ...],
    kind: str,
    object_set_name: str | None = None,
    seed: int | None = None,
    rng: np.random.Generator | None = None,
) -> Iterator[TrialResult]:
    """Reset a ``kind`` scene and yield one :class:`TrialResult` per attempt.

    The episode ends when no target is left or after :func:`max_attempts` attempts. ``policy``
    implements ``act(obs, openings, rng) -> ((i, j, k, s), score)`` (actors.policies.Policy);
    ``rng`` (default: the simulation's) drives the policy; ``seed`` re-seeds the scene.
    """
    t0 = time.perf_counter()
    sim.reset_scene(kind, object_set_name, seed=seed)
    rng = sim.rng if rng is None else rng
    for step in range(max_attempts(sim, kind)):
        if step > 0:
            t0 = time.perf_counter()
            sim.settle()
        obs = sim.observe()
        ids = sim.object_ids()
        action, score = policy.act(obs, openings, rng)
        outcome = execute_grasp(sim, gripper, action, openings, obs.heightmap)
        yield TrialResult(step, obs, tuple(int(a) for a in action), float(score), outcome, ids, time.perf_counter() - t0)
        if not sim.targets:
            return
