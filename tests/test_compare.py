"""``evaluate compare``: pairing on shared scenes, the scene bootstrap, the permutation test, errors."""

import itertools
import json
import math
import random

import numpy as np
import pytest

from actors import compare as cmp
from actors import evaluate as ev


def scene_objects(seed):
    """Objects and roles of scene ``seed``: different in every scene, as in a real result."""
    return [[f"ycb/{seed % 7:03d}", "target"], [f"random_urdfs/{seed}", "obstacle"]]


def result(policy, table, seeds, grippers=("wsg_50", "panda_hand"), scene="obstacle", objects="test"):
    """A result JSON as ``evaluate --json`` writes it (the keys compare reads).

    ``table``: per-gripper policies {gripper: [(successes, attempts) per scene]}; ``adagrasp``:
    [(successes, attempts) per scene]; ``grippers``: the cell's grippers (adagrasp's candidates).
    """
    rows = {None: table} if policy == "adagrasp" else table
    episodes, per = [], {}
    for g, cells in rows.items():
        for e, (s, a) in enumerate(cells):
            episodes.append({"index": len(episodes), "episode": e, "gripper": g, "scene_seed": seeds[e],
                             "objects": scene_objects(seeds[e]), "attempts": a, "successes": s})
    for g in rows:
        mine = [r for r in episodes if r["gripper"] == g]
        s, a = sum(r["successes"] for r in mine), sum(r["attempts"] for r in mine)
        per[g] = {"successes": s, "attempts": a, "rate": s / a}
    succ, att = sum(r["successes"] for r in episodes), sum(r["attempts"] for r in episodes)
    rate = succ / att if policy == "adagrasp" else float(np.mean([v["rate"] for v in per.values()]))
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


def brute_force_swap_p(policy, table_a, table_b, seeds):
    """The scene-swap p-value by enumerating every swap and rebuilding both results' rates."""
    def cells(table, e):
        return table[e] if policy == "adagrasp" else {g: v[e] for g, v in table.items()}

    def build(chosen):
        if policy == "adagrasp":
            return result(policy, chosen, seeds)["rate"]
        return result(policy, {g: [c[g] for c in chosen] for g in table_a}, seeds)["rate"]

    n = len(seeds)
    observed = abs(build([cells(table_b, e) for e in range(n)]) - build([cells(table_a, e) for e in range(n)]))
    hits = 0
    for swap in itertools.product((0, 1), repeat=n):
        a = [cells(table_b if s else table_a, e) for e, s in enumerate(swap)]
        b = [cells(table_a if s else table_b, e) for e, s in enumerate(swap)]
        hits += abs(build(b) - build(a)) >= observed - 1e-12
    return hits / 2**n


def test_sign_flip_test_is_mcnemar_for_one_grasp_units():
    for better, worse, same in ((8, 2, 0), (2, 8, 5), (10, 0, 3), (5, 5, 1), (0, 0, 4), (21, 2, 77)):
        diffs = np.array([1.0] * better + [-1.0] * worse + [0.0] * same)
        assert cmp.sign_flip_p(diffs) == pytest.approx(binomial_two_sided(better, worse))


def test_sign_flip_test_equals_enumerating_every_sign():
    rng = np.random.default_rng(5)
    for _ in range(20):
        diffs = rng.integers(-5, 6, size=int(rng.integers(1, 12))) / 5.0
        assert cmp.sign_flip_p(diffs, scale=5) == pytest.approx(brute_force_p(diffs))


def test_per_gripper_results_pair_on_gripper_and_scene():
    a, b = result("fix-gripper", FG_A, SEEDS), result("fix-gripper", FG_B, SEEDS)
    c = cmp.compare(*cmp.pair("a", a, "b", b), resamples=20_000)
    assert c["scenes"] == 5 and c["a"]["grippers"] == c["b"]["grippers"] == ["panda_hand", "wsg_50"]
    assert c["a"]["rate"] == pytest.approx(a["rate"]) and c["b"]["rate"] == pytest.approx(b["rate"])
    assert c["rate_difference"] == pytest.approx(b["rate"] - a["rate"])
    # Per scene, successes / attempts over both grippers: A 3/9 1/10 2/9 6/7 1/10, B 3/9 3/8 3/9 6/6 2/10.
    assert (c["b_better"], c["b_worse"], c["same"]) == (4, 0, 1)
    assert c["p_value"] == pytest.approx(brute_force_swap_p("fix-gripper", FG_A, FG_B, SEEDS), abs=0.01)
    assert "random swaps" in c["test"]
    lo, hi = c["ci95"]
    assert lo < c["rate_difference"] < hi


