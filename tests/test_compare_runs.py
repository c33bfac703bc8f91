"""``evaluate runs``: rows compared across training runs; run rates, the t and randomization tests, errors."""

import hashlib
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from actors import compare as cmp
from actors import compare_runs as cr
from actors import evaluate as ev
from common.calibration import calibration_from_result
from tests.test_compare import SEEDS, result, write

GRIPPERS = ("wsg_50", "panda_hand")


def random_table(rng, scenes, policy="fix-gripper"):
    """Random (successes, attempts) per scene; per gripper unless ``policy`` is adagrasp."""
    def cells():
        out = []
        for _ in range(scenes):
            attempts = int(rng.integers(1, 6))
            out.append((int(rng.integers(0, attempts + 1)), attempts))
        return out
    return cells() if policy == "adagrasp" else {g: cells() for g in GRIPPERS}


def run_file(tmp_path, name, policy, table, seeds, model, digest=None):
    data = {**result(policy, table, seeds), "checkpoint": model}
    if digest is not None:
        data["checkpoint_sha256"] = digest
    return write(tmp_path, name, data)


def make_runs(tmp_path, tag, policy, count, rng, seeds=SEEDS, models=None):
    """``count`` runs of one row, one file each, every run another model (or ``models``)."""
    models = models or [f"model:{tag}{i}" for i in range(count)]
    return [[run_file(tmp_path, f"{tag}{i}", policy, random_table(rng, len(seeds), policy), seeds, models[i])]
            for i in range(count)]


def cli_args(runs_a, runs_b, *extra):
    args = []
    for tag, runs in (("--a", runs_a), ("--b", runs_b)):
        for files in runs:
            args += [tag, ",".join(files)]
    return [*args, *extra]


def test_a_run_of_several_files_has_the_rate_of_one_file_of_all_its_scenes(tmp_path):
    """A run's files on other scene seeds pool into the rate one result of all its scenes has."""
    rng = np.random.default_rng(0)
    whole = [random_table(rng, 5) for _ in range(4)]
    single = [[run_file(tmp_path, f"w{i}", "fix-gripper", t, SEEDS, f"model:r{i}")] for i, t in enumerate(whole)]
    split = [[run_file(tmp_path, f"s{i}a", "fix-gripper", {g: c[:2] for g, c in t.items()}, SEEDS[:2], f"model:r{i}"),
              run_file(tmp_path, f"s{i}b", "fix-gripper", {g: c[2:] for g, c in t.items()}, SEEDS[2:], f"model:r{i}")]
             for i, t in enumerate(whole)]
    one = cr.runs_cli(cli_args(single[:2], single[2:]))
    two = cr.runs_cli(cli_args(split[:2], split[2:]))
    rates = [r["rate"] for side in ("a", "b") for r in one[side]["runs"]]
    assert rates == pytest.approx([cmp.rate_interval(f[0], json.load(open(f[0])), resamples=10)[0] for f in single])
    assert [r["rate"] for side in ("a", "b") for r in two[side]["runs"]] == pytest.approx(rates)
    for key in ("mean_difference", "t", "randomization", "scenes"):
        assert two[key] == one[key], key


def test_welch_and_paired_t_are_scipys_and_the_interval_ends_at_p_005():
    rng = np.random.default_rng(1)
    for na, nb in ((2, 2), (3, 3), (2, 4), (5, 3)):
        a, b = rng.uniform(0.2, 0.6, na), rng.uniform(0.3, 0.7, nb)
        t = cr.t_test(a, b, paired=False)
        assert t["p_value"] == pytest.approx(stats.ttest_ind(b, a, equal_var=False).pvalue, rel=1e-9)
        lo, hi = t["ci95"]
        assert stats.ttest_ind(b - hi, a, equal_var=False).pvalue == pytest.approx(0.05, abs=1e-9)
        assert stats.ttest_ind(b - lo, a, equal_var=False).pvalue == pytest.approx(0.05, abs=1e-9)
    a, b = rng.uniform(0.2, 0.6, 4), rng.uniform(0.3, 0.7, 4)
    t = cr.t_test(a, b, paired=True)
    assert t["p_value"] == pytest.approx(stats.ttest_rel(b, a).pvalue, rel=1e-9) and t["df"] == 3
    assert stats.ttest_rel(b - t["ci95"][1], a).pvalue == pytest.approx(0.05, abs=1e-9)
    same = cr.t_test(np.array([0.4, 0.4]), np.array([0.5, 0.5]), paired=False)
    assert same["p_value"] is None and same["ci95"] is None


