"""Replay shard and client: round trip, FIFO, gripper table, sampling, scores, bad input, corruption."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr

from replay.client import ReplayClient, open_local_shards
from replay.sampler import BufferPool, draw_balanced, rank_probabilities
from replay.schema import (
    HEIGHTMAP_STEP,
    ReplayCorruptError,
    ReplayEmptyError,
    ReplayError,
    ReplayInputError,
    ReplaySchemaError,
    encode_trial,
    max_errors,
)
from replay.shard import ReplayCorruptWarning, ReplayShard, find_shards
from replay.synthetic import numbered_trial as make_trial
from replay.synthetic import small_config as tiny_cfg
from replay.synthetic import synthetic_gripper_encoding, synthetic_trial


def tree_digest(path: Path) -> dict[str, str]:
    return {
        str(p.relative_to(path)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(path.rglob("*"))
        if p.is_file()
    }


def one_line(e: pytest.ExceptionInfo) -> str:
    msg = str(e.value)
    assert "\n" not in msg, msg
    return msg


# --------------------------------------------------------------------------------------
# Storage
# --------------------------------------------------------------------------------------


def test_round_trip_exact_meta_and_bounded_volume_error(tmp_path):
    cfg = tiny_cfg()
    shard = ReplayShard(tmp_path / "s", cfg)
    trials = [make_trial(cfg, i, n_objects=3, n_obstacles=2) for i in range(5)]
    for t in trials:
        t.meta = dataclasses.replace(t.meta, wall_time=1.7e9 + 1 / 3, object_ids=("ycb/ä", "set/x y"))
        shard.insert(t)
    err = max_errors(cfg.replay.tsdf_levels)
    for n, t in enumerate(trials):
        got = shard.get_trial(n)
        assert got.meta == t.meta  # every field exactly, floats bit for bit
        assert got.action == t.action and got.label == t.label and got.score == t.score
        assert got.gripper_key == t.gripper_key
        assert np.abs(got.observation.tsdf - t.observation.tsdf).max() <= err["tsdf"] + 1e-7
        assert np.abs(got.observation.obstacle - t.observation.obstacle).max() <= err["obstacle"] + 1e-7
        assert np.abs(got.observation.heightmap - t.observation.heightmap).max() <= err["heightmap_m"] + 1e-7
        assert np.array_equal(got.observation.valid, t.observation.valid)
        s = t.action[3]
        assert np.abs(got.gripper_encoding - t.gripper_encoding[s]).max() <= err["gripper_tsdf"] + 1e-7
        # saturated values (free space) come back exactly
        free = t.observation.tsdf == 1.0
        assert np.all(got.observation.tsdf[free] == 1.0)
    assert err["tsdf"] == pytest.approx(1 / 254) and err["heightmap_m"] == pytest.approx(HEIGHTMAP_STEP / 2)


def test_group_opens_with_plain_zarr_and_documents_itself(tmp_path):
    cfg = tiny_cfg(capacity=6, chunk=4)  # the second column chunk is an edge chunk (slots 4..5)
    shard = ReplayShard(tmp_path / "s", cfg)
    trials = [make_trial(cfg, i) for i in range(6)]
    trials[5].meta = dataclasses.replace(trials[5].meta, object_ids=("ycb/025_mug", "set/ü ✓"))
    for t in trials:
        shard.insert(t)
    shard.update_scores([5], [0.125])
    shard.close()
    g = zarr.open_group(str(tmp_path / "s"), mode="r")
    attrs = g.attrs["adagrasp_replay"]
    assert attrs["schema_version"] == 1 and attrs["kind"] == "shard"
    assert set(attrs["arrays"]) >= {
        "tsdf", "obstacle", "surface", "action", "label", "score", "meta", "gripper_table", "commit",
    }
    assert tuple(g["commit"][:]) == (0, 6)
    levels = attrs["tsdf_levels"]
    for n, t in enumerate(trials):
        tsdf = g["tsdf"][n].astype(np.float32) / levels
        assert np.abs(tsdf - t.observation.tsdf).max() <= 0.5 / levels + 1e-7
        heightmap = g["surface"][n, 0] * attrs["heightmap_step_m"]
        assert np.abs(heightmap - t.observation.heightmap).max() <= attrs["heightmap_step_m"] / 2 + 1e-7
        assert np.array_equal(g["surface"][n, 1] == 1, t.observation.valid)
        assert g["obstacle_voxels"][n] == 0 and not g["obstacle"][n].any()  # no obstacle: no chunk, reads 0
        meta = json.loads(str(g["meta"][n]))
        assert meta["episode_id"] == t.meta.episode_id and tuple(meta["object_ids"]) == t.meta.object_ids
        assert tuple(g["action"][n]) == t.action and g["label"][n] == int(t.label) and g["trial_id"][n] == n
        assert g["score"][n] == (0.125 if n == 5 else t.score)
        row = int(g["gripper_row"][n])
        assert g["gripper_table_key"][row] == t.gripper_key and g["gripper_table_opening"][row] == t.action[3]
        enc = g["gripper_table"][row].astype(np.float32) / levels
        assert np.abs(enc - t.gripper_encoding[t.action[3]]).max() <= 0.5 / levels + 1e-7
    assert "units" in g["tsdf"].attrs and "description" in g["surface"].attrs
    # time-major arrays are chunked along time only
    for name in ("tsdf", "obstacle", "surface", "action", "label"):
        a = g[name]
        assert tuple(a.chunks[1:]) == tuple(a.shape[1:]), name


def test_fifo_order_single_shard(tmp_path):
    cfg = tiny_cfg(capacity=6, chunk=4)
    shard = ReplayShard(tmp_path / "s", cfg)
    for i in range(15):
        assert shard.insert(make_trial(cfg, i)) == i
        assert len(shard) == min(i + 1, 6)
    assert shard.visible_ids().tolist() == list(range(9, 15))
    assert [shard.get_trial(n).meta.episode_id for n in range(9, 15)] == list(range(9, 15))
    with pytest.raises(ReplayError) as e:
        shard.get_trial(8)
    assert "not visible" in one_line(e)
    shard.close()
    again = ReplayShard(tmp_path / "s", cfg)
    assert again.visible_ids().tolist() == list(range(9, 15))
    assert again.insert(make_trial(cfg, 15)) == 15
    assert again.visible_ids().tolist() == list(range(10, 16))


def test_run_marks_over_shards(tmp_path):
    """One past each actor's largest stored episode number and the largest weights version, over
    every shard (a resumed run numbers its episodes and weights from there)."""
    cfg = tiny_cfg(capacity=8, shards=2)
    client = ReplayClient(open_local_shards(tmp_path / "r", cfg), cfg, seed=0)
    assert client.run_marks() == {"episode_ends": {}, "policy_version": -1}
    for i, (actor, episode) in enumerate([(0, 4), (3, 9), (0, 7), (3, 2), (0, 5)]):
        client.insert(make_trial(cfg, i, actor_id=actor, episode_id=episode, policy_version=10 - i))
    client.flush()
    assert client.run_marks() == {"episode_ends": {0: 8, 3: 10}, "policy_version": 10}


def test_obstacle_chunk_only_where_there_is_an_obstacle(tmp_path):
    cfg = tiny_cfg(capacity=2, chunk=2)
    shard = ReplayShard(tmp_path / "s", cfg)
    with_obstacle = make_trial(cfg, 0, n_objects=2, n_obstacles=2)
    assert with_obstacle.observation.obstacle.any()
    shard.insert(with_obstacle)
    shard.insert(make_trial(cfg, 1))
    assert _chunk_file(tmp_path / "s", "obstacle", 0).exists()
    assert not _chunk_file(tmp_path / "s", "obstacle", 1).exists()
    got = shard.get_trial(0)
    assert np.abs(got.observation.obstacle - with_obstacle.observation.obstacle).max() <= 1 / 254 + 1e-7
    shard.insert(make_trial(cfg, 2))
    shard.insert(make_trial(cfg, 3))  # ring of 2 + 1 slots: trial 3 reuses slot 0, the old obstacle chunk must go
    assert shard.visible_ids().tolist() == [2, 3]
    assert not _chunk_file(tmp_path / "s", "obstacle", 0).exists()
    assert not shard.get_trial(3).observation.obstacle.any()
    g = zarr.open_group(str(tmp_path / "s"), mode="r")
    assert not g["obstacle"][0].any() and int(g["obstacle_voxels"][0]) == 0 and int(g["trial_id"][0]) == 3


def test_fifo_across_shards_keeps_the_newest(tmp_path):
    cfg = tiny_cfg(capacity=8, shards=2)
    client = ReplayClient(open_local_shards(tmp_path / "r", cfg), cfg, seed=0)
    for i in range(21):
        client.insert(make_trial(cfg, i))
    client.flush()
    assert client.size() == 8
    readers = [ReplayShard(p, read_only=True) for p in find_shards(tmp_path / "r")]
    episodes = sorted(r.get_trial(t).meta.episode_id for r in readers for t in r.visible_ids())
    assert episodes == list(range(13, 21))


def test_gripper_table_stored_once_and_refcounted(tmp_path):
    cfg = tiny_cfg(capacity=6, chunk=4)
    shard = ReplayShard(tmp_path / "s", cfg)
    openings = (0.5, 0.75, 1.0)
    enc = synthetic_gripper_encoding(cfg.gripper_grid, openings)
    rng = np.random.default_rng(0)
    # one episode (one key), 4 attempts with the same opening index: one table row
    for step in range(4):
        t = make_trial(cfg, step, rng, scale=1.0, openings=openings, encoding=enc, episode_id=0, step=step)
        t.action = t.action[:3] + (1,)
        shard.insert(t)
    assert shard.stats()["table_rows_used"] == 1
    shared = int(shard.column("gripper_row", [0])[0])
    old_key = shard.get_trial(0).gripper_key
    assert set(shard.column("gripper_row", shard.visible_ids()).tolist()) == {shared}
    # trials with new keys evict the episode one trial at a time; its row lives while one of them is visible
    inserted = {}
    for n in range(4, 10):
        inserted[n] = make_trial(cfg, n, rng)
        shard.insert(inserted[n])
        visible = shard.visible_ids()
        users = int((visible < 4).sum())
        assert shard.stats()["table_rows_used"] == (len(visible) - users) + (1 if users else 0)
        if users:
            assert shard._refcount[shared] == users and shard._table["gripper_table_key"][shared] == old_key
        else:  # freed once its last user left, then free for (and here taken by) a later key
            assert (old_key, 1) not in shard._row_of
        for t in visible:
            assert shard.get_trial(int(t)).gripper_encoding.shape == (2, 16, 16, 8)
    assert shared in shard._free_rows  # freed once its last user left
    lowest_free = min(shard._free_rows)
    inserted[10] = make_trial(cfg, 10, rng)
    shard.insert(inserted[10])
    assert int(shard.column("gripper_row", [10])[0]) == lowest_free  # free rows are reused, lowest first
    # after eviction and row reuse every trial still reads its own encoding
    for t in shard.visible_ids():
        got, want = shard.get_trial(int(t)), inserted[int(t)]
        assert got.gripper_key == want.gripper_key
        assert np.abs(got.gripper_encoding - want.gripper_encoding[want.action[3]]).max() <= 1 / 254 + 1e-7
    shard.close()
    again = ReplayShard(tmp_path / "s", cfg)
    assert again.stats()["table_rows_used"] == len(again.visible_ids())
    for t in again.visible_ids():
        row = again.column("gripper_row", [t])[0]
        assert again.get_trial(int(t)).gripper_key == again._table["gripper_table_key"][row]


def test_row_reused_by_the_new_trial_outlives_the_evicted_user(tmp_path):
    """Keys K, A, K, B at capacity 2: the third trial reuses K's row while evicting its only other
    user; the row must stay taken, so B gets a row of its own and trial 2 still reads K."""
    cfg = tiny_cfg(capacity=2)
    shard = ReplayShard(tmp_path / "s", cfg)
    openings = (0.5, 1.0)
    trials = {}
    for n, (name, scale) in enumerate([("K", 1.0), ("A", 0.9), ("K", 1.0), ("B", 1.1)]):
        enc = synthetic_gripper_encoding(cfg.gripper_grid, openings, scale)
        t = make_trial(cfg, n, gripper=name, scale=scale, openings=openings, encoding=enc)
        t.action = t.action[:3] + (0,)
        trials[n] = t
        shard.insert(t)
        rows = shard.column("gripper_row", shard.visible_ids())
        assert len(set(rows.tolist())) == len(rows), (n, rows)  # the visible keys differ, so must their rows
        assert not set(rows.tolist()) & set(shard._free_rows), (n, rows, shard._free_rows)
    for reader in (shard, ReplayShard(tmp_path / "s", cfg, read_only=True)):
        for n in reader.visible_ids():
            got, want = reader.get_trial(int(n)), trials[int(n)]
            assert got.gripper_key == want.gripper_key
            assert np.abs(got.gripper_encoding - want.gripper_encoding[0]).max() <= 1 / 254 + 1e-7


def test_duplicate_token_is_stored_once(tmp_path):
    cfg = tiny_cfg()
    shard = ReplayShard(tmp_path / "s", cfg)
    rec = encode_trial(make_trial(cfg, 0), cfg.replay.tsdf_levels, token=(42, 7))
    assert shard.insert_encoded(rec) == 0
    assert shard.insert_encoded(rec) == 0
    assert len(shard) == 1 and shard.stats()["duplicates_skipped"] == 1
    shard.close()
    again = ReplayShard(tmp_path / "s", cfg)
    assert again.insert_encoded(rec) == 0 and len(again) == 1


def test_second_writer_is_refused(tmp_path):
    cfg = tiny_cfg()
    shard = ReplayShard(tmp_path / "s", cfg)
    with pytest.raises(ReplayError) as e:
        ReplayShard(tmp_path / "s", cfg)
    assert "another process is writing" in one_line(e)
    ReplayShard(tmp_path / "s", read_only=True)  # readers are fine
    shard.close()
    ReplayShard(tmp_path / "s", cfg).close()


# --------------------------------------------------------------------------------------
# Bad input, bad schema, corruption
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, mutate",
    [
        ("observation.tsdf", lambda t: t.observation.tsdf.__setitem__((0, 0, 0), np.nan)),
        ("observation.tsdf", lambda t: t.observation.tsdf.__setitem__((0, 0, 0), 3.0)),
        ("observation.obstacle", lambda t: t.observation.obstacle.__setitem__((0, 0, 0), -0.5)),
        ("score", lambda t: setattr(t, "score", 1.5)),
        ("meta.seed", lambda t: setattr(t, "meta", dataclasses.replace(t.meta, seed=1.5))),
        ("observation.obstacle: (48, 48, 16) float32, expected (48, 48, 15)",
         lambda t: setattr(t.observation, "tsdf", t.observation.tsdf[:, :, :-1])),
        ("observation.tsdf: (48, 48, 16) float64",
         lambda t: setattr(t.observation, "tsdf", t.observation.tsdf.astype(np.float64))),
        ("observation.valid", lambda t: setattr(t.observation, "valid", t.observation.valid.astype(np.uint8))),
        ("action: (48, ", lambda t: setattr(t, "action", (48,) + tuple(t.action[1:]))),
        ("action: rotation 16 outside the shard's 16 rotations",
         lambda t: setattr(t, "action", tuple(t.action[:2]) + (16, t.action[3]))),
        ("gripper_encoding: 4 openings, meta.openings has 5",
         lambda t: setattr(t, "gripper_encoding", t.gripper_encoding[:-1])),
    ],
)
def test_bad_trial_is_refused_and_writes_nothing(tmp_path, field, mutate):
    cfg = tiny_cfg()
    shard = ReplayShard(tmp_path / "s", cfg)
    shard.insert(make_trial(cfg, 0))
    before = tree_digest(tmp_path / "s")
    bad = make_trial(cfg, 1)
    mutate(bad)
    with pytest.raises(ReplayInputError) as e:
        shard.insert(bad)
    msg = one_line(e)
    assert field in msg and "episode 1" in msg
    assert tree_digest(tmp_path / "s") == before and len(shard) == 1


def test_shard_shape_mismatch_is_refused(tmp_path):
    cfg = tiny_cfg()
    shard = ReplayShard(tmp_path / "s", cfg)
    other = tiny_cfg()
    other.scene_grid.voxel_size = 0.004
    t = synthetic_trial(np.random.default_rng(0), other.scene_grid, other.gripper_grid, 1)
    with pytest.raises(ReplayInputError) as e:
        shard.insert(t)
    assert "observation.tsdf" in one_line(e)
    shard.close()
    with pytest.raises(ReplaySchemaError) as e:
        ReplayShard(tmp_path / "s", other)
    assert "scene_shape" in one_line(e) and str(tmp_path / "s") in str(e.value)


def test_shard_reopened_with_other_rotations_depth_or_truncation_is_refused(tmp_path):
    """Same shapes, other meaning: a stored action index or TSDF value would be read wrongly
    (e.g. a run resumed with --set model.rotations=8), so opening is refused in one line."""
    cfg = tiny_cfg()
    shard = ReplayShard(tmp_path / "s", cfg)
    shard.insert(make_trial(cfg, 0))
    shard.close()
    files = {q: q.read_bytes() for q in sorted((tmp_path / "s").rglob("*")) if q.is_file()}
    rotations, depth, truncation = tiny_cfg(), tiny_cfg(), tiny_cfg()
    rotations.model.rotations = cfg.model.rotations // 2
    depth.sim.grasp_depth = cfg.sim.grasp_depth + 0.01
    truncation.scene_grid.truncation_voxels = cfg.scene_grid.truncation_voxels + 1.0
    for other, field in ((rotations, "rotations"), (depth, "grasp_depth_m"), (truncation, "scene_grid.truncation")):
        with pytest.raises(ReplaySchemaError) as e:
            ReplayShard(tmp_path / "s", other)
        line = one_line(e)
        assert f"attributes.adagrasp_replay.{field}: stored" in line and "config gives" in line, line
    assert {q: q.read_bytes() for q in sorted((tmp_path / "s").rglob("*")) if q.is_file()} == files
    reopened = ReplayShard(tmp_path / "s", tiny_cfg())
    assert reopened.stats()["visible"] == 1
    reopened.close()


def _shard_with_edited_attributes(path: Path, edit) -> Path:
    """A one-trial shard at ``path`` whose schema attributes ``edit`` (a function of the dict)
    changed by hand; returns its group's zarr.json."""
    cfg = tiny_cfg()
    shard = ReplayShard(path, cfg)
    shard.insert(make_trial(cfg, 0))
    shard.close()
    meta_file = path / "zarr.json"
    doc = json.loads(meta_file.read_text())
    edit(doc["attributes"]["adagrasp_replay"])
    meta_file.write_text(json.dumps(doc))
    return meta_file


