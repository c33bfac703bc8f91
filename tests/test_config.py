"""Config dataclasses: every field documented, every shipped YAML loads, bad keys fail in one line."""

import ast
import dataclasses
from pathlib import Path

import pytest

import common.config as config_module
from common.config import Config, ConfigError, from_dict, load_config, to_dict

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
