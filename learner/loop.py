"""Where the parts live: one process (``run_local``) or Ray actors (``run_distributed``).

The parts are built once by the same constructors either way: replay shards
(``replay.client``), a :class:`learner.learner.Learner` wrapped by :class:`LearnerProcess`, and
:class:`actors.grasp_actor.GraspActor`. The driver loop only moves weights references, epsilon
and counters between them:

    actors:  run_episodes(n, epsilon, version, [weights_ref], first_episode) -> reports
    learner: train(steps) -> stats (+ a new weights version every P steps, one ray.put each)
    driver:  the samples-per-insert limiter on both sides (learner steps allowed; an actor's next
             chunk held back while inserts lead the learner by learner.insert_lead trials);
             progress; checkpoints; limits

Weights reach an actor with its next chunk of episodes (a reference; the actor fetches the
object only when the version is newer), so no actor ever waits for weights; an actor waits
only when the rate limiter holds its next chunk back.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

from actors.grasp_actor import EpisodeReport, GraspActor
from common.checkpoint import (
    CheckpointError,
    checkpoint_origin_file,
    initial_weights,
    portable_init_source,
    read_checkpoint,
    save_checkpoint,
)
from common.config import Config
from common.files import atomic_write_text, finite_json
from common.policy import action_region
from common.runtime import ray_init
from common.tsdf import heightmap_from_tsdf
from common.viz import score_maps_image
from learner.learner import Learner, TrainingDivergedError, epsilon_at, resolve_device
from learner.rate_limit import SamplesPerInsert
from replay.client import ReplayClient, open_local_shards, start_remote_shards
from replay.schema import ReplayEmptyError

CHECKPOINT_NAME = "latest.pt"
"""File name of the newest checkpoint inside RUN/checkpoints/."""
LEARNER_CHUNK_STEPS = 16
"""Most learner steps per train() call, so the driver stays responsive."""
LEARNER_CHUNK_S = 2.0
"""A train() call starts no further step after this many seconds, so the driver (and actors
held back by the rate limiter) see fresh sample counts even when one step takes seconds."""
LEARNER_IDLE_WAIT_S = 1.0
"""A learner call with no step allowed waits this long for new trials before returning."""
LEARNER_RESTARTS = 3
"""A lost learner process (killed, out of memory, its node gone) restarts from latest.pt and the
run goes on, this many times at most; the next loss ends the run."""
LEARNER_RESTART_WAIT_S = 300.0
"""How long the driver waits for a lost learner's new process to take calls."""


class ActorTaskError(RuntimeError):
    """An actor's episodes keep failing: the run ends, after its final checkpoint (the summary's
    ``error``)."""


ACTOR_TASK_FAILURES = 3
"""An actor whose episode chunks raise this many times in a row (an error in the episode code,
its process alive) ends the run with that error; a lost process (the actor's own, a shard's, the
owner of the weights it fetches) is Ray's to restart, and the run continues."""


ACTOR_DEATHS = 5
"""An actor whose process is lost this many times in a row without finishing an episode chunk
(its constructor fails, so every restart dies at once) ends the run with the last error; a
process lost now and then is Ray's to restart, and the run continues."""


