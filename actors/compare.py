"""``python -m launcher evaluate compare A.json B.json``: two evaluation results, paired on their scenes.

Every policy of a cell sees the same scenes (docs/EVALUATION.md, "Seeds"), so two rows differ
by chance far less than two independent samples would: the same hard scene is hard for both.
This module pairs the two results on the scenes they share (and, both per-gripper, on the
grippers they share) and says whether B's table rate differs from A's beyond chance. The
scene is the unit throughout: the grippers and attempts of one scene stay together.

- **Rate.** Each result's rate as the table has it (per-gripper policies: the mean over the
  grippers of successes / attempts; ``adagrasp``: successes / attempts), on the paired scenes.
- **Interval.** The rates are recomputed on scenes drawn with replacement, the same draw for
  both results; the 2.5 and 97.5 percentiles of B - A are its 95% interval.
- **Permutation test** (when A and B are exchangeable: the same grippers, or both ``adagrasp``).
  Under the null hypothesis that the two policies do equally well, swapping A's and B's records
  of a scene changes nothing; the two-sided p-value is the share of scene swaps whose rate
  difference is at least as far from zero as the observed one. Exact (by convolution) when
  every episode has one attempt (single-object scenes), where the rate difference is the mean of
  per-scene differences; else estimated from random swaps, p = (1 + hits) / (1 + draws). A
  per-gripper result against an ``adagrasp`` one has no swap (one chooses among the grippers the
  other runs one by one): the interval alone decides.

- **Pooled seeds** (``--also A2.json B2.json``, repeatable): results of the same two rows on
  other scenes (another ``--seed``) are paired the same way and their scenes joined to the
  first pair's, so one interval and one test cover every scene. The scenes of different pairs
  must differ (no scene seed twice), and each side must be the same row, model, cameras and
  grippers in every pair.

The scenes must be the same scenes: the same scene kind and object set, and for every shared
scene seed the same objects in the same roles in every record of both files; both files must
have the same attempt cap and gripper scale (when they record them); an ``adagrasp``
result compared with a per-gripper one must choose among that result's grippers. Otherwise the
comparison stops with one line naming the file and the key.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from actors.evaluate import EvaluationError, check_output_path, read_result, row_label, write_json

BOOTSTRAP_RESAMPLES = 10_000
"""Scene resamples of the bootstrap interval."""
COMPARE_FORMAT = "adagrasp-scale-comparison/1"
"""Value of the ``format`` key of a comparison JSON."""
_RECORD_KEYS = ("gripper", "scene_seed", "successes", "attempts", "objects")
"""Keys of an episode record that a comparison reads."""


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
    dropped: tuple[int, ...] = ()
    """Scene seeds both files ran whose objects differ between records, left out (``drop_mismatched``)."""
    unpaired: int = 0
    """Scene seeds of this file left out: not run by the other file, or not for every paired gripper, or dropped."""
    parts: tuple[tuple[str, dict], ...] = ()
    """(path, result JSON) of each file pooled into this side (:func:`pool`); () for one file."""
    scene_seeds: tuple[int, ...] = ()
    """(E,) the scene seed of each paired scene (column of the arrays)."""

    @property
    def pooled(self) -> bool:
        """True when the table's rate is successes / attempts over everything (``adagrasp``)."""
        return self.grippers == [None]


def _rates(successes: np.ndarray, attempts: np.ndarray, pooled: bool) -> np.ndarray:
    """The table's rate from per-gripper sums: (R, G) successes and attempts -> (R,) rates."""
    if pooled:
        return successes.sum(axis=1) / attempts.sum(axis=1)
    return (successes / attempts).mean(axis=1)


