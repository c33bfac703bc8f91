"""``python -m launcher evaluate compare A.json B.json``: two evaluation results, paired on their scenes.

Every policy of a cell sees the same scenes (docs/EVALUATION.md, "Seeds"), so two rows differ
by chance far less than two independent samples would: the same hard scene is hard for both.
This module pairs the two results on the scenes they share and says whether B's rate differs
from A's beyond chance, in two ways:

- **Exact paired permutation test over units.** A unit is one (gripper, scene) when both
  results are per-gripper policies (paired on the grippers they share), else one scene, where a
  per-gripper result counts the mean of its grippers' successful grasps in that scene. Under
  the null hypothesis each unit's difference B - A is as likely to have either sign; the
  two-sided p-value is the probability, over all 2^U sign flips, of a summed difference at
  least as far from zero as the observed one (computed exactly, by convolution). With every
  difference 0 or +-1 (one grasp per unit) it is McNemar's exact test. It weighs each unit by
  its difference, so a scene that A's grippers mostly lift and B misses counts for more than
  one that B lifts and A's grippers mostly miss; it treats units as independent.
- **Scene bootstrap of the rate difference.** The table's rate of each result (per-gripper
  policies: the mean of the per-gripper successes / attempts; ``adagrasp``: its successes /
  attempts) is recomputed on scenes drawn with replacement, the same draw for both results;
  the 2.5 and 97.5 percentiles of B - A are its 95% interval. Scenes are the resampling unit,
  so grippers and attempts of one scene stay together.

The scenes must be the same scenes: the same scene kind and object set, and for every shared
scene seed the same objects in the same roles; otherwise the comparison stops with one line
naming the file and the key.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass

import numpy as np

from actors.evaluate import EvaluationError, _write_atomic, read_result, row_label

BOOTSTRAP_RESAMPLES = 10_000
"""Scene resamples of the bootstrap interval."""
COMPARE_FORMAT = "adagrasp-scale-comparison/1"
"""Value of the ``format`` key of a comparison JSON."""


@dataclass(frozen=True)
class Side:
    """One result restricted to the paired scenes and grippers."""

    path: str
    """Result file."""
    summary: dict
    """The result JSON."""
    grippers: list[str | None]
    """Row keys of the arrays: gripper names (per-gripper policies) or [None] (``adagrasp``)."""
    successes: np.ndarray
    """(G, E) int64 successful grasps of gripper row g in paired scene e."""
    attempts: np.ndarray
    """(G, E) int64 grasps of gripper row g in paired scene e (>= 1 each)."""

    @property
    def pooled(self) -> bool:
        """True when the table's rate is successes / attempts over everything (``adagrasp``)."""
        return self.grippers == [None]


def table_rate(side: Side, weights: np.ndarray) -> np.ndarray:
    """The table's rate of ``side`` for each row of ``weights``.

    ``weights``: (B, E) float64 count of each paired scene in each of B resamples (all ones:
    the paired scenes once). Returns (B,) float64 rates.
    """
    assert weights.ndim == 2 and weights.shape[1] == side.successes.shape[1], weights.shape
    s = side.successes.astype(np.float64) @ weights.T
    a = side.attempts.astype(np.float64) @ weights.T
    if side.pooled:
        return s.sum(axis=0) / a.sum(axis=0)
    return (s / a).mean(axis=0)


def sign_flip_p(diffs: np.ndarray, scale: int = 1) -> float:
    """Two-sided exact p-value of the paired sign-flip permutation test of ``diffs``.

    ``diffs``: (U,) float64 per-unit differences B - A, each a multiple of 1 / ``scale``.
    Returns P(|sum of s_u * diffs_u| >= |sum of diffs|) over independent fair signs s_u; 1.0
    when every difference is 0.
    """
    assert diffs.ndim == 1 and scale >= 1, (diffs.shape, scale)
    steps = np.rint(np.abs(diffs) * scale).astype(np.int64)
    assert np.allclose(steps, np.abs(diffs) * scale), "differences are not multiples of 1/scale"
    observed = abs(int(np.rint(diffs.sum() * scale)))
    total = int(steps.sum())
    prob = np.zeros(2 * total + 1)
    prob[total] = 1.0
    for w in steps[steps > 0]:
        prob = 0.5 * (np.roll(prob, w) + np.roll(prob, -w))
    sums = np.abs(np.arange(-total, total + 1))
    return float(min(1.0, prob[sums >= observed].sum()))


