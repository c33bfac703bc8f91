"""Object sets: split, broken-mesh detection, caching, determinism, loading in PyBullet.

The module works in its own cache folder (``ADAGRASP_CACHE``), so the random_urdfs scan and the
builds run once per test session and never touch the user's cache.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pybullet
import pytest

import actors.objects as objects
from actors.objects import (
    BASE_SETS,
    ObjectModel,
    ObjectSetError,
    check_object_urdf,
    list_object_sets,
    load_object,
    object_model,
    object_names,
    object_set,
    skipped_objects,
)


@pytest.fixture(scope="module", autouse=True)
def object_cache(tmp_path_factory):
    cache = tmp_path_factory.mktemp("object_cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ADAGRASP_CACHE", str(cache))
        yield cache


@pytest.fixture
def client():
    c = pybullet.connect(pybullet.DIRECT)
    yield c
    pybullet.disconnect(c)


def _one_line(excinfo, *words):
    msg = str(excinfo.value)
    assert "\n" not in msg, msg
    for w in words:
        assert w in msg, msg


def _extents(client: int, body: int) -> np.ndarray:
    lo, hi = (np.array(v) for v in pybullet.getAABB(body, -1, physicsClientId=client))
    for link in range(pybullet.getNumJoints(body, physicsClientId=client)):
        l_lo, l_hi = (np.array(v) for v in pybullet.getAABB(body, link, physicsClientId=client))
        lo, hi = np.minimum(lo, l_lo), np.maximum(hi, l_hi)
    return hi - lo


def test_unknown_set_is_one_line_listing_known_names():
    with pytest.raises(ObjectSetError) as e:
        object_set("trian")
    _one_line(e, "trian", "train", "test", "ycb", "adversarial", "procedural_train")
    with pytest.raises(ObjectSetError) as e:
        object_model("nowhere/001")
    _one_line(e, "nowhere/001")


def test_missing_urdf_is_one_line(tmp_path, client):
    missing = tmp_path / "gone.urdf"
    with pytest.raises(ObjectSetError) as e:
        ObjectModel(name="procedural/x", urdf=missing, scale=1.0, source="procedural", split="train")
    _one_line(e, str(missing), "procedural/x", "not found")
    urdf = tmp_path / "box.urdf"
    urdf.write_text(
        '<robot name="b"><link name="l"><collision><geometry><box size="0.03 0.03 0.03"/></geometry>'
        "</collision></link></robot>"
    )
    model = ObjectModel(name="procedural/x", urdf=urdf, scale=1.0, source="procedural", split="train")
    assert load_object(client, model) >= 0
    urdf.unlink()
    with pytest.raises(ObjectSetError) as e:
        load_object(client, model)
    _one_line(e, str(urdf), "not found")
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot><link")
    model = ObjectModel(name="procedural/y", urdf=broken, scale=1.0, source="procedural", split="train")
    with pytest.raises(ObjectSetError) as e:
        load_object(client, model)
    _one_line(e, str(broken), "PyBullet cannot load")


def test_object_model_fields_are_checked(tmp_path):
    urdf = tmp_path / "a.urdf"
    urdf.write_text("<robot/>")
    with pytest.raises(ObjectSetError) as e:
        ObjectModel(name="x/1", urdf=urdf, scale=0.0, source="procedural", split="train")
    _one_line(e, "scale")
    with pytest.raises(ObjectSetError) as e:
        ObjectModel(name="x/1", urdf=urdf, scale=1.0, source="web", split="train")
    _one_line(e, "source")
    with pytest.raises(ObjectSetError) as e:
        ObjectModel(name="x/1", urdf=urdf, scale=1.0, source="ycb", split="val")
    _one_line(e, "split")


def test_bad_declarations_are_one_line(tmp_path, monkeypatch):
    good = objects._defs_path().read_text()
    bad = tmp_path / "sets.yaml"
    monkeypatch.setattr(objects, "_defs_path", lambda: bad)
    bad.write_text(good.replace("train: [random_urdfs_train, procedural_train]", "train: [random_urdfs_train, ycb]"))
    with pytest.raises(ObjectSetError) as e:
        object_names("train")
    _one_line(e, str(bad), "sets.train", "train-split")
    bad.write_text(good.replace("{name: bunny, mesh: bunny.obj}", "{name: bunny, mesh: no_such_bunny.obj}"))
    with pytest.raises(ObjectSetError) as e:
        object_names("household")
    _one_line(e, str(bad), "household.bunny.mesh", "no_such_bunny.obj")
    bad.write_text("sets: [unclosed")
    with pytest.raises(ObjectSetError) as e:
        object_names("train")
    _one_line(e, str(bad))


def test_broken_meshes_are_detected_with_reasons(tmp_path):
    def urdf(name: str, mesh: str) -> Path:
        path = tmp_path / f"{name}.urdf"
        path.write_text(
            f'<robot name="{name}"><link name="l"><collision><geometry><mesh filename="{mesh}" scale="1 1 1"/>'
            "</geometry></collision></link></robot>"
        )
        return path

    cube = "".join(f"v {x} {y} {z}\n" for x in (0, 0.05) for y in (0, 0.05) for z in (0, 0.05))
    tris = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2)]
    tris += [(3, 4, 8), (3, 8, 7), (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    faces = "".join(f"f {a} {b} {c}\n" for a, b, c in tris)
    (tmp_path / "cube.obj").write_text(cube + faces)
    (tmp_path / "nan.obj").write_text(cube.replace("0.05 0.05 0.05", "nan nan nan") + faces)
    flat = "".join(f"v {x} {y} 0\n" for x in (0, 0.05) for y in (0, 0.05))
    (tmp_path / "flat.obj").write_text(flat + "f 1 2 4\nf 1 4 3\nf 1 3 4\nf 1 4 2\n")
    (tmp_path / "junk.obj").write_text("this is not a mesh\n")
    crit = dict(min_extent=0.002, min_hull_volume=1e-7)
    ok, reason, extents = check_object_urdf(urdf("good", "cube.obj"), **crit)
    assert ok and reason == "" and np.allclose(extents, 0.05)
    assert check_object_urdf(urdf("missing", "absent.obj"), **crit)[:2] == (False, "missing mesh file 'absent.obj'")
    assert "non-finite" in check_object_urdf(urdf("nan", "nan.obj"), **crit)[1]
    assert "degenerate" in check_object_urdf(urdf("flat", "flat.obj"), **crit)[1]
    assert not check_object_urdf(urdf("junk", "junk.obj"), **crit)[0]
    (tmp_path / "bad.urdf").write_text("<robot><link")
    assert "does not parse" in check_object_urdf(tmp_path / "bad.urdf", **crit)[1]


def test_random_urdfs_scan_skips_broken_and_is_cached(object_cache, caplog, monkeypatch):
    with caplog.at_level(logging.INFO, logger="actors.objects"):
        train = object_names("random_urdfs_train")
    skipped = skipped_objects("random_urdfs_train")
    # 168 has NaN vertices, 824 is a 0.5 mm thin sliver (pybullet_data 3.2.x)
    assert "non-finite" in skipped["random_urdfs/168"] and "degenerate" in skipped["random_urdfs/824"]
    assert len(train) + len(skipped) == 900
    assert not set(train) & set(skipped)
    assert all(0 <= int(n.split("/")[1]) <= 899 for n in train)
    test = object_names("random_urdfs_test")
    assert len(test) + len(skipped_objects("random_urdfs_test")) == 100
    assert all(900 <= int(n.split("/")[1]) <= 999 for n in test)
    scans = list((object_cache / "objects").glob("random_urdfs_scan-*.json"))
    assert len(scans) == 1 and json.loads(scans[0].read_text())["objects"]["168"]["ok"] is False

    def no_rescan(*args, **kwargs):
        raise AssertionError("the cached scan was not used")

    monkeypatch.setattr(objects, "check_object_urdf", no_rescan)
    with caplog.at_level(logging.INFO, logger="actors.objects"):
        assert object_names("random_urdfs_train") == train
        object_set("random_urdfs_test")
    assert any("broken ones skipped" in r.getMessage() for r in caplog.records)


def test_train_and_test_never_overlap():
    train, test = object_names("train"), object_names("test")
    assert train and test and not set(train) & set(test)
    assert len(set(train)) == len(train) and len(set(test)) == len(test)
    counts = list_object_sets()
    assert counts["train"] == len(train) and counts["test"] == len(test)
    assert counts["test"] == sum(counts[s] for s in ("random_urdfs_test", "household", "ycb", "adversarial"))
    assert counts["procedural"] == counts["procedural_train"] + counts["adversarial"]
    assert counts["ycb"] > 50 and counts["household"] >= 10 and counts["adversarial"] > 0
    # every base set lies entirely on its side of the split
    for base, split in objects.BASE_SPLITS.items():
        assert set(object_names(base)) <= set(train if split == "train" else test), base


def test_procedural_shapes_are_deterministic(tmp_path, monkeypatch):
    models = [object_model(n) for n in ("procedural/comp_0003", "procedural/adv_plate_01", "procedural/adv_cone_01")]
    texts = [m.urdf.read_text() for m in models]
    monkeypatch.setenv("ADAGRASP_CACHE", str(tmp_path))
    again = [object_model(m.name) for m in models]
    assert [m.urdf.read_text() for m in again] == texts
    assert all(str(m.urdf).startswith(str(tmp_path)) for m in again)
    assert (again[2].urdf.parent / "shape.obj").is_file()  # cones are meshes
    assert models[0].urdf.read_text() != object_model("procedural/comp_0004").urdf.read_text()


def test_scaling_rule():
    scaling = {"longest_extent": [0.03, 0.10], "max_shortest_extent": 0.05}
    assert objects._scale([0.2, 0.04, 0.02], scaling) == pytest.approx(0.5)
    assert objects._scale([0.06, 0.04, 0.02], scaling) == pytest.approx(1.0)
    assert objects._scale([0.015, 0.01, 0.01], scaling) == pytest.approx(2.0)
    assert objects._scale([0.09, 0.09, 0.09], scaling) == pytest.approx(0.05 / 0.09)


# PyBullet adds a collision margin around meshes to the bounding box it reports.
_MARGIN = 0.008


def _check_loaded(client, model: ObjectModel) -> None:
    body = load_object(client, model, position=(0.0, 0.0, 0.3))
    ext = _extents(client, body)
    pybullet.removeBody(body, physicsClientId=client)
    assert np.all(np.isfinite(ext)) and ext.min() > 0, model.name
    if model.name.startswith("procedural/adv_"):
        assert model.scale == 1.0 and ext.max() <= 0.10 + 2 * _MARGIN, model.name
    elif not model.name.startswith("procedural/"):  # compounds of rotated primitives get loose boxes
        assert 0.03 - _MARGIN <= ext.max() <= 0.10 + _MARGIN, (model.name, ext)
        assert ext.min() <= 0.05 + _MARGIN, (model.name, ext)


def test_load_a_sample_of_every_set(client):
    rng = np.random.default_rng(0)
    for base in BASE_SETS:
        names = object_names(base)
        for n in rng.choice(names, size=min(3, len(names)), replace=False):
            model = object_model(str(n))
            assert model.name == n and model.split == objects.BASE_SPLITS[base]
            _check_loaded(client, model)


def test_object_models_are_in_the_cache(object_cache):
    model = object_model("household/torus")
    assert str(model.urdf).startswith(str(object_cache))
    assert (model.urdf.parent / "collision.obj").is_file() and (model.urdf.parent / "meta.json").is_file()
    assert not any(p.name.endswith(".tmp") for p in model.urdf.parent.parent.iterdir())
    assert object_model("random_urdfs/017").urdf.name == "017.urdf"


@pytest.mark.slow
def test_load_every_object_of_every_set(client):
    total = 0
    for base in BASE_SETS:
        models = object_set(base)
        assert len(models) == len(object_names(base)) == list_object_sets()[base]
        for model in models:
            _check_loaded(client, model)
        total += len(models)
    assert len(object_set("train")) + len(object_set("test")) == total
    assert not skipped_objects("ycb") and not skipped_objects("household")