class ActorFailures:
    """Consecutive failed episode chunks and lost processes per actor (see ACTOR_TASK_FAILURES
    and ACTOR_DEATHS)."""

    def __init__(self, n_actors: int) -> None:
        self.count = [0] * n_actors
        self.deaths = [0] * n_actors

    def succeeded(self, actor: int) -> None:
        self.count[actor] = 0
        self.deaths[actor] = 0

    def died(self, actor: int, error: Exception) -> str:
        """A chunk lost with the actor's process (a Ray actor error): its one-line description;
        ActorTaskError once the process was lost ACTOR_DEATHS times in a row."""
        lines = [line.strip() for line in str(error).strip().splitlines() if line.strip()]
        # a failed constructor's message ends with the exception it raised ("ValueError: ...")
        raised = [line for line in lines if re.match(r"^[A-Za-z_][\w.]*(Error|Exception): ", line)]
        line = f"{type(error).__name__}: {(raised or lines or [''])[-1]}".rstrip(": ")
        self.deaths[actor] += 1
        if self.deaths[actor] >= ACTOR_DEATHS:
            raise ActorTaskError(
                f"actor {actor}: its process was lost {self.deaths[actor]} times in a row without finishing an "
                f"episode chunk, the last with {line}"
            )
        return line

    def failed(self, actor: int, error: Exception) -> tuple[str, bool]:
        """A chunk that raised ``error`` (a Ray task error: its ``cause`` is the exception raised
        inside the actor): its one-line description, and whether it counts as an error of the
        episode code. A cause that is itself a Ray error (a lost shard, a lost weights owner) is
        transient and resets nothing; ActorTaskError once the actor has raised
        ACTOR_TASK_FAILURES errors of its own in a row."""
        from ray.exceptions import RayError

        cause = getattr(error, "cause", None) or error
        lines = str(cause).strip().splitlines()
        line = f"{type(cause).__name__}: {lines[0]}" if lines else type(cause).__name__
        if isinstance(cause, RayError):
            return line, False
        self.count[actor] += 1
        if self.count[actor] >= ACTOR_TASK_FAILURES:
            raise ActorTaskError(
                f"actor {actor}: {self.count[actor]} episode chunks in a row failed, the last with {line}"
            )
        return line, True


def checkpoint_path(run_dir: Path) -> Path:
    """RUN/checkpoints/latest.pt."""
    return Path(run_dir) / "checkpoints" / CHECKPOINT_NAME


def check_resumable(ckpt, path: Path) -> None:
    """CheckpointError in one line when the checkpoint ``ckpt`` (read from ``path``) holds no
    learner state or optimiser: a weights-only file (a step-*.pt snapshot, an averaged or exported
    model) cannot be resumed from."""
    if not isinstance(ckpt.extra.get("learner"), dict) or ckpt.optimizer is None:
        raise CheckpointError(f"{path}: extra.learner: missing (a weights-only file: a step-*.pt snapshot, an "
                              f"averaged or exported model); a run resumes only from the latest.pt it wrote")


def non_finite_tensors(state: dict) -> list[str]:
    """Names of the floating-point tensors of a state dict that hold NaN or infinity."""
    return [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]


def _drop_torn_line(path: Path) -> None:
    """A JSON-lines file whose last line was cut off (a killed write) loses that part-line, which
    no reader can parse (learner.curve refuses the file over it), with one line on stdout; every
    complete line stays."""
    if not path.is_file():
        return
    with open(path, "r+b") as f:
        size = f.seek(0, os.SEEK_END)
        if size == 0:
            return
        f.seek(max(0, size - 65536))
        tail = f.read()
        if tail.endswith(b"\n"):
            return
        cut = tail.rfind(b"\n")
        if cut < 0 and size > len(tail):
            return  # a last line over 64 KiB is not one of ours: left alone
        keep = size - len(tail) + cut + 1
        f.truncate(keep)
    print(f"{path}: dropped a cut-off last line of {size - keep} bytes (a write of a killed run)", flush=True)


def total_inserted(replay: ReplayClient) -> int:
    """Trials this run's actors ever committed to the replay (all shards, evicted ones included;
    trials a new replay was seeded with, replay.seed_from, are not counted)."""
    return int(sum(s["end"] - s["seeded"] for s in replay.stats()["shards"]))


