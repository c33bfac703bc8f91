"""Simulation benchmark: prints ONE JSON line of medians in seconds.

Keys: reset_1obj_s, reset_5obj_s (drop + settle + fence), observe_{1,4}cam_{default,paper}_s
(render + TSDF fusion), grasp_step_s (grasp primitive + label on a single-object scene),
trial_single_{default,paper}_s (a whole single-object trial: reset, observe, cached gripper
encoding, heuristic policy, grasp, label).

Usage::

    python tests/bench/bench_sim.py [--repeats 20] [--objects train] [--gripper parallel_jaw-0]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from actors.grasp import execute_grasp
from actors.policies import make_policy
from actors.simulation import Simulation
from common.config import load_config
from common.gripper import get_gripper
from common.gripper_encoding import GripperEncoder


def _median(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _observe(config: str, cameras: int, objects: str, repeats: int) -> float:
    cfg = load_config(config, [f"sim.cameras={cameras}"])
    with Simulation(cfg, seed=0) as sim:
        sim.reset_scene("multi", objects)
        sim.observe()
        return _median(sim.observe, repeats)


def _trials(config: str, objects: str, gripper: str, repeats: int) -> tuple[float, float]:
    """Median whole single-object trial and median grasp primitive (+ label), seconds."""
    cfg = load_config(config)
    spec = get_gripper(gripper)
    openings = tuple(cfg.grippers.eval_openings)
    encoder = GripperEncoder(cfg.gripper_grid)
    encoder.encode(spec, 1.0, openings)
    policy = make_policy("heuristic", cfg)
    trial_s, grasp_s = [], []
    with Simulation(cfg, seed=0) as sim:
        gripper = sim.load_gripper(spec, 1.0)
        for n in range(repeats + 1):
            t0 = time.perf_counter()
            sim.reset_scene("single", objects, seed=n)
            obs = sim.observe()
            encoding = encoder.encode(spec, 1.0, openings)
            assert encoding.shape[0] == len(openings)
            action, _ = policy.act(obs, openings, sim.rng)
            t1 = time.perf_counter()
            execute_grasp(sim, gripper, action, openings, obs.heightmap)
            t2 = time.perf_counter()
            if n > 0:
                trial_s.append(t2 - t0)
                grasp_s.append(t2 - t1)
    return float(np.median(trial_s)), float(np.median(grasp_s))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--objects", default="train")
    ap.add_argument("--gripper", default="parallel_jaw-0")
    args = ap.parse_args()
    r = args.repeats
    cfg = load_config("default")
    with Simulation(cfg, seed=0) as sim:
        reset_1 = _median(lambda: sim.reset_scene("single", args.objects), r)
        reset_5 = _median(lambda: sim.reset_scene("multi", args.objects), r)
    trial_default, grasp_step = _trials("default", args.objects, args.gripper, r)
    trial_paper, _ = _trials("paper", args.objects, args.gripper, r)
    result = {
        "reset_1obj_s": reset_1,
        "reset_5obj_s": reset_5,
        "observe_1cam_default_s": _observe("default", 1, args.objects, r),
        "observe_4cam_default_s": _observe("default", 4, args.objects, r),
        "observe_1cam_paper_s": _observe("paper", 1, args.objects, r),
        "observe_4cam_paper_s": _observe("paper", 4, args.objects, r),
        "grasp_step_s": grasp_step,
        "trial_single_default_s": trial_default,
        "trial_single_paper_s": trial_paper,
    }
    print(json.dumps({k: round(v, 4) for k, v in result.items()}))


if __name__ == "__main__":
    main()
