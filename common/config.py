"""Typed run configuration.

Every tunable lives in one of the dataclasses below, each field with a one-line docstring
(the string literal right under it). YAML files in ``configs/`` only *override* these
defaults; ``--set section.key=value`` on the command line overrides the YAML. The resolved
config is written into every run directory and checkpoint (:func:`to_dict`).

Bad input fails with one line naming the file and the key::

    ConfigError: configs/default.yaml: sim.cameras: expected a value in [1, 4], got 7

Call loop::

    cfg = load_config("configs/default.yaml", overrides=["learner.lr=1e-4"])
    save_config(cfg, run_dir / "config.yaml")
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from common.files import atomic_write_text


class ConfigError(ValueError):
    """A config file, key or value is wrong; the message names the file and the key."""


# --------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------


@dataclass
class SceneGridConfig:
    """Scene voxel grid in the world frame (z up, table top at z = 0)."""

    x_range: tuple[float, float] = (-0.192, 0.192)
    """Workspace x bounds in metres, world frame."""
    y_range: tuple[float, float] = (-0.192, 0.192)
    """Workspace y bounds in metres, world frame."""
    z_range: tuple[float, float] = (0.0, 0.128)
    """Workspace z bounds in metres, world frame (0 = table top)."""
    voxel_size: float = 0.004
    """Edge of one scene voxel in metres (paper 0.002, default 0.004)."""
    truncation_voxels: float = 5.0
    """TSDF truncation distance in voxels; the stored TSDF is distance / truncation in [-1, 1]."""

    @property
    def shape(self) -> tuple[int, int, int]:
        """Grid shape (X, Y, Z) in voxels."""
        return tuple(
            int(round((hi - lo) / self.voxel_size))
            for lo, hi in (self.x_range, self.y_range, self.z_range)
        )  # type: ignore[return-value]

    @property
    def origin(self) -> tuple[float, float, float]:
        """World position (m) of the corner of voxel (0, 0, 0); voxel centres sit half a voxel in."""
        return (self.x_range[0], self.y_range[0], self.z_range[0])

    @property
    def truncation(self) -> float:
        """TSDF truncation distance in metres."""
        return self.truncation_voxels * self.voxel_size


@dataclass
class GripperGridConfig:
    """Gripper voxel grid, centred on the grasp centre (TCP) in x, y; fingers point down (-z)."""

    shape: tuple[int, int, int] = (32, 32, 16)
    """Grid shape (X, Y, Z) in voxels (paper 64 x 64 x 32, default 32 x 32 x 16)."""
    voxel_size: float = 0.008
    """Edge of one gripper voxel in metres (paper 0.004, default 0.008)."""
    tcp_height: float = 0.04
    """Height (m) of the TCP above the grid's bottom face; the grid spans shape[2] * voxel_size in z."""
    truncation_voxels: float = 5.0
    """TSDF truncation distance in voxels."""

    @property
    def truncation(self) -> float:
        """TSDF truncation distance in metres."""
        return self.truncation_voxels * self.voxel_size


