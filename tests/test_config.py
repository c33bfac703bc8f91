"""Config dataclasses: every field documented, every shipped YAML loads, bad keys fail in one line."""

import ast
import dataclasses
from pathlib import Path

import pytest

import common.config as config_module
from common.config import Config, ConfigError, from_dict, load_config, save_config, to_dict

CONFIG_NAMES = sorted(
    p.stem
    for p in (Path(config_module.__file__).resolve().parents[1] / "configs").glob("*.yaml")
    if p.stem != "cluster"  # a Ray cluster file for `ray up`, not a run config
)


def test_every_config_field_has_a_docstring():
    tree = ast.parse(Path(config_module.__file__).read_text())
    sections = {f.type if isinstance(f.type, str) else f.type.__name__ for f in dataclasses.fields(Config)} | {"Config"}
    missing, seen = [], set()
    for node in tree.body:
        if not isinstance(node, ast.ClassDef) or node.name not in sections:
            continue
        seen.add(node.name)
        body = node.body
        for i, stmt in enumerate(body):
            if isinstance(stmt, ast.AnnAssign):
                doc = body[i + 1] if i + 1 < len(body) else None
                if not (isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant) and isinstance(doc.value.value, str)):
                    missing.append(f"{node.name}.{stmt.target.id}")
    assert seen == sections, sections - seen
    assert not missing, f"config fields without a docstring: {missing}"


@pytest.mark.parametrize("name", CONFIG_NAMES)
def test_shipped_configs_load_and_round_trip(name):
    cfg = load_config(name)
    assert to_dict(from_dict(to_dict(cfg))) == to_dict(cfg)


def test_unknown_key_is_one_line_naming_it():
    with pytest.raises(ConfigError) as e:
        load_config("default", overrides=["learner.init_weight=model:x"])
    assert "\n" not in str(e.value) and "learner.init_weight" in str(e.value)


@pytest.mark.parametrize(
    "override, field",
    [
        ("learner.batch_size=7", "learner.batch_size"),
        ("learner.min_replay=-5", "learner.min_replay"),
        ("learner.min_replay=0", "learner.min_replay"),
        ("learner.checkpoint_minutes=-1", "learner.checkpoint_minutes"),
        ("learner.checkpoint_minutes=.nan", "learner.checkpoint_minutes"),
        ("learner.epsilon_decay_trials=-3", "learner.epsilon_decay_trials"),
        ("run.seed=-1", "run.seed"),
        ("grippers.train_openings=0", "grippers.train_openings"),
        ("actor.weights_poll_episodes=0", "actor.weights_poll_episodes"),
        ("model.scene_widths=[]", "model.scene_widths"),
        ("model.gripper_widths=[16, 0]", "model.gripper_widths"),
        ("model.feature_cell=.nan", "model.feature_cell"),
        ("scene_grid.x_range=[.nan, 0.1]", "scene_grid.x_range"),
        ("scene_grid.y_range=[-0.096, 0.096]", "scene_grid.y_range: 48 cells, but x_range has 96"),
        ("learner.samples_per_insert=0", "learner.samples_per_insert"),
        ("gripper_grid.tcp_height=-5", "gripper_grid.tcp_height"),
        ("gripper_grid.tcp_height=0.2", "gripper_grid.tcp_height"),
    ],
)
def test_learner_values_that_would_fail_later_are_refused_at_load(override, field):
    """Values the learner cannot run with (an odd balanced batch, training on an empty replay,
    no periodic checkpoints, a negative schedule) are one line at load, not a failure in a
    Ray task after the actors have collected min_replay trials."""
    with pytest.raises(ConfigError) as e:
        load_config("default", overrides=[override])
    assert "\n" not in str(e.value) and str(e.value).startswith(f"--set: {field}: "), str(e.value)


def test_min_replay_of_zero_is_allowed_with_a_seeded_replay():
    cfg = load_config("default", overrides=["learner.min_replay=0", "replay.seed_from=runs/earlier"])
    assert cfg.learner.min_replay == 0


def test_set_mends_a_combination_the_file_got_wrong_and_errors_name_the_values_source(tmp_path):
    """Constraints between fields are checked once the overrides are in: --set can fix an odd
    batch in the file, and a remaining error names the file or --set, whichever gave the value."""
    path = tmp_path / "odd.yaml"
    path.write_text("learner:\n  batch_size: 7\n")
    assert load_config(path, overrides=["learner.batch_size=8"]).learner.batch_size == 8
    with pytest.raises(ConfigError, match=rf"^{path}: learner.batch_size: must be even"):
        load_config(path, overrides=["learner.lr=0.001"])
    with pytest.raises(ConfigError, match=r"^--set: learner.batch_size: must be even"):
        load_config("default", overrides=["learner.batch_size=9"])
    # a constraint broken by --set on another of its keys names --set, not the file
    with pytest.raises(ConfigError, match=r"^--set: scene_grid.voxel_size: .* does not divide x_range"):
        load_config("default", overrides=["scene_grid.x_range=[-0.19, 0.192]"])
    with pytest.raises(ConfigError, match=r"^--set: learner.min_replay: 0 needs replay.seed_from"):
        load_config("default", overrides=["learner={min_replay: 0}"])


