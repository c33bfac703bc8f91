"""``evaluate table`` over scene seeds and training runs: ``A.json,B.json`` pools one model's seeds,
``--runs`` averages the runs of a row; rates, titles and one-line errors."""

import numpy as np
import pytest

from actors import evaluate as ev
from tests.test_compare import SEEDS, result, write
from tests.test_compare_runs import random_table


def split_files(tmp_path, name, policy, table, model, digest=None):
    """One model's result over SEEDS as one file, and as two files at scene seeds 0 and 2
    (the first two scenes, the last three). Returns (whole, [part0, part2])."""
    def data(tab, seeds, seed):
        d = {**result(policy, tab, seeds), "checkpoint": model, "seed": seed}
        if digest is not None:
            d["checkpoint_sha256"] = digest
        return d

    head = {g: c[:2] for g, c in table.items()} if isinstance(table, dict) else table[:2]
    tail = {g: c[2:] for g, c in table.items()} if isinstance(table, dict) else table[2:]
    whole = write(tmp_path, f"{name}-whole", data(table, SEEDS, 0))
    parts = [write(tmp_path, f"{name}-s0", data(head, SEEDS[:2], 0)),
             write(tmp_path, f"{name}-s2", data(tail, SEEDS[2:], 2))]
    return whole, parts


def cells(markdown):
    """policy -> cell texts of the first table of ``markdown``."""
    lines = markdown.splitlines()
    out = {}
    for line in lines[2:]:
        if not line.startswith("|"):
            break
        parts = [c.strip() for c in line.strip("|").split("|")]
        out[parts[0]] = parts[1:]
    return out