def test_bad_schema_version_names_path_and_touches_nothing(tmp_path):
    cfg = tiny_cfg()
    meta_file = _shard_with_edited_attributes(tmp_path / "s", lambda a: a.update(schema_version=99))
    before = tree_digest(tmp_path / "s")
    for kwargs in ({"cfg": cfg}, {"read_only": True}):
        with pytest.raises(ReplaySchemaError) as e:
            ReplayShard(tmp_path / "s", **kwargs)
        msg = one_line(e)
        assert str(meta_file.parent) in msg and "schema_version" in msg and "99" in msg
    with pytest.raises(ReplaySchemaError):
        find_shards(tmp_path / "s")
    assert tree_digest(tmp_path / "s") == before


@pytest.mark.parametrize("key, value, want", [
    ("capacity", None, "capacity: expected a non-negative integer, missing"),
    ("capacity", "six", "capacity: expected a non-negative integer, got 'six'"),
    ("scene_shape", [32, 32], "scene_shape: expected three positive integers, got [32, 32]"),
    ("scene_grid", None, "scene_grid: expected a grid with a positive voxel_size, missing"),
])
def test_a_hand_edited_shard_attribute_is_one_line(tmp_path, key, value, want):
    """Attributes the readers compute with (python -m replay inspect / show / export open shards
    read-only) were a KeyError or ValueError traceback when missing or of the wrong type."""
    _shard_with_edited_attributes(tmp_path / "s", lambda a: a.pop(key) if value is None else a.update({key: value}))
    before = tree_digest(tmp_path / "s")
    with pytest.raises(ReplaySchemaError) as e:
        ReplayShard(tmp_path / "s", read_only=True)
    assert f"{tmp_path / 's'}: attributes.adagrasp_replay.{want}" in one_line(e)
    assert tree_digest(tmp_path / "s") == before


