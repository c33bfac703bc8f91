"""Client of K replay shards: routes inserts, draws balanced batches, writes scores back.

The same client drives in-process shards (tests, single-process runs) and Ray actor handles:
a thin backend turns "call method m of shard k" into either a direct call or ``.remote()``,
and everything else is shared. Requests are bounded (``replay.max_inflight``), so a fast
producer waits instead of filling the Ray object store.

Call loop::

    shards = open_local_shards(run_dir / "replay", cfg)     # or start_remote_shards(...) under Ray
    client = ReplayClient(shards, cfg, seed=cfg.run.seed)
    client.insert(trial)                                    # actor side; quantised here, stored there
    batch = client.sample(cfg.learner.batch_size)           # learner side; ready torch tensors
    client.update_scores(batch.index, new_scores)           # refreshed surprise
    client.flush()                                          # wait for outstanding requests

Insert errors of a Ray shard surface on a later call, at the latest at ``flush()``.
"""

from __future__ import annotations

import uuid
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from common.config import Config
from common.observation import Trial
from replay.sampler import BufferPool, draw_balanced, draw_counts
from replay.schema import ReplayEmptyError, ReplayError, ReplaySchemaError, encode_trial, scene_scales
from replay.shard import ReplayShard, check_shards, ensure_root, shard_path


@dataclass
class ReplayBatch:
    """A training batch, every tensor on the CPU and ready for the network."""

    scene: torch.Tensor
    """(B, 2, X, Y, Z) float32: TSDF/truncation in [-1, 1] (channel 0) and obstacle in [0, 1] (1)."""
    gripper: torch.Tensor
    """(B, 2, gX, gY, gZ) float32 gripper TSDF/truncation at the executed opening (0) and closed (1)."""
    action: torch.Tensor
    """(B, 4) int64 (i, j, k, s)."""
    label: torch.Tensor
    """(B,) float32, 1 = success."""
    score: torch.Tensor
    """(B,) float32 stored score at sampling time."""
    index: torch.Tensor
    """(B, 2) int64 (shard, trial number): pass to ReplayClient.update_scores."""
    balanced: bool
    """False when one class was empty and the other filled the batch."""


# --------------------------------------------------------------------------------------
# Backends: the only place that knows whether a shard is local or a Ray actor
# --------------------------------------------------------------------------------------


class _Done:
    """A finished local call: its value or its exception."""

    __slots__ = ("value", "error")

    def __init__(self, value: Any, error: BaseException | None) -> None:
        self.value, self.error = value, error


class _LocalBackend:
    def submit(self, shard: ReplayShard, method: str, *args: Any) -> _Done:
        try:
            return _Done(getattr(shard, method)(*args), None)
        except Exception as e:  # noqa: BLE001 - re-raised by get()
            return _Done(None, e)

    def get(self, pending: list[_Done]) -> list[Any]:
        for p in pending:
            if p.error is not None:
                raise p.error
        return [p.value for p in pending]

    def wait(self, pending: list[_Done], num_returns: int, timeout: float | None) -> list[_Done]:
        return list(pending)


class _RayBackend:
    def __init__(self) -> None:
        import ray

        self._ray = ray

    def submit(self, actor: Any, method: str, *args: Any) -> Any:
        return getattr(actor, method).remote(*args)

    def get(self, pending: list[Any]) -> list[Any]:
        return self._ray.get(list(pending))

    def wait(self, pending: list[Any], num_returns: int, timeout: float | None) -> list[Any]:
        ready, _ = self._ray.wait(list(pending), num_returns=num_returns, timeout=timeout)
        return ready


def _backend_for(shards: Sequence[Any]) -> _LocalBackend | _RayBackend:
    if not shards:
        raise ReplayError("replay client: no shards given")
    if all(isinstance(s, ReplayShard) for s in shards):
        return _LocalBackend()
    if any(isinstance(s, ReplayShard) for s in shards):
        raise ReplayError("replay client: shards mix in-process ReplayShard objects and Ray actor handles")
    return _RayBackend()


# --------------------------------------------------------------------------------------
# Client
# --------------------------------------------------------------------------------------