@dataclass
class SimConfig:
    """PyBullet simulation, scenes and cameras."""

    scene: str = "single"
    """Scene kind: single | multi | obstacle."""
    objects: str = "train"
    """Named object set to draw objects from (declared in assets/objects/sets.yaml; listed by
    actors.objects.list_object_sets(): train, test, procedural, ...)."""
    cameras: int = 1
    """Number of cameras fused into one TSDF (1 = top-down, 2-4 on a ring)."""
    camera_ring_radius: float = 0.45
    """Horizontal distance of ring cameras from the workspace centre, metres."""
    camera_height: float = 0.6
    """Camera height above the table, metres."""
    image_pixels_per_voxel: float = 1.0
    """Rendered pixels per scene voxel across the workspace (render only what the grid needs)."""
    multi_objects: int = 5
    """Objects in a `multi` scene."""
    multi_max_attempts: int = 7
    """Grasp attempts per `multi` episode before it ends."""
    obstacle_targets: int = 3
    """Targets in an `obstacle` scene."""
    obstacle_obstacles: int = 3
    """Obstacles in an `obstacle` scene."""
    lift_height: float = 0.2
    """A grasp succeeds when exactly one target ends above this height (m) and no obstacle did."""
    grasp_depth: float = 0.05
    """The grasp height is the top surface at (i, j) minus this, metres, clipped to the table."""
    time_step: float = 1.0 / 240.0
    """Physics time step in seconds."""
    solver_iterations: int = 300
    """Constraint-solver iterations per physics step (PyBullet's default is 50; gear linkages
    between revolute fingers yield under a grip with fewer)."""
    settle_velocity: float = 0.01
    """Objects are at rest when no point of any object moves faster than this (m/s, mean over a few steps)."""
    settle_max_s: float = 2.0
    """Upper bound on simulated settling time after a drop, seconds."""
    obstacle_max_attempts: int = 5
    """Grasp attempts per `obstacle` episode before it ends (targets + 2, like multi's 5 + 2)."""
    drop_half_extent: float = 0.1
    """Objects are dropped with their centre uniform in this half-size (m) square around the grid centre."""
    fence_half_extent: float = 0.128
    """Inner half-size (m) of the square fence that holds objects while they drop; grasp centres are
    clipped to this square (the paper's workspace bounds)."""
    target_bound: str = "scene_grid"
    """Where a target pushed away leaves the scene: "scene_grid" when its centre leaves the scene
    grid's x, y range (this project's rule, and that of every result written before this key), or
    "fence" when it leaves the fence square grasps are clipped to (the paper's rule: a target in
    between is reached only by clipped grasps). Objects outside the scene grid always leave."""
    fence_height: float = 0.2
    """Height (m) of the drop fence walls."""
    drop_gap: float = 0.01
    """Vertical gap (m) between a dropped object's lowest point and the highest object already down."""
    drop_retries: int = 10
    """Redraws of an object that comes to rest too tall for the grid or outside the fence."""
    object_mass: float = 0.1
    """Mass (kg) given to every object (as the paper does), so grasp forces mean the same for all."""
    object_lateral_friction: float = 0.6
    """Lateral friction coefficient of every object."""
    object_spinning_friction: float = 0.003
    """Spinning friction coefficient of every object."""
    table_lateral_friction: float = 1.0
    """Lateral friction coefficient of the table."""
    action_half_extent: float = 0.16
    """Half-size (m) of the square of cells any policy may act on, around the grid centre (the
    paper's valid bounds; common.policy.action_region and valid_cells)."""
    tcp_speed: float = 0.5
    """Speed (m/s) of the gripper's descend and lift motions."""
    tcp_max_force: float = 200.0
    """Maximum force (N; N m on yaw) of the virtual-arm motors that drive the gripper's TCP."""
    approach_clearance: float = 0.02
    """The gripper starts its descent this far (m) above the highest object."""
    table_clearance: float = 0.002
    """Grasp heights are clipped so the gripper's lowest point, open or closed, stays this far (m)
    above the table."""
    close_max_s: float = 1.0
    """Upper bound on simulated closing time; closing ends earlier when the fingers stop, seconds."""
    lift_to: float = 0.3
    """TCP height (m) the gripper lifts to before the label is read."""
    hold_s: float = 0.2
    """Simulated time the gripper holds still at the top before the label is read, seconds."""