def test_relabelling_p_equals_going_through_every_order_of_the_runs():
    rng = np.random.default_rng(2)
    for na, nb in ((2, 2), (3, 3), (2, 3), (4, 2)):
        a, b = rng.uniform(0, 1, na), rng.uniform(0, 1, nb)
        both = np.concatenate([a, b])
        observed = abs(b.mean() - a.mean())
        orders = list(itertools.permutations(range(na + nb)))
        hits = sum(abs(both[list(o[na:])].mean() - both[list(o[:na])].mean()) >= observed - 1e-12 for o in orders)
        p, smallest, how = cr.relabel_p(a, b, rng, 100)
        assert p == pytest.approx(hits / len(orders)) and how.startswith("exact")
    far = cr.relabel_p(np.array([0.1, 0.2, 0.15]), np.array([0.8, 0.9, 0.85]), rng, 100)
    assert far[0] == pytest.approx(0.1) and far[1] == pytest.approx(0.1)


def test_random_relabellings_estimate_the_exact_p(monkeypatch):
    rng = np.random.default_rng(3)
    a, b = rng.uniform(0.2, 0.5, 4), rng.uniform(0.3, 0.6, 4)
    exact = cr.relabel_p(a, b, rng, 1)[0]
    monkeypatch.setattr(cr, "EXACT_LIMIT", 10)
    p, smallest, how = cr.relabel_p(a, b, np.random.default_rng(4), 20_000)
    assert how == "20000 random relabellings" and smallest == pytest.approx(1 / 20_001)
    assert p == pytest.approx(exact, abs=0.015)


def test_sign_flip_p_equals_every_subset_of_flips():
    rng = np.random.default_rng(5)
    d = rng.normal(0.05, 0.05, 5)
    hits = 0
    for mask in range(2**5):
        flipped = np.array([-x if mask >> i & 1 else x for i, x in enumerate(d)])
        hits += abs(flipped.sum()) >= abs(d.sum()) - 1e-12
    assert cr.sign_p(d, rng, 10)[0] == pytest.approx(hits / 32)
    assert cr.sign_p(np.array([0.1, 0.2, 0.05]), rng, 10)[:2] == (pytest.approx(0.25), pytest.approx(0.25))


def test_paired_runs_take_the_differences_of_one_models_rows(tmp_path, capsys):
    """Fix-gripper and adagrasp of one training run pair; the sign-flip test and paired t read the
    per-run differences."""
    rng = np.random.default_rng(6)
    fix = make_runs(tmp_path, "fg", "fix-gripper", 3, rng, models=["model:m0", "model:m1", "model:m2"])
    ada = make_runs(tmp_path, "ad", "adagrasp", 3, rng, models=["model:m0", "model:m1", "model:m2"])
    c = cr.runs_cli(cli_args(fix, ada, "--paired"))
    ra = np.array([r["rate"] for r in c["a"]["runs"]])
    rb = np.array([r["rate"] for r in c["b"]["runs"]])
    assert c["run_differences"] == pytest.approx(list(rb - ra))
    assert c["t"]["p_value"] == pytest.approx(stats.ttest_rel(rb, ra).pvalue)
    assert c["randomization"]["smallest_p"] == pytest.approx(0.25) and c["b"]["candidates"] == list(GRIPPERS)
    out = capsys.readouterr().out
    assert "paired by run" in out and "sign-flip test of the per-run differences (exact, 8 sign patterns)" in out


def test_scenes_are_those_every_run_ran_in_one_order(tmp_path, capsys):
    """Runs pair on scene seeds whatever their order in the files; a scene some run lacks is left
    out of every run and counted."""
    rng = np.random.default_rng(7)
    runs_a = make_runs(tmp_path, "a", "fix-gripper", 2, rng)
    t = random_table(rng, 6)
    shuffled = [SEEDS[i] for i in (4, 2, 0, 3, 1)] + [99]
    extra = [[run_file(tmp_path, "bx", "fix-gripper", t, shuffled, "model:bx")]]
    plain = make_runs(tmp_path, "b", "fix-gripper", 1, rng)
    c = cr.runs_cli(cli_args(runs_a, extra + plain))
    assert c["scene_seeds"] == SEEDS and c["left_out_scenes"] == [0, 0, 1, 0]
    in_order = {g: [cells[shuffled.index(s)] for s in SEEDS] for g, cells in t.items()}
    expected = np.mean([sum(s for s, _ in cells) / sum(a for _, a in cells) for cells in in_order.values()])
    assert c["b"]["runs"][0]["rate"] == pytest.approx(expected)
    assert "(1 of the runs' scenes left out: not run by every run, or not with every gripper)" in capsys.readouterr().out


def test_a_scene_without_every_gripper_is_left_out_and_counted(tmp_path):
    rng = np.random.default_rng(13)
    runs_a, runs_b = make_runs(tmp_path, "a", "fix-gripper", 2, rng), make_runs(tmp_path, "b", "fix-gripper", 2, rng)
    data = json.load(open(runs_a[1][0]))
    data["episode_results"] = [r for r in data["episode_results"] if (r["gripper"], r["scene_seed"]) != ("wsg_50", 13)]
    json.dump(data, open(runs_a[1][0], "w"))
    c = cr.runs_cli(cli_args(runs_a, runs_b))
    assert c["scenes"] == 4 and 13 not in c["scene_seeds"] and c["left_out_scenes"] == [1, 1, 1, 1]


