"""Learner: rate limiting, a real training step on synthetic trials, score write-back, save/restore."""

import copy
import dataclasses
import errno
import json
import os

import numpy as np
import pytest
import torch

from common.config import ConfigError, load_config
from learner.learner import Learner, epsilon_at, precision_autocast
from learner.rate_limit import SamplesPerInsert
from replay.client import ReplayClient, open_local_shards
from replay.shard import ReplayShard, find_shards
from replay.synthetic import FixedBatchReplay, synthetic_trial


def test_rate_limiter_keeps_samples_per_insert():
    lim = SamplesPerInsert(spi=32, min_replay=10, batch_size=8)
    assert lim.allowed_steps(inserted=9, sampled=0) == 0
    assert lim.allowed_steps(inserted=10, sampled=0) == 4  # 32 samples for the first trial past the minimum
    assert lim.allowed_steps(inserted=10, sampled=32) == 0
    assert lim.allowed_steps(inserted=12, sampled=32) == 8
    sampled, inserted = 0, 10
    for _ in range(50):
        inserted += 1
        sampled += 8 * lim.allowed_steps(inserted, sampled)
    assert abs(sampled - 32 * (inserted - 10 + 1)) < 8


def test_actors_wait_while_inserts_lead_the_learner():
    lim = SamplesPerInsert(spi=8, min_replay=10, batch_size=8, insert_lead=4)
    assert lim.may_insert(inserted=13, sampled=0)  # 3 trials past the minimum, none sampled yet
    assert not lim.may_insert(inserted=14, sampled=0)
    assert lim.may_insert(inserted=14, sampled=8)  # one step accounts for one trial at spi 8
    assert SamplesPerInsert(spi=8, min_replay=10, batch_size=8).may_insert(inserted=10**6, sampled=0)
    # Alternating the two sides keeps the ratio: inserts never lead by the allowance or more.
    inserted, sampled = 0, 0
    for _ in range(500):
        if lim.may_insert(inserted, sampled):
            inserted += 1
        sampled += 8 * min(1, lim.allowed_steps(inserted, sampled))
        assert lim.lead(inserted, sampled) < lim.insert_lead + 1
    assert inserted > 100 and abs(sampled - 8 * (inserted - 10)) <= 8 * (lim.insert_lead + 1)


def test_epsilon_schedule_is_linear_and_clamped():
    cfg = load_config("default")
    assert epsilon_at(cfg, 0) == pytest.approx(0.8)
    assert epsilon_at(cfg, 1000) == pytest.approx(0.5)
    assert epsilon_at(cfg, 2000) == pytest.approx(0.2)
    assert epsilon_at(cfg, 10**6) == pytest.approx(0.2)


SMALL = [
    "scene_grid.x_range=[-0.064, 0.064]",
    "scene_grid.y_range=[-0.064, 0.064]",
    "scene_grid.z_range=[0.0, 0.064]",
    "gripper_grid.shape=[16, 16, 8]",
]
"""A 32 x 32 x 16 scene grid and a 16 x 16 x 8 gripper grid keep these tests fast on 2 cores."""


@pytest.fixture
def filled_replay(tmp_path):
    cfg = load_config("tiny", overrides=SMALL)
    shards = open_local_shards(tmp_path / "replay", cfg)
    client = ReplayClient(shards, cfg, seed=0)
    rng = np.random.default_rng(0)
    for n in range(12):
        t = synthetic_trial(rng, cfg.scene_grid, cfg.gripper_grid, n_objects=1, episode_id=n)
        t.label = bool(n % 2)
        client.insert(t.validate())
    client.flush()
    yield cfg, client
    for s in shards:
        s.close()


def test_train_steps_update_weights_and_scores(filled_replay):
    cfg, client = filled_replay
    torch.manual_seed(0)
    learner = Learner(cfg, client, seed=0)
    before = {k: v.clone() for k, v in learner.model.state_dict().items()}
    stored_before = np.concatenate([d["score"] for d in (s.index() for s in client._shards)])
    stats = learner.train(2)
    assert stats.steps == 2 and stats.samples == 2 * cfg.learner.batch_size
    assert np.isfinite(stats.loss)
    changed = [k for k, v in learner.model.state_dict().items() if v.dtype.is_floating_point and not torch.equal(v, before[k])]
    assert changed, "an Adam step must change the weights"
    stored_after = np.concatenate([d["score"] for d in (s.index() for s in client._shards)])
    assert (stored_after != stored_before).any(), "refreshed scores must reach the replay"
    v1, state = learner.publish()
    v2, _ = learner.publish()
    assert (v1, v2) == (1, 2) and set(state) == set(learner.model.state_dict())


def test_save_restore_continues_identically(filled_replay):
    cfg, client = filled_replay
    torch.manual_seed(1)
    a = Learner(cfg, client, seed=3)
    a.train(1)
    saved = a.state_dict()
    b = Learner(cfg, client, seed=99)
    b.load_state_dict(saved)
    for (ka, va), (kb, vb) in zip(a.model.state_dict().items(), b.model.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)
    assert b.stats.steps == 1 and b.stats.samples == cfg.learner.batch_size
    assert torch.equal(a.generator.get_state(), b.generator.get_state())
    sa = a.optimizer.state_dict()["state"]
    sb = b.optimizer.state_dict()["state"]
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k]["exp_avg"], sb[k]["exp_avg"]) for k in sa)
    assert (b.stats.version, b.stats.history) == (a.stats.version, a.stats.history)
    # and it continues: one more step on the same batch gives bit-identical weights and counters
    batch = client.sample(cfg.learner.batch_size)
    for learner in (a, b):
        learner.replay = FixedBatchReplay(batch.scene, batch.gripper, batch.action, batch.label.float())
        learner.train(1)
    for (ka, va), (kb, vb) in zip(a.model.state_dict().items(), b.model.state_dict().items()):
        assert ka == kb and torch.equal(va, vb), ka
    assert (b.stats.steps, b.stats.samples, b.stats.loss) == (a.stats.steps, a.stats.samples, a.stats.loss)
    assert b.publish()[0] == a.publish()[0] == saved["version"] + 1, "a restored learner numbers weights on"


