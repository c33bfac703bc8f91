"""Per-gripper score calibration: the MAP shift, the monotone map, fitting from result files (the
policy, the planner and evaluate use it: tests in test_policy, test_planner, test_evaluate)."""

import numpy as np
import pytest

from common.calibration import (
    CalibrationError,
    apply_shifts,
    calibration_from_result,
    fit_shift,
    logit,
    sigmoid,
)


def log_posterior(b, scores, ok, sigma):
    p = sigmoid(logit(scores) + b)
    return np.sum(np.where(ok, np.log(p), np.log1p(-p))) - 0.5 * (b / sigma) ** 2


def test_fit_recovers_a_known_shift():
    rng = np.random.default_rng(0)
    scores = rng.uniform(0.5, 0.97, size=4000)
    for true in (-2.5, 0.0, 1.0):
        ok = rng.random(4000) < sigmoid(logit(scores) + true)
        assert fit_shift(scores, ok) == pytest.approx(true, abs=0.15)


def test_fit_is_the_maximum_of_the_posterior():
    """Against a brute-force search of the log posterior, on few trials where the prior matters."""
    rng = np.random.default_rng(1)
    scores = rng.uniform(0.6, 0.95, size=12)
    ok = np.array([1, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0], dtype=bool)
    for sigma in (0.5, 2.0):
        grid = np.linspace(-8, 8, 160001)
        best = grid[np.argmax([log_posterior(b, scores, ok, sigma) for b in grid])]
        assert fit_shift(scores, ok, sigma) == pytest.approx(best, abs=2e-4)
    assert fit_shift(scores, ok, 0.5) > fit_shift(scores, ok, 2.0)  # a tighter prior pulls towards 0


def test_fit_edge_cases():
    assert fit_shift([], []) == pytest.approx(0.0, abs=1e-9)
    all_ok = fit_shift([0.5] * 10, [True] * 10)
    none_ok = fit_shift([0.5] * 10, [False] * 10)
    assert 0 < all_ok < 20 and none_ok == pytest.approx(-all_ok, abs=1e-9)
    assert fit_shift([1.0, 0.0], [False, True]) == pytest.approx(0.0, abs=1e-9)  # opposite mistakes cancel
    assert fit_shift([1.0, 1.0], [False, False]) < -2.0  # confident failures pull the shift down
    # a wide prior and one-sided trials: the maximum lies far out, and is still found
    wide = fit_shift([0.5] * 50, [True] * 50, prior_sigma=100.0)
    assert wide > 10 and abs(np.sum(1 - sigmoid(logit([0.5] * 50) + wide)) - wide / 100.0**2) < 1e-6
    with pytest.raises(CalibrationError, match="2 scores but 1 outcomes"):
        fit_shift([0.5, 0.6], [True])
    with pytest.raises(CalibrationError, match="prior_sigma"):
        fit_shift([0.5], [True], prior_sigma=0.0)


def test_shifts_keep_each_grippers_order_and_change_the_comparison():
    rng = np.random.default_rng(2)
    probs = rng.uniform(0.05, 0.95, size=(2, 3, 4, 5, 5)).astype(np.float32)
    probs[0, 1, 2, 3, 3] = 0.9999999  # gripper 0 holds the best raw score ...
    probs[0, 0, 0, 0, 0] = 0.9999995  # ... and the next, apart from it only in float32's last bits
    same = apply_shifts(probs, np.zeros(2))
    np.testing.assert_allclose(same, probs, rtol=1e-6)
    shifted = apply_shifts(probs, np.array([-15.0, 0.5]))
    assert shifted.shape == probs.shape and shifted.dtype == np.float64
    assert shifted[0, 0, 0, 0, 0] < shifted[0, 1, 2, 3, 3] < 0.9
    for g in range(2):
        assert np.array_equal(np.argsort(probs[g].ravel(), kind="stable"), np.argsort(shifted[g].ravel(), kind="stable"))
    assert np.unravel_index(np.argmax(probs), probs.shape)[0] == 0
    assert np.unravel_index(np.argmax(shifted), shifted.shape)[0] == 1
    assert np.argmax(shifted[1]) == np.argmax(probs[1])
    with pytest.raises(CalibrationError, match="one per gripper"):
        apply_shifts(probs, np.zeros(3))


def result(policy="fix-gripper", trials=None):
    trials = trials or {"a": [(0.9, False)] * 8 + [(0.9, True)] * 2, "b": [(0.6, True)] * 9 + [(0.6, False)]}
    episodes = [{"trials": [{"gripper": g, "score": s, "success": y}]} for g, rows in trials.items() for s, y in rows]
    return {"policy": policy, "episode_results": episodes}


def test_calibration_from_a_result():
    cal = calibration_from_result("cal.json", result())
    assert set(cal.grippers) == {"a", "b"}
    a, b = cal.grippers["a"], cal.grippers["b"]
    assert (a.trials, a.successes, b.trials, b.successes) == (10, 2, 10, 9)
    assert (a.scenes, b.scenes) == (10, 10)
    assert a.mean_score == pytest.approx(0.9) and a.shift < -1.5 < 0.5 < b.shift
    assert a.shift == pytest.approx(fit_shift([0.9] * 10, [False] * 8 + [True] * 2))
    np.testing.assert_allclose(cal.shifts(["b", "a"]), [b.shift, a.shift])
    record = cal.to_dict()
    assert record["source"] == "cal.json" and record["grippers"]["a"]["successes"] == 2
    assert record["grippers"]["b"]["scenes"] == 10
    with pytest.raises(CalibrationError, match=r"cal.json: episode_results: no trials of gripper c"):
        cal.shifts(["a", "c"])


def test_the_budget_counts_scenes_not_trials():
    """A pile gives several trials per scene: the budget is the scenes a gripper's trials came from."""
    episodes = [{"trials": [{"gripper": "a", "score": 0.8, "success": False},
                            {"gripper": "a", "score": 0.7, "success": True}]} for _ in range(3)]
    episodes.append({"trials": [{"gripper": "b", "score": 0.5, "success": True}]})
    cal = calibration_from_result("cal.json", {"policy": "fix-gripper", "episode_results": episodes})
    assert (cal.grippers["a"].trials, cal.grippers["a"].scenes) == (6, 3)
    assert (cal.grippers["b"].trials, cal.grippers["b"].scenes) == (1, 1)


@pytest.mark.parametrize(
    "data, needle",
    [
        (result(policy="adagrasp"), "cal.json: policy: a calibration is fitted to fix-gripper trials"),
        ({"policy": "fix-gripper", "episode_results": []}, "cal.json: episode_results: missing or empty"),
        ({"policy": "fix-gripper", "episode_results": [{"trials": [{"gripper": "a"}]}]},
         "cal.json: episode_results[0]: malformed trial"),
        ({"policy": "fix-gripper", "episode_results": [{"trials": [{"gripper": "a", "score": 0.5, "success": "false"}]}]},
         "cal.json: episode_results[0]: malformed trial (ValueError: success: expected true or false, got 'false')"),
        (result(trials={"a": [(1.5, True)]}), "cal.json: score: gripper a has scores outside"),
    ],
)
def test_bad_calibration_input_is_one_line(data, needle):
    with pytest.raises(CalibrationError) as e:
        calibration_from_result("cal.json", data)
    assert needle in str(e.value) and "\n" not in str(e.value)