def test_wrong_array_dtype_is_named(tmp_path):
    cfg = tiny_cfg()
    ReplayShard(tmp_path / "s", cfg).close()
    meta_file = tmp_path / "s" / "label" / "zarr.json"
    doc = json.loads(meta_file.read_text())
    doc["data_type"] = "int16"
    doc["fill_value"] = -1
    meta_file.write_text(json.dumps(doc))
    with pytest.raises(ReplaySchemaError) as e:
        ReplayShard(tmp_path / "s", read_only=True)
    msg = one_line(e)
    assert f"{tmp_path / 's'}/label" in msg and "data_type" in msg


def test_score_updates_and_reads_of_evicted_trials_touch_nothing(tmp_path):
    """Ids a learner sampled before their slots were reused: a score write-back changes no
    score, and a read returns none of the new trials' data under the old ids."""
    cfg = tiny_cfg(capacity=4, chunk=2)
    shard = ReplayShard(tmp_path / "s", cfg)
    for e in range(4):
        shard.insert(make_trial(cfg, e))
    old = shard.visible_ids().copy()
    for e in range(4, 8):  # evicts trials 0..3 and reuses their slots
        shard.insert(make_trial(cfg, e))
    before = shard.index()["score"].copy()
    assert shard.update_scores(old, np.full(4, 0.999)) == 0
    assert np.array_equal(shard.index()["score"], before)
    data = shard.read(old)
    assert len(data["trial_id"]) == 0 and sorted(data["missing"]) == old.tolist()


