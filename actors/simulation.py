"""The PyBullet world of one actor: table, drop fence, objects, cameras and the gripper.

A :class:`Simulation` owns exactly one PyBullet client (DIRECT, or GUI for debugging) and one
seeded ``numpy.random.Generator``; nothing is global, so many simulations live side by side in
one process. World frame: z up, table top at z = 0, metres.

Scenes (as in the paper): ``single`` (1 target), ``multi`` (``sim.multi_objects`` targets) and
``obstacle`` (``sim.obstacle_targets`` targets + ``sim.obstacle_obstacles`` obstacles, shuffled
before the roles are assigned). Objects are dropped one after another, each with a random
orientation and its centre uniform in a square of half-size ``sim.drop_half_extent``, its
lowest point ``sim.drop_gap`` above the highest object already down, inside a square fence of
half-size ``sim.fence_half_extent``. Each drop ends when every object is at rest (no point of
any object moved faster than ``sim.settle_velocity`` on average over two windows of a few steps,
see :meth:`Simulation.settle`) or after ``sim.settle_max_s``; an object that rests too tall for
the grid or outside the fence is redrawn.
Then the fence is lowered under the table (like the paper's fence, which is removed once the
objects are down) and the scene settles once more; if an object then rolled or slid out of the
fence square (where grasps can reach) the whole scene is dropped again, at most
``sim.drop_retries`` times. The fence is generated in code (four static boxes) and moved rather
than re-created.

Rendering: PyBullet's TinyRenderer (CPU, works in DIRECT), one depth and segmentation image per
camera at exactly the pixels ``common.camera.scene_cameras`` asks for. TinyRenderer samples pixel
(column c, row r) at OpenGL window coordinates (c, H - 1 - r), half a pixel off the OpenGL
convention, so :func:`tinyrenderer_projection` builds the projection for that sampling; the
rendered image then matches the pinhole model of the intrinsics exactly (tested).

Call loop::

    with Simulation(cfg, seed=7) as sim:
        sim.reset_scene("multi", "train")           # drop, settle, lower the fence
        gripper = sim.load_gripper(get_gripper("parallel_jaw-0"), scale=1.0)
        while sim.targets:
            obs = sim.observe()                       # common.observation.Observation
            outcome = actors.grasp.execute_grasp(sim, gripper, action, openings, obs.heightmap)
            sim.settle()
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet

from actors.bullet_gripper import BulletGripper
from actors.objects import ObjectModel, load_object, object_set
from common.camera import Intrinsics, depth_from_opengl_zbuffer, opengl_view_matrix, scene_cameras
from common.config import Config, ConfigError
from common.geometry import Transform, grid_centre
from common.gripper import GripperSpec
from common.observation import Observation
from common.tsdf import ObservationFuser

SCENE_KINDS = ("single", "multi", "obstacle")
"""Scene kinds of the paper."""

NEAR = 0.05
"""Near clipping plane of every scene camera, metres."""
FAR = 3.0
"""Far clipping plane of every scene camera, metres."""

_SETTLE_CHECK_STEPS = 8
"""Physics steps between two rest checks while settling."""
_SETTLE_CALM_CHECKS = 2
"""Consecutive rest checks that must pass (one alone can catch an object at the top of a bounce)."""
_FENCE_THICKNESS = 0.02
"""Wall thickness of the drop fence, metres."""
_MIN_OBJECT_EXTENT = 0.007
"""Metres: an object whose bounds are smaller in every direction is a broken mesh (PyBullet turns
NaN or empty meshes into a box of twice its collision margin, 6 mm)."""
_TOP_RAYS = 16
"""Rays per side of the grid :meth:`Simulation.body_top` casts."""
_PARK_ABOVE_CAMERA = 1.0
"""The parked gripper hangs this far (m) above the cameras, behind all of them."""


class SimulationError(RuntimeError):
    """A scene cannot be built from the given input; the message is one line naming the file or field."""


@dataclass(frozen=True)
class SceneObject:
    """One object in the scene."""

    body: int
    """PyBullet body id in this simulation's client."""
    name: str
    """Source-qualified object name (``ObjectModel.name``, e.g. ``random_urdfs/017``)."""
    role: str
    """``target`` or ``obstacle``."""


