"""Throughput of the distributed loop; prints one JSON line.

    python tests/bench/bench_loop.py [--config default] [--seconds 60] [--actors 1,2]

- trials_per_s_<N>actors: committed trials per second with N GraspActor processes (Ray,
  untrained weights, epsilon 0.8, single-object scenes) inserting into the replay shards; no
  learner runs meanwhile, so this is the collection ceiling of the machine.
- learner_samples_per_s: trials per second through the learner (sample from the Zarr replay,
  augment, forward, backward, Adam, score write-back), in this process, over the replay the
  actors just filled.
- weights_broadcast_s: median seconds from the learner's ray.put of a new version until every
  actor has loaded it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch


def _collect(cfg, root: Path, n_actors: int, seconds: float) -> tuple[float, float]:
    import ray

    from common.runtime import ray_init
    from learner.loop import ActorProcess, total_inserted
    from replay.client import ReplayClient, start_remote_shards

    ray_init(None, num_cpus=max(os.cpu_count() or 1, n_actors + 1))
    try:
        shards = start_remote_shards(root, cfg)
        replay = ReplayClient(shards, cfg)
        cls = ray.remote(num_cpus=1)(ActorProcess)
        actors = [cls.remote(cfg, i, 0, shards) for i in range(n_actors)]
        ray.get([a.pid.remote() for a in actors])
        start = total_inserted(replay)
        t0 = time.time()
        pending = {a.run_episodes.remote(1, 0.8, -1, [None], 0): a for a in actors}
        while time.time() - t0 < seconds:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                a = pending.pop(ref)
                ray.get(ref)
                pending[a.run_episodes.remote(1, 0.8, -1, [None], 0)] = a
        rate = (total_inserted(replay) - start) / (time.time() - t0)
        ray.wait(list(pending), num_returns=len(pending), timeout=120)
        broadcast = _broadcast(cfg, actors)
        return rate, broadcast
    finally:
        ray.shutdown()


def _broadcast(cfg, actors) -> float:
    """Median seconds for a ray.put of the weights plus every actor loading them."""
    import ray

    from common.network import build_model

    state = build_model(cfg).state_dict()
    times = []
    for version in range(1, 6):
        t0 = time.perf_counter()
        ref = ray.put(state)
        ray.get([a.run_episodes.remote(0, 0.8, version, [ref], 0) for a in actors])
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _learner_rate(cfg, root: Path, steps: int) -> float:
    from learner.learner import Learner
    from replay.client import ReplayClient, open_local_shards

    shards = open_local_shards(root, cfg)
    learner = Learner(cfg, ReplayClient(shards, cfg))
    learner.train(1)  # warm-up
    t0 = time.perf_counter()
    learner.train(steps)
    return steps * cfg.learner.batch_size / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    from common.config import load_config

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="default")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--actors", default="1,2")
    p.add_argument("--learner-steps", type=int, default=10)
    args = p.parse_args(argv)
    cfg = load_config(args.config)
    out: dict = {"config": args.config, "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads()}
    with tempfile.TemporaryDirectory() as tmp:
        broadcast = []
        last_root = None
        for n in (int(v) for v in args.actors.split(",")):
            root = Path(tmp) / f"replay_{n}"
            rate, b = _collect(cfg, root, n, args.seconds)
            out[f"trials_per_s_{n}actor" + ("s" if n > 1 else "")] = round(rate, 4)
            broadcast.append(b)
            last_root = root
        out["weights_broadcast_s"] = round(statistics.median(broadcast), 4)
        out["learner_samples_per_s"] = round(_learner_rate(cfg, last_root, args.learner_steps), 3)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