def test_redraw_after_a_lost_trial_keeps_the_batch_balanced(tmp_path):
    """Trials lost between drawing and reading (evicted, corrupt) are redrawn from their own class:
    a batch whose first read lost every success still holds half successes."""
    cfg = tiny_cfg(capacity=16, chunk=4)
    shard = ReplayShard(tmp_path / "s", cfg)
    for i in range(16):
        shard.insert(make_trial(cfg, i, label=bool(i % 2)))
    real_read = shard.read
    lost = []

    def read_losing_successes(ids):
        out = real_read(ids)
        if lost:
            return out
        keep = np.flatnonzero(~out["label"])
        lost.extend(out["trial_id"][out["label"]].tolist())
        return {k: v if k == "missing" else [v[i] for i in keep] if isinstance(v, list) else v[keep]
                for k, v in out.items()}

    shard.read = read_losing_successes
    client = ReplayClient([shard], cfg, seed=0)
    b = client.sample(8)
    assert lost and client.counters["redraws"] >= 1
    assert b.label.sum().item() == 4 and b.label.numel() == 8


def _chunk_file(path: Path, array: str, entry: int) -> Path:
    """File of the chunk holding entry ``entry`` (along time) of ``array``."""
    a = zarr.open_array(str(path / array), mode="r")
    return path / array / a.metadata.encode_chunk_key((entry // a.chunks[0],) + (0,) * (a.ndim - 1))


def test_corrupt_volume_chunk_only_loses_that_trial(tmp_path):
    cfg = tiny_cfg(capacity=8, chunk=4)
    shard = ReplayShard(tmp_path / "s", cfg)
    for i in range(6):
        shard.insert(make_trial(cfg, i, label=bool(i % 2)))
    f = _chunk_file(tmp_path / "s", "tsdf", 3)
    raw = bytearray(f.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    f.write_bytes(bytes(raw))
    before = tree_digest(tmp_path / "s")
    # sampling skips it, counts it and warns once; the client redraws
    client = ReplayClient([shard], cfg, seed=0)
    with pytest.warns(ReplayCorruptWarning, match="trial 3 unreadable"):
        batches = [client.sample(4) for _ in range(30)]
    drawn = torch.cat([b.index[:, 1] for b in batches]).tolist()
    assert 3 not in drawn and set(drawn) == {0, 1, 2, 4, 5}
    assert shard.stats()["corrupt"] == 1 and shard.stats()["corrupt_skipped"] >= 1 and 3 not in shard.visible_ids()
    assert client.counters["redraws"] >= 1
    with pytest.raises(ReplayCorruptError) as e:
        shard.get_trial(3)
    msg = one_line(e)
    assert f"{tmp_path / 's'}/tsdf" in msg and "trial 3" in msg and "checksum" in msg
    for n in (0, 1, 2, 4, 5):
        assert shard.get_trial(n).meta.episode_id == n
    assert tree_digest(tmp_path / "s") == before  # nothing rewritten by reading
    # a missing chunk file is reported the same way
    _chunk_file(tmp_path / "s", "tsdf", 4).unlink()
    reader = ReplayShard(tmp_path / "s", read_only=True)
    with pytest.raises(ReplayCorruptError) as e, pytest.warns(ReplayCorruptWarning):
        reader.get_trial(4)
    assert "missing" in one_line(e)


def test_unreadable_gripper_row_is_not_reused_by_later_trials(tmp_path):
    """One damaged gripper-table chunk loses the trials that share it, not every later trial of
    that gripper: once found unreadable, the next insert of its key writes a fresh row."""
    cfg = tiny_cfg(capacity=8)
    openings = (0.5, 1.0)
    enc = synthetic_gripper_encoding(cfg.gripper_grid, openings)

    def trial(i):  # one gripper, scale and openings: one table key
        t = make_trial(cfg, i, gripper="wsg_50", scale=1.0, openings=openings, encoding=enc)
        t.action = tuple(t.action[:3]) + (0,)
        return t

    shard = ReplayShard(tmp_path / "s", cfg)
    old = [shard.insert(trial(i)) for i in range(3)]
    row = int(shard.column("gripper_row", old[:1])[0])
    _chunk_file(tmp_path / "s", "gripper_table", row).write_bytes(b"bit rot")
    with pytest.warns(ReplayCorruptWarning, match="gripper_table"):
        assert shard.read(old)["trial_id"].tolist() == []
    new = [shard.insert(trial(i)) for i in range(3, 6)]
    assert row not in shard.column("gripper_row", new).tolist()
    assert shard.read(new)["trial_id"].tolist() == new
    stored = shard.get_trial(new[0]).gripper_encoding
    assert np.abs(stored - enc[0]).max() <= 1.0 / cfg.replay.tsdf_levels + 1e-6  # opening index 0
    assert shard.stats()["corrupt"] == len(old)
    # a writer that reopens the shard (a restarted shard actor) finds the damaged row in the table
    # again, as the row of the oldest trials of the key: it reads the row once before reusing it,
    # counts those trials lost, and gives the key a fresh row
    shard.close()
    shard = ReplayShard(tmp_path / "s", cfg)
    assert shard.stats()["corrupt"] == 0 and set(old) <= set(shard.visible_ids().tolist())
    with pytest.warns(ReplayCorruptWarning, match=f"gripper_table: chunk {row} of trial"):
        later = [shard.insert(trial(i)) for i in range(6, 8)]
    assert row not in shard.column("gripper_row", later).tolist()
    assert shard.read(later)["trial_id"].tolist() == later
    assert shard.stats()["corrupt"] == len(old) and not set(old) & set(shard.visible_ids().tolist())


def test_insert_without_obstacle_removes_a_cut_off_writes_obstacle_chunk(tmp_path):
    """A writer killed after writing a slot's obstacle chunk but before its commit leaves that
    chunk behind; the next trial in the slot without an obstacle must remove it, or plain-zarr
    readers of ``obstacle`` see the killed trial's obstacle for a trial that has none."""
    cfg = tiny_cfg(capacity=2)  # a ring of 3 slots
    shard = ReplayShard(tmp_path / "s", cfg)
    shard.insert(make_trial(cfg, 0, n_objects=2, n_obstacles=2))
    chunk = _chunk_file(tmp_path / "s", "obstacle", 0).read_bytes()
    for i in (1, 2, 3):  # no obstacle; trial 3 takes slot 0 and removes trial 0's chunk
        shard.insert(make_trial(cfg, i))
    shard.close()
    left = _chunk_file(tmp_path / "s", "obstacle", 1)  # slot 1 held trial 1, which had no obstacle
    left.write_bytes(chunk)  # what a writer killed while inserting trial 4 with an obstacle leaves
    shard = ReplayShard(tmp_path / "s", cfg)
    assert shard.insert(make_trial(cfg, 4)) == 4  # slot 1, no obstacle
    assert not left.exists()
    g = zarr.open_group(str(tmp_path / "s"), mode="r")
    assert not g["obstacle"][1].any() and int(g["obstacle_voxels"][1]) == 0 and int(g["trial_id"][1]) == 4


def test_a_reader_following_a_writer_does_not_call_evicted_trials_damaged(tmp_path):
    """A trial the writer evicts while a reader (inspect on a live run) reads it may have lost its
    chunks (an obstacle chunk is deleted when the slot's next trial has none): that is eviction,
    not damage, and nothing is counted corrupt."""
    cfg = tiny_cfg(capacity=4)
    writer = ReplayShard(tmp_path / "s", cfg)
    for i in range(4):
        writer.insert(make_trial(cfg, i, n_objects=2, n_obstacles=2))
    reader = ReplayShard(tmp_path / "s", read_only=True)
    for i in range(4, 6):
        writer.insert(make_trial(cfg, i))  # evicts trials 0 and 1 and deletes slot 0's obstacle chunk
    assert reader.verify() == 0 and reader.stats()["corrupt"] == 0 and reader.problems() == []
    with pytest.raises(ReplayError, match="not visible"):
        reader.get_trial(0)


def test_corrupt_column_chunk_loses_only_its_trials(tmp_path):
    cfg = tiny_cfg(capacity=12, chunk=4)
    shard = ReplayShard(tmp_path / "s", cfg)
    for i in range(12):
        shard.insert(make_trial(cfg, i))
    shard.close()
    f = _chunk_file(tmp_path / "s", "label", 4)  # chunk of slots 4..7
    f.write_bytes(f.read_bytes()[:-3] + b"xyz")
    with pytest.warns(ReplayCorruptWarning, match=r"/label: chunk of slots 4\.\.7 unreadable"):
        reader = ReplayShard(tmp_path / "s", read_only=True)
    assert reader.visible_ids().tolist() == [0, 1, 2, 3, 8, 9, 10, 11]
    assert reader.stats()["lost"] == 4
    with pytest.warns(ReplayCorruptWarning):
        writer = ReplayShard(tmp_path / "s", cfg)
    writer.insert(make_trial(cfg, 12))  # evicts trial 0; the rest stays as it was
    assert writer.visible_ids().tolist() == [1, 2, 3, 8, 9, 10, 11, 12]
    damaged = f.read_bytes()
    for i in range(13, 17):
        writer.insert(make_trial(cfg, i))
    with pytest.warns(ReplayCorruptWarning, match=r"label/c\.1: unreadable chunk kept as c\.1\.unreadable-"):
        writer.insert(make_trial(cfg, 17))  # slot 4: the damaged chunk is written again, whole
    kept = list(f.parent.glob("c.1.unreadable-*"))
    assert len(kept) == 1 and kept[0].read_bytes() == damaged, "the damaged bytes are not lost"
    writer.close()
    with pytest.warns(ReplayCorruptWarning, match=r"label: 2 visible trial\(s\) with missing values \(first: trial 6\)"):
        reopened = ReplayShard(tmp_path / "s", cfg)  # trials 6 and 7 stay lost, now as fill values
    assert 17 in reopened.visible_ids().tolist() and reopened.get_trial(17).label == make_trial(cfg, 17).label
    reopened.close()


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------


def test_rank_probabilities_follow_the_paper():
    surprise = np.array([0.9, 0.1, 0.5, 0.1])
    p = rank_probabilities(surprise)
    # ascending ranks: the two 0.1 share ranks 1 and 2 -> 1.5 each, 0.5 -> 3, 0.9 -> 4
    assert np.allclose(p, np.array([4, 1.5, 3, 1.5]) / 10)
    assert np.allclose(rank_probabilities(np.array([0.3, 0.1, 0.2])), np.array([3, 1, 2]) / 6)


def test_tied_surprises_weigh_the_same_wherever_they_are_listed():
    """Shards list their trials one shard after another, so a tie broken by position would favour
    the last shard's and the newest trials (a saturated score ties many)."""
    rng = np.random.default_rng(1)
    surprise = rng.choice(np.array([0.0, 0.25, 1.0], np.float32), size=200)
    p = rank_probabilities(surprise)
    for value in (0.0, 0.25, 1.0):
        assert np.ptp(p[surprise == value]) == 0, value
    perm = rng.permutation(len(surprise))
    assert np.array_equal(rank_probabilities(surprise[perm]), p[perm])
    assert p.sum() == pytest.approx(1.0) and p[surprise == 1.0][0] > p[surprise == 0.25][0] > p[surprise == 0.0][0]


def test_balance_one_to_one_over_2000_draws(tmp_path):
    cfg = tiny_cfg(capacity=40, shards=2)
    client = ReplayClient(open_local_shards(tmp_path / "r", cfg), cfg, seed=3)
    for i in range(40):
        client.insert(make_trial(cfg, i, label=i % 5 == 0))  # 20% successes
    client.flush()
    labels = torch.cat([client.sample(8).label for _ in range(250)])
    assert labels.numel() == 2000 and labels.sum().item() == 1000
    rng = np.random.default_rng(0)
    lab = rng.random(500) < 0.1
    for _ in range(50):
        pos, ok = draw_balanced(lab, rng.random(500), 8, rng)
        assert ok and lab[pos].sum() == 4 and len(set(pos.tolist())) == 8


def test_surprise_weighting_prefers_surprising_trials():
    rng = np.random.default_rng(0)
    n = 20
    labels = np.zeros(2 * n, bool)
    labels[:n] = True
    scores = np.concatenate([np.linspace(0, 1, n), np.linspace(0, 1, n)])  # success surprise 1 - s, failure s
    counts = np.zeros(2 * n)
    for _ in range(3000):
        pos, _ = draw_balanced(labels, scores, 8, rng)
        np.add.at(counts, pos, 1)
    succ, fail = counts[:n], counts[n:]
    # successes: the lowest scores are the most surprising; failures: the highest scores
    assert succ[:5].sum() > 2.5 * succ[-5:].sum()
    assert fail[-5:].sum() > 2.5 * fail[:5].sum()
    assert np.corrcoef(np.arange(n), fail)[0, 1] > 0.9 and np.corrcoef(np.arange(n), succ)[0, 1] < -0.9


def test_sample_batch_tensors_and_score_write_back(tmp_path):
    cfg = tiny_cfg(capacity=20, shards=2)
    shards = open_local_shards(tmp_path / "r", cfg)
    client = ReplayClient(shards, cfg, seed=1)
    trials = [make_trial(cfg, i, label=bool(i % 2), n_obstacles=1) for i in range(20)]
    for t in trials:
        client.insert(t)
    batch = client.sample(8)
    x, y, z = cfg.scene_grid.shape
    assert batch.scene.shape == (8, 2, x, y, z) and batch.scene.dtype == torch.float32
    assert batch.gripper.shape == (8, 2, 16, 16, 8) and batch.gripper.dtype == torch.float32
    assert batch.action.dtype == torch.int64 and batch.action.shape == (8, 4)
    assert batch.label.dtype == torch.float32 and batch.label.sum() == 4 and batch.balanced
    by_episode = {t.meta.episode_id: t for t in trials}
    for b in range(8):
        k, tid = batch.index[b].tolist()
        t = by_episode[shards[k].get_trial(tid).meta.episode_id]
        assert batch.action[b].tolist() == list(t.action) and batch.label[b].item() == float(t.label)
        assert (batch.scene[b, 0] - torch.from_numpy(t.observation.tsdf)).abs().max() <= 1 / 254 + 1e-6
        assert (batch.scene[b, 1] - torch.from_numpy(t.observation.obstacle)).abs().max() <= 1 / 254 + 1e-6
        enc = torch.from_numpy(t.gripper_encoding[t.action[3]])
        assert (batch.gripper[b] - enc).abs().max() <= 1 / 254 + 1e-6
    new = torch.linspace(0.05, 0.95, 8)
    client.update_scores(batch.index, new)
    client.flush()
    for b in range(8):
        k, tid = batch.index[b].tolist()
        assert shards[k].get_trial(tid).score == pytest.approx(float(new[b]))
    for s in shards:
        s.close()
    again = open_local_shards(tmp_path / "r", cfg)
    k, tid = batch.index[0].tolist()
    assert again[k].get_trial(tid).score == pytest.approx(float(new[0]))
    with pytest.raises(ReplayInputError) as e:
        again[0].update_scores([int(again[0].visible_ids()[0])], [float("nan")])
    assert "update_scores.scores" in one_line(e)


def test_sampling_redraws_past_many_unreadable_trials(tmp_path):
    """Sampling redraws until its batch is read, however many unreadable trials it meets on the
    way, and raises ReplayEmptyError only once no readable trial is left."""
    cfg = tiny_cfg(capacity=40)
    shard = ReplayShard(tmp_path / "s", cfg)
    for i in range(40):
        shard.insert(make_trial(cfg, i, label=bool(i % 2)))
    for t in range(30):  # 10 readable trials remain, 5 of each class
        _chunk_file(tmp_path / "s", "tsdf", t).write_bytes(b"x")
    for seed in range(10):
        client = ReplayClient([ReplayShard(tmp_path / "s", read_only=True)], cfg, seed=seed)
        with pytest.warns(ReplayCorruptWarning):
            b = client.sample(8)
        assert set(b.index[:, 1].tolist()) <= set(range(30, 40)) and b.label.sum().item() == 4
    for t in range(30, 40):
        _chunk_file(tmp_path / "s", "tsdf", t).write_bytes(b"x")
    client = ReplayClient([ReplayShard(tmp_path / "s", read_only=True)], cfg, seed=0)
    with pytest.raises(ReplayEmptyError), pytest.warns(ReplayCorruptWarning):
        client.sample(8)


def test_one_empty_class_fills_the_batch_and_is_counted(tmp_path):
    cfg = tiny_cfg(capacity=10)
    client = ReplayClient(open_local_shards(tmp_path / "r", cfg), cfg, seed=0)
    with pytest.raises(ReplayEmptyError):
        client.sample(8)
    for i in range(5):
        client.insert(make_trial(cfg, i, label=False))
    batch = client.sample(8)
    assert not batch.balanced and batch.label.sum() == 0 and batch.label.numel() == 8
    assert client.counters["unbalanced_batches"] == 1


def test_buffer_pool_never_hands_out_a_buffer_in_use():
    pool = BufferPool(max_buffers=2)
    first = pool.take((3, 4), np.float32)
    first_address = first.ctypes.data
    a = torch.from_numpy(first)
    del first
    view = a[1]
    del a
    b = pool.take((3, 4), np.float32)
    assert b.ctypes.data != first_address  # the view keeps the first buffer alive
    del view
    c = pool.take((3, 4), np.float32)
    assert c.ctypes.data == first_address, "a buffer no view holds is handed out again"


def test_client_refuses_mixed_or_mismatched_shards(tmp_path):
    cfg = tiny_cfg()
    s1 = ReplayShard(tmp_path / "a", cfg)
    other = tiny_cfg(levels=63)
    s2 = ReplayShard(tmp_path / "b", other)
    with pytest.raises(ReplaySchemaError) as e:
        ReplayClient([s1, s2], cfg)
    assert "tsdf_levels" in one_line(e)
    with pytest.raises(ReplayError):
        ReplayClient([s1, object()], cfg)


def test_writer_removes_partial_files_of_cut_off_writes(tmp_path):
    cfg = tiny_cfg()
    shard = ReplayShard(tmp_path / "s", cfg)
    shard.insert(make_trial(cfg, 0))
    shard.close()
    strays = [tmp_path / "s" / "tsdf" / "c.1.0.0.0123abcd.partial", tmp_path / "s" / "zarr.0123abcd.partial"]
    for stray in strays:
        stray.write_bytes(b"half")
    ReplayShard(tmp_path / "s", cfg).close()
    assert not any(stray.exists() for stray in strays)
    assert sorted(os.listdir(tmp_path / "s" / "tsdf")) == ["c.0.0.0.0", "zarr.json"]
