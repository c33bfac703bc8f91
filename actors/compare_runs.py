"""``python -m launcher evaluate runs --a ... --b ...``: two rows compared across training runs.

``evaluate compare`` tests whether two results differ beyond the chance of their scenes: the
model of each side is fixed. Whether a *method* beats another needs more: a second training
run of the same method (another root seed) gives another model, and on piles the rates of
equal runs differ by more than the steps between rows (docs/RESULTS.md). This module takes
several training runs per side, each run one or more result files of its model on other scene
seeds, and tests the difference of the mean over runs against the spread across runs.

- **Run rate.** Each run's table rate (per-gripper policies: the mean over the grippers of
  successes / attempts; ``adagrasp``: successes / attempts) on the scenes every run of both
  sides ran; the scenes are the same for every run, so scene difficulty is common to all and
  the runs differ by their training and by the chance of their grasps.
- **Difference.** The mean over B's runs minus the mean over A's runs.
- **t interval and test.** Unpaired: Welch's t (the two sides' run rates as two samples with
  unequal variances); paired (``--paired``: run i of B and run i of A are one model, e.g. the
  fix-gripper and adagrasp rows of one training run): Student's t of the per-run differences.
  Both assume the run rates are normal; with two or three runs per side nothing else checks it.
- **Randomization test.** Unpaired: every way of relabelling the runs between the sides (exact);
  paired: every sign of the per-run differences (exact). No assumption of normality, but few
  runs bound the smallest p-value it can give (``smallest_p``): 0.1 with three runs a side, 0.25
  with three pairs. A p-value at that bound means "as extreme as these runs allow".

Both tests hold the scenes fixed: they say whether the difference exceeds the spread across training
runs *on these scenes*; ``evaluate compare`` speaks to other scenes for one model. The files must be
results of one cell (:data:`CELL_KEYS` and the gripper names) simulated alike (the same
``config.sim``; with ``--across-cameras`` the sides are two camera counts, each side one, and
the rest one cell), each side one row, each run of a side another model (``checkpoint_sha256``, else
the checkpoint name), no model on both sides unless paired, and the files of one run one model on
different scene seeds (as ``evaluate compare --also``). A per-gripper file must have records of
every gripper of the cell (or of ``--gripper``). The runs of a calibrated side must be calibrated
from as many scenes per gripper, where their results record it or their calibration's source file
gives it (:func:`calibration_budget`). A scene whose objects differ between two compared records
stops the comparison with one line naming the file, unless ``--drop-mismatched-scenes`` leaves it
out.
"""

from __future__ import annotations

import argparse
import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from actors.compare import (
    Side,
    _candidates,
    _check_candidates,
    _episodes,
    _grippers,
    _side,
    check_same_candidates,
    model_difference,
    pool,
    table_rate,
)
from actors.evaluate import EvaluationError, check_output_path, read_result, row_label, write_json
from common.calibration import Calibration, calibration_from_result, file_sha256
from common.config import SimConfig, to_dict

RUNS_FORMAT = "adagrasp-scale-run-comparison/1"
"""Value of the ``format`` key of a run comparison JSON."""
EXACT_LIMIT = 1 << 16
"""Largest number of relabellings (or sign patterns) enumerated; above it, random draws."""


@dataclass(frozen=True)
class RunFile:
    """One result file of one training run."""

    path: str
    """Result file."""
    summary: dict
    """The result JSON."""
    episodes: dict
    """(gripper, scene seed) -> episode record (:func:`actors.compare._episodes`)."""


CELL_KEYS = ("scene", "objects", "cameras", "scale", "max_attempts", "openings")
"""Result keys every file of both sides shares: one cell, measured one way."""


def _check_trained(path: str, summary: dict, needs: str) -> None:
    """One line for a result without a checkpoint (``random``, ``heuristic``: nothing was trained);
    ``needs`` says which command needs training runs."""
    if summary.get("checkpoint_sha256") is None and summary.get("checkpoint") is None:
        raise EvaluationError(f"{path}: checkpoint: none ({summary.get('policy')} is not a trained model; {needs})")


def _models_line(key: str, rf: RunFile, other: RunFile) -> str:
    """``FILE: KEY: VALUE, but OTHER has VALUE`` for two results of different models."""
    mine, theirs = rf.summary.get(key), other.summary.get(key)
    if key == "checkpoint_sha256":
        return f"{rf.path}: {key}: {mine[:12]}..., but {other.path} has {theirs[:12]}..."
    return f"{rf.path}: {key}: {mine!r}, but {other.path} has {theirs!r}"


def _read_side(tag: str, groups: list[list[str]]) -> list[list[RunFile]]:
    runs = []
    for files in groups:
        if not files or any(not f for f in files):
            raise EvaluationError(f"--{tag} {','.join(files)}: expected RESULT.json[,RESULT.json...] (one run's files)")
        runs.append([RunFile(f, d := read_result(f), _episodes(f, d)) for f in files])
    return runs


