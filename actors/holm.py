"""``python -m launcher evaluate holm FILE.json ...``: Holm's correction over several comparisons.

Each ``evaluate compare`` or ``evaluate runs`` call tests one difference. Read together, several
such tests find a difference by chance more often than each p-value says: seven independent null
comparisons give a p-value below 0.05 three times in ten (1 - 0.95^7). Holm's step-down
procedure controls the chance of any false finding among the m tests (the family-wise error) at
the level asked, provided each p-value is valid, however the tests depend on each other:

- sort the p-values p_(1) <= ... <= p_(m);
- the adjusted p-value of the i-th smallest is max over j <= i of min(1, (m - j + 1) p_(j));
- a comparison is separated at level alpha when its adjusted p-value is at most alpha.

The family is the files named on one command line: the comparisons read as one claim (the steps of
one ordering, say). Which p-value is corrected: an ``evaluate compare`` file's scene permutation
test (a comparison without one, adagrasp against a per-gripper row, stops with one line); an
``evaluate runs`` file's t test (``--test t``, the default) or its randomization test (``--test
randomization``; few runs bound it below, so Holm's factor can keep every adjusted value above
alpha whatever the data: the report gives each file's smallest possible p-value). A file is
labelled by its rows, a runs file's with each side's calibration budget where it records one.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from actors.compare import COMPARE_FORMAT
from actors.compare_runs import RUNS_FORMAT, is_budget, side_label
from actors.evaluate import EvaluationError, check_output_path, read_json, write_json

HOLM_FORMAT = "adagrasp-scale-holm/1"
"""Value of the ``format`` key of a Holm correction JSON."""
TESTS = ("t", "randomization")
"""Tests of an ``evaluate runs`` file whose p-value can be corrected."""


def holm(p_values) -> np.ndarray:
    """Holm-adjusted p-values of ``p_values`` (m,) float in [0, 1], in their order; (m,) float64."""
    p = np.asarray(p_values, dtype=np.float64)
    if p.ndim != 1 or p.size == 0 or not np.all((p >= 0.0) & (p <= 1.0)):
        raise ValueError(f"p_values: expected a non-empty list of values in [0, 1], got {p_values!r}")
    m = p.size
    order = np.argsort(p, kind="stable")
    stepped = np.minimum(1.0, (m - np.arange(m)) * p[order])
    adjusted = np.empty(m)
    adjusted[order] = np.maximum.accumulate(stepped)
    return adjusted


def _number(path: str, key: str, value, optional: bool = False):
    """``value`` as a float; one line naming the file and ``key`` when it is not a number (None
    passes through when ``optional``)."""
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise EvaluationError(f"{path}: {key}: expected a number, got {value!r}")
    return float(value)


def _read(path: str, test: str) -> dict:
    """One comparison file: its label (its rows; a runs file's with each side's calibration budget
    where recorded and, across camera counts, camera count), difference, the p-value corrected and
    the smallest it can be."""
    data = read_json(path)
    fmt = data.get("format") if isinstance(data, dict) else type(data).__name__
    if fmt not in (COMPARE_FORMAT, RUNS_FORMAT):
        raise EvaluationError(f"{path}: format: {fmt!r}, expected {COMPARE_FORMAT!r} (evaluate compare) or "
                              f"{RUNS_FORMAT!r} (evaluate runs)")
    for side in ("a", "b"):
        if not isinstance(data.get(side), dict):
            raise EvaluationError(f"{path}: {side}: missing or not an object")
    a, b = data["a"], data["b"]
    for tag, side in (("a", a), ("b", b)):
        if not isinstance(side.get("row", ""), str):
            raise EvaluationError(f"{path}: {tag}.row: expected a row name, got {side.get('row')!r}")
    cameras = fmt == RUNS_FORMAT and bool(data.get("across_cameras"))
    label = f"{side_label(a, cameras)} -> {side_label(b, cameras)}"
    if fmt == COMPARE_FORMAT:
        if a.get("row") == b.get("row"):
            label = f"{a.get('row', '?')}: {a.get('checkpoint')} -> {b.get('checkpoint')}"
        if data.get("p_value") is None:
            raise EvaluationError(f"{path}: p_value: none (an adagrasp row against a per-gripper row has no "
                                  "permutation test; its interval is the comparison)")
        record, key, difference, smallest = data, "p_value", data.get("rate_difference"), None
        difference_key = "rate_difference"
    else:
        for tag, side in (("a", a), ("b", b)):
            budget = side.get("calibration_scenes")
            if budget is not None and not is_budget(budget):
                raise EvaluationError(f"{path}: {tag}: calibration_scenes: expected null or gripper -> scenes "
                                      f"(positive integers), got {budget!r}")
        label += " (runs)"
        record, key = data.get(test), f"{test}: p_value"
        if not isinstance(record, dict) or "p_value" not in record:
            raise EvaluationError(f"{path}: {test}: missing (a run comparison records 't' and 'randomization')")
        if record["p_value"] is None:
            raise EvaluationError(f"{path}: {key}: none (the runs have no spread, so t is undefined; "
                                  "use --test randomization)")
        difference, difference_key = data.get("mean_difference"), "mean_difference"
        smallest = _number(path, f"{test}: smallest_p", record.get("smallest_p"), optional=True)
    p = _number(path, key, record["p_value"])
    if not 0.0 <= p <= 1.0:
        raise EvaluationError(f"{path}: {key}: expected a value in [0, 1], got {p!r}")
    return {"path": path, "label": label, "scene": data.get("scene"),
            "difference": _number(path, difference_key, difference, optional=True),
            "test": record.get("test", test), "p_value": p, "smallest_p": smallest}


def correct(paths: list[str], test: str = "t", alpha: float = 0.05) -> dict:
    """Holm's correction over the comparison files ``paths`` (one family); the JSON-ready record."""
    if test not in TESTS:
        raise EvaluationError(f"--test {test!r}: expected one of {', '.join(TESTS)}")
    if not 0.0 < alpha < 1.0:
        raise EvaluationError(f"--alpha {alpha!r}: expected a level between 0 and 1")
    if len(paths) < 2:
        raise EvaluationError(f"{len(paths)} comparison file(s): a correction needs at least 2 tests")
    real = [os.path.realpath(p) for p in paths]
    for i, r in enumerate(real):
        if r in real[:i]:
            raise EvaluationError(f"{paths[i]}: named twice (as {paths[real.index(r)]}; one test counted twice "
                                  "would weaken the correction)")
    rows = [_read(p, test) for p in paths]
    adjusted = holm([r["p_value"] for r in rows])
    for r, a in zip(rows, adjusted):
        r["holm_p"] = float(a)
        r["separated"] = bool(a <= alpha)
    return {"format": HOLM_FORMAT, "tests": len(rows), "alpha": alpha, "runs_test": test, "comparisons": rows}


