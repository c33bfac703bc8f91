"""``evaluate holm``: Holm's step-down correction over comparison files; the adjusted p-values,
the files of ``evaluate compare`` and ``evaluate runs`` it reads, and its one-line errors."""

import itertools
import json

import numpy as np
import pytest

from actors import compare as cmp
from actors import compare_runs as cr
from actors import evaluate as ev
from actors import holm as hm
from tests.test_compare_runs import GRIPPERS, _calibrated, _with_cameras, cli_args, make_runs


def holm_by_definition(p):
    """The adjusted p-value of each test: the largest over every smaller-or-equal p (in sorted
    order) of min(1, (m - rank) p), written as the textbook loop."""
    m = len(p)
    order = sorted(range(m), key=lambda i: (p[i], i))
    out, running = [0.0] * m, 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out


def test_adjusted_p_values_follow_the_step_down_rule():
    # sorted 0.005 (x4 = 0.02), 0.01 (x3 = 0.03), 0.03 (x2 = 0.06), 0.04 (x1, raised to 0.06)
    np.testing.assert_allclose(hm.holm([0.01, 0.04, 0.03, 0.005]), [0.03, 0.06, 0.06, 0.02])
    # ties: 0.01 and 0.01 (x3 = 0.03, x2 = 0.02 raised to 0.03), 0.04 (x1 = 0.04)
    np.testing.assert_allclose(hm.holm([0.01, 0.04, 0.01]), [0.03, 0.04, 0.03])
    rng = np.random.default_rng(0)
    for m in (1, 2, 5, 9, 30):
        p = rng.uniform(0, 0.3, m).round(2)  # rounded: ties among 30 values
        np.testing.assert_allclose(hm.holm(p), holm_by_definition(list(p)))
    assert hm.holm([0.9, 0.8]).tolist() == [1.0, 1.0]


def test_holm_keeps_the_family_wise_error_under_alpha_when_every_null_holds():
    """m independent uniform p-values (every null true): any adjusted p <= 0.05 in at most 5% of
    families (Holm controls it at alpha), while the uncorrected rule errs in 1 - 0.95^m."""
    rng = np.random.default_rng(1)
    p = rng.uniform(size=(20_000, 7))
    any_holm = np.mean([hm.holm(row).min() <= 0.05 for row in p])
    any_raw = np.mean(p.min(axis=1) <= 0.05)
    assert any_holm <= 0.05 + 0.005 and abs(any_raw - (1 - 0.95**7)) < 0.015


def _run_files(tmp_path, rng, count):
    """``count`` evaluate runs comparison files, written by the tool itself."""
    out = []
    for k in range(count):
        a = make_runs(tmp_path, f"a{k}-", "fix-gripper", 3, rng)
        b = make_runs(tmp_path, f"b{k}-", "fix-gripper", 3, rng)
        path = str(tmp_path / f"runs{k}.json")
        cr.runs_cli(cli_args(a, b, "--json", path))
        out.append(path)
    return out


def _compare_file(tmp_path, rng, name, policy_b="fix-gripper"):
    """One evaluate compare file, written by the tool itself."""
    a = make_runs(tmp_path, f"{name}a", "fix-gripper", 1, rng)[0][0]
    b = make_runs(tmp_path, f"{name}b", policy_b, 1, rng)[0][0]
    path = str(tmp_path / f"{name}.json")
    cmp.compare_cli([a, b, "--resamples", "200", "--json", path])
    return path


def test_the_tools_own_files_are_one_family(tmp_path, capsys):
    rng = np.random.default_rng(2)
    files = _run_files(tmp_path, rng, 3) + [_compare_file(tmp_path, rng, "cmp")]
    out = str(tmp_path / "holm.json")
    record = hm.holm_cli([*files, "--json", out])
    raw = [json.load(open(f))["t"]["p_value"] for f in files[:3]] + [json.load(open(files[3]))["p_value"]]
    assert [r["p_value"] for r in record["comparisons"]] == raw
    assert [r["holm_p"] for r in record["comparisons"]] == pytest.approx(holm_by_definition(raw))
    assert [r["separated"] for r in record["comparisons"]] == [a <= 0.05 for a in holm_by_definition(raw)]
    assert json.load(open(out)) == record and record["format"] == hm.HOLM_FORMAT
    text = capsys.readouterr().out
    assert "holm: 4 tests, family-wise level 0.05" in text and "fix-gripper: model:cmpa0 -> model:cmpb0" in text
    randomization = hm.holm_cli([*files[:3], "--test", "randomization"])
    assert [r["p_value"] for r in randomization["comparisons"]] == [
        json.load(open(f))["randomization"]["p_value"] for f in files[:3]]
    assert all(r["smallest_p"] == 0.1 for r in randomization["comparisons"])