def calibration_budget(summary: dict, path: str | None = None) -> dict[str, int] | None:
    """Gripper name -> the scenes its calibration trials came from, for a calibrated result that
    records them for every gripper. A result written before the scene count was recorded (no
    gripper's fit has ``scenes``; their ``trials`` count grasps, several per scene of a pile) gets
    it from its calibration's source file, found and checked by :func:`_budget_from_source`, when
    ``path`` (the result's file) is given. None otherwise: no calibration, or the count is unknown."""
    calibration = summary.get("calibration")
    fits = calibration.get("grippers") if isinstance(calibration, dict) else None
    if not isinstance(fits, dict) or not fits:
        return None
    budget = {g: fit.get("scenes") if isinstance(fit, dict) else None for g, fit in sorted(fits.items())}
    if is_budget(budget):
        return budget
    legacy = all(isinstance(fit, dict) and "scenes" not in fit for fit in fits.values())
    return _budget_from_source(path, calibration) if legacy and path is not None else None


SHIFT_TOLERANCE = 1e-9
"""Logits by which a refitted calibration shift may differ from the recorded one (the order of
floating-point sums may differ between builds); trials and successes must be equal."""


def _budget_from_source(path: str, calibration: dict) -> dict[str, int] | None:
    """Gripper name -> scenes, for the calibration record ``calibration`` of the result ``path``
    written before its scene count was: its recorded ``source`` file is looked up as written (from
    the working directory) and from every folder above ``path`` (above the path as named, then above
    the file a link names), and refitted with the recorded ``prior_sigma``
    (:func:`common.calibration.calibration_from_result`). A file counts only when it is the one
    fitted: its SHA-256 equals the recorded one where recorded, and the refit gives the recorded
    grippers, trials, successes and shifts (to :data:`SHIFT_TOLERANCE`); the first that is wins.
    None when no file of that name exists; one line naming the result and the key when files exist
    but none is the one fitted (the count cannot be recovered, and a comparison would not be
    checked)."""
    source = calibration.get("source")
    if not isinstance(source, str) or not source:
        return None
    folders = []
    for here in (Path(path).absolute().parent, Path(path).resolve().parent):
        folders += [here, *here.parents]
    found = [c for c in dict.fromkeys([Path(source), *(d / source for d in folders)]) if _is_file(c)]
    reasons = []
    for candidate in found:
        reason, refit = _refit_source(candidate, calibration)
        if refit is not None:
            return {name: fit.scenes for name, fit in sorted(refit.grippers.items())}
        reasons.append(reason)
    if reasons:
        raise EvaluationError(f"{path}: calibration.{reasons[0]} (the calibration budget cannot be recovered)")
    return None


def _is_file(candidate: Path) -> bool:
    """Whether ``candidate`` names a file; a name the system cannot look up (too long, a folder on
    the way that cannot be read, a NUL byte) names none."""
    try:
        return candidate.is_file()
    except (OSError, ValueError):
        return False


def _refit_source(candidate: Path, calibration: dict) -> tuple[str, Calibration | None]:
    """(``""``, the refit) when ``candidate`` is the file the calibration record ``calibration`` was
    fitted to (:func:`_budget_from_source`); else (why not, naming the record's key, None)."""
    digest = calibration.get("sha256")
    if digest:
        try:
            actual = file_sha256(candidate)
        except OSError as e:
            return f"source: {candidate} cannot be read ({e.strerror or e})", None
        if actual != digest:
            return f"sha256: {str(digest)[:12]}..., but {candidate} has {actual[:12]}...", None
    prior = calibration.get("prior_sigma")
    if not isinstance(prior, (int, float)) or isinstance(prior, bool) or not math.isfinite(prior):
        return f"prior_sigma: expected a finite number, got {prior!r}", None
    try:
        refit = calibration_from_result(str(candidate), read_result(str(candidate)), float(prior))
    except ValueError as e:
        return f"source: {candidate} cannot be refitted ({e})", None
    recorded = calibration["grippers"]
    if sorted(refit.grippers) != sorted(recorded):
        return f"grippers: {sorted(recorded)}, but {candidate} has trials of {sorted(refit.grippers)}", None
    for name, fit in sorted(refit.grippers.items()):
        mine = recorded[name]
        shift = mine.get("shift")
        if (mine.get("trials"), mine.get("successes")) != (fit.trials, fit.successes) or not (
                isinstance(shift, (int, float)) and abs(fit.shift - shift) <= SHIFT_TOLERANCE):
            return (f"grippers.{name}: shift {shift!r} from {mine.get('successes')!r}/{mine.get('trials')!r} trials, "
                    f"but refitting {candidate} gives {fit.shift!r} from {fit.successes}/{fit.trials}"), None
    return "", refit