def assert_one_line_errors(cases, md, capsys):
    """Each (argv, needle): ``evaluate table`` exits 2 with one line holding needle, writing no ``md``."""
    for argv, needle in cases:
        capsys.readouterr()
        assert ev.cli(["table", *argv, "--md", str(md)]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and needle in err, (needle, err)
        assert not md.exists()


@pytest.mark.parametrize("policy", ["fix-gripper", "adagrasp"])
def test_pooled_scene_seeds_have_the_rate_of_one_file_of_all_their_scenes(tmp_path, policy):
    rng = np.random.default_rng(3)
    whole, parts = split_files(tmp_path, "m", policy, random_table(rng, len(SEEDS), policy), "model:m")
    one = ev.table([whole])
    pooled = ev.table([",".join(parts)])
    rate = ev.read_result(whole)["rate"]
    assert cells(one)[policy] == [f"{rate:.3f}"]
    assert cells(pooled)[policy] == [f"{rate:.3f}"]
    assert pooled.splitlines()[0] == "| policy | obstacle O_te/G_te (seeds 0, 2) |"
    source = next(line for line in pooled.splitlines() if line.startswith(f"| {parts[0]} + {parts[1]} |"))
    whole_source = next(line for line in one.splitlines() if line.startswith(f"| {whole} |"))
    fields = [c.strip() for c in source.strip("|").split("|")]
    assert fields[6:9] == [c.strip() for c in whole_source.strip("|").split("|")][6:9], "episodes, attempts, successes"
    assert fields[9] == "0, 2"


def test_runs_average_the_pooled_rates_of_other_models(tmp_path, capsys):
    rng = np.random.default_rng(4)
    tables = [random_table(rng, len(SEEDS)) for _ in range(3)]
    runs = [split_files(tmp_path, f"r{i}", "fix-gripper", t, f"model:r{i}", digest=f"{i:064x}")
            for i, t in enumerate(tables)]
    rates = [ev.read_result(whole)["rate"] for whole, _ in runs]
    args = [",".join(parts) for _, parts in runs]
    md = ev.table(["--runs", *args])
    mean = sum(rates) / 3
    assert cells(md)["fix-gripper"] == [f"{mean:.3f}"]
    row = next(line for line in md.splitlines() if line.startswith("| fix-gripper | obstacle O_te/G_te (seeds 0, 2) |"))
    assert row == ("| fix-gripper | obstacle O_te/G_te (seeds 0, 2) | 3 | "
                   + " / ".join(f"{r:.3f}" for r in rates) + f" | {mean:.3f} |")
    one_run = ev.table([args[0]])
    assert "Cells of several training runs" not in one_run
    capsys.readouterr()
    assert ev.cli(["table", *args]) == 2, "without --runs two results of one cell clash"
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "the same cell is already in" in err and "--runs" in err


def test_runs_on_other_scene_seeds_are_other_columns(tmp_path):
    rng = np.random.default_rng(5)
    _, a = split_files(tmp_path, "a", "fix-gripper", random_table(rng, len(SEEDS)), "model:a")
    b = write(tmp_path, "b", {**result("fix-gripper", random_table(rng, len(SEEDS)), SEEDS), "checkpoint": "model:b",
                              "seed": 0})
    md = ev.table(["--runs", ",".join(a), b])
    assert md.splitlines()[0] == "| policy | obstacle O_te/G_te (seed 0) | obstacle O_te/G_te (seeds 0, 2) |"


def test_table_errors_are_one_line_naming_the_file_and_key(tmp_path, capsys):
    rng = np.random.default_rng(6)
    t = random_table(rng, len(SEEDS))
    whole, parts = split_files(tmp_path, "x", "fix-gripper", t, "model:x", digest="a" * 64)
    _, other = split_files(tmp_path, "y", "fix-gripper", t, "model:y", digest="b" * 64)
    fewer = write(tmp_path, "fewer", {**result("fix-gripper", {g: c[:4] for g, c in t.items()}, SEEDS[:4]),
                                      "checkpoint": "model:z", "checkpoint_sha256": "c" * 64})
    again = write(tmp_path, "again", ev.read_result(whole))
    heuristic = [write(tmp_path, f"h{i}", {**result("heuristic", t, SEEDS), "seed": 0}) for i in range(2)]
    lopsided = {**result("fix-gripper", t, SEEDS), "checkpoint": "model:w"}
    lopsided["episode_results"] = [r for r in lopsided["episode_results"]
                                   if not (r["gripper"] == "panda_hand" and r["scene_seed"] == SEEDS[1])]
    gap = write(tmp_path, "gap", lopsided)
    md = tmp_path / "never.md"
    cases = (
        (["--runs", whole, again], f"{again}: checkpoint: the model of {whole}, in fix-gripper, obstacle O_te/G_te"),
        ([parts[0] + "," + other[1]], f"{other[1]}: checkpoint_sha256: bbbbbbbbbbbb..., but {parts[0]} has"),
        ([parts[0] + "," + whole], f"{whole}: scene_seed {SEEDS[0]}: also in {parts[0]}"),
        (["--runs", whole, fewer], f"{fewer}: scene_seed: its scenes are not those of {whole}"),
        (["--runs", *heuristic], f"{heuristic[1]}: checkpoint: none (heuristic is not a trained model"),
        ([parts[0] + "," + parts[0]], f"{parts[0]}: given twice in"),
        ([parts[0] + ","], f"{parts[0]},: expected RESULT.json or RESULT.json,RESULT.json"),
        ([gap + "," + parts[0]], f"{gap}: episode_results: gripper panda_hand has no record of scene_seed {SEEDS[1]}"),
    )
    assert_one_line_errors(cases, md, capsys)


def test_only_one_cell_measured_alike_pools_or_averages(tmp_path, capsys):
    """Results of other grippers, attempt limits, simulator settings, scene splits or calibration
    budgets are neither pooled into one result nor averaged as runs: one line naming the file and key."""
    rng = np.random.default_rng(7)
    t = random_table(rng, len(SEEDS))
    ada = random_table(rng, len(SEEDS), "adagrasp")

    def file(name, policy, table, seeds, model, seed=0, **fields):
        data = {**result(policy, table, seeds), "checkpoint": model, "checkpoint_sha256": model[-1] * 64,
                "seed": seed, "config": {"sim": {"solver_iterations": 300}}, **fields}
        return write(tmp_path, name, data)

    base = file("base", "fix-gripper", t, SEEDS, "model:a")
    g_tr = file("g_tr", "adagrasp", ada[2:], SEEDS[2:], "model:a", seed=2,
                gripper_names=["gen_a", "gen_b"], grippers="train", grippers_label="G_tr")
    ada0 = file("ada0", "adagrasp", ada[:2], SEEDS[:2], "model:a")
    attempts = file("attempts", "fix-gripper", t, SEEDS, "model:b", max_attempts=5)
    sim = file("sim", "fix-gripper", t, SEEDS, "model:c", config={"sim": {"solver_iterations": 50}})
    split_a = [file("sa0", "fix-gripper", {g: c[:3] for g, c in t.items()}, SEEDS[:3], "model:d"),
               file("sa2", "fix-gripper", {g: c[3:] for g, c in t.items()}, SEEDS[3:], "model:d", seed=2)]
    other_seeds = [11, 12, 13, 99, 98]
    split_b = [file("sb0", "fix-gripper", {g: c[:3] for g, c in t.items()}, other_seeds[:3], "model:e"),
               file("sb2", "fix-gripper", {g: c[3:] for g, c in t.items()}, other_seeds[3:], "model:e", seed=2)]

    def calibrated(name, model, scenes):
        fits = {g: {"scenes": scenes} if scenes else {"trials": 12} for g in ("wsg_50", "panda_hand")}
        return file(name, "adagrasp", ada, SEEDS, model, calibration={"source": f"{name}-fit.json", "grippers": fits})

    cal10, cal40 = calibrated("cal10", "model:f", 10), calibrated("cal40", "model:g", 40)
    unrecorded = calibrated("unrecorded", "model:i", None)  # written before the budget was recorded
    md = tmp_path / "never.md"
    cases = (
        ([ada0 + "," + g_tr], f"{g_tr}: gripper_names: ['gen_a', 'gen_b'], but {ada0} has"),
        (["--runs", base, attempts], f"{attempts}: max_attempts: 5, but {base} has"),
        (["--runs", base, sim], f"{sim}: config.sim: differs from {base} in solver_iterations"),
        (["--runs", ",".join(split_a), ",".join(split_b)],
         f"{split_b[0]} + {split_b[1]}: scene_seed: its scenes are not those of {split_a[0]} + {split_a[1]}"),
        (["--runs", cal10, cal40], f"{cal40}: calibration: from 40 scenes per gripper, but {cal10} from 10 scenes"),
        (["--runs", unrecorded, cal10, cal40], f"{cal40}: calibration: from 40 scenes per gripper, but {cal10} from"),
    )
    assert_one_line_errors(cases, md, capsys)
    fine = ev.table(["--runs", cal40, calibrated("cal40b", "model:h", 40)])
    assert "| adagrasp (calibrated) | obstacle O_te/G_te (seed 0) | 2 |" not in fine, "one seed: no seed qualifier"
    assert "| adagrasp (calibrated) | obstacle O_te/G_te | 2 |" in fine