def report(result: dict) -> str:
    """Human-readable table of :func:`correct`'s record."""
    lines = [f"holm: {result['tests']} tests, family-wise level {result['alpha']:g} "
             f"(evaluate runs files: their {result['runs_test']} test)"]
    for r in result["comparisons"]:
        diff = "" if r["difference"] is None else f"{r['difference']:+.3f}"
        floor = "" if r["smallest_p"] is None else f" (smallest possible {r['smallest_p']:.3g})"
        mark = "separated" if r["separated"] else "not separated"
        lines.append(f"  {r['path']}: {r['label']} {diff}: p = {r['p_value']:.3g}{floor}, Holm p = "
                     f"{r['holm_p']:.3g}: {mark}")
    return "\n".join(lines) + "\n"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m launcher evaluate holm",
        description="Holm's step-down correction over the p-values of several evaluate compare / evaluate runs "
        "files read as one family of tests.",
    )
    ap.add_argument("files", nargs="+", metavar="COMPARISON.json",
                    help="evaluate compare or evaluate runs --json files")
    ap.add_argument("--test", default="t", choices=TESTS,
                    help="which test of an evaluate runs file is corrected (default: t)")
    ap.add_argument("--alpha", type=float, default=0.05, help="family-wise error level (default: 0.05)")
    ap.add_argument("--json", default=None, help="write the correction here")
    return ap


def holm_cli(argv: list[str]) -> dict:
    """``evaluate holm``: parse ``argv``, print :func:`report`, write --json; returns the record."""
    args = _parser().parse_args(argv)
    check_output_path("--json", args.json, args.files)
    result = correct(args.files, args.test, args.alpha)
    print(report(result), end="")
    if args.json:
        write_json(args.json, result)
    return result
