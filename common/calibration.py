"""Per-gripper score calibration: one logit shift per gripper, fitted to that gripper's grasp trials.

The network's success probability is not calibrated across gripper kinds: a held-out gripper can
score as high as the best one and lift far less often (docs/RESULTS.md, "Calibrating the scores
across grippers"). The ``adagrasp`` policy compares scores across grippers, so an overrated gripper
is chosen where a better one was at hand. A calibration maps the score p of gripper g to

    p' = sigmoid(logit(p) + b_g),

with b_g the maximum a posteriori shift given that gripper's trials (score p_n, success y_n): the
likelihood prod_n Bernoulli(y_n; sigmoid(logit(p_n) + b_g)) times the prior N(0, prior_sigma^2).
The map is monotone for each gripper, so the best grasp of one gripper does not change; only the
comparison across grippers does. The trials come from ``evaluate --policy fix-gripper`` runs of the
same checkpoint (its greedy grasps, the ones ``adagrasp`` compares), on scenes other than those
evaluated: the usual source is a few dozen grasps per gripper on the training objects.

Call loop::

    cal = calibration_from_result("cal.json", read_result("cal.json"))   # evaluate --json output
    probs = cal.apply(probs, ["wsg_50", "g1_three_finger"])                # (G, ...) probabilities
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PRIOR_SIGMA = 2.0
"""Standard deviation (logits) of the zero-mean Gaussian prior on each gripper's shift: weak enough
that 40 trials move a shift by several logits, strong enough that a gripper which never failed
(or never succeeded) gets a finite shift."""
PROB_CLIP = 1e-12
"""Probabilities are clipped to [PROB_CLIP, 1 - PROB_CLIP] before the logit: below the spacing of
float32 scores near 1 (6e-8), so distinct network scores keep distinct logits."""


class CalibrationError(ValueError):
    """Bad calibration input (trials, gripper names, result file); one line naming the field."""


def logit(p: np.ndarray) -> np.ndarray:
    """log(p / (1 - p)) of probabilities ``p`` (any shape), clipped by :data:`PROB_CLIP`."""
    p = np.clip(np.asarray(p, dtype=np.float64), PROB_CLIP, 1.0 - PROB_CLIP)
    return np.log(p) - np.log1p(-p)


def sigmoid(z: np.ndarray) -> np.ndarray:
    """1 / (1 + exp(-z)), elementwise, without overflow warnings."""
    z = np.asarray(z, dtype=np.float64)
    return np.exp(-np.logaddexp(0.0, -z))


def fit_shift(scores, successes, prior_sigma: float = PRIOR_SIGMA) -> float:
    """The MAP logit shift b of trials with predicted probabilities ``scores`` (N,) and outcomes
    ``successes`` (N,) bool under the prior N(0, prior_sigma^2). The log posterior is strictly
    concave in b, so bisection on its derivative finds the one maximum; with no trial it is 0."""
    z = logit(scores).ravel()
    y = np.asarray(successes, dtype=np.float64).ravel()
    if z.shape != y.shape:
        raise CalibrationError(f"trials: {z.size} scores but {y.size} outcomes")
    if not prior_sigma > 0:
        raise CalibrationError(f"prior_sigma: expected a positive value, got {prior_sigma!r}")

    def slope(b: float) -> float:
        return float(np.sum(y - sigmoid(z + b)) - b / prior_sigma**2)

    # at the maximum b / prior_sigma^2 = sum(y - p), which lies in [-N, N]: |b| <= N prior_sigma^2
    hi = z.size * prior_sigma**2 + 1.0
    lo = -hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if slope(mid) > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@dataclass(frozen=True)
class GripperFit:
    """The calibration of one gripper and the trials it came from."""

    shift: float
    """b_g, logits added to the gripper's score logits."""
    trials: int
    """Number of grasp trials fitted."""
    successes: int
    """Successful trials among them."""
    mean_score: float
    """Mean predicted success probability of the trials (before calibration)."""
    scenes: int = 0
    """Number of scenes (episode records) the trials came from: the calibration budget (a scene of
    a pile gives several trials); 0 when not known (a fit from bare trials)."""


