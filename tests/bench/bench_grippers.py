"""Gripper encoding benchmark: prints one JSON line of medians (seconds).

    python tests/bench/bench_grippers.py [--repeats 5]

- ``encode_default_s``: one uncached encoding (opening + closed state) at a new scale and
  opening, at the default grid (32 x 32 x 16 at 8 mm): forward kinematics and signed distance of
  every part. This is what an episode costs when its (gripper, scale, opening) is not in the
  cache. The gripper's geometry is already built (it is built once per gripper and process,
  scale-free; see ``first_*``). Median over repeats and over the training grippers (one per
  procedural family); scales in the training range 0.8-1.2.
- ``encode_paper_s``: the same at the paper grid (64 x 64 x 32 at 4 mm).
- ``encode_default_real_s`` / ``encode_paper_real_s``: the same over the real (test-split,
  mesh) grippers; ``*_max_s`` is the slowest real gripper's median.
- ``first_default_s`` / ``first_default_real_s`` / ``first_paper_real_s``: the first encoding of a
  gripper in a process, from its spec: URDF and mesh loading, convex hulls, surface samples, the
  mesh parts' distance tables, then the encoding.
- ``encode_cached_s``: ``GripperEncoder.encode`` of 5 openings already in the memory cache.
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
    for i in range(repeats):
        t = time.perf_counter()
        fn(i)
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
    rng = np.random.default_rng(0)
    states = [(float(s), float(o)) for s, o in zip(rng.uniform(0.8, 1.2, args.repeats), rng.uniform(0.0, 1.0, args.repeats))]
    out: dict[str, float] = {}
    for gname, grid in grids.items():
        for label, specs in (("", procedural), ("_real", real)):
            if gname == "default" or label:
                firsts = [_median_time(lambda i, s=s: encode_gripper(s, 1.0, 0.75, grid), args.repeats) for s in specs]
                out[f"first_{gname}{label}_s"] = round(float(np.median(firsts)), 5)
            times = []
            for spec in specs:
                field = _GripperField(spec, grid)
                field.sdf(1.0, 0.8)
                times.append(_median_time(lambda i, f=field: (f.sdf(states[i][1], states[i][0]), f.sdf(0.0, states[i][0])),
                                          args.repeats))
            out[f"encode_{gname}{label}_s"] = round(float(np.median(times)), 5)
            if label:
                out[f"encode_{gname}{label}_max_s"] = round(float(np.max(times)), 5)
    enc = GripperEncoder(grids["default"], disk=False)
    openings = (0.5, 0.625, 0.75, 0.875, 1.0)
    enc.encode(procedural[0], 1.0, openings)
    out["encode_cached_s"] = round(_median_time(lambda i: enc.encode(procedural[0], 1.0, openings), args.repeats * 20), 6)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