def test_a_gripper_without_records_stops_unless_left_out_with_gripper(tmp_path, capsys):
    rng = np.random.default_rng(14)
    runs_a, runs_b = make_runs(tmp_path, "a", "fix-gripper", 2, rng), make_runs(tmp_path, "b", "fix-gripper", 2, rng)
    data = json.load(open(runs_b[0][0]))
    data["episode_results"] = [r for r in data["episode_results"] if r["gripper"] != "panda_hand"]
    json.dump(data, open(runs_b[0][0], "w"))
    assert ev.cli(["runs", *cli_args(runs_a, runs_b)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "b0.json: episode_results: no record of gripper panda_hand (an unfinished" in err
    c = cr.runs_cli(cli_args(runs_a, runs_b, "--gripper", "wsg_50"))
    assert c["a"]["grippers"] == ["wsg_50"] and c["scenes"] == 5


def test_other_objects_in_a_scene_stop_it_or_are_left_out(tmp_path, capsys):
    rng = np.random.default_rng(8)
    runs_a, runs_b = make_runs(tmp_path, "a", "fix-gripper", 2, rng), make_runs(tmp_path, "b", "fix-gripper", 2, rng)
    data = json.load(open(runs_b[1][0]))
    data["episode_results"][3]["objects"] = [["ycb/999", "target"]]
    json.dump(data, open(runs_b[1][0], "w"))
    assert ev.cli(["runs", *cli_args(runs_a, runs_b)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "b1.json: episode_results (scene_seed 14, gripper wsg_50).objects" in err
    c = cr.runs_cli(cli_args(runs_a, runs_b, "--drop-mismatched-scenes"))
    assert c["dropped_scene_seeds"] == [14] and c["scenes"] == 4 and 14 not in c["scene_seeds"]


def _same_model_twice(tmp_path, rng):
    a = make_runs(tmp_path, "a", "fix-gripper", 2, rng, models=["model:x", "model:x"])
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _one_run(tmp_path, rng):
    return make_runs(tmp_path, "a", "fix-gripper", 1, rng), make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _other_row(tmp_path, rng):
    a = make_runs(tmp_path, "a", "fix-gripper", 1, rng) + make_runs(tmp_path, "c", "fix-config", 1, rng)
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _other_scene_kind(tmp_path, rng):
    a = make_runs(tmp_path, "a", "fix-gripper", 2, rng)
    data = json.load(open(a[1][0]))
    json.dump({**data, "scene": "multi"}, open(a[1][0], "w"))
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _heuristic(tmp_path, rng):
    a = make_runs(tmp_path, "a", "heuristic", 2, rng, models=[None, None])
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _run_of_two_models(tmp_path, rng):
    a = make_runs(tmp_path, "a", "fix-gripper", 2, rng)
    a[0].append(run_file(tmp_path, "a0x", "fix-gripper", random_table(rng, 2), [31, 32], "model:other"))
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _a_scene_twice_in_a_run(tmp_path, rng):
    a = make_runs(tmp_path, "a", "fix-gripper", 2, rng)
    a[0].append(a[0][0])
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _digest_over_name(tmp_path, rng):
    """Two names, one digest: the same model twice on a side."""
    a = [[run_file(tmp_path, f"a{i}", "fix-gripper", random_table(rng, 5), SEEDS, f"model:n{i}", "ab" * 32)]
         for i in range(2)]
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _other_cameras(tmp_path, rng):
    b = make_runs(tmp_path, "b", "fix-gripper", 2, rng)
    data = json.load(open(b[1][0]))
    json.dump({**data, "cameras": 2}, open(b[1][0], "w"))
    return make_runs(tmp_path, "a", "fix-gripper", 2, rng), b


def _with_cameras(runs, cameras, extra_sim=None):
    """Rewrite every file of ``runs`` as evaluated with ``cameras`` cameras (key and ``config.sim``)."""
    for path in (f for run in runs for f in run):
        data = json.load(open(path))
        sim = {"cameras": cameras, "solver_iterations": 150, **(extra_sim or {})}
        json.dump({**data, "cameras": cameras, "config": {"sim": sim}}, open(path, "w"))
    return runs


def _cameras_within_a_side(tmp_path, rng):
    """--across-cameras: one run of side B with another camera count than the other."""
    b = _with_cameras(make_runs(tmp_path, "b", "fix-gripper", 2, rng), 2)
    _with_cameras(b[1:], 3)
    return _with_cameras(make_runs(tmp_path, "a", "fix-gripper", 2, rng), 1), b


def _one_camera_count_across(tmp_path, rng):
    """--across-cameras with both sides of one camera count."""
    return (_with_cameras(make_runs(tmp_path, "a", "fix-gripper", 2, rng), 2),
            _with_cameras(make_runs(tmp_path, "b", "fix-gripper", 2, rng), 2))


def _other_simulator_across_cameras(tmp_path, rng):
    """--across-cameras lets the camera count differ, not the rest of the simulator."""
    return (_with_cameras(make_runs(tmp_path, "a", "fix-gripper", 2, rng), 1),
            _with_cameras(make_runs(tmp_path, "b", "fix-gripper", 2, rng), 2, {"solver_iterations": 50}))


def _two_rows_across_cameras(tmp_path, rng):
    """--across-cameras: one row at two counts, not two rows."""
    return (_with_cameras(make_runs(tmp_path, "a", "fix-gripper", 2, rng), 1),
            _with_cameras(make_runs(tmp_path, "b", "fix-config", 2, rng), 2))


def _sim_cameras_not_the_files(tmp_path, rng):
    """Files whose cameras key (2) and config.sim.cameras (1, as on side A) disagree."""
    b = _with_cameras(make_runs(tmp_path, "b", "fix-gripper", 2, rng), 2)
    for (path,) in b:
        data = json.load(open(path))
        data["config"]["sim"]["cameras"] = 1
        json.dump(data, open(path, "w"))
    return _with_cameras(make_runs(tmp_path, "a", "fix-gripper", 2, rng), 1), b


def _sim_not_an_object(tmp_path, rng):
    b = make_runs(tmp_path, "b", "fix-gripper", 2, rng)
    data = json.load(open(b[1][0]))
    json.dump({**data, "config": {"sim": "arm"}}, open(b[1][0], "w"))
    return make_runs(tmp_path, "a", "fix-gripper", 2, rng), b


def _other_simulator(tmp_path, rng):
    """A run evaluated with other solver settings: another measurement, not another run."""
    b = make_runs(tmp_path, "b", "fix-gripper", 2, rng)
    data = json.load(open(b[1][0]))
    json.dump({**data, "config": {"sim": {"solver_iterations": 50}}}, open(b[1][0], "w"))
    return make_runs(tmp_path, "a", "fix-gripper", 2, rng), b


def _one_model_on_both_sides(tmp_path, rng):
    a = make_runs(tmp_path, "a", "fix-gripper", 2, rng)
    return a, make_runs(tmp_path, "b", "adagrasp", 2, rng, models=["model:a0", "model:b1"])


def _digest_on_one_file_only(tmp_path, rng):
    """One model, its digest recorded in one file only: the names decide, and they agree."""
    a = [[run_file(tmp_path, "a0", "fix-gripper", random_table(rng, 5), SEEDS, "model:x", "ab" * 32)],
         [run_file(tmp_path, "a1", "fix-gripper", random_table(rng, 5), SEEDS, "model:x")]]
    return a, make_runs(tmp_path, "b", "fix-gripper", 2, rng)


def _three_against_two(tmp_path, rng):
    a = make_runs(tmp_path, "a", "fix-gripper", 2, rng)
    return a, make_runs(tmp_path, "b", "adagrasp", 3, rng, models=["model:a0", "model:a1", "model:b2"])


def _calibrated(tmp_path, rng, tag, scenes, count=2):
    """``count`` calibrated adagrasp runs, each calibrated from ``scenes[i]`` scenes per gripper
    (None: a result written before the count was recorded), two grasps per scene."""
    runs = make_runs(tmp_path, tag, "adagrasp", count, rng, models=[f"model:c{i}" for i in range(count)])
    for (path,), n in zip(runs, scenes):
        data = json.load(open(path))
        fits = {g: {"shift": 0.1, "trials": 2 * (n or 40), "successes": n or 40} for g in GRIPPERS}
        if n is not None:
            for fit in fits.values():
                fit["scenes"] = n
        data["calibration"] = {"source": f"{path}.cal", "prior_sigma": 2.0, "grippers": fits}
        json.dump(data, open(path, "w"))
    return runs


def _two_calibration_budgets(tmp_path, rng):
    raw = make_runs(tmp_path, "r", "adagrasp", 2, rng, models=["model:c0", "model:c1"])
    return raw, _calibrated(tmp_path, rng, "b", [10, 40])


@pytest.mark.parametrize("build, extra, needle", [
    (_same_model_twice, [], r"a1\.json: checkpoint: the model of .*a0\.json, also a run of side A"),
    (_digest_over_name, [], r"a1\.json: checkpoint: the model of .*a0\.json, also a run of side A"),
    (_one_run, [], r"--a: 1 run\(s\); the spread across runs needs at least 2 per side"),
    (_other_row, [], r"c0\.json: row: 'fix-config', but .*a0\.json \(side A\) has 'fix-gripper'"),
    (_other_scene_kind, [], r"a1\.json: scene: 'multi', but .*a0\.json has 'obstacle': not one cell"),
    (_heuristic, [], r"a0\.json: checkpoint: none \(heuristic is not a trained model"),
    (_run_of_two_models, [], r"a0x\.json: checkpoint: 'model:other', but .*a0\.json has 'model:a0', of the same run"),
    (_a_scene_twice_in_a_run, [], r"a0\.json: scene_seed 11: also in .*a0\.json of the same run"),
    (_other_cameras, [], r"b1\.json: cameras: 2, but .*a0\.json has 1: not one cell"),
    (_other_simulator, [], r"b1\.json: config\.sim: differs from .*a0\.json in solver_iterations: not "
                           r"simulated alike"),
    (_cameras_within_a_side, ["--across-cameras"], r"b1\.json: cameras: 3, but .*b0\.json has 2: not one cell"),
    (_one_camera_count_across, ["--across-cameras"], r"b0\.json: cameras: 2, as on side A: --across-cameras "
                                                     r"compares two camera counts"),
    (_two_rows_across_cameras, ["--across-cameras"], r"b0\.json: row: 'fix-config', but .*a0\.json \(side A\) "
                                                      r"has 'fix-gripper': --across-cameras compares one row"),
    (_sim_cameras_not_the_files, ["--across-cameras"], r"b0\.json: config\.sim\.cameras: 1, but its cameras is 2"),
    (_sim_not_an_object, [], r"b1\.json: config\.sim: not an object"),
    (_other_simulator_across_cameras, ["--across-cameras"], r"b0\.json: config\.sim: differs from .*a0\.json in "
                                                            r"solver_iterations: not simulated alike"),
    (_one_model_on_both_sides, [], r"b0\.json: checkpoint: the model of .*a0\.json on side A: two rows of one "
                                   r"model compare with --paired"),
    (_digest_on_one_file_only, [], r"a1\.json: checkpoint: the model of .*a0\.json, also a run of side A"),
    (_three_against_two, ["--paired"], r"--paired: side A has 2 runs and side B 3: pairs need as many"),
    (_two_calibration_budgets, ["--paired"], r"b1\.json: calibration: 40 scenes per gripper, but .*b0\.json "
                                              r"\(side B\) has 10 scenes per gripper: each side is one calibration"),
])
def test_bad_input_is_one_line(tmp_path, capsys, build, extra, needle):
    runs_a, runs_b = build(tmp_path, np.random.default_rng(9))
    with pytest.raises(ev.EvaluationError, match=needle):
        cr.runs_cli(cli_args(runs_a, runs_b, *extra))
    assert ev.cli(["runs", *cli_args(runs_a, runs_b, *extra)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("evaluate: error: ") and "\n" not in err


def test_paired_needs_one_model_per_pair_and_names_the_key_that_differs(tmp_path):
    rng = np.random.default_rng(10)
    a, b = make_runs(tmp_path, "a", "fix-gripper", 2, rng), make_runs(tmp_path, "b", "adagrasp", 2, rng)
    with pytest.raises(ev.EvaluationError, match=r"b0\.json: checkpoint: 'model:b0', but .*a0\.json has "
                                                 r"'model:a0': --paired pairs the rows of one training run's model"):
        cr.runs_cli(cli_args(a, b, "--paired"))
    digests = [[run_file(tmp_path, f"dA{i}", "fix-gripper", random_table(rng, 5), SEEDS, "model:same", f"A{i}" * 32)]
               for i in range(2)]
    same_name = [[run_file(tmp_path, f"e{i}", "adagrasp", random_table(rng, 5, "adagrasp"), SEEDS, "model:same",
                           f"x{i}" * 32)] for i in range(2)]
    with pytest.raises(ev.EvaluationError, match=r"e0\.json: checkpoint_sha256: x0x0x0x0x0x0\.\.\., but .*dA0\.json "
                                                 r"has A0A0A0A0A0A0\.\.\.: --paired"):
        cr.runs_cli(cli_args(digests, same_name, "--paired"))


def test_a_sim_key_added_since_a_file_was_written_counts_at_its_default(tmp_path):
    """Files written before sim.target_bound existed compare with files that record its default,
    and are refused, naming it, against files that record another value."""
    rng = np.random.default_rng(11)
    a, b = make_runs(tmp_path, "a", "fix-gripper", 2, rng), make_runs(tmp_path, "b", "fix-gripper", 2, rng)
    old_sim = {"solver_iterations": 300}

    def with_sim(runs, sim):
        for files in runs:
            for path in files:
                data = json.load(open(path))
                json.dump({**data, "config": {"sim": sim}}, open(path, "w"))

    with_sim(a, old_sim)
    with_sim(b, {**old_sim, "target_bound": "scene_grid"})
    cr.runs_cli(cli_args(a, b))
    with_sim(b, {**old_sim, "target_bound": "fence"})
    with pytest.raises(ev.EvaluationError, match=r"b0\.json: config\.sim: differs from .*a0\.json in target_bound: "
                                                 r"not simulated alike"):
        cr.runs_cli(cli_args(a, b))


def test_every_file_is_one_cell_of_grippers(tmp_path):
    """adagrasp choosing among other grippers (another gripper set) is another cell."""
    rng = np.random.default_rng(11)
    a = make_runs(tmp_path, "a", "fix-gripper", 2, rng)
    b = [[write(tmp_path, f"b{i}", {**result("adagrasp", random_table(rng, 5, "adagrasp"), SEEDS,
                                             grippers=("wsg_50", "panda_hand", "robotiq")), "checkpoint": f"model:b{i}"})]
         for i in range(2)]
    with pytest.raises(ev.EvaluationError, match=r"b0\.json: gripper_names: \['panda_hand', 'robotiq', 'wsg_50'\], "
                                                 r"but .*a0\.json has \['panda_hand', 'wsg_50'\]: not one cell"):
        cr.runs_cli(cli_args(a, b))
    with pytest.raises(ev.EvaluationError, match=r"--gripper wsg_50: both sides are adagrasp runs"):
        ada = make_runs(tmp_path, "c", "adagrasp", 2, rng)
        cr.runs_cli(cli_args(ada, make_runs(tmp_path, "d", "adagrasp", 2, rng), "--gripper", "wsg_50"))


def test_t_is_undefined_without_spread_up_to_rounding():
    d = cr.t_test(np.array([0.7, 0.2]), np.array([0.8, 0.3]), paired=True)
    assert d["p_value"] is None and d["ci95"] is None
    assert cr.t_test(np.array([0.7, 0.2]), np.array([0.8, 0.35]), paired=True)["p_value"] > 0.1


def test_random_sign_patterns_estimate_the_exact_p(monkeypatch):
    d = np.random.default_rng(15).normal(0.03, 0.05, 6)
    exact = cr.sign_p(d, np.random.default_rng(0), 1)[0]
    monkeypatch.setattr(cr, "EXACT_LIMIT", 10)
    p, smallest, how = cr.sign_p(d, np.random.default_rng(16), 20_000)
    assert how == "20000 random sign patterns" and smallest == pytest.approx(1 / 20_001)
    assert p == pytest.approx(exact, abs=0.015)


def test_cli_prints_and_writes_the_comparison(tmp_path, capsys):
    rng = np.random.default_rng(12)
    a, b = make_runs(tmp_path, "a", "init-only", 3, rng), make_runs(tmp_path, "b", "fix-config", 3, rng)
    out = tmp_path / "runs.json"
    assert ev.cli(["runs", *cli_args(a, b, "--json", str(out))]) == 0
    text = capsys.readouterr().out
    written = json.loads(out.read_text())
    assert written["format"] == cr.RUNS_FORMAT and len(written["a"]["runs"]) == 3
    assert f"mean {written['b']['mean']:.3f}" in text and "run-relabelling test (exact, 20 relabellings)" in text
    assert written["a"]["sd"] == pytest.approx(np.std([r["rate"] for r in written["a"]["runs"]], ddof=1))
    assert ev.cli(["runs", *cli_args(a, b, "--json", str(tmp_path))]) == 2
    captured = capsys.readouterr()
    assert f"--json {tmp_path}: is a directory" in captured.err and captured.out == ""
    assert ev.cli(["runs", *cli_args(a, b, "--draws", "0")]) == 2
    assert "--draws 0: expected >= 1" in capsys.readouterr().err


def test_calibrated_runs_of_one_budget_compare_with_their_raw_rows(tmp_path):
    """Raw -> calibrated adagrasp of the same runs (paired) when the calibrated runs were fitted
    from as many scenes per gripper, or when a result does not record its count; another count
    for one gripper is another budget."""
    rng = np.random.default_rng(12)
    raw = make_runs(tmp_path, "r", "adagrasp", 2, rng, models=["model:c0", "model:c1"])
    cal = _calibrated(tmp_path, rng, "b", [40, 40])
    assert cr.calibration_budget(json.load(open(cal[0][0]))) == {g: 40 for g in sorted(GRIPPERS)}
    assert cr.calibration_budget(json.load(open(raw[0][0]))) is None
    both = cr.runs_cli(cli_args(raw, cal, "--paired"))
    assert both["scenes"] == len(SEEDS)
    assert both["a"]["calibration_scenes"] is None and both["b"]["calibration_scenes"] == {g: 40 for g in GRIPPERS}
    assert "B adagrasp (calibrated), 40 scenes per gripper, 2 runs:" in cr.report(both)
    old = _calibrated(tmp_path, rng, "o", [10, None])
    assert cr.calibration_budget(json.load(open(old[1][0]))) is None
    flagged = json.load(open(cal[0][0]))
    for fit in flagged["calibration"]["grippers"].values():
        fit["scenes"] = True
    assert cr.calibration_budget(flagged) is None
    mixed = cr.runs_cli(cli_args(raw, old, "--paired"))
    assert mixed["scenes"] == len(SEEDS) and mixed["b"]["calibration_scenes"] is None
    data = json.load(open(cal[1][0]))
    data["calibration"]["grippers"]["wsg_50"]["scenes"] = 39
    json.dump(data, open(cal[1][0], "w"))
    with pytest.raises(ev.EvaluationError, match=r"b1\.json: calibration: scenes per gripper panda_hand 40, wsg_50 "
                                                 r"39, but .*b0\.json \(side B\) has 40 scenes per gripper"):
        cr.runs_cli(cli_args(raw, cal, "--paired"))


def _fit_source(folder, name, scenes, rng):
    """A fix-gripper result of ``scenes`` scenes per gripper, two scored grasps each, written to
    ``folder``/``name``.json; returns its path and the calibration record an evaluation fitted to it
    writes (:meth:`common.calibration.Calibration.to_dict`)."""
    seeds = list(range(100, 100 + scenes))
    data = result("fix-gripper", {g: [(1, 2)] * scenes for g in GRIPPERS}, seeds)
    for record in data["episode_results"]:
        record["trials"] = [{"gripper": record["gripper"], "score": float(rng.uniform(0.2, 0.9)),
                             "success": bool(ok)} for ok in (True, False)]
    folder.mkdir(parents=True, exist_ok=True)
    path = write(folder, name, data)
    return path, calibration_from_result(path, data).to_dict()


def _legacy_calibrated(tmp_path, rng, tag, records):
    """Calibrated adagrasp runs in ``tmp_path``/results, run i with ``records[i]`` as its calibration,
    each fit's ``scenes`` removed (written before the count was recorded)."""
    runs = make_runs(tmp_path / "results", tag, "adagrasp", len(records), rng,
                     models=[f"model:c{i}" for i in range(len(records))])
    for (path,), record in zip(runs, records):
        data = json.load(open(path))
        old = {**record, "grippers": {g: {k: v for k, v in fit.items() if k != "scenes"}
                                      for g, fit in record["grippers"].items()}}
        data["calibration"] = {**old, "source": f"fits/{Path(record['source']).name}"}
        json.dump(data, open(path, "w"))
    return runs


def test_results_written_before_the_budget_was_recorded_get_it_from_their_source(tmp_path):
    """The calibration budget of a result without ``scenes`` comes from refitting its source file,
    found above the result's folder: a run fitted from 6 scenes is not another run of a 9-scene
    side, whatever the grasps per scene; a source that is not the one fitted is one line."""
    rng = np.random.default_rng(21)
    (tmp_path / "results").mkdir()
    six, fit6 = _fit_source(tmp_path / "fits", "six", 6, rng)
    _, fit9 = _fit_source(tmp_path / "fits", "nine", 9, rng)
    raw = make_runs(tmp_path / "results", "r", "adagrasp", 2, rng, models=["model:c0", "model:c1"])
    same = _legacy_calibrated(tmp_path, rng, "s", [fit9, fit9])
    path = same[0][0]
    assert "scenes" not in json.load(open(path))["calibration"]["grippers"]["wsg_50"]
    assert cr.calibration_budget(json.load(open(path))) is None
    assert cr.calibration_budget(json.load(open(path)), path) == {g: 9 for g in sorted(GRIPPERS)}
    assert cr.runs_cli(cli_args(raw, same, "--paired"))["b"]["calibration_scenes"] == {g: 9 for g in GRIPPERS}
    mixed = _legacy_calibrated(tmp_path, rng, "m", [fit9, fit6])
    with pytest.raises(ev.EvaluationError, match=r"m1\.json: calibration: 6 scenes per gripper, but .*m0\.json "
                                                 r"\(side B\) has 9 scenes per gripper"):
        cr.runs_cli(cli_args(raw, mixed, "--paired"))
    with pytest.raises(ev.EvaluationError, match=r"m1\.json: calibration: from 6 scenes per gripper, but .*m0\.json "
                                                 r"from 9 scenes per gripper"):
        ev.table(["--runs", mixed[0][0], mixed[1][0]])
    assert "| adagrasp (calibrated) | obstacle O_te/G_te | 2 |" in ev.table(["--runs", same[0][0], same[1][0]])
    data = json.load(open(six))
    data["episode_results"][0]["trials"][1]["success"] = True
    json.dump(data, open(six, "w"))
    with pytest.raises(ev.EvaluationError, match=r"m1\.json: calibration\.grippers\.(panda_hand|wsg_50): shift .* "
                                                 r"from 6/12 trials, but refitting .*six\.json gives .* from 7/12 \(the "
                                                 r"calibration budget cannot be recovered\)"):
        cr.runs_cli(cli_args(raw, mixed, "--paired"))
    signed = _legacy_calibrated(tmp_path, rng, "d", [{**fit6, "sha256": "ab" * 32}])
    with pytest.raises(ev.EvaluationError, match=r"d0\.json: calibration\.sha256: abababababab\.\.\., but .*six\.json "
                                                 r"has [0-9a-f]{12}\.\.\."):
        cr.calibration_budget(json.load(open(signed[0][0])), signed[0][0])
    gone = _legacy_calibrated(tmp_path, rng, "g", [{**fit9, "source": "elsewhere/none.json"}])
    assert cr.calibration_budget(json.load(open(gone[0][0])), gone[0][0]) is None


def test_the_source_search_goes_on_past_files_of_that_name_that_are_not_the_one_fitted(tmp_path):
    """A nearer file of the source's name that does not match (by SHA-256, or by refit where no
    digest is recorded) is passed over for the one fitted; a link's folders are searched before
    its target's; a name the system cannot look up names no file."""
    rng = np.random.default_rng(22)
    (tmp_path / "results").mkdir()
    nine, fit9 = _fit_source(tmp_path / "fits", "nine", 9, rng)
    digest = hashlib.sha256(Path(nine).read_bytes()).hexdigest()
    decoy, _ = _fit_source(tmp_path / "results" / "fits", "nine", 6, rng)
    for record in (fit9, {**fit9, "sha256": digest}):
        (path,), = _legacy_calibrated(tmp_path, rng, "n", [record])
        assert cr.calibration_budget(json.load(open(path)), path) == {g: 9 for g in sorted(GRIPPERS)}
    Path(nine).unlink()
    with pytest.raises(ev.EvaluationError, match=r"n0\.json: calibration\.sha256: .*, but .*results/fits/nine\.json "
                                                 r"has .*\(the calibration budget cannot be recovered\)"):
        cr.calibration_budget(json.load(open(path)), path)
    linked = tmp_path / "elsewhere"
    _, fit6 = _fit_source(linked / "fits", "six", 6, rng)
    (path,), = _legacy_calibrated(tmp_path, rng, "l", [fit6])
    (linked / "l0.json").symlink_to(path)
    assert cr.calibration_budget(json.load(open(path)), path) is None
    assert cr.calibration_budget(json.load(open(path)), str(linked / "l0.json")) == {g: 6 for g in sorted(GRIPPERS)}
    unnamed = json.load(open(path))
    for source in ("a" * 300 + "/x.json", "a\x00b.json"):
        unnamed["calibration"]["source"] = source
        assert cr.calibration_budget(unnamed, path) is None


def test_across_cameras_compares_two_camera_counts_of_one_row_as_any_two_rows(tmp_path):
    """--across-cameras: the sides are one row at two camera counts (one cell otherwise); the
    figures are those of the same files with the camera count made equal, and the comparison
    records each side's count."""
    rng = np.random.default_rng(21)
    models = [f"model:m{i}" for i in range(3)]
    a = _with_cameras(make_runs(tmp_path, "a", "fix-gripper", 3, rng, models=models), 1)
    b = _with_cameras(make_runs(tmp_path, "b", "fix-gripper", 3, rng, models=models), 4)
    with pytest.raises(ev.EvaluationError, match=r"b0\.json: cameras: 4, but .*a0\.json has 1: not one cell"):
        cr.runs_cli(cli_args(a, b, "--paired"))
    out = cr.runs_cli(cli_args(a, b, "--paired", "--across-cameras", "--json", str(tmp_path / "c.json")))
    assert (out["across_cameras"], out["a"]["cameras"], out["b"]["cameras"]) == (True, 1, 4)
    assert json.load(open(tmp_path / "c.json")) == out
    assert cr.side_label(out["b"], cameras=True) == "fix-gripper, 4 camera(s)"
    assert "B fix-gripper, 4 camera(s), 3 runs" in cr.report(out)
    same = cr.runs_cli(cli_args(a, _with_cameras(b, 1), "--paired"))
    assert "across_cameras" not in same and "cameras" not in same["a"]
    for key in ("mean_difference", "run_differences", "t", "randomization", "scene_seeds"):
        assert out[key] == same[key], key


def test_every_pair_of_a_runs_files_is_checked_for_one_model(tmp_path):
    """A run's files are one model: a file without a digest matches the others by name, files with
    digests by digest; checked pair by pair, whatever file comes first."""
    rng = np.random.default_rng(12)
    name = "runs/r1/checkpoints/latest.pt"
    seeds = ([11, 12, 13], [21, 22, 23], [31, 32, 33])
    digests = (None, "11" * 32, "22" * 32)
    files = [run_file(tmp_path, f"r{n}", "fix-gripper", random_table(rng, 3), s, name, d)
             for n, (s, d) in enumerate(zip(seeds, digests))]
    others = make_runs(tmp_path, "b", "fix-gripper", 2, rng, seeds=[11, 12, 13, 21, 22, 23, 31, 32, 33])
    second = [run_file(tmp_path, "s", "fix-gripper", random_table(rng, 9), [11, 12, 13, 21, 22, 23, 31, 32, 33],
                       "model:s")]
    for order in (files, [files[1], files[0], files[2]]):
        with pytest.raises(ev.EvaluationError, match=r"r2\.json: checkpoint_sha256: 222222222222\.\.\., but .*r1\.json"):
            cr.runs_cli(cli_args([order, second], others))
