"""``evaluate compare``: pairing on shared scenes, the sign test, the scene bootstrap and its errors."""

import itertools
import json
import math

import numpy as np
import pytest

from actors import compare as cmp
from actors import evaluate as ev

OBJECTS = [["ycb/015_peach", "target"], ["random_urdfs/901", "obstacle"]]


def result(policy, table, seeds, grippers=("wsg_50", "panda_hand"), scene="obstacle", objects="test"):
    """A result JSON as ``evaluate --json`` writes it (the keys compare reads).

    ``table``: per-gripper policies {gripper: [(successes, attempts) per scene]}; ``adagrasp``:
    [(successes, attempts) per scene].
    """
    rows = {None: table} if policy == "adagrasp" else table
    episodes, per = [], {}
    for g, cells in rows.items():
        for e, (s, a) in enumerate(cells):
            episodes.append({"index": len(episodes), "episode": e, "gripper": g, "scene_seed": seeds[e],
                             "objects": OBJECTS, "attempts": a, "successes": s})
    for g in grippers:
        mine = [r for r in episodes if r["gripper"] == g]
        s, a = sum(r["successes"] for r in mine), sum(r["attempts"] for r in mine)
        per[g] = {"successes": s, "attempts": a, "rate": s / a if a else None}
    succ, att = sum(r["successes"] for r in episodes), sum(r["attempts"] for r in episodes)
    rate = succ / att if policy == "adagrasp" else float(np.mean([per[g]["rate"] for g in grippers]))
    return {"format": ev.FORMAT, "policy": policy, "scene": scene, "objects": objects, "objects_label": "O_te",
            "grippers": "test", "grippers_label": "G_te", "gripper_names": list(grippers), "cameras": 1,
            "rate": rate, "episodes": len(seeds), "seed": 0, "scene_seeds": list(seeds),
            "average": {"rate": rate, "attempts": att, "successes": succ}, "per_gripper": per,
            "episode_results": episodes, "checkpoint": None, "calibration": None}


def write(tmp_path, name, data):
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(data))
    return str(path)


SEEDS = [11, 12, 13, 14, 15]
FG_A = {"wsg_50": [(1, 5), (0, 5), (2, 4), (3, 3), (0, 5)], "panda_hand": [(2, 4), (1, 5), (0, 5), (3, 4), (1, 5)]}
FG_B = {"wsg_50": [(2, 4), (0, 5), (2, 4), (3, 3), (1, 5)], "panda_hand": [(1, 5), (3, 3), (1, 5), (3, 3), (1, 5)]}


def binomial_two_sided(better, worse):
    """McNemar's exact test: two-sided binomial tail of the discordant pairs."""
    n, k = better + worse, min(better, worse)
    return 1.0 if better == worse else min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2**n)


def brute_force_p(diffs):
    """The sign-flip p-value by enumerating all 2^U signs."""
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=len(diffs))))
    sums = np.abs(signs @ np.asarray(diffs, dtype=float))
    return float(np.mean(sums >= abs(sum(diffs)) - 1e-9))


def test_sign_flip_test_is_mcnemar_for_one_grasp_units():
    for better, worse, same in ((8, 2, 0), (2, 8, 5), (10, 0, 3), (5, 5, 1), (0, 0, 4), (21, 2, 77)):
        diffs = np.array([1.0] * better + [-1.0] * worse + [0.0] * same)
        assert cmp.sign_flip_p(diffs) == pytest.approx(binomial_two_sided(better, worse))


def test_sign_flip_test_equals_enumerating_every_sign():
    rng = np.random.default_rng(5)
    for _ in range(20):
        diffs = rng.integers(-5, 6, size=int(rng.integers(1, 12))) / 5.0
        assert cmp.sign_flip_p(diffs, scale=5) == pytest.approx(brute_force_p(diffs))
    # Many small wins against a few large losses: a count of signs would call B better.
    diffs = np.array([0.2] * 9 + [-0.8] * 3)
    assert cmp.sign_flip_p(diffs, scale=5) == pytest.approx(brute_force_p(diffs))
    assert cmp.sign_flip_p(diffs, scale=5) > 0.5 and binomial_two_sided(9, 3) < 0.15


