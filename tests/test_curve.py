"""Learning-curve picture of a run (learner/curve.py)."""

from __future__ import annotations

import json

from common.checkpoint import save_checkpoint
from learner.curve import main, read_greedy, wilson
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


def test_curve_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "scripted.json"
    bad.write_text(json.dumps({"trials": 5, "successes": 1, "success_rate": 0.2}))
    assert main([str(tmp_path), "--out", str(tmp_path / "c.png"), "--greedy", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "scripted.json: checkpoint: missing" in err and "\n" not in err
    assert main([str(tmp_path / "nowhere"), "--out", str(tmp_path / "c.png")]) == 2
    assert "progress.jsonl: not found" in capsys.readouterr().err