def table_rate(side: Side, weights: np.ndarray) -> np.ndarray:
    """The table's rate of ``side`` for each row of ``weights``.

    ``weights``: (B, E) float64 count of each paired scene in each of B resamples (all ones:
    the paired scenes once). Returns (B,) float64 rates.
    """
    assert weights.ndim == 2 and weights.shape[1] == side.successes.shape[1], weights.shape
    return _rates(weights @ side.successes.T, weights @ side.attempts.T, side.pooled)


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
    """(gripper, scene seed) -> episode record of one result; raises one line on a malformed record."""
    records = summary.get("episode_results")
    if not isinstance(records, list) or not records:
        raise EvaluationError(f"{path}: episode_results: missing or empty (a result written by evaluate --json)")
    out: dict[tuple[str | None, int], dict] = {}
    for i, r in enumerate(records):
        where = f"{path}: episode_results[{i}]"
        if not isinstance(r, dict) or not all(k in r for k in _RECORD_KEYS):
            raise EvaluationError(f"{where}: needs {', '.join(_RECORD_KEYS[:-1])} and {_RECORD_KEYS[-1]}")
        counts = (r["scene_seed"], r["successes"], r["attempts"])
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in counts):
            raise EvaluationError(f"{where}: scene_seed, successes and attempts must be integers, got {counts}")
        if not isinstance(r["gripper"], (str, type(None))) or not isinstance(r["objects"], list):
            raise EvaluationError(f"{where}: gripper must be a name or null and objects a list")
        in_range = 0 <= r["successes"] <= r["attempts"] and 1 <= r["attempts"] < 2**31 and 0 <= r["scene_seed"] < 2**63
        if not in_range:
            raise EvaluationError(f"{where}: scene_seed {r['scene_seed']}, successes {r['successes']}, attempts "
                                  f"{r['attempts']}: expected 0 <= successes <= attempts, 1 <= attempts < 2^31 and "
                                  "0 <= scene_seed < 2^63")
        key = (r["gripper"], r["scene_seed"])
        if key in out:
            raise EvaluationError(f"{where}: gripper {key[0]}, scene_seed {key[1]}: repeated")
        out[key] = r
    if len({g is None for g, _ in out}) > 1:
        raise EvaluationError(f"{path}: episode_results: mixes adagrasp records (gripper null) with per-gripper ones")
    return out


def _side(path: str, summary: dict, episodes: dict, grippers: list[str | None], scenes: list[int],
          dropped: list[int]) -> Side:
    succ = np.array([[episodes[(g, s)]["successes"] for s in scenes] for g in grippers], dtype=np.int64)
    att = np.array([[episodes[(g, s)]["attempts"] for s in scenes] for g in grippers], dtype=np.int64)
    unpaired = len({seed for _, seed in episodes} - set(scenes))
    return Side(path, summary, grippers, succ, att, tuple(dropped), unpaired, scene_seeds=tuple(scenes))


POOL_KEYS = ("scene", "objects", "policy", "cameras", "calibration")
"""Result keys that must agree between the files pooled into one side (and the model:
:func:`_check_same_model`)."""


def _poolable(key: str, value):
    """What of a result's ``key`` must agree between pooled files: a calibration record without
    its ``sha256`` and its grippers' ``scenes`` (results written before the file hash or the scene
    count was recorded lack them, and the source, prior and per-gripper fits still name the
    calibration), anything else as it is."""
    if key == "calibration" and isinstance(value, dict):
        value = {k: v for k, v in value.items() if k != "sha256"}
        if isinstance(value.get("grippers"), dict):
            value["grippers"] = {g: {k: v for k, v in f.items() if k != "scenes"} if isinstance(f, dict) else f
                                 for g, f in value["grippers"].items()}
    return value


def model_difference(summary: dict, other: dict) -> str | None:
    """None when two results are of one model; else the key that tells them apart. The model is
    the same ``checkpoint_sha256`` (network and weights) when both record it, whatever they call
    the checkpoint; else the same ``checkpoint`` name (results written before the digest was
    recorded)."""
    mine, theirs = summary.get("checkpoint_sha256"), other.get("checkpoint_sha256")
    if mine is not None and theirs is not None:
        return None if mine == theirs else "checkpoint_sha256"
    return None if summary.get("checkpoint") == other.get("checkpoint") else "checkpoint"


def _check_same_model(s: Side, first: Side) -> None:
    """Pooled results must be of one model (:func:`model_difference`). One-line error naming the
    file and key."""
    key = model_difference(s.summary, first.summary)
    if key == "checkpoint_sha256":
        mine, theirs = s.summary[key], first.summary[key]
        raise EvaluationError(f"{s.path}: checkpoint_sha256: {mine[:12]}..., but {first.path} has "
                              f"{theirs[:12]}...: only results of one model pool")
    if key == "checkpoint":
        raise EvaluationError(f"{s.path}: checkpoint: {s.summary.get('checkpoint')!r}, but {first.path} has "
                              f"{first.summary.get('checkpoint')!r}: only results of one row pool (results "
                              "that name a checkpoint differently pool when both record checkpoint_sha256)")