def test_per_gripper_results_pair_on_gripper_and_scene(tmp_path):
    a, b = result("fix-gripper", FG_A, SEEDS), result("fix-gripper", FG_B, SEEDS)
    sa, sb = cmp.pair("a", a, "b", b)
    c = cmp.compare(sa, sb, resamples=2000)
    assert c["unit"] == "(gripper, scene)" and c["units"] == 10 and c["scenes"] == 5
    # Units: gripper (sorted by name) x scene; counted here from the tables above.
    ua = [s for g in ("panda_hand", "wsg_50") for s, _ in FG_A[g]]
    ub = [s for g in ("panda_hand", "wsg_50") for s, _ in FG_B[g]]
    better = sum(y > x for x, y in zip(ua, ub))
    worse = sum(y < x for x, y in zip(ua, ub))
    assert (c["b_better"], c["b_worse"], c["same"]) == (better, worse, 10 - better - worse) == (4, 1, 5)
    assert c["p_value"] == pytest.approx(brute_force_p([y - x for x, y in zip(ua, ub)]))
    assert c["a"]["rate"] == pytest.approx(a["rate"]) and c["b"]["rate"] == pytest.approx(b["rate"])
    assert c["rate_difference"] == pytest.approx(b["rate"] - a["rate"])
    lo, hi = c["ci95"]
    assert lo <= c["rate_difference"] <= hi and lo < hi


def test_bootstrap_weights_equal_repeating_the_scenes():
    """table_rate with count weights = the rate of the result whose scenes are repeated that often."""
    a = result("fix-gripper", FG_A, SEEDS)
    side = cmp.pair("a", a, "a", a)[0]
    draw = [3, 3, 0, 4, 3]
    weights = np.bincount(draw, minlength=5)[None, :].astype(float)
    repeated = result("fix-gripper", {g: [FG_A[g][i] for i in draw] for g in FG_A}, [100 + i for i in range(5)])
    assert cmp.table_rate(side, weights)[0] == pytest.approx(repeated["rate"])
    pooled = cmp.pair("p", result("adagrasp", FG_A["wsg_50"], SEEDS), "p", result("adagrasp", FG_A["wsg_50"], SEEDS))[0]
    again = result("adagrasp", [FG_A["wsg_50"][i] for i in draw], [100 + i for i in range(5)])
    assert cmp.table_rate(pooled, weights)[0] == pytest.approx(again["rate"])


def test_identical_results_differ_by_nothing(tmp_path):
    a = result("fix-gripper", FG_A, SEEDS)
    c = cmp.compare(*cmp.pair("a", a, "a", a), resamples=500)
    assert c["rate_difference"] == 0 and c["ci95"] == [0.0, 0.0]
    assert (c["b_better"], c["b_worse"], c["same"], c["p_value"]) == (0, 0, 10, 1.0)


def test_a_clear_difference_has_an_interval_above_zero():
    seeds = list(range(30))
    a = result("adagrasp", [(0, 5)] * 28 + [(1, 5)] * 2, seeds)
    b = result("adagrasp", [(3, 4)] * 25 + [(0, 5)] * 5, seeds)
    c = cmp.compare(*cmp.pair("a", a, "b", b))
    assert c["ci95"][0] > 0.3 and c["b_better"] == 25 and c["p_value"] < 1e-5