def tinyrenderer_projection(intrinsics: Intrinsics, near: float, far: float) -> np.ndarray:
    """(4, 4) float64 row-major projection that makes PyBullet's TinyRenderer render ``intrinsics``.

    Pixel (u, v) (OpenCV, centres at integers) then samples the ray through u = fx x/z + cx,
    v = fy y/z + cy. Pass ``m.T.ravel()`` to ``getCameraImage``.
    """
    if not 0 < near < far:
        raise ValueError(f"tinyrenderer_projection: expected 0 < near < far, got near={near}, far={far}")
    w, h = float(intrinsics.width), float(intrinsics.height)
    return np.array(
        [
            [2 * intrinsics.fx / w, 0.0, 1.0 - 2 * intrinsics.cx / w, 0.0],
            [0.0, 2 * intrinsics.fy / h, 2 * (intrinsics.cy + 1.0) / h - 1.0, 0.0],
            [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )


def check_sim_config(cfg: Config) -> None:
    """Constraints between simulation fields that a single range cannot express (ConfigError)."""
    sim, grid = cfg.sim, cfg.scene_grid
    half_x = (grid.x_range[1] - grid.x_range[0]) / 2
    half_y = (grid.y_range[1] - grid.y_range[0]) / 2
    if cfg.sim.scene not in SCENE_KINDS:
        raise ConfigError(f"sim.scene: expected one of {list(SCENE_KINDS)}, got {sim.scene!r}")
    if not sim.drop_half_extent < sim.fence_half_extent:
        raise ConfigError(
            f"sim.drop_half_extent: {sim.drop_half_extent} m must be below sim.fence_half_extent {sim.fence_half_extent} m"
        )
    if not sim.fence_half_extent + _FENCE_THICKNESS <= min(half_x, half_y):
        raise ConfigError(f"sim.fence_half_extent: {sim.fence_half_extent} m fence does not fit in the scene grid")
    if not sim.lift_to > sim.lift_height:
        raise ConfigError(f"sim.lift_to: {sim.lift_to} m must exceed sim.lift_height {sim.lift_height} m")
    if not sim.lift_height > grid.z_range[1]:
        raise ConfigError(f"sim.lift_height: {sim.lift_height} m must exceed the scene grid top {grid.z_range[1]} m")
    try:
        scene_cameras(grid, sim)  # camera height, ring radius and resolution (each error names its key)
    except ValueError as e:
        raise ConfigError(str(e)) from None


class Simulation:
    """One PyBullet world with its own client and random generator (see the module docstring)."""

    def __init__(self, cfg: Config, seed: int = 0, gui: bool = False) -> None:
        """``cfg``: resolved config (scene grid, sim); ``seed``: seed of the generator; ``gui``: open a window."""
        check_sim_config(cfg)
        self.cfg = cfg
        self.grid = cfg.scene_grid
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.objects: dict[int, SceneObject] = {}
        self.gripper: BulletGripper | None = None
        self._gripper_key: tuple[GripperSpec, float] | None = None
        self._object_sets: dict[str, list[ObjectModel]] = {}
        self.centre = np.append(grid_centre(self.grid), 0.0)
        self.cameras = scene_cameras(self.grid, cfg.sim)
        self._fuser = ObservationFuser(self.grid, self.cameras)
        self._render_args = [
            (
                k.width,
                k.height,
                opengl_view_matrix(T).T.ravel().tolist(),
                tinyrenderer_projection(k, NEAR, FAR).T.ravel().tolist(),
            )
            for k, T in self.cameras
        ]
        self.client = pybullet.connect(pybullet.GUI if gui else pybullet.DIRECT)
        if self.client < 0:
            raise SimulationError("pybullet.connect: could not start a physics client")
        try:
            self._build_world()
        except BaseException:  # the object never reaches its owner, whose close() would disconnect it
            self.close()
            raise

    # ---------------------------------------------------------------- world

    def _build_world(self) -> None:
        c = self.client
        pybullet.resetSimulation(physicsClientId=c)
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=self.cfg.sim.time_step, numSolverIterations=self.cfg.sim.solver_iterations,
            deterministicOverlappingPairs=1, physicsClientId=c,
        )
        pybullet.setGravity(0.0, 0.0, -9.81, physicsClientId=c)
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=c)
        self.table = pybullet.createMultiBody(0.0, plane, physicsClientId=c)
        pybullet.changeDynamics(
            self.table, -1, lateralFriction=self.cfg.sim.table_lateral_friction, physicsClientId=c
        )
        self.fence = self._build_fence()
        self._lower_fence()

    def _build_fence(self) -> int:
        """Four static walls around the drop square, one multibody; returns its body id."""
        c, sim = self.client, self.cfg.sim
        inner, t, h = sim.fence_half_extent, _FENCE_THICKNESS, sim.fence_height
        outer = inner + t
        half_extents = [[outer, t / 2, h / 2], [outer, t / 2, h / 2], [t / 2, outer, h / 2], [t / 2, outer, h / 2]]
        positions = [[0, inner + t / 2, h / 2], [0, -inner - t / 2, h / 2], [inner + t / 2, 0, h / 2], [-inner - t / 2, 0, h / 2]]
        shape = pybullet.createCollisionShapeArray(
            [pybullet.GEOM_BOX] * 4, halfExtents=half_extents, collisionFramePositions=positions, physicsClientId=c
        )
        body = pybullet.createMultiBody(0.0, shape, basePosition=self._fence_down_position(), physicsClientId=c)
        pybullet.changeDynamics(body, -1, lateralFriction=sim.object_lateral_friction, physicsClientId=c)
        return body

    def _fence_down_position(self) -> list[float]:
        return [float(self.centre[0]), float(self.centre[1]), -2.0 * self.cfg.sim.fence_height - 1.0]

    def _raise_fence(self) -> None:
        pybullet.resetBasePositionAndOrientation(
            self.fence, [float(self.centre[0]), float(self.centre[1]), 0.0], [0, 0, 0, 1], physicsClientId=self.client
        )

    def _lower_fence(self) -> None:
        """Move the fence under the table, where nothing touches or sees it."""
        pybullet.resetBasePositionAndOrientation(
            self.fence, self._fence_down_position(), [0, 0, 0, 1], physicsClientId=self.client
        )

    # ---------------------------------------------------------------- lifecycle

    def close(self) -> None:
        """Disconnect the client (idempotent); every body, the gripper included, goes with it."""
        if self.client >= 0 and pybullet.isConnected(physicsClientId=self.client):
            pybullet.disconnect(physicsClientId=self.client)
        self.client = -1
        self.gripper = None
        self._gripper_key = None
        self.objects.clear()

    def __enter__(self) -> "Simulation":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- objects

    @property
    def targets(self) -> list[int]:
        """Body ids of the targets still in the scene."""
        return [b for b, o in self.objects.items() if o.role == "target"]

    @property
    def obstacles(self) -> list[int]:
        """Body ids of the obstacles still in the scene."""
        return [b for b, o in self.objects.items() if o.role == "obstacle"]

    def object_ids(self) -> tuple[str, ...]:
        """Set-qualified names of the objects in the scene, in drop order."""
        return tuple(o.name for o in self.objects.values())

    def models(self, name: str) -> list[ObjectModel]:
        """The object models of set ``name`` (loaded once per simulation)."""
        if name not in self._object_sets:
            models = list(object_set(name))
            if not models:
                raise SimulationError(f"object set {name!r}: the set is empty")
            self._object_sets[name] = models
        return self._object_sets[name]

    def body_aabb(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds ((3,), (3,)) float64 metres over all links of ``body``."""
        c = self.client
        lo, hi = np.array(pybullet.getAABB(body, -1, physicsClientId=c))
        for link in range(pybullet.getNumJoints(body, physicsClientId=c)):
            l_lo, l_hi = np.array(pybullet.getAABB(body, link, physicsClientId=c))
            lo, hi = np.minimum(lo, l_lo), np.maximum(hi, l_hi)
        return lo, hi

    def body_position(self, body: int) -> np.ndarray:
        """World position (3,) float64 metres of the base of ``body``."""
        return np.array(pybullet.getBasePositionAndOrientation(body, physicsClientId=self.client)[0])

    def _random_quaternion(self) -> list[float]:
        q = self.rng.normal(size=4)
        return (q / np.linalg.norm(q)).tolist()

    def _load_object(self, model: ObjectModel) -> int:
        """Load ``model`` at a parking pose; raises ObjectSetError or SimulationError (one line
        naming the URDF) when the file is gone, does not load or has no usable geometry."""
        urdf = model.urdf
        body = load_object(
            self.client, model, position=(0.0, 0.0, 5.0), flags=pybullet.URDF_ENABLE_CACHED_GRAPHICS_SHAPES
        )
        lo, hi = self.body_aabb(body)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.max(hi - lo) < _MIN_OBJECT_EXTENT:
            pybullet.removeBody(body, physicsClientId=self.client)
            raise SimulationError(
                f"{urdf}: object {model.name}: collision geometry is empty or not finite (broken mesh)"
            )
        sim = self.cfg.sim
        for link in range(-1, pybullet.getNumJoints(body, physicsClientId=self.client)):
            pybullet.changeDynamics(
                body,
                link,
                lateralFriction=sim.object_lateral_friction,
                spinningFriction=sim.object_spinning_friction,
                physicsClientId=self.client,
            )
        pybullet.changeDynamics(body, -1, mass=sim.object_mass, physicsClientId=self.client)
        return body

    def add_box(
        self, size, position, yaw: float = 0.0, role: str = "target", name: str = "primitive/box"
    ) -> int:
        """Put a box of edge lengths ``size`` (3,) m with its centre at ``position`` (3,) m (world) and
        ``yaw`` rad into the scene as a ``role`` object, with the objects' mass and friction."""
        if role not in ("target", "obstacle"):
            raise ValueError(f"role: expected target or obstacle, got {role!r}")
        c, sim = self.client, self.cfg.sim
        shape = pybullet.createCollisionShape(
            pybullet.GEOM_BOX, halfExtents=[float(v) / 2 for v in size], physicsClientId=c
        )
        quat = pybullet.getQuaternionFromEuler([0.0, 0.0, float(yaw)])
        body = pybullet.createMultiBody(
            sim.object_mass, shape, basePosition=[float(v) for v in position], baseOrientation=quat, physicsClientId=c
        )
        pybullet.changeDynamics(
            body,
            -1,
            lateralFriction=sim.object_lateral_friction,
            spinningFriction=sim.object_spinning_friction,
            physicsClientId=c,
        )
        self.objects[body] = SceneObject(body, name, role)
        return body

    def scene_top(self) -> float:
        """Highest point (m) of the objects already in the scene, or 0 for an empty table."""
        tops = [self.body_aabb(b)[1][2] for b in self.objects]
        return max(tops, default=0.0)

    def _drop(self, model: ObjectModel) -> int:
        """Drop one object into the fence and let everything come to rest; returns its body id."""
        sim = self.cfg.sim
        body = self._load_object(model)
        xy = self.centre[:2] + self.rng.uniform(-sim.drop_half_extent, sim.drop_half_extent, size=2)
        quat = self._random_quaternion()
        floor = self.scene_top() + sim.drop_gap
        pybullet.resetBasePositionAndOrientation(body, [xy[0], xy[1], 1.0], quat, physicsClientId=self.client)
        lo, _ = self.body_aabb(body)
        pybullet.resetBasePositionAndOrientation(
            body, [xy[0], xy[1], 1.0 + floor - lo[2]], quat, physicsClientId=self.client
        )
        self.settle(list(self.objects) + [body])
        return body

    def body_top(self, body: int) -> float:
        """Highest point (m) of ``body`` seen from above: vertical rays on a grid over its bounds
        (PyBullet's bounds of rotated meshes can be centimetres too loose)."""
        lo, hi = self.body_aabb(body)
        n = _TOP_RAYS
        xs, ys = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n), indexing="ij")
        starts = np.stack([xs.ravel(), ys.ravel(), np.full(n * n, hi[2] + 0.01)], axis=1)
        ends = starts.copy()
        ends[:, 2] = lo[2] - 0.01
        hits = pybullet.rayTestBatch(starts.tolist(), ends.tolist(), physicsClientId=self.client)
        tops = [h[3][2] for h in hits if h[0] == body]
        return float(max(tops)) if tops else float(hi[2])

    def _inside_fence(self, body: int) -> bool:
        """True if the centre of mass of ``body`` lies inside the fence square (x, y)."""
        offset = self.body_position(body)[:2] - self.centre[:2]
        return bool(np.all(np.abs(offset) <= self.cfg.sim.fence_half_extent))

    def _fits(self, body: int) -> bool:
        """True if ``body`` rests below the grid top and with its centre inside the fence."""
        return self.body_top(body) <= self.grid.z_range[1] - self.grid.voxel_size and self._inside_fence(body)

    def clear(self) -> None:
        """Remove every object; park the gripper."""
        for body in list(self.objects):
            pybullet.removeBody(body, physicsClientId=self.client)
        self.objects.clear()
        self.park_gripper()

    def remove_objects(self, bodies) -> None:
        """Remove ``bodies`` (ids of scene objects) from the world and the scene."""
        for body in bodies:
            if body in self.objects:
                pybullet.removeBody(body, physicsClientId=self.client)
                del self.objects[body]

    def _drop_all(self, models: list[ObjectModel], set_name: str, count: int) -> list[tuple[int, str]]:
        """Drop ``count`` objects drawn from ``models``; returns (body, name) in drop order."""
        sim = self.cfg.sim
        dropped: list[tuple[int, str]] = []
        for _ in range(count):
            for _attempt in range(sim.drop_retries + 1):
                model = models[int(self.rng.integers(len(models)))]
                body = self._drop(model)
                if self._fits(body):
                    break
                pybullet.removeBody(body, physicsClientId=self.client)
            else:
                raise SimulationError(
                    f"object set {set_name!r}: no object came to rest inside the grid in "
                    f"{sim.drop_retries + 1} draws (sim.drop_retries; last {model.name})"
                )
            dropped.append((body, model.name))
            self.objects[body] = SceneObject(body, model.name, "target")
        return dropped

    def reset_scene(
        self, kind: str, object_set_name: str | None = None, n: int | None = None, seed: int | None = None
    ) -> None:
        """Clear the table and build a ``kind`` scene from set ``object_set_name`` (default ``sim.objects``).

        ``n`` overrides the number of targets (``single`` 1, ``multi`` ``sim.multi_objects``,
        ``obstacle`` ``sim.obstacle_targets``); ``seed``, when given, re-seeds the generator first
        (recorded in ``self.seed``) so the scene is reproducible on its own.
        """
        sim = self.cfg.sim
        if kind not in SCENE_KINDS:
            raise SimulationError(f"scene kind {kind!r}: expected one of {list(SCENE_KINDS)}")
        if seed is not None:
            self.seed = int(seed)
            self.rng = np.random.default_rng(self.seed)
        name = sim.objects if object_set_name is None else object_set_name
        models = self.models(name)
        n_targets = {"single": 1, "multi": sim.multi_objects, "obstacle": sim.obstacle_targets}[kind]
        n_targets = n_targets if n is None else int(n)
        n_obstacles = sim.obstacle_obstacles if kind == "obstacle" else 0
        if n_targets < 1:
            raise SimulationError(f"scene {kind}: n: expected at least one target, got {n_targets}")
        for _attempt in range(sim.drop_retries + 1):
            self.clear()
            self._raise_fence()
            try:
                dropped = self._drop_all(models, name, n_targets + n_obstacles)
            except BaseException:
                self.clear()
                self._lower_fence()
                raise
            self._lower_fence()
            self.settle()
            if all(self._inside_fence(b) for b, _ in dropped):
                break
        else:
            self.clear()
            raise SimulationError(
                f"object set {name!r}: objects rolled out of the fence square in {sim.drop_retries + 1} "
                f"{kind} scenes in a row (sim.drop_retries)"
            )
        order = self.rng.permutation(len(dropped)) if n_obstacles else np.arange(len(dropped))
        roles = {dropped[k][0]: ("target" if rank < n_targets else "obstacle") for rank, k in enumerate(order)}
        self.objects = {b: SceneObject(b, nm, roles[b]) for b, nm in dropped}

    # ---------------------------------------------------------------- physics

    def step(self, n: int = 1) -> None:
        """Advance the physics by ``n`` steps of ``sim.time_step``."""
        for _ in range(n):
            pybullet.stepSimulation(physicsClientId=self.client)

    def poses(self, bodies) -> np.ndarray:
        """(N, 7) float64: position (m) and quaternion (x, y, z, w) of each body's base."""
        out = np.empty((len(bodies), 7))
        for n, body in enumerate(bodies):
            pos, quat = pybullet.getBasePositionAndOrientation(body, physicsClientId=self.client)
            out[n, :3], out[n, 3:] = pos, quat
        return out

    def max_point_speed(self, before: np.ndarray, after: np.ndarray, radii: np.ndarray, seconds: float) -> float:
        """Largest mean speed (m/s) of any body point between two :meth:`poses` snapshots
        ``seconds`` apart: (displacement + rotation angle x radius) / seconds; ``radii`` (N,) m."""
        if len(radii) == 0:
            return 0.0
        shift = np.linalg.norm(after[:, :3] - before[:, :3], axis=1)
        dot = np.clip(np.abs(np.sum(after[:, 3:] * before[:, 3:], axis=1)), 0.0, 1.0)
        angle = 2.0 * np.arccos(dot)
        return float(np.max(shift + angle * radii) / seconds)

    def settle(self, bodies=None, max_s: float | None = None) -> int:
        """Step until ``bodies`` (default: all objects) are at rest or ``max_s`` (default
        ``sim.settle_max_s``) simulated seconds passed; returns the physics steps taken.

        At rest: over each of the last two windows of a few steps, no point of any body moved
        faster than ``sim.settle_velocity`` on average (displacement + rotation angle x radius,
        radius = half the diagonal of the body's bounds). Mean speeds over a window, unlike
        instantaneous ones, ignore contact jitter of an object that rests on another."""
        bodies = list(self.objects) if bodies is None else list(bodies)
        max_s = self.cfg.sim.settle_max_s if max_s is None else max_s
        max_steps = int(math.ceil(max_s / self.cfg.sim.time_step))
        radii = np.array([0.5 * math.dist(*pybullet.getAABB(b, -1, physicsClientId=self.client)) for b in bodies])
        before = self.poses(bodies)
        steps, calm = 0, 0
        while steps < max_steps and calm < _SETTLE_CALM_CHECKS:
            k = min(_SETTLE_CHECK_STEPS, max_steps - steps)
            self.step(k)
            steps += k
            after = self.poses(bodies)
            speed = self.max_point_speed(before, after, radii, k * self.cfg.sim.time_step)
            calm = calm + 1 if speed < self.cfg.sim.settle_velocity else 0
            before = after
        return steps

    # ---------------------------------------------------------------- gripper

    def load_gripper(self, spec: GripperSpec, scale: float = 1.0) -> BulletGripper:
        """The scene's gripper built from ``spec`` at ``scale`` (reused while both stay the same, every
        field of the spec compared: two specs of one name are two grippers), parked."""
        key = (spec, float(scale))
        if self.gripper is not None and self._gripper_key == key:
            self.park_gripper()
            return self.gripper
        if self.gripper is not None:
            self.gripper.remove()
            self.gripper = None
        self.gripper = BulletGripper(self.client, spec, float(scale))
        self._gripper_key = key
        self.park_gripper()
        return self.gripper

    def park_pose(self) -> Transform:
        """``T_world_tcp`` where the gripper waits: above the cameras, behind every one of them."""
        z = self.cfg.sim.camera_height + _PARK_ABOVE_CAMERA
        return Transform.from_yaw(0.0, (float(self.centre[0]), float(self.centre[1]), z))

    def park_gripper(self) -> None:
        """Teleport the gripper (if any) to :meth:`park_pose`, fully open."""
        if self.gripper is not None:
            self.gripper.reset(self.park_pose(), 1.0)

    # ---------------------------------------------------------------- cameras

    def render(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Depth and segmentation of every camera.

        Returns (depths, segmentations): per camera (H, W) float32 metres along the optical axis
        (inf where nothing was hit) and (H, W) int32 PyBullet body ids (-1 = nothing).
        """
        depths, segs = [], []
        for (k, _), (w, h, view, proj) in zip(self.cameras, self._render_args):
            _, _, _, zbuf, seg = pybullet.getCameraImage(
                w,
                h,
                viewMatrix=view,
                projectionMatrix=proj,
                shadow=0,
                renderer=pybullet.ER_TINY_RENDERER,
                physicsClientId=self.client,
            )
            zbuf = np.asarray(zbuf, dtype=np.float32).reshape(h, w)
            depths.append(depth_from_opengl_zbuffer(zbuf, NEAR, FAR))
            segs.append(np.asarray(seg, dtype=np.int32).reshape(h, w))
        return depths, segs

    def observe(self) -> Observation:
        """Render every camera and fuse them into an Observation on the scene grid.

        The gripper is parked first; the obstacle channel comes from the segmentation of the
        obstacle bodies.
        """
        self.park_gripper()
        depths, segs = self.render()
        obstacles = np.array(self.obstacles, dtype=np.int32)
        masks = [np.isin(s, obstacles) for s in segs]
        return self._fuser.fuse(depths, masks)