class _RecordingReplay(FixedBatchReplay):
    """A fixed batch that remembers the index rows of the last score write-back."""

    def update_scores(self, index, scores):
        self.written_index = torch.as_tensor(index).clone()
        super().update_scores(index, scores)


def test_written_back_score_is_each_trials_success_probability_at_its_own_action(filled_replay):
    """The score a step writes back is, for each trial of the batch, the softmax success
    probability (class 1) at that trial's executed cell and rotation under the weights of that
    step, written to that trial's index row (the replay ranks trials by these scores)."""
    cfg, client = filled_replay
    cfg.learner.augment_prob = 0.0
    b = client.sample(cfg.learner.batch_size)
    fixed = _RecordingReplay(b.scene, b.gripper, b.action, b.label.float())
    perm = torch.randperm(b.scene.shape[0], generator=torch.Generator().manual_seed(1))
    fixed.batch.index = fixed.batch.index[perm]  # index rows not in batch order
    torch.manual_seed(0)
    learner = Learner(cfg, fixed, seed=0)
    before = copy.deepcopy(learner.model).train()
    with torch.no_grad():
        logits = before.forward_train(b.scene, b.gripper, b.action[:, 2])
        rows = torch.arange(len(b.action))
        want = torch.softmax(logits[rows, :, b.action[:, 0], b.action[:, 1]], dim=1)[:, 1].numpy()
    learner.train(1)
    assert torch.equal(fixed.written_index, fixed.batch.index)
    np.testing.assert_allclose(fixed.scores[-1], want, atol=1e-5)


def test_checkpoint_snapshot_and_score_map_image(filled_replay, tmp_path):
    from common.checkpoint import read_checkpoint
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    torch.manual_seed(0)
    proc = LearnerProcess(cfg, client._shards, str(tmp_path / "run"), seed=0, torch_threads=1)
    proc.learner.train(1)
    proc.checkpoint(epsilon=0.5, inserted=12, snapshot=True)
    latest = read_checkpoint(checkpoint_path(tmp_path / "run"))
    snap = read_checkpoint(checkpoint_path(tmp_path / "run").parent / "step-0000001.pt")
    assert latest.optimizer is not None and snap.optimizer is None and snap.step == latest.step == 1
    assert all(torch.equal(snap.model_state[k], v) for k, v in latest.model_state.items())
    sampler = proc.replay.sampler_state()
    step, image = proc.score_map_image()
    assert proc.replay.sampler_state() == sampler, "the image must not draw from the training sampler"
    assert step == 1 and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    assert image.std() > 0, "a drawn figure, not a blank image"
    assert proc.learner.model.training, "the learner's model goes back to training mode"


def test_weight_average_is_published_and_follows_the_trained_weights(filled_replay):
    cfg, client = filled_replay
    cfg.learner.ema_decay = 0.5
    torch.manual_seed(0)
    learner = Learner(cfg, client, seed=0)
    expected = {k: v.clone() for k, v in learner.model.state_dict().items()}
    for n in (1, 2, 3):
        learner.train(1)
        decay = min(0.5, (1 + n) / (10 + n))
        for k, v in learner.model.state_dict().items():
            expected[k] = decay * expected[k] + (1 - decay) * v if v.dtype.is_floating_point else v.clone()
    average = learner.average.state_dict()
    for k, v in expected.items():
        torch.testing.assert_close(average[k], v, rtol=1e-6, atol=1e-7)
    trained = learner.model.state_dict()
    assert any(not torch.equal(average[k], trained[k]) for k in trained if trained[k].dtype.is_floating_point)
    _, published = learner.publish()
    assert all(torch.equal(published[k], average[k]) for k in average), "actors act with the average"
    assert learner.model.training and not learner.average.training


def test_weight_average_survives_checkpoint_resume_and_export(filled_replay, tmp_path):
    from common.checkpoint import CheckpointError, read_checkpoint
    from learner.export import export_model
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    cfg.learner.ema_decay = 0.9
    torch.manual_seed(0)
    run = tmp_path / "run"
    proc = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    proc.learner.train(2)
    proc.checkpoint(epsilon=0.5, inserted=12, snapshot=True)
    latest = read_checkpoint(checkpoint_path(run))
    average = proc.learner.average.state_dict()
    assert all(torch.equal(latest.model_state[k], average[k]) for k in average), "the file's model is the average"
    resumed = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    for a, b in ((proc.learner.model, resumed.learner.model), (proc.learner.average, resumed.learner.average)):
        assert all(torch.equal(v, b.state_dict()[k]) for k, v in a.state_dict().items())
    assert resumed.learner.average_updates == proc.learner.average_updates == 2
    shipped = read_checkpoint(export_model(run, "avg", dest=tmp_path / "models") / "checkpoint.pt")
    assert "trained_model" not in shipped.extra["learner"] and shipped.optimizer is None
    assert all(torch.equal(shipped.model_state[k], average[k]) for k in average)
    trained = proc.learner.model.state_dict()
    assert any(not torch.equal(trained[k], average[k]) for k in average if average[k].is_floating_point())
    raw = read_checkpoint(export_model(run, "raw", dest=tmp_path / "models", trained_weights=True) / "checkpoint.pt")
    assert all(torch.equal(raw.model_state[k], trained[k]) for k in trained)
    assert raw.extra["exported_weights"] == "trained" and "trained_model" not in raw.extra["learner"]
    assert "exported_weights" not in shipped.extra
    plain = tmp_path / "plain"
    LearnerProcess(load_config("tiny", overrides=SMALL), client._shards, str(plain), seed=0,
                   torch_threads=1).checkpoint(epsilon=0.5, inserted=12)
    with pytest.raises(CheckpointError, match=r"latest\.pt: learner\.trained_model: not present"):
        export_model(plain, "raw2", dest=tmp_path / "models", trained_weights=True)
    assert not (tmp_path / "models" / "raw2").exists()


