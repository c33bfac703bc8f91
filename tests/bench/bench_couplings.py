"""Coupled-finger rigidity benchmark: lift tests per gripper at several solver-iteration counts.

    python tests/bench/bench_couplings.py [--grippers NAME,...] [--iterations 50,300]

For every gripper (default: the 32 training grippers and the 5 real test grippers) and every
``numSolverIterations`` value, :func:`actors.bullet_gripper.lift_test` runs on a 4 cm box and a
4 cm cylinder at 4 placements (on the TCP axis, 1 cm off along x, 1 cm off along y, and
(-1, 0.5) cm), 8 lifts in all. Prints one JSON line per (gripper, iterations): ``lifted`` (of 8),
``held_error_median`` / ``held_error_max`` (:attr:`LiftResult.coupling_error_held`, rad or m:
how far the coupled joints are from their kinematics when closing on the object ends) and
``lift_s`` (median wall seconds of one lift test); then a summary line per iterations value with
the totals and the median lift time as a ratio to the first iterations value (same run, same
machine).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np

PLACEMENTS = ((0.0, 0.0), (0.01, 0.0), (0.0, 0.01), (-0.01, 0.005))
"""Object centre offsets (m) from the TCP axis."""
SHAPES = ("box", "cylinder")
"""Lift-test objects, 4 cm each."""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--grippers", default="", help="comma-separated names (default: train + test)")
    ap.add_argument("--iterations", default="50,300", help="comma-separated solver-iteration counts")
    args = ap.parse_args()
    os.environ.setdefault("ADAGRASP_CACHE", tempfile.mkdtemp(prefix="bench_couplings_"))

    from actors.bullet_gripper import lift_test
    from common.gripper import get_gripper, list_grippers

    if args.grippers:
        specs = [get_gripper(n) for n in args.grippers.split(",")]
    else:
        specs = list_grippers("train") + list_grippers("test")
    iterations = [int(v) for v in args.iterations.split(",")]
    totals = {it: {"lifted": 0, "lifts": 0, "errors": [], "times": []} for it in iterations}
    for spec in specs:
        for it in iterations:
            results, times = [], []
            for shape in SHAPES:
                for off in PLACEMENTS:
                    t = time.perf_counter()
                    results.append(lift_test(spec, 1.0, shape, 0.04, offset=off, solver_iterations=it))
                    times.append(time.perf_counter() - t)
            errors = [r.coupling_error_held for r in results]
            row = {
                "gripper": spec.name,
                "iterations": it,
                "lifted": sum(r.success for r in results),
                "lifts": len(results),
                "held_error_median": round(float(np.median(errors)), 5),
                "held_error_max": round(float(np.max(errors)), 5),
                "lift_s": round(float(np.median(times)), 3),
            }
            print(json.dumps(row), flush=True)
            tot = totals[it]
            tot["lifted"] += row["lifted"]
            tot["lifts"] += row["lifts"]
            tot["errors"].append(row["held_error_median"])
            tot["times"].extend(times)
    base = float(np.median(totals[iterations[0]]["times"]))
    for it, tot in totals.items():
        med = float(np.median(tot["times"]))
        print(json.dumps({
            "summary_iterations": it,
            "lifted": tot["lifted"],
            "lifts": tot["lifts"],
            "grippers_with_median_held_error_over_0.05": int(sum(e > 0.05 for e in tot["errors"])),
            "lift_s_median": round(med, 3),
            "lift_s_ratio": round(med / base, 3),
        }), flush=True)


if __name__ == "__main__":
    main()