def test_adagrasp_against_per_gripper_pairs_scenes_on_the_gripper_mean():
    fg = result("fix-gripper", FG_A, SEEDS)
    ada = result("adagrasp", [(2, 4), (1, 5), (1, 5), (3, 3), (0, 5)], SEEDS)
    c = cmp.compare(*cmp.pair("fg", fg, "ada", ada), resamples=500)
    means = [(FG_A["wsg_50"][e][0] + FG_A["panda_hand"][e][0]) / 2 for e in range(5)]  # 1.5, .5, 1, 3, .5
    ours = [2, 1, 1, 3, 0]
    assert c["unit"] == "scene" and c["units"] == 5
    better, worse = sum(o > m for o, m in zip(ours, means)), sum(o < m for o, m in zip(ours, means))
    assert (c["b_better"], c["b_worse"]) == (better, worse) == (2, 1)
    assert c["p_value"] == pytest.approx(brute_force_p([o - m for o, m in zip(ours, means)]))
    assert c["a"]["rate"] == pytest.approx(fg["rate"]) and c["b"]["rate"] == pytest.approx(ada["rate"])
    only = cmp.compare(*cmp.pair("fg", fg, "ada", ada, only=["wsg_50"]), resamples=500)
    assert only["a"]["grippers"] == ["wsg_50"]
    assert only["a"]["rate"] == pytest.approx(fg["per_gripper"]["wsg_50"]["rate"])


def test_only_shared_scenes_and_grippers_are_paired():
    long = result("fix-gripper", {g: v + v for g, v in FG_A.items()}, SEEDS + [21, 22, 23, 24, 25])
    three = result("fix-gripper", {**FG_B, "pr2_gripper": FG_B["wsg_50"]}, SEEDS,
                   grippers=("wsg_50", "panda_hand", "pr2_gripper"))
    c = cmp.compare(*cmp.pair("long", long, "three", three), resamples=200)
    assert c["scenes"] == 5 and c["units"] == 10
    assert c["b"]["grippers"] == ["panda_hand", "wsg_50"]


def test_cli_prints_and_writes_the_comparison(tmp_path, capsys):
    a = write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS))
    b = write(tmp_path, "b", result("fix-gripper", FG_B, SEEDS))
    out = tmp_path / "cmp.json"
    assert ev.cli(["compare", a, b, "--resamples", "300", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    data = json.loads(out.read_text())
    assert data["format"] == cmp.COMPARE_FORMAT and data["bootstrap"] == {"resamples": 300, "seed": 0, "unit": "scene"}
    assert f"B better in {data['b_better']} units, worse in {data['b_worse']}" in text
    assert ev.cli(["compare", a, b, "--resamples", "300", "--json", str(out)]) == 0
    assert json.loads(out.read_text()) == data, "the bootstrap is seeded"


def _changed_objects(data):
    data["episode_results"][3]["objects"] = [["ycb/other", "target"]]
    return data


@pytest.mark.parametrize(
    "change, extra, needle",
    [
        (lambda d: {**d, "scene": "multi"}, [], "scene: 'multi', but"),
        (lambda d: {**d, "objects": "train"}, [], "objects: 'train', but"),
        (_changed_objects, [], "gripper wsg_50).objects: not the objects of"),
        (lambda d: result("fix-gripper", FG_B, [91, 92, 93, 94, 95]), [], "scene_seeds: no scene in common"),
        (lambda d: result("fix-gripper", {"pr2_gripper": FG_B["wsg_50"]}, SEEDS, grippers=("pr2_gripper",)), [],
         "per_gripper: no gripper in common"),
        (lambda d: {**d, "episode_results": []}, [], "episode_results: missing or empty"),
        (lambda d: d, ["--gripper", "robotiq"], "--gripper robotiq: not among its grippers"),
        (lambda d: d, ["--resamples", "0"], "--resamples 0: expected >= 1"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, change, extra, needle):
    a = write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS))
    b = write(tmp_path, "b", change(result("fix-gripper", FG_B, SEEDS)))
    out = tmp_path / "never.json"
    assert ev.cli(["compare", a, b, *extra, "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and needle in err, err
    assert not out.exists()


def test_gripper_filter_needs_a_per_gripper_result(tmp_path, capsys):
    a = write(tmp_path, "a", result("adagrasp", FG_A["wsg_50"], SEEDS))
    assert ev.cli(["compare", a, a, "--gripper", "wsg_50"]) == 2
    assert "both results are adagrasp runs" in capsys.readouterr().err