@dataclass
class GripperConfig:
    """Which grippers actors train with and how they are sampled."""

    train_grippers: str = "train"
    """Training grippers: train (the 32-gripper catalogue) | pool (the 511 procedural grippers of
    assets/grippers/catalog.yaml that passed their physics checks) | comma-separated names."""
    scale_range: tuple[float, float] = (0.8, 1.2)
    """Global gripper scale sampled uniformly per training episode."""
    train_openings: int = 5
    """Candidate initial openings per training episode, sampled in opening_range."""
    opening_range: tuple[float, float] = (0.5, 1.0)
    """Range of initial openings sampled for training (0 = closed, 1 = open)."""
    eval_openings: tuple[float, ...] = (0.5, 0.625, 0.75, 0.875, 1.0)
    """Openings evaluated by the policies at test time (the paper's list)."""
    multi_finger_fraction: float = 0.5
    """Fraction of training episodes that use a multi-finger (3+) gripper."""


@dataclass
class ModelConfig:
    """AdaGrasp network."""

    variant: str = "adagrasp"
    """adagrasp (open + closed gripper TSDF) | init-only (open only) | scene-only (no gripper)."""
    rotations: int = 16
    """Number of rotations R about z; theta_k = 2 pi k / R."""
    channels: int = 16
    """Feature channels of both encoders at the 8 mm cell."""
    feature_cell: float = 0.008
    """Physical cell size (m) where scene features and gripper kernel meet."""
    rotate: str = "scene"
    """scene (the paper: re-encode the scene once per rotation) | kernel (speed option: encode the
    scene once and rotate the gripper kernel; scores differ, see common/network.py)."""
    correlation: str = "fft"
    """How the cross-correlation is computed: fft (real FFTs) | grouped (one grouped convolution);
    the same sums, up to float rounding."""
    train_stem: bool = True
    """Train the scene encoder's first conv block; false keeps it at its initialisation (a
    training speed option: its full-resolution backward pass is skipped; see common/network.py)."""
    scene_chunk: int = 0
    """Rotated scenes encoded per batch at inference (bounds memory; results do not depend on
    it); 0 = per device: 1 on the CPU, all rotations on a GPU."""
    decoder_chunk: int = 0
    """Score maps decoded per batch at inference (bounds memory; results do not depend on it);
    0 = per device: 16 on the CPU, 256 on a GPU."""
    min_surface_height: float = 0.0
    """Learned policies only pick cells higher than this (m); 0 = any observed cell of the action
    square (the paper's valid mask)."""
    scene_widths: tuple[int, ...] = (16, 32, 64)
    """Output channels of the scene encoder's 3-D conv stages (stride 2 from the second on)."""
    gripper_widths: tuple[int, ...] = (16, 64)
    """Output channels of the gripper encoder's 3-D conv stages (stride 2 from the second on)."""
    decoder_width: int = 64
    """Decoder channels (its last, finest stage has half); 64 is the reference decoder, fewer is a
    speed option whose speed and accuracy tests/bench/bench_model.py measures."""


@dataclass
class ReplayConfig:
    """Sharded Zarr replay."""

    shards: int = 2
    """Number of replay shards (one writer each)."""
    capacity: int = 12000
    """FIFO capacity in trials across all shards (paper 12,000)."""
    chunk_trials: int = 64
    """Trials per Zarr chunk of the per-trial columns (volumes are chunked one trial per chunk)."""
    max_inflight: int = 8
    """Maximum outstanding insert/sample requests per client (bounds the object store)."""
    tsdf_levels: int = 127
    """Stored TSDF code = round(tsdf * levels) as int8; max error 1/(2 levels) of the truncation."""
    compression_level: int = 3
    """Zstandard level of every stored chunk (new shards only)."""
    actor_task_retries: int = 3
    """Times Ray re-sends a shard request after the shard actor died and restarted (-1 = forever)."""
    shard_num_cpus: float = 0.0
    """CPUs a shard actor reserves in Ray (it mostly waits on disk)."""
    seed_from: str = ""
    """An earlier replay (RUN or RUN/replay) whose newest readable trials, up to capacity, a new run's
    replay starts with (sampled like the run's own; not counted in its trials, epsilon schedule or
    rate limit); "" = an empty start. A resume keeps the recorded value: one that sets a different
    seed_from is refused."""