def is_budget(budget) -> bool:
    """Whether ``budget`` is a calibration budget: a non-empty map of gripper names to scene
    counts, positive integers (not booleans)."""
    return isinstance(budget, dict) and bool(budget) and all(
        isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in budget.values())


def _budget_text(budget: dict[str, int]) -> str:
    """``40 scenes per gripper``, or each gripper's count where they differ."""
    counts = set(budget.values())
    if len(counts) == 1:
        return f"{counts.pop()} scenes per gripper"
    return "scenes per gripper " + ", ".join(f"{g} {n}" for g, n in budget.items())


def _check_calibration_budget(tag: str, files: list[RunFile]) -> dict[str, int] | None:
    """The calibrated runs of one side were calibrated from as many scenes per gripper (a larger
    budget is another method, not another run); files whose count is unknown are not checked. Returns
    the side's budget where every file records it, else None."""
    known = [(rf, b) for rf in files if (b := calibration_budget(rf.summary, rf.path)) is not None]
    if not known:
        return None
    head, first = known[0]
    for rf, budget in known[1:]:
        if budget != first:
            raise EvaluationError(f"{rf.path}: calibration: {_budget_text(budget)}, but {head.path} (side {tag}) "
                                  f"has {_budget_text(first)}: each side is one calibration budget")
    return first if len(known) == len(files) else None


def _check_cell_and_rows(sides: list[list[list[RunFile]]], across_cameras: bool = False
                         ) -> list[dict[str, int] | None]:
    """Every file: the first file's cell (:func:`check_one_cell`) and its side's row;
    ``across_cameras``: the sides may differ in camera count, each side one count (a camera count
    of a row against another). Returns each side's calibration budget
    (:func:`_check_calibration_budget`)."""
    budgets = []
    first = sides[0][0][0]
    for tag, runs in zip("AB", sides):
        head = runs[0][0]
        for rf in (f for run in runs for f in run):
            if across_cameras:
                check_one_cell(rf.path, rf.summary, head.path, head.summary)
                check_one_cell(rf.path, rf.summary, first.path, first.summary, ignore=("cameras",))
            else:
                check_one_cell(rf.path, rf.summary, first.path, first.summary)
            if row_label(rf.summary) != row_label(head.summary):
                raise EvaluationError(f"{rf.path}: row: {row_label(rf.summary)!r}, but {head.path} (side {tag}) "
                                      f"has {row_label(head.summary)!r}: each side is one row")
        budgets.append(_check_calibration_budget(tag, [f for run in runs for f in run]))
    if across_cameras:
        _check_across_cameras(sides)
    return budgets


def _check_across_cameras(sides: list[list[list[RunFile]]]) -> None:
    """``--across-cameras``: every file's ``config.sim.cameras`` (where recorded) is its
    ``cameras``, the sides' first files are one row at two camera counts. One line otherwise."""
    for rf in (f for runs in sides for run in runs for f in run):
        sim = _sim(rf.path, rf.summary)
        if sim is not None and "cameras" in sim and sim["cameras"] != rf.summary.get("cameras"):
            raise EvaluationError(f"{rf.path}: config.sim.cameras: {sim['cameras']!r}, but its cameras is "
                                  f"{rf.summary.get('cameras')!r}")
    a, b = sides[0][0][0], sides[1][0][0]
    if row_label(b.summary) != row_label(a.summary):
        raise EvaluationError(f"{b.path}: row: {row_label(b.summary)!r}, but {a.path} (side A) has "
                              f"{row_label(a.summary)!r}: --across-cameras compares one row at two camera counts")
    if b.summary.get("cameras") == a.summary.get("cameras"):
        raise EvaluationError(f"{b.path}: cameras: {b.summary.get('cameras')!r}, as on side A: --across-cameras "
                              "compares two camera counts")


def check_one_cell(path: str, summary: dict, first_path: str, first: dict, ignore: tuple[str, ...] = ()) -> None:
    """The result ``summary`` (file ``path``) is of the cell of ``first`` and measured alike: the
    same :data:`CELL_KEYS`, gripper names and ``config.sim`` (:func:`_check_sim`), but for the keys
    in ``ignore`` (of both). One line naming the file and the key otherwise."""
    for key in ("scene", "objects"):
        if key not in summary:
            raise EvaluationError(f"{path}: {key}: missing")
    for key in CELL_KEYS:
        if key not in ignore and summary.get(key) != first.get(key):
            raise EvaluationError(f"{path}: {key}: {summary.get(key)!r}, but {first_path} has {first.get(key)!r}: "
                                  "not one cell")
    check_same_candidates(path, summary, first_path, first, "not one cell")
    _check_sim(path, summary, first_path, first, ignore)


def _sim(path: str, summary: dict) -> dict | None:
    """The result's ``config.sim`` (None where not recorded); one line when it is not an object."""
    config = summary.get("config")
    sim = config.get("sim") if isinstance(config, dict) else config
    if not isinstance(sim, (dict, type(None))):
        raise EvaluationError(f"{path}: config.sim: not an object")
    return sim