def _episodes(path: str, summary: dict) -> dict[tuple[str | None, int], dict]:
    records = summary.get("episode_results")
    if not isinstance(records, list) or not records:
        raise EvaluationError(f"{path}: episode_results: missing or empty (a result written by evaluate --json)")
    out: dict[tuple[str | None, int], dict] = {}
    for i, r in enumerate(records):
        try:
            key = (r["gripper"], int(r["scene_seed"]))
            r["successes"], r["attempts"], r["objects"]
        except (KeyError, TypeError, ValueError):
            raise EvaluationError(
                f"{path}: episode_results[{i}]: needs gripper, scene_seed, successes, attempts and objects"
            ) from None
        if r["attempts"] < 1:
            raise EvaluationError(f"{path}: episode_results[{i}].attempts: {r['attempts']}, expected >= 1")
        out[key] = r
    return out


def _side(path: str, summary: dict, episodes: dict, grippers: list[str | None], scenes: list[int]) -> Side:
    succ = np.array([[episodes[(g, s)]["successes"] for s in scenes] for g in grippers], dtype=np.int64)
    att = np.array([[episodes[(g, s)]["attempts"] for s in scenes] for g in grippers], dtype=np.int64)
    return Side(path, summary, grippers, succ, att)


def _grippers(path: str, episodes: dict, only: list[str] | None) -> list[str | None]:
    names = sorted({g for g, _ in episodes}, key=lambda g: (g is None, g or ""))
    if names == [None] or only is None:
        return names
    missing = [g for g in only if g not in names]
    if missing:
        raise EvaluationError(f"{path}: --gripper {','.join(missing)}: not among its grippers {names}")
    return [g for g in names if g in only]


def pair(path_a: str, a: dict, path_b: str, b: dict, only: list[str] | None = None) -> tuple[Side, Side]:
    """Restrict results ``a`` and ``b`` to the scenes (and, both per-gripper, the grippers) they share.

    ``only``: gripper names to keep on the per-gripper side(s) (None: all). Raises
    :class:`EvaluationError` (one line naming the file and the key) when they are not the same
    scenes or share none.
    """
    for key in ("scene", "objects"):
        if a[key] != b[key]:
            raise EvaluationError(f"{path_b}: {key}: {b[key]!r}, but {path_a} has {a[key]!r}: not the same scenes")
    ea, eb = _episodes(path_a, a), _episodes(path_b, b)
    ga, gb = _grippers(path_a, ea, only), _grippers(path_b, eb, only)
    if None not in ga and None not in gb:
        ga = gb = [g for g in ga if g in gb]
        if not ga:
            raise EvaluationError(f"{path_b}: per_gripper: no gripper in common with {path_a}")
    seeds_a = [s for _, s in ea]
    common = [s for s in dict.fromkeys(seeds_a) if all((g, s) in ea for g in ga) and all((g, s) in eb for g in gb)]
    if not common:
        raise EvaluationError(f"{path_b}: scene_seeds: no scene in common with {path_a}")
    for s in common:
        objects_a = next(ea[(g, s)]["objects"] for g in ga)
        for g in gb:
            if eb[(g, s)]["objects"] != objects_a:
                raise EvaluationError(
                    f"{path_b}: episode_results (scene_seed {s}, gripper {g}).objects: not the objects of "
                    f"{path_a}'s scene {s} (another simulation or object set)"
                )
    return _side(path_a, a, ea, ga, common), _side(path_b, b, eb, gb, common)


def _unit_counts(sa: Side, sb: Side) -> tuple[np.ndarray, np.ndarray, int]:
    """Per paired unit, A's and B's successful grasps, (U,) float64 each, and the least common
    multiple of the number of grippers each is averaged over (the differences are multiples of
    its inverse)."""
    if not sa.pooled and not sb.pooled:
        return sa.successes.ravel().astype(np.float64), sb.successes.ravel().astype(np.float64), 1
    scale = math.lcm(1 if sa.pooled else len(sa.grippers), 1 if sb.pooled else len(sb.grippers))
    return sa.successes.mean(axis=0), sb.successes.mean(axis=0), scale


