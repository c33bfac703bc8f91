"""Class-balanced, surprise-ranked draws and the assembly of ready torch batches.

The draw follows the AdaGrasp paper's training code: half the batch from successes, half from
failures; within a class, trials are sorted by surprise |label - score| (ascending) and
trial at rank r (1 = least surprising) is drawn with probability r / sum(1..n), without
replacement. Tied surprises share the mean of their ranks (a score that saturates at 0 or 1
ties many trials), so the order the shards list trials in weighs nothing. A class with fewer
trials than its half batch is drawn with replacement; an empty class hands its half to the other
class (the batch says so in ``balanced``).

Usage::

    pos, balanced = draw_balanced(labels, scores, 8, rng)
    pool = BufferPool()
    scene = pool.take((8, 2, X, Y, Z), np.float32)   # reused once no tensor refers to it
"""

from __future__ import annotations

import sys

import numpy as np

from replay.schema import ReplayEmptyError


def rank_probabilities(surprise: np.ndarray) -> np.ndarray:
    """(n,) float64 draw probabilities: proportional to the rank of each surprise (1 = smallest;
    equal surprises share their mean rank)."""
    n = len(surprise)
    order = np.argsort(surprise, kind="stable")
    ordered = np.asarray(surprise)[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    ends = np.r_[starts[1:], n]
    ranks = np.empty(n, np.float64)
    ranks[order] = np.repeat((starts + ends + 1) / 2, ends - starts)  # mean of ranks starts+1..ends
    return ranks / ranks.sum()


def draw_class(
    candidates: np.ndarray, surprise: np.ndarray, count: int, rng: np.random.Generator
) -> np.ndarray:
    """``count`` positions from ``candidates`` (n,), rank-weighted by ``surprise`` (n,)."""
    if count <= 0:
        return np.empty(0, np.int64)
    p = rank_probabilities(surprise)
    replace = len(candidates) < count
    return candidates[rng.choice(len(candidates), size=count, replace=replace, p=p)]


def draw_counts(
    labels: np.ndarray,
    scores: np.ndarray,
    n_success: int,
    n_failure: int,
    rng: np.random.Generator,
    exclude: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """``n_success`` successes and ``n_failure`` failures, as positions into ``labels``/``scores`` (n,).

    ``exclude`` (n,) bool removes entries from the draw. A class with no candidate hands its count
    to the other one; the returned flag is False then. Positions come back shuffled.
    """
    labels = np.asarray(labels, bool)
    scores = np.asarray(scores, np.float64)
    assert labels.shape == scores.shape and labels.ndim == 1, (labels.shape, scores.shape)
    allowed = np.ones(len(labels), bool) if exclude is None else ~np.asarray(exclude, bool)
    groups = [np.flatnonzero(allowed & labels), np.flatnonzero(allowed & ~labels)]
    counts = [int(n_success), int(n_failure)]
    if not len(groups[0]) and not len(groups[1]):
        raise ReplayEmptyError("replay: no readable trial left to sample from")
    balanced = True
    for cls in (0, 1):
        if counts[cls] and not len(groups[cls]):
            counts[1 - cls] += counts[cls]
            counts[cls] = 0
            balanced = False
    picks = []
    for cls, (cand, count) in enumerate(zip(groups, counts)):
        target = 1.0 if cls == 0 else 0.0
        picks.append(draw_class(cand, np.abs(target - scores[cand]), count, rng))
    out = np.concatenate(picks).astype(np.int64)
    rng.shuffle(out)
    return out, balanced


def draw_balanced(
    labels: np.ndarray,
    scores: np.ndarray,
    batch_size: int,
    rng: np.random.Generator,
    exclude: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """Positions (batch_size,) int64, half successes and half failures (see :func:`draw_counts`)."""
    assert batch_size >= 2 and batch_size % 2 == 0, f"batch_size must be even and >= 2, got {batch_size}"
    half = batch_size // 2
    return draw_counts(labels, scores, half, half, rng, exclude)


class BufferPool:
    """Large output arrays reused once nothing else refers to them.

    A batch at paper scale is ~150 MB of float32; fresh memory of that size costs more in page
    faults than the decoding itself. ``take`` hands out an array that no live tensor or view
    refers to (checked by reference count: ``torch.from_numpy`` keeps the array alive as long as
    any tensor on it exists), so a buffer is never overwritten while someone still uses it.
    """

    def __init__(self, max_buffers: int = 3) -> None:
        self.max_buffers = max_buffers
        self._buffers: list[np.ndarray] = []

    def take(self, shape: tuple[int, ...], dtype) -> np.ndarray:
        dtype = np.dtype(dtype)
        for i in range(len(self._buffers)):
            # references while free: the pool's list and getrefcount's argument
            if (
                self._buffers[i].shape == shape
                and self._buffers[i].dtype == dtype
                and sys.getrefcount(self._buffers[i]) <= 2
            ):
                return self._buffers[i]
        buf = np.empty(shape, dtype)
        if len(self._buffers) < self.max_buffers:
            self._buffers.append(buf)
        else:
            self._buffers[0] = buf
            self._buffers.append(self._buffers.pop(0))
        return buf
