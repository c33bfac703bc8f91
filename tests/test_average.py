"""Averaging a run's checkpoints (learner/average.py)."""

from __future__ import annotations

import shutil

import pytest
import torch

from common.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from learner.average import average_checkpoints, cli
from learner.export import export_model
from tests.test_network import small_model


def _snapshot(tmp_path, seed, step, inserted, *overrides):
    cfg, model = small_model(*overrides, seed=seed)
    for m in model.modules():
        if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
            m.running_mean.uniform_(-1, 1)
            m.running_var.uniform_(0.5, 2)
            m.num_batches_tracked.fill_(step)
    return save_checkpoint(tmp_path / f"step-{step:07d}.pt", model, cfg, step=step, version=step // 10,
                           epsilon=0.2, optimizer={"state": {}, "param_groups": []},
                           extra={"replay": {"inserted": inserted}, "learner": {"sampling": 1}})


def test_average_is_the_mean_of_every_float_tensor(tmp_path):
    paths = [_snapshot(tmp_path, seed, 100 * (seed + 1), 150 * (seed + 1)) for seed in range(3)]
    out = average_checkpoints(paths, tmp_path / "avg.pt")
    states = [read_checkpoint(p).model_state for p in paths]
    avg = read_checkpoint(out)
    floats = 0
    for k, v in avg.model_state.items():
        if v.is_floating_point():
            floats += 1
            want = sum(s[k].double() for s in states) / 3
            assert torch.allclose(v.double(), want, atol=1e-6), k
            assert v.dtype == states[-1][k].dtype
        else:
            assert torch.equal(v, states[-1][k]), k
    assert floats > 10 and any("running_mean" in k for k in avg.model_state)
    assert (avg.step, avg.version, avg.optimizer) == (300, 30, None)
    assert avg.extra["replay"] == {"inserted": 450} and "learner" not in avg.extra
    assert avg.extra["averaged_from"] == [{"file": f"step-{100 * (s + 1):07d}.pt", "step": 100 * (s + 1),
                                           "inserted": 150 * (s + 1)} for s in range(3)]


def test_average_of_copies_scores_like_the_checkpoint_and_ships(tmp_path):
    path = _snapshot(tmp_path, 4, 50, 80)
    copy = shutil.copy(path, tmp_path / "copy.pt")
    out = average_checkpoints([path, copy], tmp_path / "avg.pt")
    (m1, _), (m2, _) = load_checkpoint(path), load_checkpoint(out)
    for (k, a), b in zip(m1.state_dict().items(), m2.state_dict().values()):
        assert torch.equal(a, b), k
    shipped = export_model(tmp_path, "averaged", checkpoint=out, dest=tmp_path / "models")
    assert read_checkpoint(shipped / "checkpoint.pt").extra["averaged_from"][1]["file"] == "copy.pt"


def test_average_refuses_unlike_checkpoints_in_one_line(tmp_path, capsys):
    a = _snapshot(tmp_path, 0, 10, 20)
    other = tmp_path / "other"
    other.mkdir()
    b = _snapshot(other, 1, 20, 40, "model.channels=8")
    out = tmp_path / "avg.pt"
    assert cli([str(a), str(b), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "other/step-0000020.pt: config: model.channels" in err and "\n" not in err
    assert cli([str(a), "--out", str(out)]) == 2
    assert "at least two" in capsys.readouterr().err
    assert cli([str(a), str(a), "--out", str(out)]) == 2
    assert "named twice" in capsys.readouterr().err
    (tmp_path / "d").mkdir()
    assert cli([str(a), str(tmp_path / "d" / ".." / a.name), "--out", str(out)]) == 2
    assert "the file is named twice" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(ValueError, match="checkpoint file not found"):
        average_checkpoints([a, tmp_path / "gone.pt"], out)


def test_average_refuses_a_missing_or_reshaped_tensor(tmp_path):
    a = _snapshot(tmp_path, 0, 10, 20)
    state = torch.load(a, weights_only=True)
    key = next(k for k, v in state["model"].items() if v.is_floating_point() and v.dim() > 1)
    state["model"][key] = state["model"][key][:1]
    torch.save(state, tmp_path / "reshaped.pt")
    with pytest.raises(ValueError, match=f"reshaped.pt: model: {key} is"):
        average_checkpoints([a, tmp_path / "reshaped.pt"], tmp_path / "avg.pt")
    del state["model"][key]
    torch.save(state, tmp_path / "missing.pt")
    with pytest.raises(ValueError, match=f"missing.pt: model: tensor {key} is not in both"):
        average_checkpoints([a, tmp_path / "missing.pt"], tmp_path / "avg.pt")
    assert not (tmp_path / "avg.pt").exists()


def test_average_never_overwrites_an_input_and_replaces_an_existing_file_only_with_force(tmp_path, capsys):
    """--out naming one of the averaged checkpoints (a run's latest.pt, say) is refused, as is an
    existing file without --force; both in one line, with every file as it was."""
    a = _snapshot(tmp_path, 0, 10, 20)
    b = _snapshot(tmp_path, 1, 20, 40)
    taken = tmp_path / "taken.pt"
    taken.write_bytes(b"mine")
    before = {p: p.read_bytes() for p in (a, b, taken)}
    for out, extra, needle in ((b, ["--force"], "is one of the checkpoints averaged"), (taken, [], "exists (use --force")):
        assert cli([str(a), str(b), "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and f"--out {out}: {needle}" in err, err
    assert {p: p.read_bytes() for p in (a, b, taken)} == before
    assert cli([str(a), str(b), "--out", str(taken), "--force"]) == 0 and taken.read_bytes() != b"mine"