@dataclass
class LearnerConfig:
    """Learner and exploration schedule."""

    lr: float = 5e-4
    """Adam learning rate."""
    adam_beta1: float = 0.9
    """Adam's first-moment decay (torch's default and the paper's)."""
    adam_beta2: float = 0.999
    """Adam's second-moment decay: torch's default, with which every shipped model was trained; the
    paper's code uses 0.95 (configs/paper.yaml)."""
    batch_size: int = 8
    """Trials per batch (half successes, half failures)."""
    augment_prob: float = 0.7
    """Probability of a random shift + rotation applied to scene and action."""
    epsilon_start: float = 0.8
    """Exploration epsilon at the start."""
    epsilon_end: float = 0.2
    """Exploration epsilon after epsilon_decay_trials."""
    epsilon_decay_trials: int = 2000
    """Collected trials over which epsilon falls linearly (a laptop budget; the paper's 2,000
    epochs of 8 trials are 16,000, configs/paper.yaml)."""
    samples_per_insert: float = 32.0
    """Learner samples (trials) drawn per inserted trial; paper: 32 x 8 samples per 8 trials."""
    min_replay: int = 32
    """Trials the run's actors have collected before training starts (trials seeded from another replay aside)."""
    insert_lead: float = 32.0
    """Trials the actors may insert ahead of the samples-per-insert schedule before they wait for
    the learner (the actor side of the rate limiter); 0 = actors never wait."""
    publish_every: int = 20
    """Learner steps between weight publications."""
    ema_decay: float = 0.0
    """Decay of an exponential moving average of the weights, updated every learner step; the
    decay used at update n is min(ema_decay, (1 + n) / (10 + n)), so 0.999 takes effect from
    update 8,990 on; when above 0 the average is what actors act with and what checkpoints
    carry as the model (the trained weights are kept in latest.pt for resuming); 0 = off."""
    init_weights: str = ""
    """Checkpoint (a path or model:NAME) whose model weights start a new run, i.e. fine-tuning
    (the optimiser, counters and epsilon schedule start fresh; its network and grids must match
    this run's); "" = random initialisation. A resumed run ignores it."""
    checkpoint_minutes: float = 5.0
    """Minutes between checkpoints (one more is written at exit)."""
    keep_snapshots: bool = True
    """Also keep each periodic checkpoint's weights as RUN/checkpoints/step-NNNNNNN.pt (no optimiser
    state), for learning curves of greedy success; latest.pt alone is what --resume reads."""
    device: str = "auto"
    """Torch device for the learner: auto | cpu | cuda."""
    precision: str = "fp32"
    """Learner forward pass and loss: fp32 | bf16 (torch.autocast to bfloat16 on the learner's
    device; weights, gradients and the Adam state stay float32; actors infer in float32)."""


@dataclass
class ActorConfig:
    """Grasp actors."""

    torch_threads: int = 1
    """Torch intra-op threads per actor process."""
    weights_poll_episodes: int = 1
    """Episodes between non-blocking checks for newer weights."""
    policy: str = "adagrasp"
    """Not read: training actors act in fix-gripper mode, epsilon-greedy. Kept so that earlier
    configs and checkpoints, which record it, load."""


@dataclass
class RunConfig:
    """One run: seed, limits, where it lives."""

    seed: int = 0
    """Root seed: the network's initial weights; actor k draws from numpy SeedSequence([seed, k]),
    or SeedSequence([seed, k, trials committed so far]) in a resumed run; a restarted Ray actor
    uses seed + 7919 x its incarnation in place of seed."""
    run_dir: str = "runs"
    """Parent folder of run directories (a run gets runs/<timestamp>)."""
    max_trials: int = 0
    """Stop after this many collected trials (0 = no limit)."""
    max_minutes: float = 0.0
    """Stop after this many minutes (0 = no limit)."""