def test_resume_trains_at_the_configured_learning_rate(filled_replay, tmp_path):
    """A run resumed with a new learner.lr trains at it: the optimiser state in latest.pt keeps
    Adam's moments but not the old rate."""
    from learner.loop import LearnerProcess

    cfg, client = filled_replay
    run = tmp_path / "run"
    proc = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    proc.learner.train(2)
    proc.checkpoint(epsilon=0.5, inserted=12, snapshot=False)
    moments = {k: v["exp_avg"].clone() for k, v in proc.learner.optimizer.state_dict()["state"].items()}
    lowered = copy.deepcopy(cfg)
    lowered.learner.lr = cfg.learner.lr / 5
    resumed = LearnerProcess(lowered, client._shards, str(run), seed=0, torch_threads=1)
    groups = resumed.learner.optimizer.param_groups
    assert [g["lr"] for g in groups] == [lowered.learner.lr] * len(groups)
    state = resumed.learner.optimizer.state_dict()["state"]
    assert all(torch.equal(state[k]["exp_avg"], m) for k, m in moments.items())
    same = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    assert [g["lr"] for g in same.learner.optimizer.param_groups] == [cfg.learner.lr] * len(groups)


def test_resumed_learner_draws_the_batches_the_uninterrupted_one_draws(filled_replay, tmp_path):
    """The checkpoint keeps the replay sampler's generator: after a resume the learner samples the
    trials it would have sampled had the run gone on (not the first part's draws again)."""
    from learner.loop import LearnerProcess

    cfg, client = filled_replay
    run = tmp_path / "run"
    proc = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    first = [proc.replay.sample(cfg.learner.batch_size).index.tolist() for _ in range(3)]
    proc.checkpoint(epsilon=0.5, inserted=12)
    resumed = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    after = [resumed.replay.sample(cfg.learner.batch_size).index.tolist() for _ in range(3)]
    going_on = [proc.replay.sample(cfg.learner.batch_size).index.tolist() for _ in range(3)]
    assert after == going_on and after != first, (first, after, going_on)


def test_bf16_precision_matches_fp32_loss_and_keeps_float32_weights(filled_replay):
    """learner.precision=bf16: the first step's loss (before any update) within 2% of fp32 on the
    same weights and batch; weights, gradients and scores stay float32."""
    cfg, client = filled_replay
    cfg.learner.augment_prob = 0.0
    b = client.sample(cfg.learner.batch_size)
    fixed = FixedBatchReplay(b.scene, b.gripper, b.action, b.label.float())
    losses = {}
    for precision in ("fp32", "bf16"):
        cfg.learner.precision = precision
        torch.manual_seed(0)
        learner = Learner(cfg, fixed, seed=0)
        with precision_autocast(learner.device, cfg.learner.precision):
            assert torch.is_autocast_enabled(learner.device.type) == (precision == "bf16")
        before = {k: v.clone() for k, v in learner.model.state_dict().items()}
        losses[precision] = learner.train(1).loss
        weights = learner.model.state_dict()
        assert all(v.dtype == torch.float32 for v in weights.values() if v.is_floating_point())
        assert all(p.grad is None or p.grad.dtype == torch.float32 for p in learner.model.parameters())
        assert any(not torch.equal(v, before[k]) for k, v in weights.items() if v.is_floating_point())
        scores = fixed.scores[-1]
        assert scores.dtype == np.float32 and np.all((scores >= 0) & (scores <= 1))
    assert np.isfinite(losses["bf16"]) and losses["bf16"] == pytest.approx(losses["fp32"], rel=0.02)


def test_unknown_precision_is_one_line():
    with pytest.raises(ConfigError, match=r"learner\.precision: expected one of \['fp32', 'bf16'\], got 'fp16'"):
        load_config("default", ["learner.precision=fp16"])


def test_init_weights_starts_a_new_run_from_a_checkpoint_and_resume_ignores_it(filled_replay, tmp_path):
    from common.checkpoint import read_checkpoint
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    torch.manual_seed(0)
    source = LearnerProcess(cfg, client._shards, str(tmp_path / "source"), seed=0, torch_threads=1)
    source.learner.train(2)
    trained = read_checkpoint(source.checkpoint(epsilon=0.3, inserted=12))
    cfg.learner.init_weights = str(checkpoint_path(tmp_path / "source"))
    cfg.learner.ema_decay = 0.9
    torch.manual_seed(7)  # a different random initialisation, which the loaded weights replace
    tuned = LearnerProcess(cfg, client._shards, str(tmp_path / "tuned"), seed=0, torch_threads=1)
    for model in (tuned.learner.model, tuned.learner.average):
        assert all(torch.equal(v, trained.model_state[k]) for k, v in model.state_dict().items())
    assert tuned.resumed_from is None and tuned.learner.stats.steps == 0
    assert not tuned.learner.optimizer.state_dict()["state"], "the optimiser starts fresh"
    tuned.learner.train(1)
    tuned.checkpoint(epsilon=0.5, inserted=12)
    after = {k: v.clone() for k, v in tuned.learner.model.state_dict().items()}
    resumed = LearnerProcess(cfg, client._shards, str(tmp_path / "tuned"), seed=0, torch_threads=1)
    assert resumed.resumed_from == 1
    assert all(torch.equal(v, after[k]) for k, v in resumed.learner.model.state_dict().items()), (
        "a resumed run continues its own weights, not init_weights"
    )


def test_init_weights_of_another_network_fails_in_one_line(filled_replay, tmp_path):
    from common.checkpoint import CheckpointError, initial_weights
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    proc = LearnerProcess(cfg, client._shards, str(tmp_path / "source"), seed=0, torch_threads=1)
    path = proc.checkpoint(epsilon=0.5, inserted=12)
    other = load_config("tiny", overrides=SMALL + ["model.variant=init-only", f"learner.init_weights={path}"])
    with pytest.raises(CheckpointError) as e:
        initial_weights(other)
    msg = str(e.value)
    assert "\n" not in msg and str(checkpoint_path(tmp_path / "source")) in msg
    assert "learner.init_weights" in msg and "model.variant" in msg
    wider = load_config("tiny", overrides=SMALL + ["model.channels=4", f"learner.init_weights={path}"])
    with pytest.raises(CheckpointError, match="model.channels"):
        initial_weights(wider)
    # Same tensors, other meaning: kernel-rotation features are not rotation-equivariant.
    kernel = load_config("tiny", overrides=SMALL + ["model.rotate=kernel", f"learner.init_weights={path}"])
    with pytest.raises(CheckpointError, match="model.rotate"):
        initial_weights(kernel)
    missing = load_config("tiny", overrides=SMALL + [f"learner.init_weights={tmp_path / 'none.pt'}"])
    with pytest.raises(CheckpointError, match=r"learner.init_weights: .*none.pt: checkpoint file not found"):
        initial_weights(missing)


