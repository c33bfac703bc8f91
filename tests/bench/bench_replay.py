"""Replay benchmark on real simulated observations: prints ONE JSON line.

Observations come from ``actors.simulation.Simulation`` (PyBullet scenes of the ``train``
object set, rendered and fused into the TSDF) and gripper encodings from
``common.gripper_encoding.GripperEncoder`` (training grippers, scale and 5 openings drawn per
episode as in training, so every trial brings a new gripper key: the worst case for the
gripper table). Labels, scores and actions are random: they do not change the storage.

Keys (medians; seconds or bytes):

- ``bytes_per_trial_{1obj,5obj}_{paper,default}``: bytes a trial adds on disk (file sizes,
  everything: volumes, gripper-table row, columns; the group's fixed metadata excluded and
  reported as ``group_overhead_bytes``); ``..._allocated`` counts filesystem blocks instead.
- ``insert_s``: one in-process insert at paper scale (quantise + compress + write + commit).
- ``sample_b8_{paper,default}_s``: one batch of 8 (index, rank draw, read from disk, decode,
  float32 tensors) from 2 shards of 64 trials; the OS page cache is warm. ``..._cpu_s`` is the
  process CPU time of the same call (what it costs when the machine is not oversubscribed;
  ``loadavg_1min`` says how busy the machine was).
- ``inserts_per_s_4w2s``: 4 Ray writer tasks inserting default-scale trials into 2 shard
  actors (bounded in-flight requests, every insert flushed).
- ``tsdf_max_abs_error`` (truncation units) and ``tsdf_max_abs_error_mm``: measured round-trip
  error of the stored TSDF at paper scale.

Usage::

    python tests/bench/bench_replay.py [--trials 16] [--samples 30] [--skip-ray]
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import json
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import sys

import numpy as np

from common.config import Config, load_config
from common.gripper import list_grippers
from common.gripper_encoding import GripperEncoder, gripper_key
from common.observation import Trial, TrialMeta
from replay.client import ReplayClient, open_local_shards
from replay.schema import encode_trial
from replay.shard import ReplayShard, disk_usage


@contextlib.contextmanager
def _stdout_fd_silenced():
    """pybullet prints a build banner from C when imported; keep this script's stdout to one JSON line."""
    sys.stdout.flush()
    saved, devnull = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        yield
    finally:
        ctypes.CDLL(None).fflush(None)
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def collect(cfg: Config, kind: str, count: int, seed: int) -> list[Trial]:
    """``count`` trials, each on a fresh ``kind`` scene with a fresh gripper, scale and openings."""
    with _stdout_fd_silenced():
        from actors.simulation import Simulation
    rng = np.random.default_rng(seed)
    specs = list_grippers(split="train")
    encoder = GripperEncoder(cfg.gripper_grid, disk=False)
    lo, hi = cfg.grippers.opening_range
    x, y, _ = cfg.scene_grid.shape
    trials = []
    with Simulation(cfg, seed=seed) as sim:
        for e in range(count):
            spec = specs[int(rng.integers(len(specs)))]
            scale = float(rng.uniform(*cfg.grippers.scale_range))
            openings = tuple(float(o) for o in np.sort(rng.uniform(lo, hi, cfg.grippers.train_openings)))
            encoding = encoder.encode(spec, scale, openings)
            sim.reset_scene(kind, "train")
            obs = sim.observe()
            action = (int(rng.integers(x)), int(rng.integers(y)), int(rng.integers(cfg.model.rotations)),
                      int(rng.integers(len(openings))))
            meta = TrialMeta(
                episode_id=e, step=0, scene=kind, object_set="train", object_ids=sim.object_ids(), gripper=spec.name,
                gripper_scale=scale, openings=openings, cameras=cfg.sim.cameras, actor_id=0, policy_version=0,
                seed=seed, wall_time=time.time(),
            )
            trials.append(Trial(obs, gripper_key(spec.name, scale, openings), np.asarray(encoding), action,
                                bool(rng.random() < 0.5), float(rng.random()), meta).validate())
    return trials


def bytes_per_trial(cfg: Config, trials: list[Trial], where: Path) -> dict:
    """Marginal bytes per trial in one fresh shard; also the insert times."""
    cfg = dataclasses.replace(cfg, replay=dataclasses.replace(cfg.replay, capacity=max(64, len(trials))))
    shard = ReplayShard(where, cfg)
    empty, empty_alloc = disk_usage(where)
    times = []
    for t in trials:
        t0 = time.perf_counter()
        shard.insert(t)
        times.append(time.perf_counter() - t0)
    full, full_alloc = disk_usage(where)
    err = max(
        float(np.abs(shard.get_trial(n).observation.tsdf - t.observation.tsdf).max()) for n, t in enumerate(trials)
    )
    shard.close()
    return {
        "bytes": (full - empty) / len(trials),
        "allocated": (full_alloc - empty_alloc) / len(trials),
        "overhead": empty,
        "insert_s": statistics.median(times),
        "tsdf_err": err,
    }