@dataclass
class Config:
    """The whole resolved configuration of a run."""

    scene_grid: SceneGridConfig = field(default_factory=SceneGridConfig)
    """Scene voxel grid."""
    gripper_grid: GripperGridConfig = field(default_factory=GripperGridConfig)
    """Gripper voxel grid."""
    sim: SimConfig = field(default_factory=SimConfig)
    """Simulation, scenes and cameras."""
    grippers: GripperConfig = field(default_factory=GripperConfig)
    """Gripper sampling."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Network."""
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    """Replay."""
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    """Learner."""
    actor: ActorConfig = field(default_factory=ActorConfig)
    """Actors."""
    run: RunConfig = field(default_factory=RunConfig)
    """Run limits and seed."""


# --------------------------------------------------------------------------------------
# Validation rules: (section.key) -> (predicate, description)
# --------------------------------------------------------------------------------------

_CHOICES: dict[str, tuple[str, ...]] = {
    "sim.scene": ("single", "multi", "obstacle"),
    "model.variant": ("adagrasp", "init-only", "scene-only"),
    "model.rotate": ("scene", "kernel"),
    "model.correlation": ("fft", "grouped"),
    "learner.device": ("auto", "cpu", "cuda"),
    "learner.precision": ("fp32", "bf16"),
    "actor.policy": ("adagrasp", "fix-gripper", "fix-config", "random", "heuristic"),
    "sim.target_bound": ("scene_grid", "fence"),
}

_RANGES: dict[str, tuple[float, float]] = {
    "sim.cameras": (1, 4),
    "scene_grid.voxel_size": (1e-4, 0.1),
    "gripper_grid.voxel_size": (1e-4, 0.1),
    "scene_grid.truncation_voxels": (1.0, 100.0),
    "gripper_grid.truncation_voxels": (1.0, 100.0),
    "model.rotations": (1, 64),
    "model.channels": (1, 512),
    "model.scene_chunk": (0, 1024),
    "model.decoder_chunk": (0, 100000),
    "model.min_surface_height": (0.0, 1.0),
    "model.decoder_width": (2, 4096),
    "replay.shards": (1, 1024),
    "replay.capacity": (1, 10**9),
    "replay.chunk_trials": (1, 10**6),
    "replay.max_inflight": (1, 10**4),
    "replay.tsdf_levels": (1, 127),
    "replay.compression_level": (1, 22),
    "replay.actor_task_retries": (-1, 10**6),
    "replay.shard_num_cpus": (0.0, 1024.0),
    "learner.lr": (1e-9, 1.0),
    "learner.adam_beta1": (0.0, 0.9999),
    "learner.adam_beta2": (0.0, 0.99999),
    "learner.batch_size": (2, 4096),
    "learner.min_replay": (0, 10**9),
    "learner.epsilon_decay_trials": (0, 10**12),
    "learner.checkpoint_minutes": (1e-3, 1e6),
    "learner.augment_prob": (0.0, 1.0),
    "learner.epsilon_start": (0.0, 1.0),
    "learner.epsilon_end": (0.0, 1.0),
    "learner.samples_per_insert": (1e-6, 1e6),
    "learner.insert_lead": (0.0, 1e9),
    "learner.publish_every": (1, 10**9),
    "learner.ema_decay": (0.0, 0.9999),
    "actor.torch_threads": (1, 256),
    "actor.weights_poll_episodes": (1, 10**6),
    "grippers.train_openings": (1, 64),
    "run.seed": (0, 2**63 - 1),
    "grippers.multi_finger_fraction": (0.0, 1.0),
    "sim.lift_height": (0.0, 10.0),
    "sim.multi_objects": (1, 50),
    "sim.multi_max_attempts": (1, 1000),
    "sim.obstacle_max_attempts": (1, 1000),
    "sim.obstacle_targets": (1, 50),
    "sim.obstacle_obstacles": (0, 50),
    "sim.grasp_depth": (0.0, 1.0),
    "sim.time_step": (1e-4, 0.1),
    "sim.solver_iterations": (1, 10000),
    "sim.settle_velocity": (1e-6, 10.0),
    "sim.settle_max_s": (0.0, 60.0),
    "sim.drop_half_extent": (0.0, 1.0),
    "sim.fence_half_extent": (0.01, 1.0),
    "sim.fence_height": (0.01, 2.0),
    "sim.drop_gap": (0.0, 1.0),
    "sim.drop_retries": (0, 1000),
    "sim.object_mass": (1e-4, 100.0),
    "sim.object_lateral_friction": (0.0, 10.0),
    "sim.object_spinning_friction": (0.0, 10.0),
    "sim.table_lateral_friction": (0.0, 10.0),
    "sim.action_half_extent": (0.0, 1.0),
    "sim.tcp_speed": (1e-3, 10.0),
    "sim.tcp_max_force": (1e-3, 1e6),
    "sim.approach_clearance": (0.0, 1.0),
    "sim.table_clearance": (0.0, 0.1),
    "sim.close_max_s": (0.01, 60.0),
    "sim.lift_to": (0.0, 10.0),
    "sim.hold_s": (0.0, 60.0),
    "run.max_trials": (0, 10**12),
    "run.max_minutes": (0.0, 1e9),
}