class LearnerProcess:
    """The learner with its replay client, checkpointing and weight publishing; local or a Ray actor."""

    def __init__(self, cfg: Config, shards: list, run_dir: str, seed: int, torch_threads: int | None = None) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        device = resolve_device(cfg.learner.device)
        if device.type == "cpu":
            # More torch threads than free cores makes CPU convolutions many times slower
            # (threads spin-wait on each other), so the driver passes the cores actors leave free.
            torch.set_num_threads(torch_threads or max(1, min(os.cpu_count() or 1, 4)))
        self.replay = ReplayClient(shards, cfg, seed=seed)
        self.learner = Learner(cfg, self.replay, device=device, seed=seed)
        self.seed = seed
        ckpt = checkpoint_path(self.run_dir)
        self.resumed_from = None
        self.next_episode: list[int] = []
        """Per actor id, the number its next episode takes: recorded in every checkpoint, so that a
        resumed run numbers its episodes after the earlier parts' ((actor_id, episode_id) is unique)."""
        marks = self.replay.run_marks()  # read once: it parses every stored trial's metadata
        self.stored_episode_ends: dict[int, int] = marks["episode_ends"]
        """Per actor id, one past the largest episode number the replay holds (after a crash,
        trials committed since the last checkpoint are among them)."""
        self.init_source: dict | None = None
        """Where a fine-tuned run's first weights came from (learner.init_weights, the file: inside
        the package for a shipped model, else absolute; its step and version); written into every
        checkpoint; None for a random start."""
        if ckpt.is_file():
            c = read_checkpoint(ckpt)
            check_resumable(c, ckpt)
            ls = dict(c.extra["learner"])
            sampler = ls.pop("replay_sampler", None)
            if sampler is not None:  # checkpoints before it was kept: a stream from the seed
                self.replay.set_sampler_state(sampler)
            trained = ls.pop("trained_model", None)
            averaged = trained is not None
            self.learner.load_state_dict({
                "model": trained if averaged else c.model_state, "average": c.model_state if averaged else None,
                "optimizer": c.optimizer, "steps": c.step, "version": c.version, **ls,
            })
            self.resumed_from = c.step
            self.next_episode = [int(e) for e in c.extra.get("replay", {}).get("next_episode", [])]
            self.init_source = portable_init_source(c.extra.get("init_weights"))
        else:
            start = initial_weights(cfg)
            if start is not None:
                self.learner.start_from(start.model_state)
                self.init_source = {
                    "init_weights": cfg.learner.init_weights,
                    "file": checkpoint_origin_file(cfg.learner.init_weights),
                    "step": start.step,
                    "version": start.version,
                }
        # after a crash the replay may hold trials of weights published after the last checkpoint,
        # or before the first one: number the next weights after those, so that a version names
        # one set of weights
        self.learner.stats.version = max(self.learner.stats.version, marks["policy_version"])

    def inserted(self) -> int:
        """Trials this run's actors ever committed to the replay (see total_inserted)."""
        return total_inserted(self.replay)

    def train(
        self, max_steps: int, idle_wait_s: float = 0.0, force_publish: bool = False, after_version: int = 0
    ) -> dict:
        """Up to ``max_steps`` steps as the rate limiter allows; a new weights version when due
        (or always, with ``force_publish``: the first call of a run, fresh or resumed, or of a
        restarted learner). A published version is above ``after_version``: a learner restarted
        from latest.pt numbers its weights after those the actors already hold.

        When no step is allowed yet, waits up to ``idle_wait_s`` for new trials before returning.
        Returns a stats dict; ``weights`` holds ``(version, [ref or state])`` when one was published.
        """
        deadline = time.time() + idle_wait_s
        while True:
            inserted = self.inserted()
            steps = min(max_steps, self.learner.limiter.allowed_steps(inserted, self.learner.stats.samples))
            if steps > 0 or time.time() >= deadline:
                break
            time.sleep(0.25)
        before = self.learner.stats.steps
        if steps > 0:
            self.learner.train(steps, max_seconds=LEARNER_CHUNK_S)
        s = self.learner.stats
        out = {
            "steps": s.steps, "samples": s.samples, "version": s.version, "loss": s.loss,
            "pos_score": s.pos_score, "neg_score": s.neg_score, "inserted": inserted, "ran": s.steps - before,
            "weights": None,
        }
        if force_publish or self.learner.steps_since_publish >= self.cfg.learner.publish_every:
            self.learner.stats.version = max(self.learner.stats.version, int(after_version))
            out["weights"] = self.publish()
            out["version"] = self.learner.stats.version
        return out

    def publish(self) -> tuple[int, list]:
        """A new weights version: (version, [object ref]) under Ray, (version, [state]) in-process."""
        version, state = self.learner.publish()
        try:
            import ray

            if ray.is_initialized() and ray.get_runtime_context().get_actor_id() is not None:
                return version, [ray.put(state)]
        except ImportError:
            pass
        return version, [state]

    def checkpoint(
        self, epsilon: float, inserted: int, snapshot: bool = False, next_episode: list[int] | None = None
    ) -> str:
        """Write RUN/checkpoints/latest.pt atomically; returns its path. With ``snapshot`` (and
        ``learner.keep_snapshots``) also RUN/checkpoints/step-NNNNNNN.pt: the weights, without the
        optimiser and learner state. ``next_episode``: the actors' next episode numbers (the
        driver's; kept from the last call or the resumed checkpoint when None)."""
        if next_episode is not None:
            self.next_episode = [int(e) for e in next_episode]
        ls = self.learner.state_dict()
        latest = checkpoint_path(self.run_dir)
        bad = non_finite_tensors(ls["model"]) + non_finite_tensors(ls["average"] or {})
        if bad:
            print(f"learner step {ls['steps']}: weights not finite ({bad[0]} and {len(bad) - 1} more tensors); "
                  f"{latest} not overwritten, it keeps the last finite weights", flush=True)
            return str(latest)
        try:
            self.replay.flush()  # score updates in flight land before the sampler state is saved
        except Exception as e:  # noqa: BLE001 - a lost shard must not cost the checkpoint
            print(f"learner: score updates in flight failed before the checkpoint ({type(e).__name__})", flush=True)
        replay = {"inserted": int(inserted), "shards": self.cfg.replay.shards, "next_episode": list(self.next_episode)}
        learner_state = {
            "samples": ls["samples"], "history": ls["history"], "generator": ls["generator"],
            "replay_sampler": self.replay.sampler_state(),
        }
        if ls["average"] is not None:
            # The file's model is the average (what planners and evaluations load); resuming
            # continues from the trained weights.
            learner_state["trained_model"] = {k: v.detach().to("cpu", copy=True) for k, v in ls["model"].items()}
            learner_state["average_updates"] = ls["average_updates"]
        policy = self.learner.policy_model
        origin = {} if self.init_source is None else {"init_weights": self.init_source}
        path = save_checkpoint(
            latest, policy, self.cfg,
            step=ls["steps"], version=ls["version"], epsilon=epsilon, optimizer=ls["optimizer"],
            extra={"learner": learner_state, "replay": replay, **origin},
        )
        if snapshot and self.cfg.learner.keep_snapshots:
            save_checkpoint(
                path.parent / f"step-{ls['steps']:07d}.pt", policy, self.cfg,
                step=ls["steps"], version=ls["version"], epsilon=epsilon, extra={"replay": replay, **origin},
            )
        return str(path)

    def score_map_image(self) -> tuple[int, np.ndarray] | None:
        """(learner step, (H, W, 3) uint8 image): the policy weights' score maps (3 of the R
        rotations, best marked) of one replayed trial's scene and gripper at its executed opening;
        None while the replay holds no trial. The trial is drawn by a generator of its own (seeded
        by the run seed and the step), so the training batches do not depend on when images are made."""
        try:
            batch = self.replay.sample(2, np.random.default_rng([self.seed, self.learner.stats.steps]))
        except ReplayEmptyError:
            return None
        model = self.learner.policy_model
        was_training = model.training
        model.eval()
        try:
            probs = model.predict(batch.scene[:1].to(model.device), [batch.gripper[:1].to(model.device)])
        finally:
            model.train(was_training)
        grid = self.cfg.scene_grid
        heightmap = heightmap_from_tsdf(batch.scene[0, 0].numpy(), grid)
        mask = action_region(self.cfg)
        if self.cfg.model.min_surface_height > 0:
            mask &= heightmap > self.cfg.model.min_surface_height
        label = "success" if float(batch.label[0]) > 0.5 else "failure"
        title = f"step {self.learner.stats.steps}, replayed trial ({label}), executed opening"
        return self.learner.stats.steps, score_maps_image(probs[0, 0].cpu().numpy(), heightmap, self.cfg, mask=mask, title=title)

    def first_episodes(self, n_actors: int) -> list[int]:
        """The first episode number of each actor id in this part of the run: for ``n_actors`` ids
        at least, and for every id the checkpoint recorded (a part with fewer actors keeps the
        numbers of the others for a later part). After a crash the replay may hold episodes
        committed after the last checkpoint: numbering starts after those too."""
        ends = self.stored_episode_ends
        n = max(n_actors, len(self.next_episode), max(ends, default=-1) + 1)
        recorded = self.next_episode + [0] * (n - len(self.next_episode))
        return [max(recorded[a], ends.get(a, 0)) for a in range(n)]

    def history(self) -> list:
        """(step, loss) pairs since the run started."""
        return list(self.learner.stats.history)