def compare(sa: Side, sb: Side, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> dict:
    """The paired comparison of B against A (JSON-ready); ``seed`` seeds the bootstrap's generator."""
    scenes = sa.successes.shape[1]
    assert sb.successes.shape[1] == scenes and resamples >= 1
    ua, ub, scale = _unit_counts(sa, sb)
    better, worse = int((ub > ua).sum()), int((ub < ua).sum())
    ones = np.ones((1, scenes))
    rate_a, rate_b = float(table_rate(sa, ones)[0]), float(table_rate(sb, ones)[0])
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, scenes, size=(resamples, scenes))
    weights = np.zeros((resamples, scenes))
    np.add.at(weights, (np.arange(resamples)[:, None], draws), 1.0)
    diffs = table_rate(sb, weights) - table_rate(sa, weights)
    low, high = np.percentile(diffs, [2.5, 97.5])

    def side(s: Side, rate: float) -> dict:
        return {
            "path": s.path,
            "row": row_label(s.summary),
            "checkpoint": s.summary.get("checkpoint"),
            "cameras": s.summary.get("cameras"),
            "grippers": s.grippers,
            "rate": rate,
            "file_rate": s.summary["rate"],
            "successes": int(s.successes.sum()),
            "attempts": int(s.attempts.sum()),
        }

    return {
        "format": COMPARE_FORMAT,
        "scene": sa.summary["scene"],
        "objects": sa.summary["objects"],
        "scenes": scenes,
        "unit": "(gripper, scene)" if not sa.pooled and not sb.pooled else "scene",
        "a": side(sa, rate_a),
        "b": side(sb, rate_b),
        "units": int(ua.size),
        "b_better": better,
        "b_worse": worse,
        "same": int(ua.size) - better - worse,
        "p_value": sign_flip_p(ub - ua, scale),
        "test": "exact paired sign-flip permutation test of the summed per-unit difference in successful grasps",
        "rate_difference": rate_b - rate_a,
        "ci95": [float(low), float(high)],
        "bootstrap": {"resamples": resamples, "seed": seed, "unit": "scene"},
    }


def report(c: dict) -> str:
    """Three lines of text for a comparison from :func:`compare`."""

    def side(tag: str, s: dict) -> str:
        return (f"  {tag} {s['row']}: rate {s['rate']:.3f} ({s['successes']}/{s['attempts']} grasps), "
                f"{s['path']}")

    lo, hi = c["ci95"]
    return "\n".join([
        f"compare: {c['scene']} scenes of objects {c['objects']}, {c['scenes']} paired scenes, "
        f"{c['units']} units of {c['unit']}",
        side("A", c["a"]),
        side("B", c["b"]),
        f"  B - A: {c['rate_difference']:+.3f} (95% interval {lo:+.3f} to {hi:+.3f}, "
        f"{c['bootstrap']['resamples']} scene resamples); B better in {c['b_better']} units, worse in "
        f"{c['b_worse']}, same in {c['same']}: paired permutation test p = {c['p_value']:.3g}",
    ]) + "\n"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m launcher evaluate compare",
        description="Compare two evaluation results of one cell on the scenes they share: exact paired "
        "permutation test over units and a scene-bootstrap 95%% interval of the rate difference B - A.",
    )
    ap.add_argument("a", metavar="A.json", help="result written by evaluate --json (the baseline)")
    ap.add_argument("b", metavar="B.json", help="result written by evaluate --json (compared against A)")
    ap.add_argument("--gripper", default=None, metavar="NAME[,NAME...]",
                    help="per-gripper results: keep only these grippers")
    ap.add_argument("--resamples", type=int, default=BOOTSTRAP_RESAMPLES, help="bootstrap scene resamples")
    ap.add_argument("--seed", type=int, default=0, help="seed of the bootstrap's generator")
    ap.add_argument("--json", default=None, help="write the comparison here")
    return ap


def compare_cli(argv: list[str]) -> dict:
    """``evaluate compare``: parse ``argv``, print :func:`report`, write --json; returns the comparison."""
    args = _parser().parse_args(argv)
    if args.resamples < 1:
        raise EvaluationError(f"--resamples {args.resamples}: expected >= 1")
    only = [g.strip() for g in args.gripper.split(",")] if args.gripper else None
    sa, sb = pair(args.a, read_result(args.a), args.b, read_result(args.b), only)
    if only is not None and sa.pooled and sb.pooled:
        raise EvaluationError(f"--gripper {args.gripper}: both results are adagrasp runs, which choose the gripper")
    result = compare(sa, sb, args.resamples, args.seed)
    print(report(result), end="")
    if args.json:
        _write_atomic(args.json, json.dumps(result, indent=1) + "\n")
    return result