_YAML12_FLOAT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?")
_YAML12_INT = re.compile(r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+")


class _ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2 integers and no repeated keys: YAML 1.1 reads ``010`` as
    8 (octal) and ``1:30`` as 90 (base 60), and a repeated section or key silently keeps the last."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice (the second would replace the first)", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node):
        text = self.construct_scalar(node)
        if text.startswith(("0o", "0x")):
            return int(text[2:], 8 if text[1] == "o" else 16)
        return int(text, 10)


_ConfigLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:int"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_ConfigLoader.add_implicit_resolver("tag:yaml.org,2002:int", re.compile(rf"^(?:{_YAML12_INT.pattern})$"),
                                    list("-+0123456789"))
_ConfigLoader.add_constructor("tag:yaml.org,2002:int", _ConfigLoader.construct_yaml_int)


def _load_yaml(text: str):
    """A config file's or a ``--set`` value's YAML (see :class:`_ConfigLoader`)."""
    return yaml.load(text, Loader=_ConfigLoader)
"""A YAML 1.2 core-schema number, finite (no .inf / .nan)."""


_NAMED: tuple[str, ...] = ("sim.objects", "grippers.train_grippers")
"""Text keys that must name something (an object set, grippers): not empty. (An empty
``run.run_dir`` is refused where a new run starts: it plays no part in a checkpoint's use.)"""


def _check_value(name: str, value: Any, source: str) -> None:
    if name in _NAMED and value == "":
        raise ConfigError(f"{source}: {name}: empty; it must name something")
    if name in _CHOICES and value not in _CHOICES[name]:
        raise ConfigError(f"{source}: {name}: expected one of {list(_CHOICES[name])}, got {value!r}")
    if name in _RANGES:
        lo, hi = _RANGES[name]
        if not lo <= value <= hi:
            raise ConfigError(f"{source}: {name}: expected a value in [{lo}, {hi}], got {value!r}")