def _one_file(tmp_path, rng):
    return _run_files(tmp_path, rng, 1)


def _two_files(tmp_path, rng):
    return _run_files(tmp_path, rng, 2)


def _twice(tmp_path, rng):
    f = _run_files(tmp_path, rng, 1)
    return f + f


def _evaluation_result(tmp_path, rng):
    return _run_files(tmp_path, rng, 1) + [make_runs(tmp_path, "e", "fix-gripper", 1, rng)[0][0]]


def _no_permutation_test(tmp_path, rng):
    return _run_files(tmp_path, rng, 1) + [_compare_file(tmp_path, rng, "ada", policy_b="adagrasp")]


def _no_spread(tmp_path, rng):
    files = _run_files(tmp_path, rng, 2)
    data = json.load(open(files[1]))
    data["t"]["p_value"] = None
    json.dump(data, open(files[1], "w"))
    return files


def _edited(tmp_path, rng, edit, compare=False):
    """A family of two whose second file (a runs file, or a compare file) is edited by ``edit``."""
    (tmp_path / "more").mkdir()
    files = _run_files(tmp_path, rng, 1) + ([_compare_file(tmp_path, rng, "cmp")] if compare
                                            else _run_files(tmp_path / "more", rng, 1))
    data = json.load(open(files[1]))
    json.dump(edit(data), open(files[1], "w"))
    return files


def _no_side(tmp_path, rng):
    return _edited(tmp_path, rng, lambda d: {k: v for k, v in d.items() if k != "a"}, compare=True)


def _side_not_an_object(tmp_path, rng):
    return _edited(tmp_path, rng, lambda d: {**d, "b": "x"})


def _a_list(tmp_path, rng):
    return _edited(tmp_path, rng, lambda d: [d])


def _p_true(tmp_path, rng):
    return _edited(tmp_path, rng, lambda d: {**d, "p_value": True}, compare=True)


def _difference_text(tmp_path, rng):
    return _edited(tmp_path, rng, lambda d: {**d, "mean_difference": "+0.1"})


def _p_out_of_range(tmp_path, rng):
    return _edited(tmp_path, rng, lambda d: {**d, "t": {**d["t"], "p_value": 1.5}})


def _row_null(tmp_path, rng):
    return _edited(tmp_path, rng, lambda d: {**d, "b": {**d["b"], "row": None}})


def _same_file_by_another_path(tmp_path, rng):
    files = _run_files(tmp_path, rng, 1)
    (tmp_path / "d").mkdir()
    return files + [str(tmp_path / "d" / ".." / "runs0.json")]


def _budget(value):
    """A family whose second runs file's side B has ``calibration_scenes`` set to ``value``."""
    def build(tmp_path, rng):
        return _edited(tmp_path, rng, lambda d: {**d, "b": {**d["b"], "calibration_scenes": value}})
    return build


def _not_text(tmp_path, rng):
    bad = tmp_path / "binary.json"
    bad.write_bytes(b"\xff\xfe{")
    return _run_files(tmp_path, rng, 1) + [str(bad)]


def _not_json(tmp_path, rng):
    bad = tmp_path / "broken.json"
    bad.write_text('{"format": ')
    return _run_files(tmp_path, rng, 1) + [str(bad)]