def pool(sides: list[Side]) -> Side:
    """One side from the paired sides of several results of one row (other scene seeds): their
    scenes side by side. Raises :class:`EvaluationError` (one line naming the file and the key)
    when the files are not the same row, model, cameras or grippers, or share a scene seed."""
    first = sides[0]
    if len(sides) == 1:
        return first
    seen: dict[int, str] = {}
    for n, s in enumerate(sides):
        for earlier in sides[:n]:  # every pair: a file without a digest matches by name, which is not transitive
            _check_same_model(s, earlier)
        for key in POOL_KEYS:
            mine, theirs = _poolable(key, s.summary.get(key)), _poolable(key, first.summary.get(key))
            if mine == theirs:
                continue
            if isinstance(mine, dict) and isinstance(theirs, dict):
                differ = sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))
                raise EvaluationError(f"{s.path}: {key}: differs from {first.path} in {', '.join(differ)}: "
                                      "only results of one row pool")
            raise EvaluationError(f"{s.path}: {key}: {s.summary.get(key)!r}, but {first.path} has "
                                  f"{first.summary.get(key)!r}: only results of one row pool")
        if row_label(s.summary) != row_label(first.summary):
            raise EvaluationError(f"{s.path}: opening_rule: row {row_label(s.summary)!r}, but {first.path} is "
                                  f"{row_label(first.summary)!r}: only results of one row pool")
        if s.grippers != first.grippers:
            raise EvaluationError(f"{s.path}: grippers {s.grippers}: {first.path} pairs {first.grippers}")
        # adagrasp pairs one row of choices: the grippers it chose among must agree too
        check_same_candidates(s.path, s.summary, first.path, first.summary, "only results of one row pool")
        for seed in s.scene_seeds:
            if seed in seen:
                raise EvaluationError(f"{s.path}: scene_seed {seed}: also in {seen[seed]} (pool other scenes, "
                                      "e.g. another --seed)")
            seen[seed] = s.path
    return Side(
        path=" + ".join(s.path for s in sides), summary=first.summary, grippers=first.grippers,
        successes=np.concatenate([s.successes for s in sides], axis=1),
        attempts=np.concatenate([s.attempts for s in sides], axis=1),
        dropped=tuple(d for s in sides for d in s.dropped), unpaired=sum(s.unpaired for s in sides),
        parts=tuple((s.path, s.summary) for s in sides),
        scene_seeds=tuple(seed for s in sides for seed in s.scene_seeds),
    )


def _candidates(path: str, summary: dict) -> list[str]:
    """The ``gripper_names`` of a result: the grippers of its cell (``adagrasp``: its candidates)."""
    names = summary.get("gripper_names")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise EvaluationError(f"{path}: gripper_names: expected a non-empty list of gripper names, got {names!r}")
    return names


def check_same_candidates(path: str, summary: dict, first_path: str, first: dict, why: str) -> None:
    """One line (ending in ``why``) when the result ``summary`` (file ``path``) is of other grippers
    than ``first``: its :func:`_candidates`, in any order."""
    mine, theirs = sorted(_candidates(path, summary)), sorted(_candidates(first_path, first))
    if mine != theirs:
        raise EvaluationError(f"{path}: gripper_names: {mine}, but {first_path} has {theirs}: {why}")


def _grippers(path: str, episodes: dict, only: list[str] | None) -> list[str | None]:
    names = sorted({g for g, _ in episodes}, key=lambda g: g or "")
    if names == [None] or only is None:
        return names
    missing = [g for g in only if g not in names]
    if missing:
        raise EvaluationError(f"{path}: --gripper {','.join(missing)}: not among its grippers {names}")
    return [g for g in names if g in only]


def _check_candidates(path_fix: str, grippers: list[str | None], path_ada: str, ada: dict, only) -> None:
    """A per-gripper result against an ``adagrasp`` one: its grippers must be the candidates
    ``adagrasp`` chose among (all of them, unless ``--gripper`` keeps fewer)."""
    candidates = _candidates(path_ada, ada)
    fine = set(grippers) <= set(candidates) if only else set(grippers) == set(candidates)
    if not fine:
        raise EvaluationError(
            f"{path_fix}: grippers {grippers}: adagrasp in {path_ada} chose among {sorted(candidates)} "
            "(--gripper compares with some of them)"
        )