def _coerce(name: str, tp: Any, value: Any, source: str) -> Any:
    """Convert a YAML value to the annotated type, or raise ConfigError naming source and key."""
    origin = typing.get_origin(tp)
    if tp is float:
        if isinstance(value, str) and _YAML12_FLOAT.fullmatch(value):
            # PyYAML reads YAML 1.1, where 1e-4 (no dot) is a string; YAML 1.2 makes it a float.
            value = float(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {name}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{source}: {name}: expected a finite number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: {name}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {name}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if value is None:  # `--set key=` or an empty YAML value: the empty string (the "none" of a path)
            return ""
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {name}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{source}: {name}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(name, args[0], v, source) for v in value)
        if len(value) != len(args):
            raise ConfigError(f"{source}: {name}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(name, a, v, source) for a, v in zip(args, value))
    if origin in (typing.Union, types.UnionType):
        for a in typing.get_args(tp):
            try:
                return _coerce(name, a, value, source)
            except ConfigError:
                continue
        raise ConfigError(f"{source}: {name}: {value!r} does not fit {tp}")
    raise ConfigError(f"{source}: {name}: unsupported field type {tp}")


def _apply(obj: Any, data: dict, source: str, prefix: str = "") -> None:
    """Override dataclass ``obj`` in place from a nested dict."""
    if not isinstance(data, dict):
        section = prefix.rstrip(".") or "<top>"
        empty = " (an empty section: remove it, or give it keys)" if data is None else ""
        raise ConfigError(f"{source}: {section}: expected a mapping, got {data!r}{empty}")
    hints = typing.get_type_hints(type(obj))
    names = {f.name for f in dataclasses.fields(obj)}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if key not in names:
            raise ConfigError(f"{source}: {name}: unknown key (known: {', '.join(sorted(names))})")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            _apply(current, value, source, prefix=f"{name}.")
        else:
            coerced = _coerce(name, hints[key], value, source)
            _check_value(name, coerced, source)
            setattr(obj, key, coerced)


def _cross_checks(cfg: Config, source: str | typing.Callable[[tuple[str, ...]], str]) -> None:
    """Constraints between fields; ``source`` names where the values came from, or gives it for the
    keys a constraint involves."""

    def fail(key: str, problem: str, *others: str) -> typing.NoReturn:
        where = source((key,) + others) if callable(source) else source
        raise ConfigError(f"{where}: {key}: {problem}")

    for axis, (lo, hi) in zip("xyz", (cfg.scene_grid.x_range, cfg.scene_grid.y_range, cfg.scene_grid.z_range)):
        if hi <= lo:
            fail(f"scene_grid.{axis}_range", f"upper bound must exceed lower, got {(lo, hi)}")
        cells = (hi - lo) / cfg.scene_grid.voxel_size
        if abs(cells - round(cells)) > 1e-6:
            fail("scene_grid.voxel_size", f"{cfg.scene_grid.voxel_size} does not divide {axis}_range {(lo, hi)}",
                 f"scene_grid.{axis}_range")
    nx, ny = (round((hi - lo) / cfg.scene_grid.voxel_size) for lo, hi in (cfg.scene_grid.x_range, cfg.scene_grid.y_range))
    if nx != ny:
        fail("scene_grid.y_range", f"{ny} cells, but x_range has {nx}: the grid must be square in x and y (the "
             "network and the augmentation rotate it in place)", "scene_grid.x_range")
    for name, size in (("scene_grid", cfg.scene_grid.voxel_size), ("gripper_grid", cfg.gripper_grid.voxel_size)):
        ratio = cfg.model.feature_cell / size
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            fail(f"{name}.voxel_size", f"{size} must divide model.feature_cell {cfg.model.feature_cell}",
                 "model.feature_cell")
    if any(s <= 0 for s in cfg.gripper_grid.shape):
        fail("gripper_grid.shape", f"every dimension must be positive, got {cfg.gripper_grid.shape}")
    top = cfg.gripper_grid.shape[2] * cfg.gripper_grid.voxel_size
    if not 0 < cfg.gripper_grid.tcp_height < top:
        fail("gripper_grid.tcp_height", f"{cfg.gripper_grid.tcp_height} m must lie inside the grid's height, "
             f"(0, {top:g}) m (gripper_grid.shape[2] x voxel_size)", "gripper_grid.shape", "gripper_grid.voxel_size")
    for name in ("scene_widths", "gripper_widths"):
        widths = getattr(cfg.model, name)
        if not widths or any(w < 1 for w in widths):
            fail(f"model.{name}", f"expected one or more positive channel counts, got {list(widths)}")
    lo, hi = cfg.grippers.scale_range
    if not 0 < lo <= hi:
        fail("grippers.scale_range", f"expected 0 < low <= high, got {(lo, hi)}")
    lo, hi = cfg.grippers.opening_range
    if not 0 <= lo <= hi <= 1:
        fail("grippers.opening_range", f"expected 0 <= low <= high <= 1, got {(lo, hi)}")
    if any(not 0 <= o <= 1 for o in cfg.grippers.eval_openings):
        fail("grippers.eval_openings", "every opening must lie in [0, 1]")
    if cfg.learner.batch_size % 2:
        fail("learner.batch_size", f"must be even (half successes, half failures), got {cfg.learner.batch_size}")
    if cfg.learner.min_replay == 0 and not cfg.replay.seed_from:
        fail("learner.min_replay", "0 needs replay.seed_from (training on an empty replay)", "replay.seed_from")


def config_path(name_or_path: str | Path) -> Path:
    """Resolve ``default`` / ``paper`` / ``tiny`` to the packaged run YAML, else treat it as a path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    packaged = importlib.resources.files("configs") / f"{name_or_path}.yaml"
    return Path(str(packaged))


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then the YAML file (if any), then ``key.sub=value`` overrides; validated.

    Raises ConfigError with one line naming the file (or ``--set``) and the key.
    """
    cfg = Config()
    if path is not None:
        p = config_path(path)
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        try:
            data = _load_yaml(p.read_text()) or {}
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            where = f": line {mark.line + 1}" if mark is not None else ""
            problem = " ".join(str(getattr(e, "problem", None) or e).split())
            raise ConfigError(f"{p}{where}: not valid YAML ({problem})") from None
        _apply(cfg, data, str(p))
    overridden: set[str] = set()
    for item in overrides:
        key, raw = item.split("=", 1) if "=" in item else ("", "")
        if not key.strip():
            raise ConfigError(f"--set {item}: expected section.key=value")
        try:
            value = _load_yaml(raw)
        except yaml.YAMLError:
            value = raw
        set_value(cfg, key.strip(), value, "--set")
        overridden.add(key.strip())
    # once the overrides are in: --set may mend a combination the file got wrong; an error names
    # --set when it set a key the constraint involves (or its section), else the file
    file_source = str(config_path(path)) if path is not None else "<defaults>"

    def source(keys: tuple[str, ...]) -> str:
        hit = any(k == o or k.startswith(o + ".") for k in keys for o in overridden)
        return "--set" if hit else file_source

    _cross_checks(cfg, source)
    return cfg


def set_value(cfg: Config, key: str, value: Any, source: str) -> None:
    """Set the dotted ``key`` to ``value`` as a YAML file or ``--set`` would: coerced to the field's
    type and checked against its range or choices; ConfigError in one line naming ``source`` (a
    command-line flag, say) and the key otherwise. Constraints between fields are load_config's."""
    nested: dict = {}
    cur = nested
    parts = key.split(".")
    for part in parts[:-1]:
        cur = cur.setdefault(part, {})
    cur[parts[-1]] = value
    _apply(cfg, nested, source)


def set_flags(cfg: Config, flags) -> None:
    """Each (flag, dotted key, value) of a command line whose value was given (not None), set as
    :func:`set_value` does, an error naming the flag the value came from."""
    for flag, key, value in flags:
        if value is not None:
            set_value(cfg, key, value, flag)


def to_dict(cfg: Any) -> dict:
    """Plain nested dict of a config (tuples as lists), for YAML, JSON and checkpoints."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v

    return conv(cfg)


def from_dict(data: dict, source: str = "<checkpoint>") -> Config:
    """Rebuild a Config from :func:`to_dict` output (e.g. stored in a checkpoint)."""
    cfg = Config()
    _apply(cfg, data, source)
    _cross_checks(cfg, source)
    return cfg


def save_config(cfg: Config, path: str | Path) -> None:
    """Write the resolved config as YAML, whole or not at all (a crash leaves the old file)."""
    atomic_write_text(Path(path), yaml.safe_dump(to_dict(cfg), sort_keys=False))
