"""Gripper encoding benchmark: prints one JSON line of medians (seconds).

    python tests/bench/bench_grippers.py [--repeats 5]

- ``encode_default_s``: one uncached encoding (opening + closed state) at the default grid
  (32 x 32 x 16 at 8 mm), from the spec: URDF load, geometry, FK, signed distance. Median over
  repeats and over the training grippers (one per procedural family).
- ``encode_paper_s``: the same at the paper grid (64 x 64 x 32 at 4 mm).
- ``encode_cached_s``: ``GripperEncoder.encode`` of 5 openings already in the memory cache.
- ``encode_default_real_s`` / ``encode_paper_real_s``: the uncached figure over the real
  (test-split, mesh) grippers.
- ``encode_state_default_s``: one more opening of a gripper whose geometry is already built
  (what an episode with a new opening costs), procedural grippers.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    os.environ.setdefault("ADAGRASP_CACHE", tempfile.mkdtemp(prefix="bench_grippers_"))

    from common.config import load_config
    from common.gripper import get_gripper
    from common.gripper_encoding import GripperEncoder, _GripperField, encode_gripper

    grids = {"default": load_config("default").gripper_grid, "paper": load_config("paper").gripper_grid}
    procedural = [get_gripper(n) for n in ("parallel_jaw-0", "revolute-0", "three_finger-0", "underactuated-0")]
    real = [get_gripper(n) for n in ("wsg_50", "panda_hand", "pr2_gripper", "xarm_gripper", "g1_three_finger")]
    out: dict[str, float] = {}
    for gname, grid in grids.items():
        for label, specs in (("", procedural), ("_real", real)):
            times = [_median_time(lambda s=s: encode_gripper(s, 1.0, 0.75, grid), args.repeats) for s in specs]
            out[f"encode_{gname}{label}_s"] = round(float(np.median(times)), 5)
    fields = [_GripperField(s, 1.0, grids["default"]) for s in procedural]
    out["encode_state_default_s"] = round(float(np.median(
        [_median_time(lambda f=f: f.sdf(0.6), args.repeats) for f in fields])), 5)
    enc = GripperEncoder(grids["default"], disk=False)
    openings = (0.5, 0.625, 0.75, 0.875, 1.0)
    enc.encode(procedural[0], 1.0, openings)
    out["encode_cached_s"] = round(_median_time(lambda: enc.encode(procedural[0], 1.0, openings), args.repeats * 20), 6)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