def test_init_weights_path_is_made_absolute_and_checked_until_the_run_has_a_checkpoint(filled_replay, tmp_path, monkeypatch):
    from common.checkpoint import CheckpointError, read_checkpoint
    from learner.loop import LearnerProcess, checkpoint_path
    from learner.run import parse_args, resolve

    cfg, client = filled_replay
    source = LearnerProcess(cfg, client._shards, str(tmp_path / "source"), seed=0, torch_threads=1)
    source.checkpoint(epsilon=0.5, inserted=12)
    monkeypatch.chdir(tmp_path)
    fence = ["sim.fence_half_extent=0.04", "sim.drop_half_extent=0.03"]  # a fence the small grid holds
    sets = [f"--set={o}" for o in SMALL + fence] + ["--set=learner.init_weights=source/checkpoints/latest.pt"]
    fresh, run_dir = resolve(parse_args(["--config", "tiny", "--run-dir", "tuned", *sets]))
    assert fresh.learner.init_weights == str(checkpoint_path(tmp_path / "source"))
    assert load_config(run_dir / "config.yaml").learner.init_weights == fresh.learner.init_weights
    tuned = LearnerProcess(fresh, client._shards, str(run_dir), seed=0, torch_threads=1)
    tuned.checkpoint(epsilon=0.5, inserted=12)
    origin = read_checkpoint(checkpoint_path(run_dir)).extra["init_weights"]
    assert origin["file"] == fresh.learner.init_weights and origin["step"] == 0, origin
    assert LearnerProcess(fresh, client._shards, str(run_dir), seed=0, torch_threads=1).init_source == origin
    checkpoint_path(tmp_path / "source").unlink()
    # The run has its own checkpoint now: --resume no longer needs (or reads) the source.
    resumed, _ = resolve(parse_args(["--resume", "--run-dir", "tuned"]))
    assert resumed.learner.init_weights == fresh.learner.init_weights
    # A run stopped before its first checkpoint still starts from the source, so it is checked.
    checkpoint_path(run_dir).unlink()
    with pytest.raises(CheckpointError, match="checkpoint file not found"):
        resolve(parse_args(["--resume", "--run-dir", "tuned"]))


def test_fine_tuning_from_a_shipped_model_records_its_place_in_the_package(filled_replay, tmp_path, monkeypatch):
    """A shipped source is recorded as assets/models/NAME/checkpoint.pt, not as this machine's path."""
    import common.checkpoint as ck
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    models = tmp_path / "package" / "assets" / "models"
    source = LearnerProcess(cfg, client._shards, str(tmp_path / "source"), seed=0, torch_threads=1)
    source.checkpoint(epsilon=0.5, inserted=12)
    (models / "tiny-net").mkdir(parents=True)
    checkpoint_path(tmp_path / "source").rename(models / "tiny-net" / "checkpoint.pt")
    monkeypatch.setattr(ck, "shipped_models_dir", lambda: models)
    tuned_cfg = load_config("tiny", overrides=SMALL + ["learner.init_weights=model:tiny-net"])
    tuned = LearnerProcess(tuned_cfg, client._shards, str(tmp_path / "tuned"), seed=0, torch_threads=1)
    tuned.checkpoint(epsilon=0.5, inserted=12)
    origin = ck.read_checkpoint(checkpoint_path(tmp_path / "tuned")).extra["init_weights"]
    assert origin["init_weights"] == "model:tiny-net", origin
    assert origin["file"] == "assets/models/tiny-net/checkpoint.pt", origin
    assert str(tmp_path) not in str(origin)


def test_resume_and_export_rewrite_an_absolute_record_of_a_shipped_source(filled_replay, tmp_path, monkeypatch):
    """A run fine-tuned from model:NAME before its record named the package place holds this
    machine's absolute path; resuming it and exporting it both write assets/models/NAME/checkpoint.pt."""
    import common.checkpoint as ck
    from learner.export import export_model
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    monkeypatch.setattr(ck, "shipped_models_dir", lambda: tmp_path / "package" / "assets" / "models")
    run = tmp_path / "run"
    old = {"init_weights": "model:gone-net", "file": str(tmp_path / "elsewhere" / "checkpoint.pt"), "step": 7, "version": 3}
    first = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    first.init_source = dict(old)
    first.checkpoint(epsilon=0.5, inserted=12)
    assert ck.read_checkpoint(checkpoint_path(run)).extra["init_weights"] == old
    shipped = ck.read_checkpoint(export_model(run, "exported", dest=tmp_path / "out") / "checkpoint.pt")
    resumed = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    resumed.checkpoint(epsilon=0.5, inserted=12)
    for record in (shipped.extra["init_weights"], ck.read_checkpoint(checkpoint_path(run)).extra["init_weights"]):
        assert record == {**old, "file": "assets/models/gone-net/checkpoint.pt"}, record
    local = {"init_weights": str(tmp_path / "a.pt"), "file": str(tmp_path / "a.pt"), "step": 1, "version": 1}
    assert ck.portable_init_source(local) == local and ck.portable_init_source(None) is None


def _tiny_run_with_one_trial(run):
    """A tiny-config run directory (config.yaml and replay) holding one stored trial."""
    from learner.run import parse_args, resolve

    cfg, _ = resolve(parse_args(["--config", "tiny", "--run-dir", str(run)]))
    shards = open_local_shards(run / "replay", cfg)
    shards[0].insert(synthetic_trial(np.random.default_rng(0), cfg.scene_grid, cfg.gripper_grid, 1))
    for s in shards:
        s.close()
    return run


def _files(folder):
    """Every file under ``folder`` with its bytes."""
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_resume_with_overrides_its_replay_cannot_take_is_refused_in_one_line(tmp_path, capsys):
    """--resume --set model.rotations=8 (or another shard count) would read the stored trials'
    actions at other angles: refused before anything starts, config and replay untouched."""
    from learner.run import cli, parse_args, resolve

    run = _tiny_run_with_one_trial(tmp_path / "run")
    before = _files(run)
    for extra, where, field in (
        (["--set", "model.rotations=8"], "replay/shard_000", "rotations: stored 16, config gives 8"),
        (["--shards", "3"], "replay", "num_shards: replay root has 2 shards, config asks for 3"),
    ):
        rc = cli(["--resume", "--run-dir", str(run), "--actors", "0", *extra])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and f"{run / where}:" in err[0] and field in err[0], err
    assert _files(run) == before
    resumed, _ = resolve(parse_args(["--resume", "--run-dir", str(run)]))
    assert resumed.model.rotations == 16


