"""The GraspActor: runs grasp episodes with the newest weights and pushes every trial to the replay.

A plain object; ``learner.loop`` decides whether it lives in this process or in a restartable
Ray actor process (one torch thread). Call loop::

    actor = GraspActor(cfg, actor_id=0, seed=0, replay=client)
    actor.set_weights(version, state_dict)          # before acting; a restarted actor gets them first
    report = actor.run_episodes(2, epsilon=0.8)     # every trial inserted into the replay
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from actors.grasp import run_episode
from actors.simulation import Simulation
from common import gripper_procedural
from common.config import Config
from common.gripper import GripperSpec, get_gripper, list_grippers
from common.gripper_encoding import GripperEncoder, gripper_key
from common.network import build_model
from common.observation import Trial, TrialMeta
from common.policy import LearnedPolicy


def split_grippers(cfg: Config) -> tuple[list[GripperSpec], list[GripperSpec]]:
    """Training grippers of ``grippers.train_grippers`` as (two-finger, multi-finger) lists.

    ``train_grippers`` is a split name (``train``, ``test``), ``pool`` (the checked procedural pool of
    assets/grippers/catalog.yaml) or comma-separated gripper names.
    """
    sel = cfg.grippers.train_grippers
    if sel in ("train", "test"):
        specs = list_grippers(split=sel)
    elif sel == "pool":
        specs = [get_gripper(n) for n in gripper_procedural.catalog_names("pool")]
    else:
        specs = [get_gripper(n.strip()) for n in sel.split(",")]
    if not specs:
        raise ValueError(f"grippers.train_grippers: {sel!r} selects no gripper")
    two = [s for s in specs if s.family == "2-finger"]
    multi = [s for s in specs if s.family != "2-finger"]
    return two, multi


@dataclass
class EpisodeReport:
    """What one episode did, for progress lines and TensorBoard."""

    actor_id: int
    """Actor that ran it."""
    episode_id: int
    """Episode index of that actor."""
    gripper: str
    """Gripper name."""
    family: str
    """Gripper family."""
    scene: str
    """Scene kind."""
    trials: int
    """Grasp attempts."""
    successes: int
    """Successful attempts."""
    policy_version: int
    """Weights version used."""
    seconds: float
    """Wall seconds of the episode."""
    trial_seconds: list = field(default_factory=list)
    """Wall seconds of each attempt."""


class GraspActor:
    """One simulation, one model copy, one seeded generator; inserts trials through a replay client."""

    def __init__(self, cfg: Config, actor_id: int, seed: int, replay, stream: int = 0, first_episode: int = 0) -> None:
        """``stream`` picks the random stream of this (seed, actor_id): 0 for a new run; a resumed
        run passes the trials its earlier parts committed, so that it does not draw their grippers,
        openings and scenes again. ``first_episode`` numbers this actor's first episode."""
        torch.set_num_threads(cfg.actor.torch_threads)
        self.cfg = cfg
        self.actor_id = int(actor_id)
        seq = np.random.SeedSequence([int(seed), self.actor_id] + ([int(stream)] if stream else []))
        self.seed_sequence = seq
        self.rng = np.random.default_rng(seq)
        self.two_finger, self.multi_finger = split_grippers(cfg)  # before the physics client: it may raise
        self.replay = replay
        # each episode draws its scale and openings from continuous ranges, so an encoding is never
        # asked for twice: kept in memory only (on disk they grew by 6 never-read files an episode)
        self.encoder = GripperEncoder(cfg.gripper_grid, disk=False)
        self.model = build_model(cfg).eval()
        self.version = -1
        self.episode = int(first_episode)
        self.sim = Simulation(cfg, seed=int(seq.generate_state(1)[0]))

    def set_weights(self, version: int, state: dict) -> None:
        """Load weights ``version`` (ignored if not newer than the loaded one)."""
        if version > self.version:
            self.model.set_weights(state, version)
            self.version = int(version)

    def _pick_gripper(self) -> tuple[GripperSpec, float, tuple[float, ...]]:
        g = self.cfg.grippers
        use_multi = bool(self.multi_finger) and (not self.two_finger or self.rng.random() < g.multi_finger_fraction)
        pool = self.multi_finger if use_multi else self.two_finger
        spec = pool[int(self.rng.integers(len(pool)))]
        scale = float(self.rng.uniform(*g.scale_range))
        lo, hi = g.opening_range
        openings = tuple(float(o) for o in np.sort(self.rng.uniform(lo, hi, size=g.train_openings)))
        return spec, scale, openings

    def run_episodes(self, n: int, epsilon: float) -> list[EpisodeReport]:
        """Run ``n`` episodes with exploration ``epsilon``; every trial goes to the replay."""
        reports = []
        for _ in range(n):
            reports.append(self._episode(epsilon))
        self.replay.flush()
        return reports

    def _episode(self, epsilon: float) -> EpisodeReport:
        t0 = time.perf_counter()
        cfg = self.cfg
        spec, scale, openings = self._pick_gripper()
        encoding = self.encoder.encode(spec, scale, openings)
        key = gripper_key(spec.name, scale, openings)
        policy = LearnedPolicy(self.model, cfg, [(key, encoding)], mode="fix-gripper", epsilon=epsilon)
        gripper = self.sim.load_gripper(spec, scale)  # owned by the simulation, reused while unchanged
        episode_seed = int(self.rng.integers(2**31))
        report = EpisodeReport(self.actor_id, self.episode, spec.name, spec.family, cfg.sim.scene, 0, 0, self.version, 0.0)
        for result in run_episode(
            self.sim, gripper, policy, openings, cfg.sim.scene, cfg.sim.objects, seed=episode_seed, rng=self.rng
        ):
            trial = Trial(
                observation=result.observation,
                gripper_key=key,
                gripper_encoding=encoding,
                action=result.action,
                label=bool(result.outcome.success),
                score=float(result.score),
                meta=TrialMeta(
                    episode_id=self.episode,
                    step=result.step,
                    scene=cfg.sim.scene,
                    object_set=cfg.sim.objects,
                    object_ids=tuple(result.object_ids),
                    gripper=spec.name,
                    gripper_scale=scale,
                    openings=openings,
                    cameras=cfg.sim.cameras,
                    actor_id=self.actor_id,
                    policy_version=self.version,
                    seed=episode_seed,
                    wall_time=time.time(),
                ),
            ).validate()
            self.replay.insert(trial)
            report.trials += 1
            report.successes += int(trial.label)
            report.trial_seconds.append(result.trial_s)
        self.episode += 1
        report.seconds = time.perf_counter() - t0
        return report

    def close(self) -> None:
        """Flush the replay client and close the simulation."""
        self.replay.flush()
        self.sim.close()