@pytest.mark.parametrize("build, extra, needle", [
    (_one_file, [], r"1 comparison file\(s\): a correction needs at least 2 tests"),
    (_twice, [], r"runs0\.json: named twice"),
    (_evaluation_result, [], r"e0\.json: format: 'adagrasp-scale-evaluation/1', expected"),
    (_no_permutation_test, [], r"ada\.json: p_value: none \(an adagrasp row against a per-gripper row"),
    (_no_spread, [], r"runs1\.json: t: p_value: none \(the runs have no spread"),
    (_not_json, [], r"broken\.json: not valid JSON"),
    (_not_text, [], r"binary\.json: not valid JSON"),
    (_no_side, [], r"cmp\.json: a: missing or not an object"),
    (_side_not_an_object, [], r"runs0\.json: b: missing or not an object"),
    (_a_list, [], r"runs0\.json: format: 'list', expected"),
    (_p_true, [], r"cmp\.json: p_value: expected a number, got True"),
    (_difference_text, [], r"runs0\.json: mean_difference: expected a number, got '\+0\.1'"),
    (_row_null, [], r"runs0\.json: b\.row: expected a row name, got None"),
    (_p_out_of_range, [], r"runs0\.json: t: p_value: expected a value in \[0, 1\], got 1\.5"),
    *[(_budget(value), [], r"runs0\.json: b: calibration_scenes: expected null or gripper -> scenes \(positive "
                           r"integers\), got " + shown)
      for value, shown in [({"wsg_50": "40"}, r"\{'wsg_50': '40'\}"), ([40], r"\[40\]"), ({}, r"\{\}"),
                           ({"wsg_50": 0}, r"\{'wsg_50': 0\}"), ({"wsg_50": -1}, r"\{'wsg_50': -1\}"),
                           ({"wsg_50": True}, r"\{'wsg_50': True\}"), ({"wsg_50": 40.0}, r"\{'wsg_50': 40\.0\}")]],
    (_same_file_by_another_path, [], r"runs0\.json: named twice \(as .*runs0\.json"),
    (_two_files, ["--alpha", "1.5"], r"--alpha 1\.5: expected a level between 0 and 1"),
])
def test_bad_input_is_one_line(tmp_path, capsys, build, extra, needle):
    files = build(tmp_path, np.random.default_rng(3))
    capsys.readouterr()
    with pytest.raises(ev.EvaluationError, match=needle):
        hm.holm_cli([*files, *extra])
    assert ev.cli(["holm", *files, *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("evaluate: error: ") and "\n" not in err


def test_the_order_of_the_files_does_not_change_a_files_adjusted_p(tmp_path):
    files = _run_files(tmp_path, np.random.default_rng(5), 3)
    by_order = []
    for perm in itertools.permutations(files):
        rec = hm.correct(list(perm))
        by_order.append({r["path"]: r["holm_p"] for r in rec["comparisons"]})
    assert all(d == by_order[0] for d in by_order)


def test_two_calibration_budgets_of_one_row_are_told_apart_by_their_labels(tmp_path):
    """The same raw -> calibrated rows of the same runs, calibrated from 10 and from 40 scenes per
    gripper: the runs files record each side's budget, and Holm's labels name it."""
    rng = np.random.default_rng(6)
    raw = make_runs(tmp_path, "r", "adagrasp", 2, rng, models=["model:c0", "model:c1"])
    files = []
    for n in (10, 40):
        path = str(tmp_path / f"cal{n}.json")
        cr.runs_cli(cli_args(raw, _calibrated(tmp_path, rng, f"b{n}-", [n, n]), "--paired", "--json", path))
        files.append(path)
    assert [json.load(open(f))["b"]["calibration_scenes"] for f in files] == [
        {g: n for g in sorted(GRIPPERS)} for n in (10, 40)]
    assert json.load(open(files[0]))["a"]["calibration_scenes"] is None
    labels = [r["label"] for r in hm.holm_cli(files)["comparisons"]]
    assert labels == [f"adagrasp -> adagrasp (calibrated), {n} scenes per gripper (runs)" for n in (10, 40)]


def test_labels_name_camera_counts_only_for_a_comparison_across_them(tmp_path):
    """An evaluate compare file records each side's cameras; its label is its two rows. An
    evaluate runs file --across-cameras names each side's count."""
    rng = np.random.default_rng(7)
    rows = _compare_file(tmp_path, rng, "rows", policy_b="fix-config")
    models = ["model:m0", "model:m1"]
    a = _with_cameras(make_runs(tmp_path, "one", "fix-gripper", 2, rng, models=models), 1)
    b = _with_cameras(make_runs(tmp_path, "three", "fix-gripper", 2, rng, models=models), 3)
    across = str(tmp_path / "across.json")
    cr.runs_cli(cli_args(a, b, "--paired", "--across-cameras", "--json", across))
    assert json.load(open(rows))["a"]["cameras"] == 1
    labels = [r["label"] for r in hm.holm_cli([rows, across])["comparisons"]]
    assert labels == ["fix-gripper -> fix-config",
                      "fix-gripper, 1 camera(s) -> fix-gripper, 3 camera(s) (runs)"]