def _check_sim(path: str, summary: dict, first_path: str, first: dict, ignore: tuple[str, ...] = ()) -> None:
    """The two results were simulated alike (the same ``config.sim`` but for the keys in ``ignore``;
    where both record it, a key added to the config since one was written counts at its default, as
    a checkpoint's config is read). One line naming the keys otherwise."""
    sims = (_sim(path, summary), _sim(first_path, first))
    if None not in sims:
        defaults = to_dict(SimConfig())
        sims = tuple({**defaults, **sim} for sim in sims)
    mine, theirs = ({k: v for k, v in sim.items() if k not in ignore} if sim is not None else None for sim in sims)
    if mine != theirs:
        differ = sorted(k for k in (mine or {}).keys() | (theirs or {}).keys()
                        if (mine or {}).get(k) != (theirs or {}).get(k))
        raise EvaluationError(f"{path}: config.sim: differs from {first_path} in {', '.join(differ) or 'presence'}: "
                              "not simulated alike")


def _scene_set(path: str, summary: dict) -> list[int]:
    """The sorted scene seeds of a result's episode records (read by :func:`actors.compare._episodes`)."""
    return sorted({seed for _, seed in _episodes(path, summary)})


def pool_result(paths: list[str]) -> dict:
    """One row's result over several scene seeds: the result files of one model at other
    ``--seed`` values read as one result, for ``evaluate table``. Returns the first file's result
    with ``rate`` the table's rate over every scene of every file (per-gripper policies: the mean
    over the grippers of their pooled successes / attempts; ``adagrasp``: successes / attempts),
    ``seed`` the sorted list of the files' scene seeds, ``scene_seeds`` and ``episode_results``
    joined, ``episodes`` and the ``average`` counts summed, ``pooled_from`` the paths, and no
    ``per_gripper``. The files must be one cell measured alike (:func:`check_one_cell` and the same
    ``grippers_label``) and pool as ``evaluate compare --also`` sides do
    (:func:`actors.compare.pool`: one row, model and cameras, no scene twice); one line naming the
    file and the key otherwise."""
    assert len(paths) > 1, paths
    if len(set(paths)) < len(paths):
        twice = next(p for p in paths if paths.count(p) > 1)
        raise EvaluationError(f"{twice}: given twice in {','.join(paths)}")
    sides = []
    for path in paths:
        summary = read_result(path)
        if sides:
            head = sides[0]
            check_one_cell(path, summary, head.path, head.summary)
            if summary["grippers_label"] != head.summary["grippers_label"]:
                raise EvaluationError(f"{path}: grippers_label: {summary['grippers_label']!r}, but {head.path} has "
                                      f"{head.summary['grippers_label']!r}: not one cell")
        episodes = _episodes(path, summary)
        grippers = _grippers(path, episodes, None)
        scenes = sorted({seed for _, seed in episodes})
        for g in grippers:
            lacking = [seed for seed in scenes if (g, seed) not in episodes]
            if lacking:
                raise EvaluationError(f"{path}: episode_results: gripper {g} has no record of scene_seed {lacking[0]}, "
                                      "which other grippers ran")
        sides.append(_side(path, summary, episodes, grippers, scenes, []))
    side = pool(sides)
    rate = float(table_rate(side, np.ones((1, len(side.scene_seeds))))[0])
    parts = [s.summary for s in sides]
    first = parts[0]
    successes, attempts = int(side.successes.sum()), int(side.attempts.sum())
    pooled = {key: value for key, value in first.items() if key != "per_gripper"}
    return {
        **pooled,
        "rate": rate,
        "seed": sorted(s["seed"] for s in parts),
        "scene_seeds": [seed for s in parts for seed in s.get("scene_seeds", [])],
        "episode_results": [r for s in parts for r in s["episode_results"]],
        "episodes": sum(s["episodes"] for s in parts),
        "average": {**first["average"], "rate": rate, "attempts": attempts, "successes": successes,
                    "pooled_rate": successes / attempts},
        "pooled_from": list(paths),
    }