def test_new_run_in_a_folder_whose_replay_its_config_cannot_take_is_refused_in_one_line(tmp_path, capsys):
    """A run directory holding a replay but no config.yaml (deleted, or copied in by hand) starts a
    new run: shards its config cannot open are one line and rc 2 before anything is written, and
    the stored trials are untouched."""
    from learner.run import cli

    run = _tiny_run_with_one_trial(tmp_path / "run")
    (run / "config.yaml").unlink()
    before = _files(run)
    rc = cli(["--config", "tiny", "--run-dir", str(run), "--actors", "0", "--max-trials", "1", "--quiet",
              "--set", "model.rotations=8"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "shard_000" in err[0] and "rotations: stored 16, config gives 8" in err[0], err
    assert _files(run) == before, "nothing written"


def test_resume_from_an_unreadable_checkpoint_or_with_another_network_is_refused_in_one_line(tmp_path, capsys):
    """--resume of a run whose latest.pt is damaged, or with a --set that builds another network
    than its checkpoint's, is one line and rc 2 before anything starts (both were tracebacks from
    inside the run), with every file untouched."""
    from learner.loop import LearnerProcess, checkpoint_path
    from learner.run import cli, parse_args, resolve

    run = _tiny_run_with_one_trial(tmp_path / "run")
    cfg, _ = resolve(parse_args(["--resume", "--run-dir", str(run)]))
    shards = open_local_shards(run / "replay", cfg)
    LearnerProcess(cfg, shards, str(run), seed=0, torch_threads=1).checkpoint(epsilon=0.5, inserted=1)
    for s in shards:
        s.close()
    ckpt = checkpoint_path(run)
    before = _files(run)
    rc = cli(["--resume", "--run-dir", str(run), "--actors", "0", "--set", "model.variant=scene-only"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert f"{ckpt}: model.variant is 'adagrasp' there but 'scene-only'" in err[0], err
    assert _files(run) == before
    ckpt.write_bytes(before[ckpt][:1000])
    damaged = _files(run)
    rc = cli(["--resume", "--run-dir", str(run), "--actors", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and f"{ckpt}: not a readable checkpoint" in err[0], err
    assert _files(run) == damaged


def _raise_no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_run_directory_that_is_a_file_or_holds_an_unreadable_replay_root_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    """--run-dir naming a file, a folder inside a file, or a folder whose replay root metadata is
    damaged, is one line and rc 2 (all were tracebacks), and nothing is written: no config.yaml,
    the file as it was. An OSError that names no file names the run directory."""
    from learner.run import cli

    start = ["--config", "tiny", "--actors", "0", "--max-trials", "1", "--quiet", "--run-dir"]
    taken = tmp_path / "notes.txt"
    taken.write_text("mine")
    rc = cli([*start, str(taken)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"error: {taken}: --run-dir: exists and is not a folder"], err
    assert taken.read_text() == "mine"
    rc = cli([*start, str(taken / "run")])  # a folder that cannot be made: the OSError, in one line
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"error: {taken / 'run'}: Not a directory"], err
    assert taken.read_text() == "mine"
    with monkeypatch.context() as m:  # an OSError that names no file: the run directory instead of 'None'
        m.setattr("learner.run.save_config", _raise_no_space)
        rc = cli([*start, str(tmp_path / "full")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"error: {tmp_path / 'full'}: No space left on device"], err
    run = tmp_path / "run"
    (run / "replay").mkdir(parents=True)
    (run / "replay" / "zarr.json").write_text("{")
    rc = cli([*start, str(run)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and f"{run / 'replay' / 'zarr.json'}: unreadable group metadata" in err[0], err
    assert _files(run) == {run / "replay" / "zarr.json": b"{"}



def _metas(run):
    """The TrialMeta of every stored trial of the run."""
    for path in find_shards(run / "replay"):
        shard = ReplayShard(path, read_only=True)
        try:
            yield from (shard.get_trial(int(t)).meta for t in shard.visible_ids())
        finally:
            shard.close()


def _episodes(run):
    """{(actor_id, episode_id): (gripper, scale, openings, episode seed)} of every stored trial."""
    out = {}
    for m in _metas(run):
        draw = (m.gripper, m.gripper_scale, m.openings, m.seed)
        assert out.setdefault((m.actor_id, m.episode_id), draw) == draw, "one episode, one draw"
    return out


def test_a_local_run_counts_every_weights_version_it_published(tmp_path):
    """--actors 0 catches the learner up after each episode, several chunks in a row, each of which
    may publish: the summary counts every version (as the Ray driver does), none twice."""
    from learner.run import cli

    run = tmp_path / "run"
    assert cli(["--config", "tiny", "--run-dir", str(run), "--actors", "0", "--max-trials", "6", "--quiet",
                "--set", "learner.min_replay=2", "--set", "learner.samples_per_insert=64"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["weights_published"] == summary["weights_version"] > 2, summary


def test_a_resumed_run_draws_new_episodes_and_numbers_them_after_the_first_part(tmp_path):
    """A resumed part seeds its actor with a new stream (keyed by the trials committed so far) and
    numbers its episodes after those the checkpoint recorded: it does not repeat the first part's
    grippers, openings and scene seeds, and (actor_id, episode_id) stays one episode."""
    from common.checkpoint import read_checkpoint
    from learner.loop import checkpoint_path
    from learner.run import cli

    run = tmp_path / "run"
    assert cli(["--config", "tiny", "--run-dir", str(run), "--actors", "0", "--max-trials", "2", "--quiet"]) == 0
    first = _episodes(run)
    recorded = read_checkpoint(checkpoint_path(run)).extra["replay"]["next_episode"]
    assert recorded == [max(e for _, e in first) + 1], (recorded, sorted(first))
    assert cli(["--resume", "--run-dir", str(run), "--actors", "0", "--max-trials", "4", "--quiet"]) == 0
    both = _episodes(run)
    second = {k: v for k, v in both.items() if k not in first}
    assert second and min(e for _, e in second) == recorded[0], (sorted(first), sorted(second))
    assert all(both[k] == v for k, v in first.items()), "the first part's trials are as they were"
    assert not set(first.values()) & set(second.values()), "a resumed part drew an episode of the first part again"


def test_after_a_crash_a_resumed_run_numbers_its_episodes_after_those_the_replay_holds(tmp_path):
    """A crash after trials were committed but before the next checkpoint: the replay holds
    episodes the checkpoint does not know of. The resumed part numbers its episodes after those,
    so (actor_id, episode_id) stays one episode (``_episodes`` asserts one draw per key)."""
    import shutil

    from learner.loop import checkpoint_path
    from learner.run import cli

    run = tmp_path / "run"
    assert cli(["--config", "tiny", "--run-dir", str(run), "--actors", "0", "--max-trials", "2", "--quiet"]) == 0
    ckpt = checkpoint_path(run)
    shutil.copy(ckpt, tmp_path / "at_crash.pt")
    assert cli(["--resume", "--run-dir", str(run), "--actors", "0", "--max-trials", "4", "--quiet"]) == 0
    before = _episodes(run)
    shutil.copy(tmp_path / "at_crash.pt", ckpt)  # the second part's checkpoints never reached the disk
    assert cli(["--resume", "--run-dir", str(run), "--actors", "0", "--max-trials", "6", "--quiet"]) == 0
    after = _episodes(run)
    third = {k: v for k, v in after.items() if k not in before}
    assert third and min(e for _, e in third) == max(e for _, e in before) + 1, (sorted(before), sorted(third))
    assert all(after[k] == v for k, v in before.items()), "earlier trials keep their episode numbers"
    versions = _versions(run)
    crashed = max(v for k, v in versions.items() if k in before)
    assert crashed > 1 and min(v for k, v in versions.items() if k in third) > crashed, (
        "the resumed part's weights are numbered after those of trials committed after the checkpoint")


def _versions(run):
    """{(actor_id, episode_id): weights version} of every stored trial."""
    return {(m.actor_id, m.episode_id): m.policy_version for m in _metas(run)}


def test_a_restarted_learner_numbers_its_weights_after_those_the_actors_hold(filled_replay, tmp_path):
    """train(..., after_version=V) publishes a version above V (the actors load only a version
    newer than theirs), and never numbers back below the learner's own."""
    from learner.loop import LearnerProcess

    cfg, client = filled_replay
    proc = LearnerProcess(cfg, client._shards, str(tmp_path / "run"), seed=0, torch_threads=1)
    assert proc.train(0, force_publish=True)["weights"][0] == 1
    assert proc.train(0, force_publish=True, after_version=7)["weights"][0] == 8
    assert proc.train(0, force_publish=True, after_version=3)["weights"][0] == 9
    assert proc.train(0)["weights"] is None, "after_version publishes nothing by itself"


def test_without_a_checkpoint_a_resumed_learner_numbers_its_weights_after_the_replays(filled_replay, tmp_path):
    """A run killed before its first checkpoint left trials of published weights in the replay:
    the learner that starts over numbers its weights after theirs, so a version names one set."""
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    t = synthetic_trial(np.random.default_rng(1), cfg.scene_grid, cfg.gripper_grid, n_objects=1, episode_id=12)
    t.meta = dataclasses.replace(t.meta, policy_version=16)
    client.insert(t.validate())
    client.flush()
    run = tmp_path / "run"
    proc = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    assert not checkpoint_path(run).is_file()
    assert proc.train(0, force_publish=True)["weights"][0] == 17


def test_checkpoint_keeps_history_and_version_and_publishes_every_n_steps(filled_replay, tmp_path):
    """learner.publish_every steps between versions (not one more); a resumed learner continues the
    loss history and numbers its weights after the checkpoint's version, even when the replay's
    trials carry only older versions."""
    from learner.loop import LearnerProcess

    cfg, client = filled_replay
    cfg = dataclasses.replace(cfg, learner=dataclasses.replace(cfg.learner, publish_every=2, samples_per_insert=1e6))
    run = tmp_path / "run"
    proc = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    assert proc.train(0, force_publish=True)["weights"][0] == 1
    assert proc.train(1)["weights"] is None
    assert proc.train(1)["weights"][0] == 2
    assert proc.train(1)["weights"] is None and proc.train(1)["weights"][0] == 3
    history = proc.history()
    assert len(history) == 4 and [step for step, _ in history] == [1, 2, 3, 4]
    proc.checkpoint(epsilon=0.5, inserted=12)
    resumed = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    assert resumed.history() == history
    assert resumed.train(0, force_publish=True)["weights"][0] == 4


def test_initial_weights_follow_the_seed_not_the_process(filled_replay):
    """run.seed fixes the network's first weights; torch's global generator neither decides them
    nor is moved by them."""
    cfg, client = filled_replay

    def first_weights(seed, global_seed):
        torch.manual_seed(global_seed)
        weights = Learner(cfg, client, seed=seed).model.state_dict()
        return weights, torch.rand(1)

    a, after_a = first_weights(3, 0)
    b, after_b = first_weights(3, 1)
    c, _ = first_weights(4, 0)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(v.dtype.is_floating_point and not torch.equal(v, c[k]) for k, v in a.items())
    torch.manual_seed(0)
    assert torch.equal(after_a, torch.rand(1)), "building the learner must not draw from the global generator"


def test_an_actor_whose_episodes_keep_failing_ends_the_run_with_the_error():
    """An error raised inside an actor's episodes (its process alive) is not a lost process to
    restart forever: it is reported with its first line, and the third in a row ends the run. A
    cause that is a Ray error (a lost shard, a lost weights owner) is transient and not counted."""
    from ray.exceptions import ActorDiedError, RayTaskError

    from learner.loop import ACTOR_TASK_FAILURES, ActorFailures, ActorTaskError

    def task_error(cause):
        return RayTaskError("run_episodes", "Traceback ...", cause)

    failures = ActorFailures(2)
    assert failures.failed(0, task_error(ValueError("openings must be a non-empty tuple\n  detail"))) == (
        "ValueError: openings must be a non-empty tuple", True)
    failures.succeeded(0)  # a chunk that ran clears the count
    for _ in range(ACTOR_TASK_FAILURES - 1):
        failures.failed(0, task_error(ValueError("bad")))
        failures.failed(1, task_error(ValueError("other")))
    for _ in range(5):
        line, own = failures.failed(1, task_error(ActorDiedError()))
        assert not own and line.startswith("ActorDiedError")
    with pytest.raises(ActorTaskError, match=r"^actor 1: 3 episode chunks in a row failed, the last with ValueError: x$"):
        failures.failed(1, task_error(ValueError("x")))


def test_an_actor_whose_process_keeps_dying_ends_the_run_with_its_constructors_error():
    """A constructor that raises kills the actor's process at every restart, so each chunk fails at
    once: the driver counts the losses in a row (a finished chunk clears them) and the fifth ends
    the run, naming the exception the constructor raised; before, it resubmitted forever."""
    from learner.loop import ACTOR_DEATHS, ActorFailures, ActorTaskError

    class ActorDiedError(Exception):  # the message Ray gives for a failed creation task
        pass

    died = ActorDiedError(
        "The actor died because of an error raised in its creation task, ray::ActorProcess.__init__() (pid=1)\n"
        "           ^^^^^^^^\n  File \"actors/grasp_actor.py\", line 90, in __init__\n"
        "ValueError: sim.camera_height: -1.0 m must exceed the grid top z = 0.128 m"
    )
    failures = ActorFailures(2)
    line = failures.died(0, died)
    assert line == "ActorDiedError: ValueError: sim.camera_height: -1.0 m must exceed the grid top z = 0.128 m"
    assert failures.died(1, ActorDiedError("")) == "ActorDiedError"
    failures.succeeded(0)  # a chunk that ran: a process lost now and then never ends the run
    for _ in range(ACTOR_DEATHS - 1):
        failures.died(0, died)
    with pytest.raises(ActorTaskError, match=r"^actor 0: its process was lost 5 times in a row without finishing an "
                                             r"episode chunk, the last with ActorDiedError: ValueError: sim.camera"):
        failures.died(0, died)


def test_the_actors_never_wait_while_the_learner_cannot_step():
    """With samples_per_insert x (insert_lead + 1) below one batch, the actors reached their lead
    before the learner had a whole batch of budget: both sides waited for ever."""
    from learner.rate_limit import SamplesPerInsert

    for spi, lead in ((0.1, 1), (0.1, 32), (0.25, 4), (0.5, 4), (32.0, 32.0)):
        limiter = SamplesPerInsert(spi=spi, min_replay=8, batch_size=8, insert_lead=lead)
        inserted = sampled = 0
        for _ in range(100_000):
            if limiter.allowed_steps(inserted, sampled):
                sampled += 8
            elif limiter.may_insert(inserted, sampled) and inserted < 400:
                inserted += 1
            elif inserted >= 400:
                break
            else:
                raise AssertionError(f"spi {spi}, insert_lead {lead}: stuck at {inserted} trials, {sampled} samples")
        assert inserted >= 400
        assert sampled == 8 * int(spi * (inserted - 8 + 1) // 8), (spi, lead)


def test_a_resume_keeps_the_rate_limits_ratio_and_start(tmp_path):
    """The learner's budget is samples_per_insert x (trials since min_replay): a new ratio on a
    resume would apply to the whole run (at 8 instead of 32 after 1,000 trials, the learner idles
    for about 2,900 trials; at 64, it takes thousands of steps on no new data). Refused in one
    line, config untouched; other learner keys still change."""
    from learner.run import parse_args, resolve

    run = _tiny_run_with_one_trial(tmp_path / "run")
    before = (run / "config.yaml").read_bytes()
    for key, value in (("samples_per_insert", 64), ("min_replay", 100)):
        with pytest.raises(ConfigError, match=rf"config.yaml: learner.{key}: .* a resumed run keeps it") as e:
            resolve(parse_args(["--resume", "--run-dir", str(run), "--set", f"learner.{key}={value}"]))
        assert "\n" not in str(e.value)
        assert (run / "config.yaml").read_bytes() == before
    cfg, _ = resolve(parse_args(["--resume", "--run-dir", str(run), "--set", "learner.lr=0.0005"]))
    assert cfg.learner.lr == 0.0005


def test_a_resume_can_mend_the_runs_config_with_set(tmp_path):
    """--set on --resume is applied before the cross-field checks: an odd batch size in the run's
    config.yaml is mended by --set learner.batch_size=8, not refused."""
    import yaml

    from learner.run import parse_args, resolve

    run = _tiny_run_with_one_trial(tmp_path / "run")
    data = yaml.safe_load((run / "config.yaml").read_text())
    data["learner"]["batch_size"] = 7
    (run / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="learner.batch_size: must be even"):
        resolve(parse_args(["--resume", "--run-dir", str(run)]))
    cfg, _ = resolve(parse_args(["--resume", "--run-dir", str(run), "--set", "learner.batch_size=8"]))
    assert cfg.learner.batch_size == 8
    for seed in ("replay.seed_from=/elsewhere", "replay={seed_from: /elsewhere}"):  # a resumed run keeps its replay
        with pytest.raises(ConfigError, match="replay.seed_from: a resumed run keeps its replay"):
            resolve(parse_args(["--resume", "--run-dir", str(run), "--set", seed]))


def test_a_diverged_learner_stops_and_keeps_the_last_finite_checkpoint(filled_replay, tmp_path, capsys):
    """A non-finite weight makes the next step's loss and scores non-finite: train() raises before
    the scores reach the replay, and the checkpoint call that follows (the driver's, at exit)
    leaves latest.pt with the last finite weights instead of overwriting it."""
    from common.checkpoint import read_checkpoint
    from learner.learner import TrainingDivergedError
    from learner.loop import LearnerProcess, checkpoint_path

    cfg, client = filled_replay
    run = tmp_path / "run"
    proc = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    proc.learner.train(2)
    proc.checkpoint(epsilon=0.5, inserted=12)
    good = checkpoint_path(run).read_bytes()
    scores = np.concatenate([d["score"] for d in (s.index() for s in client._shards)])
    with torch.no_grad():
        next(proc.learner.model.parameters()).fill_(float("inf"))
    with pytest.raises(TrainingDivergedError, match=r"learner step 3: loss .* not finite"):
        proc.learner.train(1)
    assert proc.learner.stats.steps == 2
    after = np.concatenate([d["score"] for d in (s.index() for s in client._shards)])
    assert np.array_equal(after, scores), "no score of a diverged step reaches the replay"
    proc.checkpoint(epsilon=0.5, inserted=12, snapshot=True)
    assert "weights not finite" in capsys.readouterr().out
    assert checkpoint_path(run).read_bytes() == good
    assert not list(checkpoint_path(run).parent.glob("step-*.pt"))
    kept = read_checkpoint(checkpoint_path(run))
    assert kept.step == 2 and all(torch.isfinite(v).all() for v in kept.model_state.values() if v.is_floating_point())


def test_adam_betas_come_from_the_config_also_on_a_resume(filled_replay, tmp_path):
    """learner.adam_beta2: 0.999 by default (torch's, the shipped models'), the paper's 0.95 in
    configs/paper.yaml; a resumed run takes the config's betas, not those stored with Adam's state;
    a value outside [0, 1) is one line."""
    from learner.loop import LearnerProcess

    assert load_config("paper").learner.adam_beta2 == 0.95
    cfg, client = filled_replay
    assert (cfg.learner.adam_beta1, cfg.learner.adam_beta2) == (0.9, 0.999)
    run = tmp_path / "run"
    proc = LearnerProcess(cfg, client._shards, str(run), seed=0, torch_threads=1)
    assert [g["betas"] for g in proc.learner.optimizer.param_groups] == [(0.9, 0.999)]
    proc.learner.train(1)
    proc.checkpoint(epsilon=0.5, inserted=12)
    paper_betas = copy.deepcopy(cfg)
    paper_betas.learner.adam_beta2 = 0.95
    resumed = LearnerProcess(paper_betas, client._shards, str(run), seed=0, torch_threads=1)
    assert [g["betas"] for g in resumed.learner.optimizer.param_groups] == [(0.9, 0.95)]
    with pytest.raises(ConfigError, match="learner.adam_beta2"):
        load_config("tiny", overrides=["learner.adam_beta2=1.0"])


def test_resume_from_a_weights_only_checkpoint_is_refused_in_one_line(filled_replay, tmp_path, capsys):
    """A step-*.pt snapshot copied over latest.pt (a roll-back) holds no learner state or
    optimiser: --resume says so in one line naming the file (it was a KeyError), files untouched."""
    import shutil

    from learner.loop import LearnerProcess, checkpoint_path
    from learner.run import cli, parse_args, resolve

    run = _tiny_run_with_one_trial(tmp_path / "run")
    cfg, _ = resolve(parse_args(["--resume", "--run-dir", str(run)]))
    shards = open_local_shards(run / "replay", cfg)
    LearnerProcess(cfg, shards, str(run), seed=0, torch_threads=1).checkpoint(epsilon=0.5, inserted=1, snapshot=True)
    ckpt = checkpoint_path(run)
    shutil.copyfile(ckpt.parent / "step-0000000.pt", ckpt)
    from common.checkpoint import CheckpointError

    with pytest.raises(CheckpointError, match="extra.learner: missing"):
        LearnerProcess(cfg, shards, str(run), seed=0, torch_threads=1)
    for s in shards:
        s.close()
    before = _files(run)
    rc = cli(["--resume", "--run-dir", str(run), "--actors", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and f"{ckpt}: extra.learner: missing (a weights-only file" in err[0], err
    assert _files(run) == before


def test_a_torn_last_progress_line_is_dropped_before_the_resumed_part_writes(tmp_path, capsys):
    """A part killed in the middle of a progress.jsonl line: the resumed part drops the cut-off
    line (it swallowed the next line, and the curve refuses a file with a line it cannot parse),
    says so, and keeps every complete line; the curve then draws the run."""
    from learner.curve import main as curve
    from learner.loop import Progress

    cfg = load_config("tiny")
    log = tmp_path / "progress.jsonl"
    first = '{"time": 1.0, "trials": 3, "success_rate": 0.5, "epsilon": 0.8, "loss": 0.7}'
    log.write_text(first + '\n{"time": 2.')
    progress = Progress(cfg, tmp_path, quiet=True)
    progress.tick(5, {"steps": 1, "samples": 8, "version": 1, "loss": 0.5}, 0.5, force=True)
    progress.close()
    assert "dropped a cut-off last line of 11 bytes" in capsys.readouterr().out
    lines = log.read_text().splitlines()
    assert lines[0] == first and len(lines) == 2 and json.loads(lines[1])["learner_steps"] == 1
    assert curve([str(tmp_path), "--out", str(tmp_path / "curve.png")]) == 0


def test_a_local_run_whose_training_diverges_ends_with_one_line(tmp_path, capsys, monkeypatch):
    """--actors 0: the learner's weights turn non-finite after its first steps; the run stops with
    the divergence as its error (rc 2, one line on stderr) and latest.pt keeps finite weights."""
    from common.checkpoint import read_checkpoint
    from learner.learner import Learner as Plain
    from learner.loop import checkpoint_path
    from learner.run import cli

    train = Plain.train

    def diverging(self, steps, max_seconds=None):
        if self.stats.steps >= 2:
            with torch.no_grad():
                next(self.model.parameters()).fill_(float("nan"))
        return train(self, steps, max_seconds)

    monkeypatch.setattr(Plain, "train", diverging)
    run = tmp_path / "run"
    rc = cli(["--config", "tiny", "--run-dir", str(run), "--actors", "0", "--max-trials", "40", "--quiet",
              "--set", "learner.min_replay=2", "--set", "learner.checkpoint_minutes=0.001"])
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "training diverged" in err[0] and "last checkpoint:" in err[0], err
    assert "weights not finite" in captured.out
    summary = json.loads((run / "summary.json").read_text())
    assert "training diverged" in summary["error"] and summary["trials"] < 40
    kept = read_checkpoint(checkpoint_path(run))
    assert kept.step >= 2 and all(torch.isfinite(v).all() for v in kept.model_state.values() if v.is_floating_point())
