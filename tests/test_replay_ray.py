"""Replay shards as Ray actors: a shard its actor cannot open is one line naming it; restart after
a kill keeps committed trials; sampling while a separate Ray worker inserts (slow: ``-m slow``)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from replay.client import ReplayClient, open_local_shards, start_remote_shards
from replay.schema import ReplayError
from replay.synthetic import numbered_trial as make_trial
from replay.synthetic import small_config as tiny_cfg


@pytest.fixture
def ray_local():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


def test_shard_its_actor_cannot_open_is_one_line_naming_it(tmp_path, ray_local):
    """A config the stored trials cannot take used to fail in the shard actors' constructors,
    which Ray reports as tracebacks and restarts; the shards are now opened in this process
    first, and the error names the shard and the field, with nothing written."""
    cfg = tiny_cfg(capacity=64, shards=2)
    for shard in open_local_shards(tmp_path / "r", cfg):
        shard.insert(make_trial(cfg, 0))
        shard.close()
    before = {p: p.read_bytes() for p in sorted((tmp_path / "r").rglob("*")) if p.is_file()}
    other = tiny_cfg(capacity=64, shards=2)
    other.model.rotations = 8
    with pytest.raises(ReplayError) as e:
        start_remote_shards(tmp_path / "r", other)
    line = str(e.value)
    assert "\n" not in line and "shard_000" in line and "rotations: stored 16, config gives 8" in line, line
    assert {p: p.read_bytes() for p in sorted((tmp_path / "r").rglob("*")) if p.is_file()} == before
    assert len(start_remote_shards(tmp_path / "r", cfg)) == 2, "with its own config the replay still opens"


@pytest.mark.slow
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