class ReplayClient:
    """Routes inserts round-robin over K shards and samples class-balanced batches from all of them."""

    def __init__(self, shards: Sequence[Any], cfg: Config, seed: int = 0, max_buffers: int = 3) -> None:
        self._shards = list(shards)
        self._backend = _backend_for(self._shards)
        self._max_inflight = cfg.replay.max_inflight
        infos = self._backend.get([self._backend.submit(s, "info") for s in self._shards])
        first = infos[0]
        for k, info in enumerate(infos):
            for key in ("scene_shape", "gripper_shape", "tsdf_levels", "schema_version"):
                if info.get(key) != first.get(key):
                    raise ReplaySchemaError(
                        f"shard {k}: attributes.{key}: {info.get(key)!r} differs from shard 0's {first.get(key)!r}"
                    )
        self.info = first
        self.levels = int(first["tsdf_levels"])
        self.scene_shape = tuple(first["scene_shape"])
        self.gripper_shape = tuple(first["gripper_shape"])
        self._rng = np.random.default_rng(seed)
        self._client_id = uuid.uuid4().int >> 65
        self._seq = 0
        self._next = self._client_id % len(self._shards)
        self._pending: deque = deque()
        self._pool = BufferPool(max_buffers)
        self.counters = {"inserts": 0, "samples": 0, "unbalanced_batches": 0, "redraws": 0, "score_updates": 0}

    @property
    def num_shards(self) -> int:
        return len(self._shards)

    def sampler_state(self) -> dict:
        """State of the generator that draws sample batches (kept in learner checkpoints)."""
        return self._rng.bit_generator.state

    def set_sampler_state(self, state: dict) -> None:
        """Continue drawing batches from a :meth:`sampler_state`."""
        self._rng.bit_generator.state = state

    # ----------------------------------------------------------------------------------
    # Requests in flight
    # ----------------------------------------------------------------------------------

    def _submit_bounded(self, shard: Any, method: str, *args: Any) -> None:
        """Send a fire-and-forget request, first waiting while max_inflight requests are outstanding."""
        while len(self._pending) >= self._max_inflight:
            self._backend.get([self._pending.popleft()])
        self._pending.append(self._backend.submit(shard, method, *args))
        self._collect_finished()

    def _collect_finished(self) -> None:
        """Pop finished requests from the front of the queue; re-raise the first error."""
        if not self._pending:
            return
        ready = set(self._backend.wait(list(self._pending), len(self._pending), 0))
        while self._pending and self._pending[0] in ready:
            self._backend.get([self._pending.popleft()])

    def flush(self) -> None:
        """Wait for every outstanding insert and score update; raises the first error."""
        while self._pending:
            self._backend.get([self._pending.popleft()])

    @property
    def inflight(self) -> int:
        return len(self._pending)

    # ----------------------------------------------------------------------------------
    # Actor side
    # ----------------------------------------------------------------------------------

    def insert(self, trial: Trial) -> None:
        """Quantise ``trial`` here and send it to the next shard (round-robin)."""
        rec = encode_trial(trial, self.levels, (self._client_id, self._seq))
        self._seq += 1
        shard = self._shards[self._next]
        self._next = (self._next + 1) % len(self._shards)
        self._submit_bounded(shard, "insert_encoded", rec)
        self.counters["inserts"] += 1

    # ----------------------------------------------------------------------------------
    # Learner side
    # ----------------------------------------------------------------------------------

    def _gather_index(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        idx = self._backend.get([self._backend.submit(s, "index") for s in self._shards])
        shard_of = np.concatenate([np.full(len(d["trial_id"]), k, np.int64) for k, d in enumerate(idx)])
        ids = np.concatenate([d["trial_id"] for d in idx]).astype(np.int64)
        labels = np.concatenate([d["label"] for d in idx]).astype(bool)
        scores = np.concatenate([d["score"] for d in idx]).astype(np.float32)
        return shard_of, ids, labels, scores

    def sample(self, batch_size: int, rng: np.random.Generator | None = None) -> ReplayBatch:
        """A batch of ``batch_size`` trials (even), half successes and half failures, surprise-ranked.

        Trials evicted or found corrupt between the index and the read are replaced by fresh
        draws of the same class. Raises ReplayEmptyError when no shard holds a readable trial.
        ``rng``: the generator that draws (default the client's own, whose state checkpoints keep).
        """
        rng = self._rng if rng is None else rng
        shard_of, ids, labels, scores = self._gather_index()
        if not len(ids):
            raise ReplayEmptyError(f"replay: no readable trial in {len(self._shards)} shard(s)")
        excluded = np.zeros(len(ids), bool)
        parts: dict[int, dict] = {}
        pos, balanced = draw_balanced(labels, scores, batch_size, rng)
        chosen = np.empty(0, np.int64)
        while True:  # every round excludes its unreadable trials for good, so the rounds end
            got = self._read(shard_of, ids, pos, parts)
            excluded[pos[~got]] = True
            chosen = np.concatenate([chosen, pos[got]])
            lost = pos[~got]
            if not len(lost):
                break
            self.counters["redraws"] += 1
            need_success, need_failure = int(labels[lost].sum()), int((~labels[lost]).sum())
            taken = excluded.copy()
            taken[chosen] = True
            # a class with enough untaken trials draws without repeats; a short one may repeat
            short = np.where(labels, (~taken & labels).sum() < need_success, (~taken & ~labels).sum() < need_failure)
            pos, ok = draw_counts(  # ReplayEmptyError once every trial is excluded
                labels, scores, need_success, need_failure, rng, exclude=excluded | (taken & ~short),
            )
            balanced &= ok
        self.counters["samples"] += 1
        self.counters["unbalanced_batches"] += int(not balanced)
        rng.shuffle(chosen)
        return self._assemble(chosen, shard_of, ids, parts, balanced)

    def _read(self, shard_of: np.ndarray, ids: np.ndarray, positions: np.ndarray, parts: dict) -> np.ndarray:
        """Read ``positions`` from their shards in parallel; returns which were read."""
        got = np.zeros(len(positions), bool)
        by_shard: dict[int, list[int]] = {}
        for b, p in enumerate(positions):
            by_shard.setdefault(int(shard_of[p]), []).append(b)
        keys = list(by_shard)
        pending = [self._backend.submit(self._shards[k], "read", ids[positions[by_shard[k]]]) for k in keys]
        for k, data in zip(keys, self._backend.get(pending)):
            where = {int(t): i for i, t in enumerate(data["trial_id"])}
            for b in by_shard[k]:
                i = where.get(int(ids[positions[b]]))
                if i is not None:
                    got[b] = True
                    parts[int(positions[b])] = {
                        "tsdf": data["tsdf"][i],
                        "obstacle": data["obstacle"][i],
                        "gripper": data["gripper"][i],
                        "action": data["action"][i],
                        "label": data["label"][i],
                        "score": data["score"][i],
                    }
        return got

    def _assemble(self, chosen, shard_of, ids, parts, balanced) -> ReplayBatch:
        """Dequantise the read codes into (pooled) float32 arrays and wrap them as tensors.

        numpy, single-threaded: torch's intra-op threads stall badly on a busy 2-core machine.
        """
        b = len(chosen)
        scene = self._pool.take((b, 2) + self.scene_shape, np.float32)
        gripper = self._pool.take((b, 2) + self.gripper_shape, np.float32)
        s_scale = scene_scales(self.levels)
        g_scale = np.float32(1.0 / self.levels)
        action = np.empty((b, 4), np.int64)
        label = np.empty(b, np.float32)
        score = np.empty(b, np.float32)
        for i, p in enumerate(chosen):
            part = parts[int(p)]
            np.multiply(part["tsdf"], s_scale[0], out=scene[i, 0])
            if part["obstacle"] is None:
                scene[i, 1].fill(0.0)  # no obstacle voxel (single and multi scenes): nothing stored, nothing read
            else:
                np.multiply(part["obstacle"], s_scale[1], out=scene[i, 1])
            np.multiply(part["gripper"], g_scale, out=gripper[i])
            action[i] = part["action"]
            label[i] = float(part["label"])
            score[i] = part["score"]
        index = np.stack([shard_of[chosen], ids[chosen]], axis=1)
        return ReplayBatch(
            scene=torch.from_numpy(scene),
            gripper=torch.from_numpy(gripper),
            action=torch.from_numpy(action),
            label=torch.from_numpy(label),
            score=torch.from_numpy(score),
            index=torch.from_numpy(index),
            balanced=balanced,
        )

    def update_scores(self, index, scores) -> None:
        """Send refreshed scores: ``index`` (B, 2) int64 from a batch, ``scores`` (B,) in [0, 1]."""
        idx = np.asarray(index.cpu() if isinstance(index, torch.Tensor) else index, np.int64)
        sc = np.asarray(scores.detach().cpu() if isinstance(scores, torch.Tensor) else scores, np.float32)
        if idx.ndim != 2 or idx.shape[1] != 2 or sc.shape != (idx.shape[0],):
            raise ValueError(f"update_scores: index must be (B, 2) and scores (B,), got {idx.shape} and {sc.shape}")
        for k in np.unique(idx[:, 0]):
            m = idx[:, 0] == k
            self._submit_bounded(self._shards[int(k)], "update_scores", idx[m, 1], sc[m])
        self.counters["score_updates"] += int(idx.shape[0])

    # ----------------------------------------------------------------------------------
    # Introspection
    # ----------------------------------------------------------------------------------

    def size(self) -> int:
        """Readable visible trials over all shards."""
        return int(sum(self._backend.get([self._backend.submit(s, "size") for s in self._shards])))

    def run_marks(self) -> dict:
        """:meth:`ReplayShard.run_marks` over all shards: ``episode_ends`` {actor id: one past its
        largest episode number} and the largest ``policy_version`` (-1: none)."""
        ends: dict[int, int] = {}
        version = -1
        for part in self._backend.get([self._backend.submit(s, "run_marks") for s in self._shards]):
            for a, e in part["episode_ends"].items():
                ends[int(a)] = max(ends.get(int(a), 0), int(e))
            version = max(version, int(part["policy_version"]))
        return {"episode_ends": ends, "policy_version": version}

    def stats(self) -> dict:
        """Per-shard counters and totals, plus this client's counters."""
        per = self._backend.get([self._backend.submit(s, "stats") for s in self._shards])
        keys = ("visible", "successes", "failures", "lost", "corrupt", "corrupt_skipped", "duplicates_skipped")
        total = {k: sum(d[k] for d in per) for k in keys}
        return {"total": total, "shards": per, "client": dict(self.counters), "inflight": len(self._pending)}


# --------------------------------------------------------------------------------------
# Building the shards (once); where they live is the caller's choice
# --------------------------------------------------------------------------------------


def open_local_shards(root: str | Path, cfg: Config, read_only: bool = False) -> list[ReplayShard]:
    """K = cfg.replay.shards in-process shards under ``root`` (created on first use, reopened after)."""
    k = cfg.replay.shards
    if not read_only:
        ensure_root(root, k)
    return [
        ReplayShard(shard_path(root, i), cfg, shard_index=i, num_shards=k, read_only=read_only) for i in range(k)
    ]


def remote_shard_class(cfg: Config):
    """ReplayShard as a restartable Ray actor class (made on call, never at import)."""
    import ray

    return ray.remote(
        max_restarts=-1,
        max_task_retries=cfg.replay.actor_task_retries,
        num_cpus=cfg.replay.shard_num_cpus,
    )(ReplayShard)


def start_remote_shards(root: str | Path, cfg: Config, name_prefix: str | None = None) -> list[Any]:
    """K shard actors under ``root``; a restarted actor reopens its group and keeps every committed trial.

    Existing shards are first opened here with ``cfg`` (:func:`replay.shard.check_shards`): one
    its config cannot take raises in one line, instead of failing in its actor's constructor,
    which Ray reports as tracebacks and restarts.
    """
    k = cfg.replay.shards
    check_shards(root, cfg)
    ensure_root(root, k)
    cls = remote_shard_class(cfg)
    handles = []
    for i in range(k):
        opts = {"name": f"{name_prefix}_{i}"} if name_prefix else {}
        handles.append(cls.options(**opts).remote(str(shard_path(root, i)), cfg, shard_index=i, num_shards=k))
    return handles