def sample_time(cfg: Config, trials: list[Trial], where: Path, samples: int, seed: int) -> tuple[float, float]:
    """Median wall time and median process CPU time of one batch of 8 from 2 in-process shards of 64 trials."""
    cfg = dataclasses.replace(cfg, replay=dataclasses.replace(cfg.replay, shards=2, capacity=128))
    shards = open_local_shards(where, cfg)
    client = ReplayClient(shards, cfg, seed=seed)
    rng = np.random.default_rng(seed)
    for n in range(64):
        t = trials[n % len(trials)]
        client.insert(dataclasses.replace(t, label=bool(rng.random() < 0.3), score=float(rng.random()),
                                          meta=dataclasses.replace(t.meta, episode_id=n)))
    client.flush()
    times, cpu = [], []
    for _ in range(samples + 2):
        t0, c0 = time.perf_counter(), time.process_time()
        batch = client.sample(8)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        del batch
    for s in shards:
        s.close()
    return statistics.median(times[2:]), statistics.median(cpu[2:])


def ray_throughput(cfg: Config, trials: list[Trial], where: Path, per_writer: int) -> float:
    """Inserts per second of 4 writer tasks into 2 shard actors."""
    import ray

    from replay.client import start_remote_shards

    cfg = dataclasses.replace(cfg, replay=dataclasses.replace(cfg.replay, shards=2, capacity=4 * per_writer + 64))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        handles = start_remote_shards(where, cfg)
        trials_ref = ray.put(trials)

        @ray.remote(num_cpus=0)
        def writer(hs, cfg, trials, offset, count):
            client = ReplayClient(hs, cfg, seed=offset)
            for n in range(count):
                t = trials[n % len(trials)]
                client.insert(dataclasses.replace(t, meta=dataclasses.replace(t.meta, episode_id=offset + n)))
            client.flush()
            return count

        ray.get([writer.remote(handles, cfg, trials_ref, 10_000 * (w + 1), 2) for w in range(4)])  # warm-up
        t0 = time.perf_counter()
        done = ray.get([writer.remote(handles, cfg, trials_ref, 100_000 * (w + 1), per_writer) for w in range(4)])
        elapsed = time.perf_counter() - t0
        return sum(done) / elapsed
    finally:
        ray.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=16, help="trials per scene kind and scale")
    parser.add_argument("--samples", type=int, default=30, help="batches timed per scale")
    parser.add_argument("--per-writer", type=int, default=40, help="inserts per writer in the 4w2s run")
    parser.add_argument("--skip-ray", action="store_true")
    args = parser.parse_args()
    out: dict = {}
    tmp = Path(tempfile.mkdtemp(prefix="bench_replay_"))
    try:
        for scale in ("paper", "default"):
            cfg = load_config(scale)
            kinds = {}
            for label, kind in (("1obj", "single"), ("5obj", "multi")):
                trials = collect(cfg, kind, args.trials, seed=1 if kind == "single" else 2)
                res = bytes_per_trial(cfg, trials, tmp / f"{scale}_{label}")
                out[f"bytes_per_trial_{label}_{scale}"] = round(res["bytes"])
                out[f"bytes_per_trial_{label}_{scale}_allocated"] = round(res["allocated"])
                if scale == "paper":
                    out.setdefault("insert_s", [])
                    out["insert_s"].append(res["insert_s"])
                    out["tsdf_max_abs_error"] = max(out.get("tsdf_max_abs_error", 0.0), res["tsdf_err"])
                    out["group_overhead_bytes"] = res["overhead"]
                kinds[label] = trials
            wall, cpu = sample_time(cfg, kinds["1obj"] + kinds["5obj"], tmp / f"{scale}_sample", args.samples, seed=3)
            out[f"sample_b8_{scale}_s"] = wall
            out[f"sample_b8_{scale}_cpu_s"] = cpu
            if scale == "default" and not args.skip_ray:
                out["inserts_per_s_4w2s"] = ray_throughput(cfg, kinds["1obj"] + kinds["5obj"], tmp / "ray",
                                                           args.per_writer)
            del kinds
        out["insert_s"] = statistics.median(out["insert_s"])
        paper = load_config("paper")
        out["tsdf_max_abs_error_mm"] = out["tsdf_max_abs_error"] * paper.scene_grid.truncation * 1000
        encode_t = []
        trial = collect(paper, "single", 1, seed=9)[0]
        for n in range(5):
            t0 = time.perf_counter()
            encode_trial(trial, paper.replay.tsdf_levels, (1, n))
            encode_t.append(time.perf_counter() - t0)
        out["insert_encode_s"] = statistics.median(encode_t)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out["loadavg_1min"] = os.getloadavg()[0]
    print(json.dumps({k: (round(v, 6) if isinstance(v, float) else v) for k, v in out.items()}))


if __name__ == "__main__":
    main()