def check_table_run(path: str, summary: dict, title: str, cell: list[tuple[str, dict]]) -> None:
    """``evaluate table --runs``: ``summary`` (file ``path``) may join the table cell ``title``,
    which holds ``cell`` (path, result) already, as another training run of its row: a trained
    model other than each run there (:func:`model_difference`; without ``checkpoint_sha256`` in
    both, the checkpoint name tells them apart), of the cell of the first (:func:`check_one_cell`),
    simulated alike, on the same scenes, and, for calibrated runs, calibrated from as many scenes
    per gripper where both budgets are known (recorded, or recovered from the
    calibration's source: :func:`calibration_budget`; a pooled result's from its first file). One
    line naming the file and key otherwise."""
    head, first = cell[0]
    _check_trained(path, summary, "--runs averages training runs")
    for other_path, other in cell:
        if model_difference(summary, other) is None:
            raise EvaluationError(f"{path}: checkpoint: the model of {other_path}, in {row_label(summary)}, {title} "
                                  "too (--runs averages other training runs of a row)")
    check_one_cell(path, summary, head, first)
    if _scene_set(path, summary) != _scene_set(head, first):
        raise EvaluationError(f"{path}: scene_seed: its scenes are not those of {head}: the runs of one cell must be "
                              "evaluated on the same scenes")
    mine = calibration_budget(summary, summary.get("pooled_from", [path])[0])
    for other_path, other in cell:
        theirs = calibration_budget(other, other.get("pooled_from", [other_path])[0])
        if mine is not None and theirs is not None and mine != theirs:
            raise EvaluationError(f"{path}: calibration: from {_budget_text(mine)}, but {other_path} from "
                                  f"{_budget_text(theirs)} (another calibration budget is another method, "
                                  "not another run)")


def _check_models(sides: list[list[list[RunFile]]], paired: bool) -> None:
    """One model per run, another one per run of a side; ``paired``: run i of both sides one model,
    else no model on both sides (Welch's samples must be independent)."""
    for tag, runs in zip("AB", sides):
        for i, run in enumerate(runs):
            for n, rf in enumerate(run):
                _check_trained(rf.path, rf.summary, "runs compares training runs")
                for earlier in run[:n]:  # every pair: matching by name where a digest is missing is not transitive
                    key = model_difference(rf.summary, earlier.summary)
                    if key:
                        raise EvaluationError(f"{_models_line(key, rf, earlier)}, of the same run (a run's files "
                                              "are one model on other scene seeds)")
            for other in runs[:i]:
                if model_difference(run[0].summary, other[0].summary) is None:
                    raise EvaluationError(f"{run[0].path}: checkpoint: the model of {other[0].path}, also a run of "
                                          f"side {tag} (each run of a side is another training run)")
    runs_a, runs_b = sides
    if not paired:
        for rb in runs_b:
            for ra in runs_a:
                if model_difference(rb[0].summary, ra[0].summary) is None:
                    raise EvaluationError(f"{rb[0].path}: checkpoint: the model of {ra[0].path} on side A: two "
                                          "rows of one model compare with --paired")
        return
    if len(runs_a) != len(runs_b):
        raise EvaluationError(f"--paired: side A has {len(runs_a)} runs and side B {len(runs_b)}: pairs need as many")
    for ra, rb in zip(runs_a, runs_b):
        key = model_difference(rb[0].summary, ra[0].summary)
        if key:
            raise EvaluationError(f"{_models_line(key, rb[0], ra[0])}: --paired pairs the rows of one training "
                                  "run's model")


def _side_grippers(sides: list[list[list[RunFile]]], only: list[str] | None) -> list[list[str | None]]:
    """The gripper rows of each side: the cell's grippers (or ``only``) for a per-gripper row,
    each with a record in every file; [None] for an ``adagrasp`` row."""
    out: list[list[str | None]] = []
    fixed: RunFile | None = None
    for runs in sides:
        rows: list[str | None] = []
        for rf in (f for run in runs for f in run):
            rows = _grippers(rf.path, rf.episodes, only)
            if rows == [None]:
                continue
            fixed = rf
            missing = sorted(set(only or _candidates(rf.path, rf.summary)) - set(rows))
            if missing:
                raise EvaluationError(f"{rf.path}: episode_results: no record of gripper {', '.join(missing)} (an "
                                      "unfinished evaluation?); --gripper compares the others")
        out.append(rows)
    if fixed is None:
        if only is not None:
            raise EvaluationError(f"--gripper {','.join(only)}: both sides are adagrasp runs, which choose the gripper")
        return out
    rows = next(r for r in out if r != [None])
    for runs, side in zip(sides, out):
        if side == [None]:
            for rf in (f for run in runs for f in run):
                _check_candidates(fixed.path, rows, rf.path, rf.summary, only)
    return out


