"""Learning-curve picture of a run (learner/curve.py)."""

from __future__ import annotations

import json

from common.checkpoint import save_checkpoint
from learner.curve import main, read_greedy, read_held_out, wilson
from tests.test_compare import FG_A, FG_B, SEEDS, result
from tests.test_network import small_model


def test_wilson_interval_brackets_the_rate():
    lo, hi = wilson(53, 100)
    assert 0.43 < lo < 0.53 < hi < 0.63
    assert wilson(0, 0) == (0.0, 1.0)


def test_curve_draws_progress_and_greedy_points(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    lines = [{"time": t, "trials": 10 * t, "success_rate": 0.3 + 0.01 * t, "epsilon": 0.8 - 0.01 * t, "loss": 1.0 / (t + 1)}
             for t in range(20)]
    (run / "progress.jsonl").write_text("".join(json.dumps(d) + "\n" for d in lines))
    cfg, model = small_model(seed=1)
    summaries = []
    for step, inserted, ok in ((5, 60, 20), (9, 150, 35)):
        ckpt = save_checkpoint(run / "checkpoints" / f"step-{step:07d}.pt", model, cfg, step=step,
                               extra={"replay": {"inserted": inserted}})
        path = tmp_path / f"g{step}.json"
        path.write_text(json.dumps({"checkpoint": str(ckpt), "mode": "fix-gripper", "trials": 50,
                                    "successes": ok, "success_rate": ok / 50}))
        summaries.append(str(path))
    points = read_greedy(summaries[::-1])
    assert [p["inserted"] for p in points] == [60, 150] and [p["step"] for p in points] == [5, 9]
    out = tmp_path / "curve.png"
    assert main([str(run), "--out", str(out), "--greedy", *summaries]) == 0
    assert out.stat().st_size > 10_000


def test_progress_before_the_first_step_is_strict_json_and_still_draws(tmp_path):
    """The loss and success rate before the first learner step and episode are null, not NaN
    (which strict JSON parsers refuse); the curve reads such a file."""
    from common.config import load_config
    from learner.loop import Progress

    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    run = tmp_path / "run"
    run.mkdir()
    progress = Progress(load_config("default"), run, quiet=True)
    progress.tick(0, {}, 0.8, force=True)
    progress.tick(12, {"steps": 2, "samples": 8, "loss": 0.69, "version": 1}, 0.7, force=True)
    progress.close()
    first, second = (json.loads(line, parse_constant=refuse) for line in (run / "progress.jsonl").read_text().splitlines())
    assert first["loss"] is None and first["success_rate"] is None and first["weights_lag"] is None
    assert second["loss"] == 0.69 and second["trials"] == 12
    assert main([str(run), "--out", str(tmp_path / "curve.png")]) == 0


def test_curve_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "scripted.json"
    bad.write_text(json.dumps({"trials": 5, "successes": 1, "success_rate": 0.2}))
    assert main([str(tmp_path), "--out", str(tmp_path / "c.png"), "--greedy", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "scripted.json: checkpoint: missing" in err and "\n" not in err
    for text, needle in (("3", "number.json: checkpoint: missing"), ("{", "number.json: not valid JSON"),
                         (json.dumps({"checkpoint": "x.pt", "rate": 0.5}), "number.json: success_rate: missing")):
        (tmp_path / "number.json").write_text(text)
        assert main([str(tmp_path), "--out", str(tmp_path / "c.png"), "--greedy", str(tmp_path / "number.json")]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and needle in err, err
    assert main([str(tmp_path / "nowhere"), "--out", str(tmp_path / "c.png")]) == 2
    assert "progress.jsonl: not found" in capsys.readouterr().err
    good = json.dumps({"time": 1, "trials": 10, "success_rate": 0.3, "epsilon": 0.8, "loss": 0.7})
    for last, needle in (('{"time": 2, "tri', "line 2: not valid JSON"), ('{"foo": 1}', "line 2: trials: missing"),
                         ("[1, 2]", "line 2: trials: missing")):
        (tmp_path / "progress.jsonl").write_text(f"{good}\n{last}\n")
        assert main([str(tmp_path), "--out", str(tmp_path / "c.png")]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and f"progress.jsonl: {needle}" in err, err
    assert not (tmp_path / "c.png").exists()


def test_held_out_results_are_lines_per_row_at_the_trials_their_checkpoints_saw(tmp_path):
    """Evaluation results of a run's checkpoints: one line per row and scene seed, points at the
    checkpoints' replay.inserted, rates with a scene-bootstrap interval; a checkpoint path from
    another directory is found in RUN/checkpoints by its file name."""
    run = tmp_path / "run"
    run.mkdir()
    lines = [{"time": t, "trials": 10 * t, "success_rate": 0.4, "epsilon": 0.2, "loss": 0.5} for t in range(10)]
    (run / "progress.jsonl").write_text("".join(json.dumps(d) + "\n" for d in lines))
    cfg, model = small_model(seed=1)
    paths = []
    for step, inserted, table, seed in ((3, 40, FG_A, 0), (7, 90, FG_B, 0), (7, 90, FG_A, 2)):
        save_checkpoint(run / "checkpoints" / f"step-{step:07d}.pt", model, cfg, step=step,
                        extra={"replay": {"inserted": inserted}})
        data = result("fix-gripper", table, SEEDS)
        data.update(seed=seed, checkpoint=f"../elsewhere/checkpoints/step-{step:07d}.pt")
        paths.append(tmp_path / f"r{step}-{seed}.json")
        paths[-1].write_text(json.dumps(data))
    got = read_held_out([str(p) for p in paths[::-1]], run)
    assert sorted(got) == ["fix-gripper, obstacle O_te/G_te, seed 0", "fix-gripper, obstacle O_te/G_te, seed 2"]
    seed0 = got["fix-gripper, obstacle O_te/G_te, seed 0"]
    assert [(d["inserted"], d["step"]) for d in seed0] == [(40, 3), (90, 7)]
    assert [d["rate"] for d in seed0] == [result("fix-gripper", t, SEEDS)["rate"] for t in (FG_A, FG_B)]
    assert all(d["low"] <= d["rate"] <= d["high"] and d["high"] > d["low"] for d in seed0)
    out = tmp_path / "curve.png"
    assert main([str(run), "--out", str(out), "--held-out", *map(str, paths)]) == 0
    assert out.stat().st_size > 10_000


def test_held_out_errors_name_the_file(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "progress.jsonl").write_text(json.dumps({"trials": 1, "success_rate": 0, "epsilon": 1, "loss": 1}) + "\n")
    scripted = tmp_path / "heuristic.json"
    scripted.write_text(json.dumps(result("heuristic", FG_A, SEEDS)))
    assert main([str(run), "--out", str(tmp_path / "c.png"), "--held-out", str(scripted)]) == 2
    err = capsys.readouterr().err.strip()
    assert "heuristic.json: checkpoint: missing" in err and "\n" not in err
    lost = tmp_path / "lost.json"
    lost.write_text(json.dumps({**result("fix-gripper", FG_A, SEEDS), "checkpoint": "gone/step-0000009.pt"}))
    assert main([str(run), "--out", str(tmp_path / "c.png"), "--held-out", str(lost)]) == 2
    err = capsys.readouterr().err.strip()
    assert "lost.json: checkpoint: gone/step-0000009.pt not found" in err and "\n" not in err