def test_one_grasp_scenes_get_the_exact_test():
    rng = random.Random(3)
    seeds = list(range(100, 110))
    fa = {g: [(rng.randint(0, 1), 1) for _ in seeds] for g in ("wsg_50", "panda_hand")}
    fb = {g: [(rng.randint(0, 1), 1) for _ in seeds] for g in ("wsg_50", "panda_hand")}
    c = cmp.compare(*cmp.pair("a", result("fix-gripper", fa, seeds), "b", result("fix-gripper", fb, seeds)))
    assert c["test"] == "exact scene-swap permutation test"
    assert c["p_value"] == pytest.approx(brute_force_swap_p("fix-gripper", fa, fb, seeds))
    ada_a, ada_b = fa["wsg_50"], fb["panda_hand"]
    c = cmp.compare(*cmp.pair("a", result("adagrasp", ada_a, seeds), "b", result("adagrasp", ada_b, seeds)))
    better = sum(x[0] < y[0] for x, y in zip(ada_a, ada_b))
    worse = sum(x[0] > y[0] for x, y in zip(ada_a, ada_b))
    assert c["p_value"] == pytest.approx(binomial_two_sided(better, worse)), "McNemar's exact test"


def test_random_swaps_estimate_the_enumerated_p_value():
    rng = random.Random(8)
    seeds = list(range(200, 210))
    ta = [(rng.randint(0, 3), rng.randint(3, 5)) for _ in seeds]
    tb = [(rng.randint(1, 3), rng.randint(3, 5)) for _ in seeds]
    c = cmp.compare(*cmp.pair("a", result("adagrasp", ta, seeds), "b", result("adagrasp", tb, seeds)),
                    resamples=40_000)
    assert c["p_value"] == pytest.approx(brute_force_swap_p("adagrasp", ta, tb, seeds), abs=0.01)


def test_bootstrap_weights_equal_repeating_the_scenes():
    """table_rate with count weights = the rate of the result whose scenes are repeated that often."""
    a = result("fix-gripper", FG_A, SEEDS)
    side = cmp.pair("a", a, "a", a)[0]
    draw = [3, 3, 0, 4, 3]
    weights = np.bincount(draw, minlength=5)[None, :].astype(float)
    repeated = result("fix-gripper", {g: [FG_A[g][i] for i in draw] for g in FG_A}, [100 + i for i in range(5)])
    assert cmp.table_rate(side, weights)[0] == pytest.approx(repeated["rate"])
    ada = result("adagrasp", FG_A["wsg_50"], SEEDS)
    pooled = cmp.pair("p", ada, "p", ada)[0]
    again = result("adagrasp", [FG_A["wsg_50"][i] for i in draw], [100 + i for i in range(5)])
    assert cmp.table_rate(pooled, weights)[0] == pytest.approx(again["rate"])


def test_identical_results_differ_by_nothing():
    a = result("fix-gripper", FG_A, SEEDS)
    c = cmp.compare(*cmp.pair("a", a, "a", a), resamples=500)
    assert c["rate_difference"] == 0 and c["ci95"] == [0.0, 0.0], "A and B share every bootstrap draw"
    assert (c["b_better"], c["b_worse"], c["same"], c["p_value"]) == (0, 0, 5, 1.0)


def test_more_attempts_for_the_same_successes_is_a_lower_rate():
    seeds = list(range(30))
    c = cmp.compare(*cmp.pair("a", result("adagrasp", [(3, 3)] * 30, seeds),
                              "b", result("adagrasp", [(3, 7)] * 30, seeds)))
    assert c["rate_difference"] == pytest.approx(3 / 7 - 1) and c["ci95"][1] < -0.5
    assert (c["b_better"], c["b_worse"]) == (0, 30) and c["p_value"] < 1e-3