def pair(path_a: str, a: dict, path_b: str, b: dict, only: list[str] | None = None,
         drop_mismatched: bool = False) -> tuple[Side, Side]:
    """Restrict results ``a`` and ``b`` to the scenes (and, both per-gripper, the grippers) they share.

    ``only``: gripper names to keep on the per-gripper side(s) (None: all). ``drop_mismatched``:
    leave out a shared scene seed whose objects differ between records (recorded in
    ``Side.dropped``) instead of stopping. Raises :class:`EvaluationError` (one line naming the
    file and the key) when they are not the same scenes (scene kind, object set, or the objects
    of a shared seed) or protocol (attempt cap, gripper scale) or share none, share no gripper, when ``adagrasp`` chose among other
    grippers than the per-gripper result ran, or on a malformed record. The object check compares
    names and roles: necessary for the same scenes, not sufficient (objects placed elsewhere with
    the same draw pass it).
    """
    for key in ("scene", "objects"):
        for path, data in ((path_a, a), (path_b, b)):
            if key not in data:
                raise EvaluationError(f"{path}: {key}: missing")
        if a[key] != b[key]:
            raise EvaluationError(f"{path_b}: {key}: {b[key]!r}, but {path_a} has {a[key]!r}: not the same scenes")
    for key in ("max_attempts", "scale"):  # the same trials per scene, the same gripper size
        if key in a and key in b and a[key] != b[key]:
            raise EvaluationError(f"{path_b}: {key}: {b[key]!r}, but {path_a} has {a[key]!r}: not the same protocol")
    ea, eb = _episodes(path_a, a), _episodes(path_b, b)
    ga, gb = _grippers(path_a, ea, only), _grippers(path_b, eb, only)
    if ga != [None] and gb != [None]:
        ga = gb = [g for g in ga if g in gb]
        if not ga:
            raise EvaluationError(f"{path_b}: per_gripper: no gripper in common with {path_a}")
    elif ga != [None]:
        _check_candidates(path_a, ga, path_b, b, only)
    elif gb != [None]:
        _check_candidates(path_b, gb, path_a, a, only)
    seeds_a = dict.fromkeys(s for _, s in ea)
    shared = [s for s in seeds_a if all((g, s) in ea for g in ga) and all((g, s) in eb for g in gb)]
    if not shared:
        raise EvaluationError(f"{path_b}: scene_seeds: no scene in common with {path_a}")
    common, dropped = [], []
    for s in shared:
        reference = ea[(ga[0], s)]["objects"]
        odd = [(path, g) for path, episodes, grippers in ((path_a, ea, ga), (path_b, eb, gb))
               for g in grippers if episodes[(g, s)]["objects"] != reference]
        if not odd:
            common.append(s)
        elif drop_mismatched:
            dropped.append(s)
        else:
            path, g = odd[0]
            raise EvaluationError(
                f"{path}: episode_results (scene_seed {s}, gripper {g}).objects: not the objects of "
                f"{path_a}'s scene {s}, gripper {ga[0]} (another simulation, object set or machine; "
                "--drop-mismatched-scenes pairs the rest)"
            )
    if not common:
        raise EvaluationError(f"{path_b}: episode_results: no shared scene has the same objects as in {path_a}")
    return _side(path_a, a, ea, ga, common, dropped), _side(path_b, b, eb, gb, common, dropped)


def scene_resamples(rng: np.random.Generator, resamples: int, scenes: int) -> np.ndarray:
    """(resamples, scenes) float64: how often each scene is drawn in each bootstrap resample
    (``scenes`` draws with replacement per row)."""
    draws = rng.integers(0, scenes, size=(resamples, scenes))
    weights = np.zeros((resamples, scenes))
    np.add.at(weights, (np.arange(resamples)[:, None], draws), 1.0)
    return weights


def rate_interval(path: str, summary: dict, resamples: int = BOOTSTRAP_RESAMPLES,
                  seed: int = 0) -> tuple[float, float, float]:
    """The table rate of one result and its 95% interval over scene resamples.

    The scenes are those with a record for every gripper of the result (all of them, for a
    finished run); ``seed`` seeds the bootstrap draws. Returns (rate, low, high). Raises
    :class:`EvaluationError` on a malformed record.
    """
    episodes = _episodes(path, summary)
    grippers = _grippers(path, episodes, None)
    scenes = [s for s in dict.fromkeys(s for _, s in episodes) if all((g, s) in episodes for g in grippers)]
    if not scenes:
        raise EvaluationError(f"{path}: episode_results: no scene has a record for every gripper")
    side = _side(path, summary, episodes, grippers, scenes, [])
    weights = scene_resamples(np.random.default_rng(seed), resamples, len(scenes))
    low, high = np.percentile(table_rate(side, weights), [2.5, 97.5])
    return float(table_rate(side, np.ones((1, len(scenes))))[0]), float(low), float(high)