def _scenes(sides, grippers, drop_mismatched) -> tuple[list[int], list[int], list[int]]:
    """The scene seeds every run of both sides ran for all its gripper rows, in the first run's
    order; the ones left out for other objects; and per run the count of the scene seeds in its
    records left out otherwise (not run by every run, or not for every gripper row)."""
    per_run: list[list[int]] = []
    any_record: list[set[int]] = []
    for runs, rows in zip(sides, grippers):
        for run in runs:
            seen: dict[int, str] = {}
            any_record.append({seed for rf in run for _, seed in rf.episodes})
            for rf in run:
                for s in dict.fromkeys(seed for _, seed in rf.episodes):
                    if all((g, s) in rf.episodes for g in rows):
                        if s in seen:
                            raise EvaluationError(f"{rf.path}: scene_seed {s}: also in {seen[s]} of the same run "
                                                  "(a run's files cover other scenes, e.g. another --seed)")
                        seen[s] = rf.path
            per_run.append(list(seen))
    shared = set.intersection(*map(set, per_run))
    order = [s for s in per_run[0] if s in shared]
    if not order:
        raise EvaluationError(f"{sides[0][0][0].path}: scene_seeds: no scene run by every run of both sides")
    reference: dict[int, tuple[str, list]] = {}
    dropped = []
    for runs, rows in zip(sides, grippers):
        for run in runs:
            for rf in run:
                for g in rows:
                    for s in order:
                        if (g, s) not in rf.episodes or s in dropped:
                            continue
                        objects = rf.episodes[(g, s)]["objects"]
                        ref_path, ref = reference.setdefault(s, (rf.path, objects))
                        if objects == ref:
                            continue
                        if not drop_mismatched:
                            raise EvaluationError(
                                f"{rf.path}: episode_results (scene_seed {s}, gripper {g}).objects: not the objects "
                                f"of scene {s} in {ref_path} (another simulation, object set or machine; "
                                "--drop-mismatched-scenes compares the rest)")
                        dropped.append(s)
    kept = [s for s in order if s not in dropped]
    if not kept:
        raise EvaluationError(f"{sides[0][0][0].path}: episode_results: no shared scene has the same objects in "
                              "every run")
    return kept, dropped, [len(seeds - set(kept) - set(dropped)) for seeds in any_record]


def run_sides(groups_a: list[list[str]], groups_b: list[list[str]], only: list[str] | None = None,
              paired: bool = False, drop_mismatched: bool = False, across_cameras: bool = False
              ) -> tuple[list[Side], list[Side], dict]:
    """Read and check the runs of both sides; one :class:`~actors.compare.Side` per run, its files
    pooled and its columns the shared scenes in one order for every run.

    ``groups_a`` / ``groups_b``: per run, its result files. Returns (A's runs, B's runs, info:
    ``scene_seeds`` used, ``dropped_scene_seeds``, ``left_out`` per run, ``calibration_scenes`` per
    side: gripper name -> scenes its calibration came from, every calibrated gripper whatever
    ``only`` keeps, or None). Raises
    :class:`EvaluationError` (one line naming the file and the key) on the checks of the module
    docstring.
    """
    for tag, groups in (("a", groups_a), ("b", groups_b)):
        if len(groups) < 2:
            raise EvaluationError(f"--{tag}: {len(groups)} run(s); the spread across runs needs at least 2 per side")
    sides = [_read_side("a", groups_a), _read_side("b", groups_b)]
    budgets = _check_cell_and_rows(sides, across_cameras)
    _check_models(sides, paired)
    grippers = _side_grippers(sides, only)
    kept, dropped, left_out = _scenes(sides, grippers, drop_mismatched)
    keep = set(kept)
    out = []
    for runs, rows in zip(sides, grippers):
        built = []
        for run in runs:
            parts = []
            for rf in run:
                seeds = [s for s in dict.fromkeys(seed for _, seed in rf.episodes) if s in keep
                         and all((g, s) in rf.episodes for g in rows)]
                if seeds:
                    parts.append(_side(rf.path, rf.summary, rf.episodes, rows, seeds, []))
            side = pool(parts)
            column = {s: i for i, s in enumerate(side.scene_seeds)}
            index = [column[s] for s in kept]
            built.append(Side(side.path, side.summary, side.grippers, side.successes[:, index],
                              side.attempts[:, index], side.dropped, side.unpaired, side.parts, tuple(kept)))
        out.append(built)
    return out[0], out[1], {"scene_seeds": kept, "dropped_scene_seeds": dropped, "left_out": left_out,
                            "calibration_scenes": budgets}


def run_rates(runs: list[Side]) -> np.ndarray:
    """(R,) float64 table rate of each run on its (shared) scenes."""
    return np.array([table_rate(r, np.ones((1, r.successes.shape[1])))[0] for r in runs])


def relabel_p(rates_a: np.ndarray, rates_b: np.ndarray, rng: np.random.Generator,
              draws: int) -> tuple[float, float, str]:
    """Two-sided p-value of the run-relabelling test of mean(B) - mean(A), the smallest p-value it
    can give, and how it was computed. Exact (every split of the runs into the two sides' sizes)
    up to :data:`EXACT_LIMIT` splits; else ``draws`` random splits, p = (1 + hits) / (1 + draws)."""
    both = np.concatenate([rates_a, rates_b])
    n, na = len(both), len(rates_a)
    observed = abs(rates_b.mean() - rates_a.mean())
    total = math.comb(n, na)
    smallest = (2 if na == n - na else 1) / total
    if total <= EXACT_LIMIT:
        picks = np.zeros((total, n), dtype=bool)
        for row, chosen in enumerate(itertools.combinations(range(n), na)):
            picks[row, list(chosen)] = True
        diffs = (~picks) @ both / (n - na) - picks @ both / na
        return float((np.abs(diffs) >= observed - 1e-12).mean()), smallest, f"exact, {total} relabellings"
    hits = 0
    for _ in range(draws):
        order = rng.permutation(n)
        hits += abs(both[order[na:]].mean() - both[order[:na]].mean()) >= observed - 1e-12
    return (1 + hits) / (1 + draws), 1 / (1 + draws), f"{draws} random relabellings"