def test_a_clear_difference_has_an_interval_above_zero():
    seeds = list(range(30))
    a = result("adagrasp", [(0, 5)] * 28 + [(1, 5)] * 2, seeds)
    b = result("adagrasp", [(3, 4)] * 25 + [(0, 5)] * 5, seeds)
    c = cmp.compare(*cmp.pair("a", a, "b", b))
    assert c["ci95"][0] > 0.3 and c["b_better"] == 25 and c["p_value"] < 1e-3


def test_adagrasp_against_per_gripper_pairs_scenes_without_a_permutation_test(tmp_path, capsys):
    fg = result("fix-gripper", FG_A, SEEDS)
    ada = result("adagrasp", [(2, 4), (1, 5), (1, 5), (3, 3), (0, 5)], SEEDS)
    c = cmp.compare(*cmp.pair("fg", fg, "ada", ada), resamples=500)
    assert c["a"]["rate"] == pytest.approx(fg["rate"]) and c["b"]["rate"] == pytest.approx(ada["rate"])
    assert c["p_value"] is None and c["b"]["grippers"] == [None]
    only = cmp.compare(*cmp.pair("fg", fg, "ada", ada, only=["wsg_50"]), resamples=500)
    assert only["a"]["grippers"] == ["wsg_50"]
    assert only["a"]["rate"] == pytest.approx(fg["per_gripper"]["wsg_50"]["rate"])
    assert ev.cli(["compare", write(tmp_path, "fg", fg), write(tmp_path, "ada", ada), "--resamples", "100"]) == 0
    assert "no permutation test" in capsys.readouterr().out


def test_pairing_follows_the_scene_seed_not_the_record_order():
    """B ran other scenes too, in another order: only the shared seeds pair, each with its own record."""
    seeds_b = [13, 99, 15, 11, 98]
    b_table = {g: [FG_B[g][SEEDS.index(s)] if s in SEEDS else (5, 5) for s in seeds_b] for g in FG_B}
    b = result("fix-gripper", b_table, seeds_b)
    random.Random(1).shuffle(b["episode_results"])
    c = cmp.compare(*cmp.pair("a", result("fix-gripper", FG_A, SEEDS), "b", b), resamples=200)
    kept = [0, 2, 4]  # seeds 11, 13, 15
    expected_b = result("fix-gripper", {g: [FG_B[g][i] for i in kept] for g in FG_B}, [11, 13, 15])
    expected_a = result("fix-gripper", {g: [FG_A[g][i] for i in kept] for g in FG_A}, [11, 13, 15])
    assert c["scenes"] == 3
    assert c["b"]["rate"] == pytest.approx(expected_b["rate"]) and c["a"]["rate"] == pytest.approx(expected_a["rate"])


def test_only_shared_grippers_are_paired():
    three = result("fix-gripper", {**FG_B, "pr2_gripper": FG_B["wsg_50"]}, SEEDS,
                   grippers=("wsg_50", "panda_hand", "pr2_gripper"))
    c = cmp.compare(*cmp.pair("a", result("fix-gripper", FG_A, SEEDS), "three", three), resamples=200)
    assert c["b"]["grippers"] == ["panda_hand", "wsg_50"]
    assert c["b"]["rate"] == pytest.approx(result("fix-gripper", FG_B, SEEDS)["rate"])