def swapped_differences(sa: Side, sb: Side, swaps: np.ndarray) -> np.ndarray:
    """Rate difference B - A after swapping A's and B's records of the scenes marked in each row of
    ``swaps`` ((R, E) 0/1); needs the same grippers on both sides. Returns (R,) float64."""
    assert sa.grippers == sb.grippers and swaps.shape[1] == sa.successes.shape[1], (sa.grippers, swaps.shape)
    keep = 1.0 - swaps
    s_a = keep @ sa.successes.T + swaps @ sb.successes.T
    a_a = keep @ sa.attempts.T + swaps @ sb.attempts.T
    s_b = keep @ sb.successes.T + swaps @ sa.successes.T
    a_b = keep @ sb.attempts.T + swaps @ sa.attempts.T
    return _rates(s_b, a_b, sb.pooled) - _rates(s_a, a_a, sa.pooled)


def permutation_p(sa: Side, sb: Side, draws: int, rng: np.random.Generator) -> tuple[float | None, str]:
    """Two-sided p-value of the scene-swap permutation test of the rate difference, and how it was
    computed; (None, why) when A and B are not exchangeable."""
    if sa.grippers != sb.grippers:
        return None, "none: a per-gripper result and an adagrasp one are not exchangeable"
    if (sa.attempts == 1).all() and (sb.attempts == 1).all():
        per_scene = (sb.successes - sa.successes).mean(axis=0).astype(np.float64)
        return sign_flip_p(per_scene, scale=len(sa.grippers)), "exact scene-swap permutation test"
    scenes = sa.successes.shape[1]
    observed = abs(swapped_differences(sa, sb, np.zeros((1, scenes)))[0])
    hits = 0
    for start in range(0, draws, 10_000):
        swaps = rng.integers(0, 2, size=(min(10_000, draws - start), scenes)).astype(np.float64)
        hits += int((np.abs(swapped_differences(sa, sb, swaps)) >= observed - 1e-12).sum())
    return (1 + hits) / (1 + draws), f"scene-swap permutation test, {draws} random swaps"


