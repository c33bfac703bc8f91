"""The learner: class-balanced batches from the replay -> augmentation -> loss on the executed
action (under bfloat16 autocast with ``learner.precision=bf16``) -> Adam step -> refreshed scores
written back -> versioned weights.

It is a plain object; ``learner.run`` decides whether it lives in this process or in a Ray
actor. Call loop::

    learner = Learner(cfg, replay, device="cpu")
    while running:
        steps = learner.limiter.allowed_steps(total_inserted(replay), learner.stats.samples)  # learner.loop
        stats = learner.train(steps)
        if learner.steps_since_publish >= cfg.learner.publish_every:
            version, state = learner.publish()
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import torch

from common.config import Config
from common.network import build_model
from learner.augment import augment_batch
from learner.rate_limit import SamplesPerInsert


def epsilon_at(cfg: Config, trials: int) -> float:
    """Exploration epsilon after ``trials`` collected trials: linear from start to end."""
    lc = cfg.learner
    frac = min(1.0, trials / max(1, lc.epsilon_decay_trials))
    return lc.epsilon_start + frac * (lc.epsilon_end - lc.epsilon_start)


def precision_autocast(device: torch.device, precision: str) -> torch.autocast:
    """The autocast context of a training forward pass and loss at ``learner.precision``: bfloat16
    on ``device`` for ``bf16``, a disabled one (float32) for ``fp32``."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu; ValueError in one line for ``cuda`` where this
    process's torch sees no CUDA device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"learner.device: cuda, but torch {torch.__version__} sees no CUDA device here "
                         "(auto uses one when there is one)")
    return torch.device(name)


class TrainingDivergedError(RuntimeError):
    """A training step gave a non-finite loss or scores: the weights can no longer be trusted."""


@dataclass
class TrainStats:
    """Running statistics of the learner since it started."""

    steps: int = 0
    """Optimiser steps taken."""
    samples: int = 0
    """Trials drawn from the replay."""
    version: int = 0
    """Version of the newest published weights."""
    loss: float = float("nan")
    """Mean loss over the last train() call."""
    pos_score: float = float("nan")
    """Mean predicted success probability of successful trials in the last train() call."""
    neg_score: float = float("nan")
    """Mean predicted success probability of failed trials in the last train() call."""
    train_seconds: float = 0.0
    """Wall seconds spent inside train()."""
    history: list = field(default_factory=list)
    """(step, loss) after every train() call, for learning curves."""