class Progress:
    """Progress line, progress.jsonl and TensorBoard scalars, shared by both drivers."""

    def __init__(self, cfg: Config, run_dir: Path, quiet: bool, dashboard: str | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.cfg = cfg
        self.quiet = quiet
        self.t0 = time.time()
        self.last_print = 0.0
        self.trials_at_start: int | None = None
        self.samples_at_start: int | None = None
        self.recent: deque = deque(maxlen=200)
        self.by_group: dict[str, deque] = {}
        log = Path(run_dir) / "progress.jsonl"
        _drop_torn_line(log)
        self.log = open(log, "a")
        self.tb = SummaryWriter(str(Path(run_dir) / "tb"))
        self.dashboard = dashboard
        self.episodes = 0

    def add_reports(self, reports: list[EpisodeReport]) -> None:
        for r in reports:
            self.episodes += 1
            outcomes = [1] * r.successes + [0] * (r.trials - r.successes)
            self.recent.extend((o, r.policy_version) for o in outcomes)
            for group in (f"family/{r.family}", f"scene/{r.scene}"):
                self.by_group.setdefault(group, deque(maxlen=200)).extend(outcomes)

    def tick(self, inserted: int, stats: dict, epsilon: float, force: bool = False) -> dict:
        now = time.time()
        if self.trials_at_start is None:
            self.trials_at_start, self.samples_at_start = inserted, stats.get("samples", 0)
        elapsed = max(1e-6, now - self.t0)
        trials_s = (inserted - self.trials_at_start) / elapsed
        samples_s = (stats.get("samples", 0) - (self.samples_at_start or 0)) / elapsed
        success = sum(o for o, _ in self.recent) / len(self.recent) if self.recent else float("nan")
        lag = stats.get("version", 0) - (sum(v for _, v in self.recent) / len(self.recent)) if self.recent else float("nan")
        line = {
            "time": round(now - self.t0, 1), "trials": inserted, "episodes": self.episodes,
            "success_rate": success, "learner_steps": stats.get("steps", 0), "loss": stats.get("loss", float("nan")),
            "version": stats.get("version", 0), "trials_per_s": trials_s, "samples_per_s": samples_s,
            "epsilon": epsilon, "weights_lag": lag,
        }
        if force or now - self.last_print >= 5.0:
            self.last_print = now
            self.log.write(json.dumps(finite_json(line)) + "\n")
            self.log.flush()
            step = int(stats.get("steps", 0))
            for key in ("loss", "pos_score", "neg_score"):
                if not math.isnan(stats.get(key, float("nan"))):
                    self.tb.add_scalar(f"learner/{key}", stats[key], step)
            self.tb.add_scalar("collect/trials_per_s", trials_s, inserted)
            self.tb.add_scalar("learner/samples_per_s", samples_s, step)
            self.tb.add_scalar("collect/epsilon", epsilon, inserted)
            if not math.isnan(lag):
                self.tb.add_scalar("collect/weights_version_lag", lag, inserted)
            for group, outcomes in self.by_group.items():
                if outcomes:
                    self.tb.add_scalar(f"success/{group}", sum(outcomes) / len(outcomes), inserted)
            if not self.quiet:
                dash = f" | dashboard {self.dashboard}" if self.dashboard else ""
                print(
                    f"[{line['time']:7.1f}s] trials {inserted} | success {success:.2f} | steps {line['learner_steps']}"
                    f" | loss {line['loss']:.4f} | weights v{line['version']} | {trials_s:.2f} trials/s"
                    f" | {samples_s:.1f} samples/s | eps {epsilon:.2f}{dash}",
                    flush=True,
                )
        return line

    def add_score_maps(self, shot: tuple[int, np.ndarray] | None) -> None:
        """TensorBoard image ``learner/score_maps`` at its learner step (see LearnerProcess.score_map_image)."""
        if shot is not None:
            step, image = shot
            self.tb.add_image("learner/score_maps", image, step, dataformats="HWC")
            self.tb.flush()

    def close(self) -> None:
        self.log.close()
        self.tb.close()


def _done(cfg: Config, inserted: int, t0: float, stop: dict) -> bool:
    if stop["flag"]:
        return True
    if cfg.run.max_trials and inserted >= cfg.run.max_trials:
        return True
    return bool(cfg.run.max_minutes and time.time() - t0 >= cfg.run.max_minutes * 60)


def _summary(run_dir: Path, inserted: int, stats: dict, progress: Progress, extra: dict) -> dict:
    return {
        "run_dir": str(run_dir), "trials": inserted, "episodes": progress.episodes,
        "learner_steps": stats.get("steps", 0), "learner_samples": stats.get("samples", 0),
        "weights_version": stats.get("version", 0),
        "loss": stats.get("loss"), "checkpoint": str(checkpoint_path(run_dir)), **extra,
    }


def run_local(cfg: Config, run_dir: Path, stop: dict, quiet: bool = False) -> dict:
    """Everything in this process: shards, learner and one actor, interleaved episode by episode.

    Limits come from ``cfg.run``; an existing RUN/checkpoints/latest.pt is resumed from.
    """
    shards = open_local_shards(run_dir / "replay", cfg)
    learner = LearnerProcess(cfg, shards, str(run_dir), seed=cfg.run.seed)
    episodes = learner.first_episodes(1)
    actor = GraspActor(
        cfg, actor_id=0, seed=cfg.run.seed, replay=ReplayClient(shards, cfg, seed=cfg.run.seed + 1),
        stream=learner.inserted(), first_episode=episodes[0],
    )
    progress = Progress(cfg, run_dir, quiet)
    t0 = last_ckpt = time.time()
    stats = learner.train(0, force_publish=True)
    version, box = stats["weights"]
    actor.set_weights(version, box[0])
    published = 1
    inserted = learner.inserted()
    error = None  # training diverged: the run ends with this line
    try:
        while not _done(cfg, inserted, t0, stop):
            eps = epsilon_at(cfg, inserted)
            progress.add_reports(actor.run_episodes(1, eps))
            stats = learner.train(LEARNER_CHUNK_STEPS)
            weights = stats["weights"]
            published += weights is not None
            while stats["ran"] > 0 and not stop["flag"]:
                stats = learner.train(LEARNER_CHUNK_STEPS)
                weights = stats["weights"] or weights
                published += stats["weights"] is not None
            if weights is not None:
                version, box = weights
                actor.set_weights(version, box[0])
            inserted = stats["inserted"]
            progress.tick(inserted, stats, eps)
            if time.time() - last_ckpt >= cfg.learner.checkpoint_minutes * 60:
                learner.checkpoint(eps, inserted, snapshot=True, next_episode=[actor.episode, *episodes[1:]])
                progress.add_score_maps(learner.score_map_image())
                last_ckpt = time.time()
    except TrainingDivergedError as e:
        error = str(e)
    finally:
        actor.close()
        inserted = learner.inserted()
        learner.checkpoint(epsilon_at(cfg, inserted), inserted, next_episode=[actor.episode, *episodes[1:]])
        progress.tick(inserted, stats, epsilon_at(cfg, inserted), force=True)
        progress.close()
        for s in shards:
            s.close()
    extra = {"mode": "local", "weights_published": published, **({"error": error} if error is not None else {})}
    return _summary(run_dir, inserted, stats, progress, extra)


def _first_call_after_restart(call):
    """``ray.get(call())`` once the restarting actor takes calls (up to LEARNER_RESTART_WAIT_S)."""
    import ray
    from ray.exceptions import ActorUnavailableError

    deadline = time.time() + LEARNER_RESTART_WAIT_S
    while True:
        try:
            return ray.get(call())
        except ActorUnavailableError:
            if time.time() > deadline:
                raise
            time.sleep(1.0)


class ActorProcess:
    """A GraspActor inside a Ray actor process: fetches weights by reference when they are newer."""

    def __init__(self, cfg: Config, actor_id: int, seed: int, shards: list, stream: int = 0) -> None:
        import ray

        incarnation = 0
        if ray.get_runtime_context().was_current_actor_reconstructed:
            incarnation = time.time_ns() % (2**31)  # a restarted actor must not replay its old random stream
        replay = ReplayClient(shards, cfg, seed=seed * 1000 + actor_id + incarnation)
        self.actor = GraspActor(cfg, actor_id, seed + 7919 * incarnation, replay, stream=stream)
        self.incarnation = incarnation

    def run_episodes(self, n: int, epsilon: float, version: int, box: list, first_episode: int) -> list[EpisodeReport]:
        import ray

        if version > self.actor.version:
            self.actor.set_weights(version, ray.get(box[0]))
        self.actor.episode = max(self.actor.episode, first_episode)
        return self.actor.run_episodes(n, epsilon)

    def pid(self) -> int:
        return os.getpid()

    def close(self) -> None:
        self.actor.close()


def run_distributed(
    cfg: Config, run_dir: Path, stop: dict, n_actors: int, address: str | None = None, quiet: bool = False
) -> dict:
    """Replay shards, the learner and ``n_actors`` grasp actors as restartable Ray actors.

    Limits come from ``cfg.run``; an existing RUN/checkpoints/latest.pt is resumed from.
    """
    import ray
    from ray.exceptions import RayActorError, RayTaskError

    # Logical CPUs: actors and the learner share the physical cores of a laptop.
    dashboard = ray_init(address, num_cpus=max(os.cpu_count() or 1, n_actors + 1))
    gpus = 1 if ray.cluster_resources().get("GPU", 0) >= 1 and cfg.learner.device != "cpu" else 0
    shards = start_remote_shards(run_dir / "replay", cfg)
    learner_cls = ray.remote(num_cpus=1, num_gpus=gpus, max_restarts=-1)(LearnerProcess)
    # On a local instance the actors take n_actors of this machine's cores; the learner gets the rest.
    threads = None if address else max(1, (os.cpu_count() or 1) - n_actors)
    learner = learner_cls.remote(cfg, shards, str(run_dir), cfg.run.seed, threads)
    # A resumed run: a new random stream per actor (keyed by the trials committed so far), and
    # episode numbers after those its checkpoint recorded.
    stream = ray.get(learner.inserted.remote())
    next_episode = ray.get(learner.first_episodes.remote(n_actors))
    actor_cls = ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=0)(ActorProcess)
    actors = [
        actor_cls.options(scheduling_strategy="SPREAD").remote(cfg, i, cfg.run.seed, shards, stream)
        for i in range(n_actors)
    ]
    progress = Progress(cfg, run_dir, quiet, dashboard)
    replay = ReplayClient(shards, cfg, seed=cfg.run.seed + 2)  # the driver's view: counts only
    stats = ray.get(learner.train.remote(0, force_publish=True))
    version, box = stats["weights"]
    published, restarts, learner_restarts = 1, 0, 0
    failures = ActorFailures(n_actors)
    pending: dict = {}

    inserted = stats["inserted"]

    def submit(a: int) -> None:
        eps = epsilon_at(cfg, inserted)
        pending[actors[a].run_episodes.remote(cfg.actor.weights_poll_episodes, eps, version, box, next_episode[a])] = a
        next_episode[a] += cfg.actor.weights_poll_episodes

    limiter = SamplesPerInsert.from_config(cfg.learner)
    waiting: dict[int, float] = {}  # actor -> time it began waiting for the learner
    wait_s = 0.0

    for a in range(n_actors):
        submit(a)
    learner_future = learner.train.remote(LEARNER_CHUNK_STEPS, idle_wait_s=LEARNER_IDLE_WAIT_S)

    def learner_lost(e: Exception) -> None:
        """The learner's process died (its train chunk or a checkpoint call failed): count it, wait
        for the process Ray restarts from latest.pt, take its first weights (numbered after those
        the actors hold) and start its next chunk; past LEARNER_RESTARTS, raise ``e``."""
        nonlocal learner_restarts, stats, version, box, published, learner_future
        if learner_restarts >= LEARNER_RESTARTS:
            raise e
        learner_restarts += 1
        print(f"learner: process lost ({type(e).__name__}); it restarts from its last checkpoint and continues",
              flush=True)
        stats = _first_call_after_restart(lambda: learner.train.remote(0, force_publish=True, after_version=version))
        version, box = stats["weights"]
        published += 1
        learner_future = learner.train.remote(LEARNER_CHUNK_STEPS, idle_wait_s=LEARNER_IDLE_WAIT_S)

    t0 = last_ckpt = time.time()
    error = None  # an actor's episodes kept failing, or training diverged: the run ends with this line
    try:
        while error is None and not _done(cfg, inserted, t0, stop):
            ready, _ = ray.wait(list(pending) + [learner_future], num_returns=1, timeout=1.0)
            for ref in ready:
                if ref is learner_future:
                    try:
                        stats = ray.get(ref)
                    except RayActorError as e:
                        learner_lost(e)
                        continue
                    except RayTaskError as e:
                        if not isinstance(e.cause, TrainingDivergedError):
                            raise
                        error = str(e.cause)
                        break
                    if stats["weights"] is not None:
                        version, box = stats["weights"]
                        published += 1
                    learner_future = learner.train.remote(LEARNER_CHUNK_STEPS, idle_wait_s=LEARNER_IDLE_WAIT_S)
                    continue
                a = pending.pop(ref)
                try:
                    progress.add_reports(ray.get(ref))
                    failures.succeeded(a)
                except RayActorError as e:
                    try:
                        line = failures.died(a, e)
                    except ActorTaskError as end:
                        error = str(end)
                        break
                    restarts += 1
                    print(f"actor {a}: process lost ({line}); it restarts and continues", flush=True)
                except RayTaskError as e:
                    try:
                        line, own = failures.failed(a, e)
                    except ActorTaskError as end:
                        error = str(end)
                        break
                    restarts += not own
                    print(f"actor {a}: episode chunk failed ({line}); it runs the next one", flush=True)
                waiting[a] = time.time()
            if error is not None:
                break
            inserted = total_inserted(replay)
            # The actor side of the rate limiter: an actor starts its next chunk only while the
            # inserts are less than insert_lead trials ahead of the learner's samples.
            for a in sorted(waiting):
                if not limiter.may_insert(inserted, stats["samples"]):
                    break
                wait_s += time.time() - waiting.pop(a)
                submit(a)
            progress.tick(inserted, stats, epsilon_at(cfg, inserted))
            if time.time() - last_ckpt >= cfg.learner.checkpoint_minutes * 60:
                try:
                    ray.get(learner.checkpoint.remote(epsilon_at(cfg, inserted), inserted, snapshot=True,
                                                      next_episode=next_episode))
                    progress.add_score_maps(ray.get(learner.score_map_image.remote()))
                    last_ckpt = time.time()
                except RayActorError as e:
                    learner_lost(e)  # and the checkpoint is taken at the next tick
    finally:
        # Let every running chunk finish its episode (no partial trials), then checkpoint.
        ray.wait(list(pending), num_returns=len(pending), timeout=120)
        for ref in list(pending):
            try:
                progress.add_reports(ray.get(ref, timeout=0))
            except Exception as e:  # noqa: BLE001 - an actor lost at shutdown loses only unfinished episodes
                print(f"actor {pending[ref]}: last chunk lost at shutdown ({type(e).__name__})", flush=True)
        for a, handle in enumerate(actors):
            try:
                ray.get(handle.close.remote(), timeout=60)
            except Exception as e:  # noqa: BLE001
                print(f"actor {a}: close failed at shutdown ({type(e).__name__})", flush=True)
        try:
            stats = ray.get(learner_future)
            published += stats["weights"] is not None  # the last chunk's version, which no actor took
        except (RayActorError, RayTaskError) as e:
            # A learner chunk that failed (the error that ended the loop, or one at shutdown): the
            # learner, alive or restarted from latest.pt, still writes the final checkpoint.
            print(f"learner: last chunk failed ({type(e).__name__}); writing the checkpoint", flush=True)
        try:
            # a learner lost at the end is still restarting: wait for it to write the checkpoint
            inserted = _first_call_after_restart(lambda: learner.inserted.remote())
            ckpt = _first_call_after_restart(
                lambda: learner.checkpoint.remote(epsilon_at(cfg, inserted), inserted, next_episode=next_episode)
            )
            history = _first_call_after_restart(lambda: learner.history.remote())
            progress.tick(inserted, stats, epsilon_at(cfg, inserted), force=True)
        finally:
            progress.close()
            ray.shutdown()
    atomic_write_text(Path(run_dir) / "history.json", json.dumps(finite_json(history)))
    return _summary(
        run_dir, inserted, stats, progress,
        {"mode": "ray", "actors": n_actors, "weights_published": published, "actor_restarts": restarts,
         "learner_restarts": learner_restarts, "checkpoint": ckpt,
         "actor_wait_s": round(wait_s + sum(time.time() - w for w in waiting.values()), 1),  # summed over actors
         **({"error": error} if error is not None else {})},
    )