@dataclass(frozen=True)
class Calibration:
    """Logit shifts per gripper name, and where they came from."""

    grippers: dict[str, GripperFit]
    """Registered gripper name -> its fit."""
    prior_sigma: float
    """Prior standard deviation the shifts were fitted with (logits)."""
    source: str
    """The result file the trials came from."""
    sha256: str = ""
    """SHA-256 of that file's bytes, when it was read from one."""

    def shifts(self, names: list[str]) -> np.ndarray:
        """(G,) float64 shifts (logits) of the grippers ``names``, in that order."""
        missing = [n for n in names if n not in self.grippers]
        if missing:
            raise CalibrationError(
                f"{self.source}: episode_results: no trials of gripper {missing[0]} (it has {sorted(self.grippers)})"
            )
        return np.array([self.grippers[n].shift for n in names], dtype=np.float64)

    def apply(self, probs: np.ndarray, names: list[str]) -> np.ndarray:
        """``probs`` (G, ...) float success probabilities of grippers ``names`` -> calibrated, float64."""
        return apply_shifts(probs, self.shifts(names))

    def to_dict(self) -> dict:
        """JSON-ready record of the calibration."""
        return {
            "source": self.source,
            "sha256": self.sha256,
            "prior_sigma": self.prior_sigma,
            "grippers": {
                n: {"shift": f.shift, "trials": f.trials, "successes": f.successes, "mean_score": f.mean_score,
                    "scenes": f.scenes}
                for n, f in self.grippers.items()
            },
        }


def apply_shifts(probs: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """sigmoid(logit(probs[g]) + shifts[g]) for ``probs`` (G, ...) float and ``shifts`` (G,) logits;
    float64 (float32 would round scores near 1 together and break the order within a gripper),
    the shape of ``probs``."""
    probs = np.asarray(probs)
    shifts = np.asarray(shifts, dtype=np.float64)
    if probs.ndim < 1 or shifts.shape != (probs.shape[0],):
        raise CalibrationError(f"shifts: expected one per gripper ({probs.shape[:1]}), got shape {shifts.shape}")
    expand = shifts.reshape((-1,) + (1,) * (probs.ndim - 1))
    return sigmoid(logit(probs) + expand)


def fit_calibration(trials: dict[str, list[tuple[float, bool]]], source: str,
                    prior_sigma: float = PRIOR_SIGMA, scenes: dict[str, int] | None = None) -> Calibration:
    """A calibration from (score, success) trials per gripper name; ``source`` names their origin,
    ``scenes`` the number of scenes each gripper's trials came from (0 when not given)."""
    fits = {}
    for name, rows in trials.items():
        if not rows:
            raise CalibrationError(f"{source}: episode_results: no trials of gripper {name}")
        scores = np.array([s for s, _ in rows], dtype=np.float64)
        ok = np.array([bool(y) for _, y in rows])
        if not np.all((scores >= 0.0) & (scores <= 1.0)):
            raise CalibrationError(f"{source}: score: gripper {name} has scores outside [0, 1]")
        fits[name] = GripperFit(fit_shift(scores, ok, prior_sigma), len(rows), int(ok.sum()), float(scores.mean()),
                                (scenes or {}).get(name, 0))
    return Calibration(fits, float(prior_sigma), source)


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of the bytes of the file ``path``: the digest a calibration records of its
    source (:attr:`Calibration.sha256`) and the one its source is checked against."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def calibration_from_result(path: str, data: dict, prior_sigma: float = PRIOR_SIGMA) -> Calibration:
    """The calibration fitted to every attempt of an evaluation result ``data`` (read from ``path``
    by ``actors.evaluate.read_result``) of the ``fix-gripper`` policy; one-line errors name the
    file and the key."""
    if data.get("policy") != "fix-gripper":
        raise CalibrationError(
            f"{path}: policy: a calibration is fitted to fix-gripper trials (the greedy grasps adagrasp "
            f"compares), got {data.get('policy')!r}"
        )
    episodes = data.get("episode_results")
    if not isinstance(episodes, list) or not episodes:
        raise CalibrationError(f"{path}: episode_results: missing or empty")
    trials: dict[str, list[tuple[float, bool]]] = {}
    scenes: dict[str, int] = {}
    for n, record in enumerate(episodes):
        names = set()
        try:
            for t in record["trials"]:
                if not isinstance(t["success"], bool):
                    raise ValueError(f"success: expected true or false, got {t['success']!r}")
                names.add(str(t["gripper"]))
                trials.setdefault(str(t["gripper"]), []).append((float(t["score"]), t["success"]))
        except (KeyError, TypeError, ValueError) as e:
            raise CalibrationError(f"{path}: episode_results[{n}]: malformed trial ({type(e).__name__}: {e})") from None
        for name in names:
            scenes[name] = scenes.get(name, 0) + 1
    return fit_calibration(trials, str(path), prior_sigma, scenes)
