"""Exporting a run's checkpoint as a shipped model (learner/export.py)."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from common.checkpoint import CheckpointError, load_checkpoint, model_sha256, read_checkpoint, save_checkpoint
from common.config import load_config
from learner.export import cli, export_model
from tests.test_network import small_model


def make_run(tmp_path):
    cfg, model = small_model(seed=4)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.learner.lr)
    model.train()  # one Adam step on a dummy loss so the optimiser has state to drop
    loss = sum(p.square().sum() for p in model.parameters())
    loss.backward()
    opt.step()
    model.eval()
    run = tmp_path / "run"
    save_checkpoint(run / "checkpoints" / "latest.pt", model, cfg, step=7, version=3, epsilon=0.6,
                    optimizer=opt, extra={"replay_inserted": 42})
    (run / "progress.jsonl").write_text(json.dumps({"time": 1.0, "trials": 5}) + "\n")
    return run, model


def test_export_keeps_weights_and_log_drops_optimizer(tmp_path):
    run, model = make_run(tmp_path)
    out = export_model(run, "tiny", dest=tmp_path / "models")
    ckpt = read_checkpoint(out / "checkpoint.pt")
    assert ckpt.optimizer is None and ckpt.step == 7 and ckpt.version == 3 and ckpt.epsilon == 0.6
    assert ckpt.extra == {"replay_inserted": 42}
    loaded, _ = load_checkpoint(out / "checkpoint.pt")
    assert all(torch.equal(v, loaded.state_dict()[k]) for k, v in model.state_dict().items())
    assert load_config(out / "config.yaml") == ckpt.cfg
    assert (out / "progress.jsonl").read_text() == (run / "progress.jsonl").read_text()
    assert (out / "checkpoint.pt").stat().st_size < (run / "checkpoints" / "latest.pt").stat().st_size


def test_model_digest_follows_network_and_weights_not_the_file(tmp_path):
    """The exported model and its source share one digest (other counters, no optimiser, another
    path); one changed weight or one network key gives another."""
    run, model = make_run(tmp_path)
    source = read_checkpoint(run / "checkpoints" / "latest.pt")
    exported = read_checkpoint(export_model(run, "tiny", dest=tmp_path / "models") / "checkpoint.pt")
    again = read_checkpoint(save_checkpoint(tmp_path / "again.pt", model, source.cfg, step=0, version=0))
    digest = source.model_sha256()
    assert len(digest) == 64 and exported.model_sha256() == digest == again.model_sha256()
    with torch.no_grad():
        first = next(model.parameters())
        first[(0,) * first.dim()] += 1e-6
    changed = read_checkpoint(save_checkpoint(tmp_path / "changed.pt", model, source.cfg, step=7, version=3))
    assert changed.model_sha256() != digest
    other_net = dataclasses.replace(source.cfg, model=dataclasses.replace(source.cfg.model, rotate="kernel"))
    assert other_net != source.cfg and model_sha256(other_net, source.model_state) != digest


def test_export_refuses_to_overwrite_and_bad_sources_fail_clearly(tmp_path, capsys):
    run, _ = make_run(tmp_path)
    dest = tmp_path / "models"
    export_model(run, "tiny", dest=dest)
    before = (dest / "tiny" / "checkpoint.pt").read_bytes()
    assert cli([str(run), "tiny", "--dest", str(dest)]) == 2
    err = capsys.readouterr().err.strip()
    assert "tiny: exists" in err and "\n" not in err
    assert (dest / "tiny" / "checkpoint.pt").read_bytes() == before
    assert cli([str(run), "tiny", "--dest", str(dest), "--force"]) == 0
    with pytest.raises(CheckpointError, match="checkpoint file not found"):
        export_model(tmp_path / "nowhere", "x", dest=dest)
    assert not (dest / "x").exists()


def test_force_never_deletes_the_run_it_exports(tmp_path, capsys):
    """--force replaces an earlier export; a destination that is the run directory itself (or a
    folder holding it) is refused, where rmtree would have deleted the run's replay and checkpoints."""
    run, _ = make_run(tmp_path)
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    assert cli([str(run), run.name, "--dest", str(run.parent), "--force"]) == 2
    err = capsys.readouterr().err.strip()
    assert "is the run directory or holds it" in err and "\n" not in err
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before