def test_cli_prints_and_writes_the_comparison(tmp_path, capsys):
    a = write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS))
    b = write(tmp_path, "b", result("fix-gripper", FG_B, SEEDS))
    out = tmp_path / "cmp.json"
    assert ev.cli(["compare", a, b, "--resamples", "300", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    data = json.loads(out.read_text())
    assert data["format"] == cmp.COMPARE_FORMAT and data["bootstrap"] == {"resamples": 300, "seed": 0, "unit": "scene"}
    assert f"per scene B above A in {data['b_better']}, below in {data['b_worse']}" in text
    assert f"p = {data['p_value']:.3g}" in text
    assert ev.cli(["compare", a, b, "--resamples", "300", "--json", str(out)]) == 0
    assert json.loads(out.read_text()) == data, "the draws and swaps are seeded"


def _edit_record(i, **fields):
    def change(d):
        d["episode_results"][i].update(fields)
        return d
    return change


def _drop_key(key):
    def change(d):
        del d[key]
        return d
    return change


def _duplicate(d):
    d["episode_results"].append(dict(d["episode_results"][0]))
    return d


def _without_record_key(i, key):
    def change(d):
        del d["episode_results"][i][key]
        return d
    return change


def _mix(d):
    d["episode_results"][0]["gripper"] = None
    return d


def _ada(d):
    return result("adagrasp", FG_B["wsg_50"], SEEDS, grippers=("wsg_50", "pr2_gripper"))


@pytest.mark.parametrize(
    "change, extra, needle",
    [
        (lambda d: {**d, "scene": "multi"}, [], "b.json: scene: 'multi', but"),
        (lambda d: {**d, "objects": "train"}, [], "b.json: objects: 'train', but"),
        (_drop_key("objects"), [], "b.json: objects: missing"),
        (_edit_record(3, objects=[["ycb/other", "target"]]), [], "gripper wsg_50).objects: not the objects of"),
        (lambda d: result("fix-gripper", FG_B, [91, 92, 93, 94, 95]), [], "scene_seeds: no scene in common"),
        (lambda d: result("fix-gripper", {"pr2_gripper": FG_B["wsg_50"]}, SEEDS, grippers=("pr2_gripper",)), [],
         "per_gripper: no gripper in common"),
        (lambda d: {**d, "episode_results": []}, [], "episode_results: missing or empty"),
        (_without_record_key(2, "attempts"), [],
         "episode_results[2]: needs gripper, scene_seed, successes, attempts and objects"),
        (_edit_record(2, attempts="5"), [], "episode_results[2]: scene_seed, successes and attempts must be integers"),
        (_edit_record(2, successes=6), [], "episode_results[2]: scene_seed 13, successes 6, attempts 4"),
        (_edit_record(1, attempts=0), [], "episode_results[1]: scene_seed 12, successes 0, attempts 0"),
        (_duplicate, [], "gripper wsg_50, scene_seed 11: repeated"),
        (_mix, [], "mixes adagrasp records (gripper null) with per-gripper ones"),
        (_ada, [], "a.json: grippers ['panda_hand', 'wsg_50']: adagrasp in"),
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


def test_objects_are_checked_in_every_record_of_both_files(tmp_path, capsys):
    """A scene whose objects differ in A's second gripper is named in A, not blamed on B."""
    a = result("fix-gripper", FG_A, SEEDS)
    odd = next(r for r in a["episode_results"] if r["gripper"] == "wsg_50" and r["scene_seed"] == 12)
    odd["objects"] = [["ycb/other", "target"]]
    assert ev.cli(["compare", write(tmp_path, "a", a), write(tmp_path, "b", result("fix-gripper", FG_B, SEEDS))]) == 2
    err = capsys.readouterr().err
    assert "a.json: episode_results (scene_seed 12, gripper wsg_50).objects" in err


def test_gripper_filter_needs_a_per_gripper_result(tmp_path, capsys):
    a = write(tmp_path, "a", result("adagrasp", FG_A["wsg_50"], SEEDS))
    assert ev.cli(["compare", a, a, "--gripper", "wsg_50"]) == 2
    assert "both results are adagrasp runs" in capsys.readouterr().err


def test_mismatched_scenes_can_be_left_out(tmp_path, capsys):
    """A scene drawn with other objects (another machine's redraw) stops the comparison unless
    --drop-mismatched-scenes, which pairs the rest and names the seeds it left out."""
    b = _edit_record(3, objects=[["ycb/other", "target"]])(result("fix-gripper", FG_B, SEEDS))
    assert b["episode_results"][3]["scene_seed"] == 14
    paths = [write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS)), write(tmp_path, "b", b)]
    assert ev.cli(["compare", *paths]) == 2
    assert "--drop-mismatched-scenes pairs the rest" in capsys.readouterr().err
    out = tmp_path / "cmp.json"
    assert ev.cli(["compare", *paths, "--drop-mismatched-scenes", "--json", str(out)]) == 0
    assert "(1 shared seeds left out: other objects)" in capsys.readouterr().out
    data = json.loads(out.read_text())
    kept = [0, 1, 2, 4]
    assert data["scenes"] == 4 and data["dropped_scene_seeds"] == [14]
    expected = result("fix-gripper", {g: [FG_B[g][i] for i in kept] for g in FG_B}, [SEEDS[i] for i in kept])
    assert data["b"]["rate"] == pytest.approx(expected["rate"])


def test_ties_count_as_at_least_as_far_in_the_random_swaps():
    """Three grippers with three attempts per scene make swapped differences that equal the
    observed one up to rounding; they count as hits (the enumeration counts them too). 12,345
    swaps: not a multiple of the 10,000 per batch."""
    rng = random.Random(23)  # a draw where ties move the enumerated p from 0.74 to 0.88
    seeds = list(range(300, 308))
    names = ("wsg_50", "panda_hand", "pr2_gripper")
    fa = {g: [(rng.randint(0, 3), 3) for _ in seeds] for g in names}
    fb = {g: [(rng.randint(0, 3), 3) for _ in seeds] for g in names}
    a, b = result("fix-gripper", fa, seeds, grippers=names), result("fix-gripper", fb, seeds, grippers=names)
    c = cmp.compare(*cmp.pair("a", a, "b", b), resamples=12_345)
    assert "12345 random swaps" in c["test"]
    assert c["p_value"] == pytest.approx(brute_force_swap_p("fix-gripper", fa, fb, seeds), abs=0.02)


def test_one_attempt_against_several_takes_the_random_swaps():
    seeds = list(range(400, 408))
    ta = [(1, 1), (0, 1), (1, 1), (1, 1), (0, 1), (1, 1), (0, 1), (1, 1)]
    tb = [(2, 3), (1, 4), (1, 1), (3, 3), (0, 2), (1, 5), (1, 2), (2, 2)]
    c = cmp.compare(*cmp.pair("a", result("adagrasp", ta, seeds), "b", result("adagrasp", tb, seeds)),
                    resamples=30_000)
    assert "random swaps" in c["test"]
    assert c["p_value"] == pytest.approx(brute_force_swap_p("adagrasp", ta, tb, seeds), abs=0.015)


def test_report_names_the_candidates_and_the_unpaired_scenes(tmp_path, capsys):
    long = result("fix-gripper", {g: v + v for g, v in FG_A.items()}, SEEDS + [21, 22, 23, 24, 25])
    ada = result("adagrasp", FG_B["wsg_50"], SEEDS)
    assert ev.cli(["compare", write(tmp_path, "long", long), write(tmp_path, "ada", ada), "--resamples", "100"]) == 0
    out = capsys.readouterr().out
    assert "5 of its scenes unpaired" in out and "choosing among wsg_50,panda_hand" in out


def test_output_errors_are_one_line_before_any_work(tmp_path, capsys):
    a = write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS))
    assert ev.cli(["compare", a, a, "--json", str(tmp_path)]) == 2
    captured = capsys.readouterr()
    assert f"--json {tmp_path}: is a directory" in captured.err and captured.out == ""
    assert list(tmp_path.iterdir()) == [tmp_path / "a.json"]