def sign_p(diffs: np.ndarray, rng: np.random.Generator, draws: int) -> tuple[float, float, str]:
    """Two-sided p-value of the sign-flip test of the per-pair differences' mean, the smallest
    p-value it can give, and how it was computed (exact up to :data:`EXACT_LIMIT` sign patterns)."""
    k = len(diffs)
    observed = abs(diffs.sum())
    if 2**k <= EXACT_LIMIT:
        signs = np.array(list(itertools.product((1.0, -1.0), repeat=k)))
        return float((np.abs(signs @ diffs) >= observed - 1e-12).mean()), 2 / 2**k, f"exact, {2**k} sign patterns"
    signs = rng.choice((1.0, -1.0), size=(draws, k))
    hits = int((np.abs(signs @ diffs) >= observed - 1e-12).sum())
    return (1 + hits) / (1 + draws), 1 / (1 + draws), f"{draws} random sign patterns"


def t_test(rates_a: np.ndarray, rates_b: np.ndarray, paired: bool) -> dict:
    """Welch's (unpaired) or Student's paired t: p-value, 95% interval of the difference and its
    degrees of freedom; all None when the runs have no spread (every run rate of both sides, or
    every per-run difference, the same up to rounding): t is undefined."""
    name = "paired t" if paired else "Welch t"
    if paired:
        se = (rates_b - rates_a).std(ddof=1) / math.sqrt(len(rates_a))
    else:
        va, vb = rates_a.var(ddof=1) / len(rates_a), rates_b.var(ddof=1) / len(rates_b)
        se = math.sqrt(va + vb)
    if se < 1e-12:
        return {"test": name, "p_value": None, "ci95": None, "df": None}
    if paired:
        df = len(rates_a) - 1.0
    else:
        df = (va + vb) ** 2 / (va**2 / (len(rates_a) - 1) + vb**2 / (len(rates_b) - 1))
    diff = float(rates_b.mean() - rates_a.mean())
    half = float(stats.t.ppf(0.975, df)) * se
    p = float(2 * stats.t.sf(abs(diff) / se, df))
    return {"test": name, "p_value": p, "ci95": [diff - half, diff + half], "df": float(df)}


def compare_runs(runs_a: list[Side], runs_b: list[Side], info: dict, paired: bool,
                 draws: int = 10_000, seed: int = 0, across_cameras: bool = False) -> dict:
    """The comparison of B's runs against A's (JSON-ready); ``seed`` seeds the random relabellings
    (used only above :data:`EXACT_LIMIT`); ``across_cameras`` (sides of two camera counts, checked
    by :func:`run_sides`): the result records ``across_cameras`` and each side's ``cameras``."""
    ra, rb = run_rates(runs_a), run_rates(runs_b)
    rng = np.random.default_rng(seed)
    if paired:
        p, smallest, how = sign_p(rb - ra, rng, draws)
        test = f"sign-flip test of the per-run differences ({how})"
    else:
        p, smallest, how = relabel_p(ra, rb, rng, draws)
        test = f"run-relabelling test ({how})"

    def side(runs: list[Side], rates: np.ndarray, budget: dict[str, int] | None) -> dict:
        head = runs[0]
        return {
            "row": row_label(head.summary),
            **({"cameras": head.summary["cameras"]} if across_cameras else {}),
            "calibration_scenes": budget,
            "grippers": head.grippers,
            "candidates": _candidates(head.path, head.summary) if head.pooled else None,
            "runs": [{"path": r.path, "checkpoint": r.summary.get("checkpoint"),
                      "checkpoint_sha256": r.summary.get("checkpoint_sha256"), "rate": float(x),
                      "successes": int(r.successes.sum()), "attempts": int(r.attempts.sum())}
                     for r, x in zip(runs, rates)],
            "mean": float(rates.mean()),
            "sd": float(rates.std(ddof=1)),
            "range": [float(rates.min()), float(rates.max())],
        }

    return {
        "format": RUNS_FORMAT,
        "scene": runs_a[0].summary["scene"],
        "objects": runs_a[0].summary["objects"],
        "scenes": len(info["scene_seeds"]),
        "scene_seeds": info["scene_seeds"],
        "dropped_scene_seeds": info["dropped_scene_seeds"],
        "left_out_scenes": info["left_out"],
        "paired": paired,
        **({"across_cameras": True} if across_cameras else {}),
        "a": side(runs_a, ra, info["calibration_scenes"][0]),
        "b": side(runs_b, rb, info["calibration_scenes"][1]),
        "mean_difference": float(rb.mean() - ra.mean()),
        "run_differences": [float(x) for x in rb - ra] if paired else None,
        "t": t_test(ra, rb, paired),
        "randomization": {"test": test, "p_value": p, "smallest_p": smallest},
    }