def test_an_empty_value_of_a_text_field_is_the_empty_string(tmp_path, capsys):
    """``--set learner.init_weights=`` and an empty YAML value clear a path field (the empty string
    is its "none"); a text field that must name something still refuses it in one line."""
    cfg = load_config("default", overrides=["learner.init_weights=model:x", "learner.init_weights="])
    assert cfg.learner.init_weights == ""
    f = tmp_path / "empty.yaml"
    f.write_text("replay:\n  seed_from:\n")
    assert load_config(f).replay.seed_from == ""
    with pytest.raises(ConfigError, match=r"^--set: model\.variant: .*''"):
        load_config("default", overrides=["model.variant="])
    for key in ("sim.objects", "grippers.train_grippers"):
        with pytest.raises(ConfigError, match=rf"^--set: {key}: empty; it must name something$"):
            load_config("default", overrides=[f"{key}="])
    # an empty run folder loads (a checkpoint of such a run stays usable); a new run refuses it
    assert load_config("default", overrides=["run.run_dir="]).run.run_dir == ""
    from learner.run import cli

    assert cli(["--config", "tiny", "--set", "run.run_dir=", "--actors", "0", "--max-trials", "1"]) == 2
    assert "run.run_dir: empty; name the folder new runs go in, or pass --run-dir" in capsys.readouterr().err


def test_exponent_numbers_without_a_dot_are_numbers(tmp_path):
    """PyYAML reads YAML 1.1, where 1e-4 is a string; in --set and in YAML files it is the number
    1e-4 (YAML 1.2), and the saved config reads back the same. Words stay errors."""
    assert load_config("default", overrides=["learner.lr=1e-4"]).learner.lr == 1e-4
    f = tmp_path / "exp.yaml"
    f.write_text("learner:\n  lr: 2E-5\n  ema_decay: 9.99e-1\n")
    cfg = load_config(f)
    assert (cfg.learner.lr, cfg.learner.ema_decay) == (2e-5, 0.999)
    save_config(cfg, tmp_path / "saved.yaml")
    assert load_config(tmp_path / "saved.yaml").learner.lr == 2e-5
    for bad in ("learner.lr=fast", "learner.lr=1e-4x", "learner.lr=1e"):
        with pytest.raises(ConfigError, match=r"^--set: learner\.lr: expected a number, got '"):
            load_config("default", overrides=[bad])
    with pytest.raises(ConfigError, match=r"^--set: learner\.lr: expected a finite number, got nan$"):
        load_config("default", overrides=["learner.lr=.nan"])


def test_paper_config_explores_over_the_papers_2000_epochs_of_8_trials():
    """The paper's epsilon falls 0.8 -> 0.2 over 2,000 epochs; one epoch collects one trial in
    each of its 8 environments, so the schedule spans 16,000 trials."""
    from learner.learner import epsilon_at

    cfg = load_config("paper")
    assert epsilon_at(cfg, 0) == pytest.approx(0.8)
    assert epsilon_at(cfg, 8 * 1000) == pytest.approx(0.5)
    assert epsilon_at(cfg, 8 * 2000) == pytest.approx(0.2) == epsilon_at(cfg, 10**6)


def test_integers_follow_yaml_1_2_and_repeated_keys_are_refused(tmp_path):
    """PyYAML reads YAML 1.1: 010 was 8 (octal), 1:30 was 90 (base 60), and a section given twice
    kept only the second, silently."""
    assert load_config("default", overrides=["run.seed=010"]).run.seed == 10
    assert load_config("default", overrides=["run.seed=0x10"]).run.seed == 16
    with pytest.raises(ConfigError, match=r"^--set: run.max_minutes: expected a number, got '1:30'$"):
        load_config("default", overrides=["run.max_minutes=1:30"])
    f = tmp_path / "twice.yaml"
    f.write_text("learner:\n  lr: 0.001\n  batch_size: 4\nlearner:\n  samples_per_insert: 4.0\n")
    with pytest.raises(ConfigError, match=r"twice\.yaml: line 4: not valid YAML \(key 'learner' given twice"):
        load_config(str(f))
    f.write_text("run:\n  seed: 010\n")
    assert load_config(str(f)).run.seed == 10


@pytest.mark.parametrize("text, override, message", [
    ("learner:\n", [], "twice.yaml: learner: expected a mapping, got None (an empty section"),
    ("run:\n  seed: 1\n", ["=3"], "--set =3: expected section.key=value"),
])
def test_an_empty_section_or_key_is_worded_as_such(tmp_path, text, override, message):
    f = tmp_path / "twice.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(str(f), overrides=override)
    assert message in str(e.value) and "\n" not in str(e.value), str(e.value)