def test_all_scenes_mismatched_or_no_candidates_is_one_line(tmp_path, capsys):
    b = result("fix-gripper", FG_B, SEEDS)
    for r in b["episode_results"]:
        r["objects"] = [["ycb/other", "target"]]
    paths = [write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS)), write(tmp_path, "b", b)]
    assert ev.cli(["compare", *paths, "--drop-mismatched-scenes"]) == 2
    assert "b.json: episode_results: no shared scene has the same objects" in capsys.readouterr().err
    ada = result("adagrasp", FG_B["wsg_50"], SEEDS)
    del ada["gripper_names"]
    assert ev.cli(["compare", paths[0], write(tmp_path, "ada", ada)]) == 2
    assert "ada.json: gripper_names: expected a non-empty list" in capsys.readouterr().err


@pytest.mark.parametrize("key, other", [("max_attempts", 7), ("scale", 0.8)])
def test_another_attempt_cap_or_gripper_scale_is_not_the_same_protocol(tmp_path, capsys, key, other):
    a, b = result("fix-gripper", FG_A, SEEDS), result("fix-gripper", FG_B, SEEDS)
    a[key] = b[key] = {"max_attempts": 5, "scale": 1.0}[key]
    assert cmp.pair("a", a, "b", b)[0].scene_seeds == tuple(SEEDS)
    b[key] = other
    paths = [write(tmp_path, "a", a), write(tmp_path, "b", b)]
    assert ev.cli(["compare", *paths]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"b.json: {key}: {other!r}, but " in err and "not the same protocol" in err


def test_rate_interval_of_one_result():
    """The rate of a result's complete scenes, with an interval that brackets it and is empty
    when every scene is alike; a scene missing a gripper's record is left out."""
    a = result("fix-gripper", FG_A, SEEDS)
    rate, low, high = cmp.rate_interval("a", a, resamples=2000)
    assert rate == pytest.approx(a["rate"]) and low < rate < high
    same = result("fix-gripper", {g: [(2, 4)] * 5 for g in FG_A}, SEEDS)
    assert cmp.rate_interval("s", same, resamples=200) == (0.5, 0.5, 0.5)
    a["episode_results"] = [r for r in a["episode_results"] if (r["gripper"], r["scene_seed"]) != ("wsg_50", 13)]
    four = result("fix-gripper", {g: [c for c, s in zip(FG_A[g], SEEDS) if s != 13] for g in FG_A},
                  [s for s in SEEDS if s != 13])
    assert cmp.rate_interval("a", a, resamples=200)[0] == pytest.approx(four["rate"])
    ada = result("adagrasp", FG_A["wsg_50"], SEEDS)
    assert cmp.rate_interval("p", ada, resamples=200)[0] == pytest.approx(6 / 22)


def _split(table, cut):
    """A per-gripper table's first ``cut`` scenes and the rest."""
    return {g: cells[:cut] for g, cells in table.items()}, {g: cells[cut:] for g, cells in table.items()}


def test_pooled_seeds_equal_one_result_of_all_their_scenes(tmp_path, capsys):
    """Two results per row on other scenes, pooled with --also, give what one result holding every
    scene gives: the rates, the interval (the same draws), the tally and the p-value."""
    files = {}
    for name, table in (("a", FG_A), ("b", FG_B)):
        first, rest = _split(table, 3)
        files[name] = write(tmp_path, name, result("fix-gripper", table, SEEDS))
        files[name + "1"] = write(tmp_path, name + "1", result("fix-gripper", first, SEEDS[:3]))
        files[name + "2"] = write(tmp_path, name + "2", result("fix-gripper", rest, SEEDS[3:]))
    whole = cmp.compare_cli([files["a"], files["b"], "--resamples", "2000"])
    pooled = cmp.compare_cli([files["a1"], files["b1"], "--also", files["a2"], files["b2"], "--resamples", "2000"])
    for key in ("scenes", "rate_difference", "ci95", "b_better", "b_worse", "same", "p_value"):
        assert pooled[key] == whole[key], key
    assert pooled["a"]["rate"] == whole["a"]["rate"] and pooled["a"]["path"] == f"{files['a1']} + {files['a2']}"
    assert len(pooled["a"]["file_rate"]) == 2
    alone = cmp.compare_cli([files["a1"], files["b1"], "--resamples", "2000"])
    assert alone["scenes"] == 3 and alone["rate_difference"] != whole["rate_difference"]
    assert f"+ {files['b2']}" in capsys.readouterr().out


def test_pooling_follows_the_model_digest_over_the_checkpoint_name(tmp_path):
    """Results that name one model differently (a run's file, then the exported model) pool when
    both record the same checkpoint_sha256; one name with two digests does not, and without a
    digest on both sides the names decide."""
    later = [21, 22, 23, 24, 25]
    a, b = (write(tmp_path, n, {**result("fix-gripper", t, SEEDS), "checkpoint": "runs/x/averaged.pt",
                                "checkpoint_sha256": "ab" * 32}) for n, t in (("a", FG_A), ("b", FG_B)))
    a2, b2 = (write(tmp_path, n, {**result("fix-gripper", t, later), "checkpoint": "model:x",
                                  "checkpoint_sha256": "ab" * 32}) for n, t in (("a2", FG_A), ("b2", FG_B)))
    pooled = cmp.compare_cli([a, b, "--also", a2, b2])
    assert pooled["scenes"] == 10 and pooled["a"]["checkpoint_sha256"] == "ab" * 32
    other = write(tmp_path, "other", {**result("fix-gripper", FG_B, later), "checkpoint": "runs/x/averaged.pt",
                                      "checkpoint_sha256": "cd" * 32})
    with pytest.raises(ev.EvaluationError, match=r"other\.json: checkpoint_sha256: cdcdcdcdcdcd\.\.\., but .*b\.json "
                                                 r"has abababababab\.\.\.: only results of one model pool"):
        cmp.compare_cli([a, b, "--also", a2, other])
    unrecorded = write(tmp_path, "old", {**result("fix-gripper", FG_B, later), "checkpoint": "model:x"})
    with pytest.raises(ev.EvaluationError, match=r"old\.json: checkpoint: 'model:x', but .*b\.json has "
                                                 r"'runs/x/averaged\.pt'"):
        cmp.compare_cli([a, b, "--also", a2, unrecorded])


def test_pooling_refuses_a_scene_twice_or_another_row(tmp_path, capsys):
    a = write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS))
    b = write(tmp_path, "b", result("fix-gripper", FG_B, SEEDS))
    with pytest.raises(ev.EvaluationError, match=r"a\.json: scene_seed 11: also in .*a\.json \(pool other scenes"):
        cmp.compare_cli([a, b, "--also", a, b])
    other = result("fix-gripper", FG_B, [21, 22, 23, 24, 25])
    other["checkpoint"] = "model:another"
    o = write(tmp_path, "o", other)
    a2 = write(tmp_path, "a2", result("fix-gripper", FG_A, [21, 22, 23, 24, 25]))
    with pytest.raises(ev.EvaluationError, match=r"o\.json: checkpoint: 'model:another', but .*b\.json has None"):
        cmp.compare_cli([a, b, "--also", a2, o])
    fewer = write(tmp_path, "f", result("fix-gripper", {"wsg_50": FG_B["wsg_50"]}, [21, 22, 23, 24, 25]))
    assert ev.cli(["compare", a, b, "--also", a2, fewer]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "grippers ['wsg_50']" in err


def test_pooling_reads_a_calibration_the_same_with_or_without_its_file_hash(tmp_path, capsys):
    """A calibrated result written before the calibration file's hash and scene counts were
    recorded pools with one that records them; a calibration with another fit is another row,
    named in one line."""
    fits = {"wsg_50": {"shift": -0.98, "trials": 56, "successes": 46, "mean_score": 0.92},
            "panda_hand": {"shift": 0.68, "trials": 52, "successes": 49, "mean_score": 0.89}}
    cal = {"source": "calibration/fit.json", "prior_sigma": 2.0, "grippers": fits}
    ada = [(3, 5), (2, 4), (4, 5), (1, 5), (3, 3)]
    later = [21, 22, 23, 24, 25]
    files = {"a": write(tmp_path, "a", result("fix-gripper", FG_A, SEEDS)),
             "a2": write(tmp_path, "a2", result("fix-gripper", FG_A, later))}
    counted = {g: {**f, "scenes": 20} for g, f in fits.items()}
    for name, seeds, record in (("b", SEEDS, cal), ("b2", later, {**cal, "sha256": "ab" * 32, "grippers": counted}),
                                ("c2", later, {**cal, "sha256": "ab" * 32, "grippers": {
                                    **fits, "wsg_50": {**fits["wsg_50"], "shift": -0.5}}})):
        data = result("adagrasp", ada, seeds)
        data["calibration"] = record
        files[name] = write(tmp_path, name, data)
    pooled = cmp.compare_cli([files["a"], files["b"], "--also", files["a2"], files["b2"], "--resamples", "500"])
    assert pooled["scenes"] == 10 and pooled["b"]["attempts"] == 2 * sum(a for _, a in ada)
    assert ev.cli(["compare", files["a"], files["b"], "--also", files["a2"], files["c2"]]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "c2.json: calibration: differs from" in err and "in grippers:" in err


def test_help_prints_the_interval_text_as_written():
    text = cmp._parser().format_help()
    assert "95% interval" in " ".join(text.split()) and "%%" not in text


@pytest.mark.parametrize("argv", [
    ["table", "{a}", "{b}", "--md", "{a}"],
    ["compare", "{a}", "{b}", "--json", "{b}"],
    ["compare", "{a}", "{b}", "--also", "{c}", "{a}", "--json", "{c}"],
    ["runs", "--a", "{a},{c}", "--a", "{b}", "--b", "{b}", "--b", "{c}", "--json", "{c}"],
    ["holm", "{a}", "{b}", "--json", "{a}"],
])
def test_an_output_that_is_one_of_the_inputs_is_refused_before_anything_is_read(tmp_path, capsys, argv):
    """--json / --md naming one of the command's own input files (through another spelling of its
    path, too) is one line, and the file is left as it was."""
    files = {}
    for name in "abc":
        files[name] = tmp_path / f"{name}.json"
        files[name].write_text(json.dumps({"format": "not read", "name": name}))
    spelled = {name: str(tmp_path / "." / f"{name}.json") if name == "c" else str(p) for name, p in files.items()}
    before = {p: p.read_bytes() for p in files.values()}
    rc = ev.cli([arg.format(**spelled) for arg in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "is one of this command's input files; it would be overwritten" in err[0], err
    assert {p: p.read_bytes() for p in files.values()} == before


def test_pooling_refuses_adagrasp_results_that_chose_among_other_grippers(tmp_path):
    """adagrasp pairs one row (its choice), so its candidates were never compared between pooled
    files: a training-gripper file pooled with a test-gripper file read as one result."""
    ada = [(1, 1), (0, 1), (1, 1), (1, 1), (0, 1)]
    later = [21, 22, 23, 24, 25]
    a, b = (write(tmp_path, n, result("adagrasp", ada, SEEDS)) for n in ("a", "b"))
    a2 = write(tmp_path, "a2", result("adagrasp", ada, later))
    b2 = write(tmp_path, "b2", result("adagrasp", ada, later, grippers=("wsg_50", "panda_hand", "g1_three_finger")))
    same = write(tmp_path, "same", result("adagrasp", ada, later))
    assert cmp.compare_cli([a, b, "--also", a2, same])["scenes"] == 10
    with pytest.raises(ev.EvaluationError, match=r"b2\.json: gripper_names: \['g1_three_finger', 'panda_hand', "
                                                 r"'wsg_50'\], but .*b\.json has \['panda_hand', 'wsg_50'\]"):
        cmp.compare_cli([a, b, "--also", a2, b2])


def test_pooling_checks_every_pair_of_files_for_one_model(tmp_path):
    """Without a digest on one file the checkpoint name decides, with digests on both the digests:
    not transitive, so a file without a digest first let two networks of one name pool."""
    later, third = [21, 22, 23, 24, 25], [31, 32, 33, 34, 35]
    named = {"checkpoint": "runs/r1/checkpoints/latest.pt"}
    a0 = write(tmp_path, "a0", {**result("fix-gripper", FG_A, SEEDS), **named})
    a2 = write(tmp_path, "a2", {**result("fix-gripper", FG_A, later), **named, "checkpoint_sha256": "11" * 32})
    a3 = write(tmp_path, "a3", {**result("fix-gripper", FG_A, third), **named, "checkpoint_sha256": "22" * 32})
    b0, b2, b3 = (write(tmp_path, n, result("fix-gripper", FG_B, s)) for n, s in (("b0", SEEDS), ("b2", later),
                                                                                   ("b3", third)))
    for order in ((b0, a0, b2, a2, b3, a3), (b2, a2, b0, a0, b3, a3)):
        with pytest.raises(ev.EvaluationError, match=r"a3\.json: checkpoint_sha256: 222222222222\.\.\., but "):
            cmp.compare_cli([order[0], order[1], "--also", order[2], order[3], "--also", order[4], order[5]])
