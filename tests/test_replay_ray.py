"""Replay shards as Ray actors: restart after a kill keeps committed trials; sampling while a
separate Ray worker inserts. Slow (starts a local Ray cluster): run with ``-m slow``."""

from __future__ import annotations

import os

import numpy as np
import pytest

from replay.client import ReplayClient, start_remote_shards
from replay.synthetic import numbered_trial as make_trial
from replay.synthetic import small_config as tiny_cfg

pytestmark = pytest.mark.slow


@pytest.fixture
def ray_local():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


def test_ray_shards_restart_and_sample_while_inserting(tmp_path, ray_local):
    ray = ray_local
    cfg = tiny_cfg(capacity=64, shards=2)
    cfg.replay.max_inflight = 3
    handles = start_remote_shards(tmp_path / "r", cfg)
    client = ReplayClient(handles, cfg, seed=0)
    for i in range(12):
        client.insert(make_trial(cfg, i, label=i % 2 == 0))
        assert client.inflight <= 3
    client.flush()
    assert client.size() == 12

    # kill shard 0's process; Ray restarts it, it reopens its group and keeps every committed trial
    pid = ray.get(handles[0].__ray_call__.remote(lambda self: os.getpid()))
    ray.kill(handles[0], no_restart=False)
    assert client.size() == 12
    assert ray.get(handles[0].__ray_call__.remote(lambda self: os.getpid())) != pid
    batch = client.sample(8)
    assert batch.label.sum().item() == 4
    client.update_scores(batch.index, np.full(8, 0.25))
    client.flush()

    @ray.remote(num_cpus=0)
    def writer(hs, cfg, start, count):
        c = ReplayClient(hs, cfg, seed=start)
        for i in range(start, start + count):
            c.insert(make_trial(cfg, i, label=i % 3 == 0))
        c.flush()
        return count

    job = writer.remote(handles, cfg, 100, 24)
    sampled = 0
    while not ray.wait([job], timeout=0)[0]:
        b = client.sample(8)
        assert b.label.sum().item() == 4 and b.scene.shape[0] == 8
        sampled += 1
    assert ray.get(job) == 24
    assert client.size() == 36
    stats = client.stats()
    assert stats["total"]["visible"] == 36 and stats["total"]["lost"] == 0
    assert sampled >= 1