def side_label(side: dict, cameras: bool = False) -> str:
    """A side's row, with its camera count (``cameras``: a comparison ``--across-cameras``) and its
    calibration budget where recorded (``calibration_scenes``; comparisons written before it was
    recorded lack the key)."""
    budget = side.get("calibration_scenes")
    row = side.get("row", "?") + (f", {side.get('cameras')} camera(s)" if cameras else "")
    return f"{row}, {_budget_text(budget)}" if is_budget(budget) else row


def report(c: dict) -> str:
    """Text lines of a run comparison from :func:`compare_runs`."""

    def side(tag: str, s: dict) -> str:
        rates = " ".join(f"{r['rate']:.3f}" for r in s["runs"])
        label = side_label(s, bool(c.get("across_cameras")))
        return (f"  {tag} {label}, {len(s['runs'])} runs: {rates} -> mean {s['mean']:.3f} "
                f"(sd {s['sd']:.3f}, range {s['range'][0]:.3f} to {s['range'][1]:.3f})")

    t = c["t"]
    if t["p_value"] is None:
        t_line = f"{t['test']}: none (no spread across runs: t is undefined)"
    else:
        t_line = (f"95% interval {t['ci95'][0]:+.3f} to {t['ci95'][1]:+.3f} ({t['test']}, df {t['df']:.1f}, "
                  f"p = {t['p_value']:.3g})")
    r = c["randomization"]
    left = sum(c["left_out_scenes"])
    head = (f"runs: {c['scene']} scenes of objects {c['objects']}, {c['scenes']} scenes run by every run"
            + (f" ({left} of the runs' scenes left out: not run by every run, or not with every gripper)"
               if left else "")
            + (f" ({len(c['dropped_scene_seeds'])} left out: other objects)" if c["dropped_scene_seeds"] else ""))
    kind = "paired by run" if c["paired"] else "unpaired"
    return "\n".join([
        head,
        side("A", c["a"]),
        side("B", c["b"]),
        f"  B - A, mean over runs ({kind}): {c['mean_difference']:+.3f}; {t_line}; {r['test']}: "
        f"p = {r['p_value']:.3g} (smallest possible {r['smallest_p']:.3g})",
    ]) + "\n"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m launcher evaluate runs",
        description="Compare two rows across training runs on the scenes every run ran: the mean over runs, "
        "a t interval and test against the spread across runs, and an exact randomization test over runs.",
    )
    ap.add_argument("--a", action="append", default=[], required=True, metavar="RUN.json[,RUN.json...]",
                    help="one training run of the baseline row: its result files (other scene seeds); repeat per run")
    ap.add_argument("--b", action="append", default=[], required=True, metavar="RUN.json[,RUN.json...]",
                    help="one training run of the row compared against A; repeat per run")
    ap.add_argument("--paired", action="store_true",
                    help="run i of B is the model of run i of A (two rows of one training run)")
    ap.add_argument("--across-cameras", action="store_true",
                    help="the sides are two camera counts (each side one count; the rest one cell)")
    ap.add_argument("--gripper", default=None, metavar="NAME[,NAME...]",
                    help="per-gripper results: keep only these grippers")
    ap.add_argument("--drop-mismatched-scenes", action="store_true",
                    help="leave out scene seeds whose objects differ between records (else: an error)")
    ap.add_argument("--draws", type=int, default=10_000,
                    help=f"random relabellings when there are more than {EXACT_LIMIT} (else exact)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random relabellings")
    ap.add_argument("--json", default=None, help="write the comparison here")
    return ap


def runs_cli(argv: list[str]) -> dict:
    """``evaluate runs``: parse ``argv``, print :func:`report`, write --json; returns the comparison."""
    args = _parser().parse_args(argv)
    if args.draws < 1:
        raise EvaluationError(f"--draws {args.draws}: expected >= 1")
    check_output_path("--json", args.json, [*args.a, *args.b])
    only = [g.strip() for g in args.gripper.split(",")] if args.gripper else None
    split = [[[f.strip() for f in group.split(",")] for group in groups] for groups in (args.a, args.b)]
    runs_a, runs_b, info = run_sides(split[0], split[1], only, args.paired, args.drop_mismatched_scenes,
                                     args.across_cameras)
    result = compare_runs(runs_a, runs_b, info, args.paired, args.draws, args.seed, args.across_cameras)
    print(report(result), end="")
    if args.json:
        write_json(args.json, result)
    return result