class Learner:
    """Owns the model, the optimiser and the sampling generator; talks to a replay client."""

    def __init__(self, cfg: Config, replay, device: str | torch.device = "cpu", seed: int = 0):
        self.cfg = cfg
        self.replay = replay
        self.device = torch.device(device)
        with torch.random.fork_rng(devices=[]):  # the initial weights follow ``seed``, not the process
            torch.manual_seed(seed)
            self.model = build_model(cfg).to(self.device)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=cfg.learner.lr, betas=(cfg.learner.adam_beta1, cfg.learner.adam_beta2)
        )
        self.generator = torch.Generator().manual_seed(seed)
        self.limiter = SamplesPerInsert.from_config(cfg.learner)
        self.stats = TrainStats()
        self.steps_since_publish = 0
        self.average = copy.deepcopy(self.model).eval().requires_grad_(False) if cfg.learner.ema_decay > 0 else None
        """Exponential moving average of the weights (``learner.ema_decay`` > 0), else None."""
        self.average_updates = 0
        """Steps folded into :attr:`average` since it was (re)started."""

    @property
    def policy_model(self):
        """The weights actors act with and checkpoints carry: the average when one is kept."""
        return self.model if self.average is None else self.average

    def _update_average(self) -> None:
        """Fold the current weights into the average. The decay ramps up as (1 + n) / (10 + n)
        towards ``learner.ema_decay`` so that the first steps do not keep the initial weights."""
        if self.average is None:
            return
        self.average_updates += 1
        n = self.average_updates
        decay = min(self.cfg.learner.ema_decay, (1 + n) / (10 + n))
        with torch.no_grad():
            for avg, cur in zip(self.average.state_dict().values(), self.model.state_dict().values()):
                if avg.dtype.is_floating_point:
                    avg.lerp_(cur, 1.0 - decay)
                else:
                    avg.copy_(cur)
        self.average.clear_cache()

    def train(self, steps: int, max_seconds: float | None = None) -> TrainStats:
        """Run ``steps`` optimiser steps, or fewer (at least one) once ``max_seconds`` have passed;
        returns the updated statistics (loss and scores: means over the steps of this call)."""
        if steps <= 0:
            return self.stats
        t0 = time.perf_counter()
        self.model.train()
        losses, pos, neg = [], [], []
        for n in range(steps):
            if n > 0 and max_seconds is not None and time.perf_counter() - t0 >= max_seconds:
                break
            batch = self.replay.sample(self.cfg.learner.batch_size)
            scene, action = augment_batch(  # on the learner's device: the scene resampling is the heavy part
                batch.scene.to(self.device, non_blocking=True),
                batch.action,
                self.cfg.model.rotations,
                self.cfg.learner.augment_prob,
                self.generator,
            )
            gripper = batch.gripper.to(self.device, non_blocking=True)
            action = action.to(self.device)
            label = batch.label.to(self.device)
            with precision_autocast(self.device, self.cfg.learner.precision):
                logits = self.model.forward_train(scene, gripper, action[:, 2])
                loss = self.model.loss(logits, action, label)
            logits = logits.float()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            self._update_average()
            with torch.no_grad():
                b = torch.arange(logits.shape[0], device=logits.device)
                prob = torch.softmax(logits[b, :, action[:, 0], action[:, 1]], dim=1)[:, 1].cpu()
            if not (torch.isfinite(prob).all() and torch.isfinite(loss.detach())):
                # before the scores reach the replay; checkpoints keep the last finite weights
                raise TrainingDivergedError(
                    f"learner step {self.stats.steps + 1}: loss {float(loss.detach()):.4g} or predicted scores not finite: "
                    f"training diverged (try a lower learner.lr, or learner.precision=fp32)"
                )
            self.replay.update_scores(batch.index, prob.numpy())
            losses.append(float(loss.detach()))
            lab = batch.label.bool()
            if lab.any():
                pos.append(float(prob[lab].mean()))
            if (~lab).any():
                neg.append(float(prob[~lab].mean()))
            self.stats.steps += 1
            self.stats.samples += scene.shape[0]
            self.steps_since_publish += 1
        self.stats.loss = sum(losses) / len(losses)
        self.stats.pos_score = sum(pos) / len(pos) if pos else float("nan")
        self.stats.neg_score = sum(neg) / len(neg) if neg else float("nan")
        self.stats.train_seconds += time.perf_counter() - t0
        self.stats.history.append((self.stats.steps, self.stats.loss))
        return self.stats

    def publish(self) -> tuple[int, dict]:
        """A new weights version of :attr:`policy_model`: (version, CPU state dict)."""
        self.stats.version += 1
        self.steps_since_publish = 0
        state = {k: v.detach().to("cpu", copy=True) for k, v in self.policy_model.state_dict().items()}
        return self.stats.version, state

    def state_dict(self) -> dict:
        """Everything needed to resume the learner (trained weights, their average or None,
        optimiser, counters, generator)."""
        return {
            "model": self.model.state_dict(),
            "average": None if self.average is None else self.average.state_dict(),
            "average_updates": self.average_updates,
            "optimizer": self.optimizer.state_dict(),
            "steps": self.stats.steps,
            "samples": self.stats.samples,
            "version": self.stats.version,
            "history": list(self.stats.history),
            "generator": self.generator.get_state(),
        }

    def start_from(self, weights: dict) -> None:
        """Start a new run from trained ``weights`` (a model state dict; the average, when kept,
        starts from them too); the optimiser and counters stay fresh."""
        self.model.load_state_dict(weights)
        if self.average is not None:
            self.average.load_state_dict(weights)

    def load_state_dict(self, state: dict) -> None:
        """Inverse of :meth:`state_dict`. Without a stored average (a run resumed with averaging
        newly switched on) the average restarts from the loaded weights. The learning rate and Adam's
        betas are this learner's (``learner.lr``, ``learner.adam_beta1/2``), not the stored ones: a
        run resumed with ``--set learner.lr=...`` trains at the new rate (Adam's moment estimates
        are kept). The optimiser state is copied:
        torch's optimiser would otherwise keep the given tensors, and a state taken from a live
        learner in the same process would then move with that learner's steps."""
        self.model.load_state_dict(state["model"])
        if self.average is not None:
            stored = state.get("average")
            self.average.load_state_dict(state["model"] if stored is None else stored)
            self.average_updates = int(state.get("average_updates", 0)) if stored is not None else 0
        self.optimizer.load_state_dict(copy.deepcopy(state["optimizer"]))
        for group in self.optimizer.param_groups:
            group["lr"] = self.cfg.learner.lr
            group["betas"] = (self.cfg.learner.adam_beta1, self.cfg.learner.adam_beta2)
        self.stats.steps = int(state["steps"])
        self.stats.samples = int(state["samples"])
        self.stats.version = int(state["version"])
        self.stats.history = list(state.get("history", []))
        self.generator.set_state(state["generator"])