def compare(sa: Side, sb: Side, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> dict:
    """The paired comparison of B against A (JSON-ready); ``seed`` seeds the generator of the
    bootstrap draws and the random swaps (``resamples`` of each)."""
    scenes = sa.successes.shape[1]
    assert sb.successes.shape[1] == scenes and resamples >= 1
    scene_rate_a = sa.successes.sum(axis=0) / sa.attempts.sum(axis=0)
    scene_rate_b = sb.successes.sum(axis=0) / sb.attempts.sum(axis=0)
    better, worse = int((scene_rate_b > scene_rate_a).sum()), int((scene_rate_b < scene_rate_a).sum())
    ones = np.ones((1, scenes))
    rate_a, rate_b = float(table_rate(sa, ones)[0]), float(table_rate(sb, ones)[0])
    rng = np.random.default_rng(seed)
    weights = scene_resamples(rng, resamples, scenes)
    diffs = table_rate(sb, weights) - table_rate(sa, weights)
    low, high = np.percentile(diffs, [2.5, 97.5])
    p_value, test = permutation_p(sa, sb, resamples, rng)

    def side(s: Side, rate: float) -> dict:
        return {
            "path": s.path,
            "row": row_label(s.summary),
            "checkpoint": s.summary.get("checkpoint"),
            "checkpoint_sha256": s.summary.get("checkpoint_sha256"),
            "cameras": s.summary.get("cameras"),
            "grippers": s.grippers,
            "candidates": _candidates(s.path, s.summary) if s.pooled else None,
            "unpaired_scenes": s.unpaired,
            "rate": rate,
            "file_rate": [d["rate"] for _, d in s.parts] if s.parts else s.summary["rate"],
            "successes": int(s.successes.sum()),
            "attempts": int(s.attempts.sum()),
        }

    return {
        "format": COMPARE_FORMAT,
        "scene": sa.summary["scene"],
        "objects": sa.summary["objects"],
        "scenes": scenes,
        "dropped_scene_seeds": list(sa.dropped),
        "a": side(sa, rate_a),
        "b": side(sb, rate_b),
        "b_better": better,
        "b_worse": worse,
        "same": scenes - better - worse,
        "tally": "scenes where B's successes / attempts (over the paired grippers) is above, below or equal to A's",
        "p_value": p_value,
        "test": test,
        "rate_difference": rate_b - rate_a,
        "ci95": [float(low), float(high)],
        "bootstrap": {"resamples": resamples, "seed": seed, "unit": "scene"},
    }


def report(c: dict) -> str:
    """Four lines of text for a comparison from :func:`compare`."""

    def side(tag: str, s: dict) -> str:
        names = s["grippers"] if s["candidates"] is None else s["candidates"]
        grippers = ",".join(names) if len(names) <= 6 else f"{len(names)} grippers"
        if s["candidates"] is not None:
            grippers = "choosing among " + grippers
        if s["unpaired_scenes"]:
            grippers += f"; {s['unpaired_scenes']} of its scenes unpaired"
        return (f"  {tag} {s['row']}: rate {s['rate']:.3f} ({s['successes']}/{s['attempts']} grasps; "
                f"{grippers}), {s['path']}")

    lo, hi = c["ci95"]
    test = "no permutation test (a per-gripper and an adagrasp result are not exchangeable)"
    if c["p_value"] is not None:
        test = f"{c['test']}: p = {c['p_value']:.3g}"
    dropped = c["dropped_scene_seeds"]
    return "\n".join([
        f"compare: {c['scene']} scenes of objects {c['objects']}, {c['scenes']} paired scenes"
        + (f" ({len(dropped)} shared seeds left out: other objects)" if dropped else ""),
        side("A", c["a"]),
        side("B", c["b"]),
        f"  B - A: {c['rate_difference']:+.3f} (95% interval {lo:+.3f} to {hi:+.3f}, "
        f"{c['bootstrap']['resamples']} scene resamples); per scene B above A in {c['b_better']}, below in "
        f"{c['b_worse']}, level in {c['same']}; {test}",
    ]) + "\n"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m launcher evaluate compare",
        description="Compare two evaluation results of one cell on the scenes they share: a scene-bootstrap "
        "95% interval of the rate difference B - A and a scene-swap permutation test.",
    )
    ap.add_argument("a", metavar="A.json", help="result written by evaluate --json (the baseline)")
    ap.add_argument("b", metavar="B.json", help="result written by evaluate --json (compared against A)")
    ap.add_argument("--also", nargs=2, action="append", default=[], metavar=("A2.json", "B2.json"),
                    help="the same two rows on other scenes (another --seed), pooled with A and B; repeatable")
    ap.add_argument("--gripper", default=None, metavar="NAME[,NAME...]",
                    help="per-gripper results: keep only these grippers")
    ap.add_argument("--drop-mismatched-scenes", action="store_true",
                    help="leave out shared scene seeds whose objects differ (else: an error)")
    ap.add_argument("--resamples", type=int, default=BOOTSTRAP_RESAMPLES,
                    help="bootstrap scene draws, and random swaps of the permutation test")
    ap.add_argument("--seed", type=int, default=0, help="seed of the generator of the draws and swaps")
    ap.add_argument("--json", default=None, help="write the comparison here")
    return ap


def compare_cli(argv: list[str]) -> dict:
    """``evaluate compare``: parse ``argv``, print :func:`report`, write --json; returns the comparison."""
    args = _parser().parse_args(argv)
    if args.resamples < 1:
        raise EvaluationError(f"--resamples {args.resamples}: expected >= 1")
    check_output_path("--json", args.json, [args.a, args.b, *(f for pair in args.also for f in pair)])
    only = [g.strip() for g in args.gripper.split(",")] if args.gripper else None
    pairs = [pair(a, read_result(a), b, read_result(b), only, args.drop_mismatched_scenes)
             for a, b in [(args.a, args.b), *args.also]]
    sa, sb = pool([p[0] for p in pairs]), pool([p[1] for p in pairs])
    if only is not None and sa.pooled and sb.pooled:
        raise EvaluationError(f"--gripper {args.gripper}: both results are adagrasp runs, which choose the gripper")
    result = compare(sa, sb, args.resamples, args.seed)
    print(report(result), end="")
    if args.json:
        write_json(args.json, result)
    return result
