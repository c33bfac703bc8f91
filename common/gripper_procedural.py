"""Procedural gripper families: URDF + spec YAML generated from a seed, then loaded like any gripper.

Families (parameter ranges in assets/grippers/procedural/families.yaml):

- ``parallel_jaw``: two prismatic fingers (mimic or independent closing), pad shapes flat /
  rounded / padded / tapered.
- ``revolute``: two fingers on hinges at the palm.
- ``three_finger``: three hinged fingers, opposed 2 + 1 or 120 degrees apart, each finger closing
  on its own motor towards the common target (adaptive), with an optional palm spread joint
  coupled to the drive.
- ``underactuated``: two or three fingers of two links each; the distal link follows the
  proximal motor's *target* (it keeps curling when the proximal link is blocked).

Usage::

    g = generate("parallel_jaw", 7)     # deterministic from (family, seed)
    g.spec.name                          # "parallel_jaw-7"
    g.spec.description                   # the parameters, e.g. "parallel_jaw L=62mm W=18mm ..."

Every generated gripper passes :func:`common.gripper.check_kinematics` or is rejected with the
reason (:class:`GripperSpecError`); ``grippers check`` adds the physics lift tests.
Files go under the user cache (``<cache>/grippers/procedural``), never the package.
"""

from __future__ import annotations

import hashlib
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np
import yaml

from common.files import atomic_write_text
from common.gripper import GripperSpec, assets_dir, cache_root, check_kinematics, load_spec

FAMILY_NAMES = ("parallel_jaw", "revolute", "three_finger", "underactuated")
"""Procedural family names; a procedural gripper is called ``<family>-<seed>``."""
PALM_MASS = 0.3
"""kg, palm of every procedural gripper."""
FINGER_DENSITY = 1200.0
"""kg / m^3 of finger links (plastic-like)."""


@dataclass(frozen=True)
class Generated:
    """A generated gripper: its spec and the sampled parameters."""

    spec: GripperSpec
    params: dict


def family_ranges() -> dict:
    """Parameter ranges per family from assets/grippers/procedural/families.yaml."""
    return yaml.safe_load((assets_dir() / "procedural" / "families.yaml").read_text())


CATALOG_SECTIONS = ("train", "pool")
"""Sections of assets/grippers/catalog.yaml: ``train``, the 32 grippers ``grippers list`` shows and
training uses by default; ``pool``, every seed of 0-127 per family that passed
``grippers generate``'s physics checks (``grippers.train_grippers=pool``)."""


def catalog_names(section: str = "train") -> list[str]:
    """Procedural gripper names of one section of the catalogue (assets/grippers/catalog.yaml)."""
    if section not in CATALOG_SECTIONS:
        raise ValueError(f"catalog section: expected one of {list(CATALOG_SECTIONS)}, got {section!r}")
    path = assets_dir() / "catalog.yaml"
    data = yaml.safe_load(path.read_text())
    if section not in data:
        raise ValueError(f"{path}: no section {section!r}")
    for fam in data[section]:
        if fam not in FAMILY_NAMES:
            raise ValueError(f"{path}: {section}.{fam}: unknown procedural family (known: {', '.join(FAMILY_NAMES)})")
    return [f"{fam}-{int(seed)}" for fam, seeds in data[section].items() for seed in seeds]


def sample_params(family: str, seed: int) -> dict:
    """Parameters of ``<family>-<seed>``, deterministic (NumPy SeedSequence of family index and seed)."""
    if family not in FAMILY_NAMES:
        raise ValueError(f"unknown procedural family {family!r} (known: {', '.join(FAMILY_NAMES)})")
    rng = np.random.default_rng(np.random.SeedSequence([FAMILY_NAMES.index(family), int(seed)]))
    out: dict = {}
    for key, rng_spec in family_ranges()[family].items():
        if len(rng_spec) == 2 and all(isinstance(v, float) for v in rng_spec):
            out[key] = round(float(rng.uniform(rng_spec[0], rng_spec[1])), 5)
        else:
            out[key] = rng_spec[int(rng.integers(len(rng_spec)))]
    return out


# --------------------------------------------------------------------------------------
# URDF building blocks (primitives only, so visual == collision and the encoder is exact)
# --------------------------------------------------------------------------------------


def _f(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.ravel(v))


class _Builder:
    def __init__(self, name: str) -> None:
        self.robot = ET.Element("robot", {"name": name})

    def link(self, name: str, shapes: list[tuple[str, tuple, tuple, tuple]], mass: float) -> None:
        """shapes: (kind, size, xyz, rpy) with kind box (size = extents) or cylinder (radius, length)."""
        link = ET.SubElement(self.robot, "link", {"name": name})
        vol = [(np.prod(s) if k == "box" else math.pi * s[0] ** 2 * s[1]) for k, s, _, _ in shapes]
        com = np.sum([v * np.asarray(x) for v, (_, _, x, _) in zip(vol, shapes)], axis=0) / max(sum(vol), 1e-12)
        ext = np.max([np.abs(np.asarray(x)) + (np.asarray(s) / 2 if k == "box" else s[0]) for k, s, x, _ in shapes], axis=0)
        ext = np.maximum(ext, 0.005)
        inertial = ET.SubElement(link, "inertial")
        ET.SubElement(inertial, "origin", {"xyz": _f(com), "rpy": "0 0 0"})
        ET.SubElement(inertial, "mass", {"value": f"{mass:.6g}"})
        i = mass / 3.0 * np.array([ext[1] ** 2 + ext[2] ** 2, ext[0] ** 2 + ext[2] ** 2, ext[0] ** 2 + ext[1] ** 2])
        ET.SubElement(inertial, "inertia", {"ixx": f"{i[0]:.6g}", "iyy": f"{i[1]:.6g}", "izz": f"{i[2]:.6g}",
                                            "ixy": "0", "ixz": "0", "iyz": "0"})
        for tag in ("visual", "collision"):
            for kind, size, xyz, rpy in shapes:
                el = ET.SubElement(link, tag)
                ET.SubElement(el, "origin", {"xyz": _f(xyz), "rpy": _f(rpy)})
                g = ET.SubElement(el, "geometry")
                if kind == "box":
                    ET.SubElement(g, "box", {"size": _f(size)})
                else:
                    ET.SubElement(g, "cylinder", {"radius": f"{size[0]:.6g}", "length": f"{size[1]:.6g}"})
                if tag == "visual":
                    mat = ET.SubElement(el, "material", {"name": "grey"})
                    ET.SubElement(mat, "color", {"rgba": "0.6 0.6 0.65 1"})

    def joint(self, name: str, jtype: str, parent: str, child: str, xyz=(0, 0, 0), rpy=(0, 0, 0),
              axis=(1, 0, 0), limits: tuple[float, float] | None = None, effort: float = 10.0,
              velocity: float = 1.0, mimic: tuple[str, float, float] | None = None) -> None:
        j = ET.SubElement(self.robot, "joint", {"name": name, "type": jtype})
        ET.SubElement(j, "parent", {"link": parent})
        ET.SubElement(j, "child", {"link": child})
        ET.SubElement(j, "origin", {"xyz": _f(xyz), "rpy": _f(rpy)})
        if jtype != "fixed":
            ET.SubElement(j, "axis", {"xyz": _f(axis)})
            lo, hi = limits
            ET.SubElement(j, "limit", {"lower": f"{lo:.6g}", "upper": f"{hi:.6g}", "effort": f"{effort:.6g}",
                                       "velocity": f"{velocity:.6g}"})
            ET.SubElement(j, "dynamics", {"damping": "0.0", "friction": "0.0"})
        if mimic is not None:
            ET.SubElement(j, "mimic", {"joint": mimic[0], "multiplier": f"{mimic[1]:.6g}", "offset": f"{mimic[2]:.6g}"})


def _finger_shapes(p: dict, length: float, sign: float) -> list[tuple[str, tuple, tuple, tuple]]:
    """A straight finger hanging from z = 0 to -length, inner face at x = 0, body towards ``sign`` * x."""
    t, w = p["finger_thickness"], p["finger_width"]
    shape = p.get("pad_shape", "flat")
    cx = sign * t / 2
    if shape == "rounded":
        r = t / 2
        return [("box", (t, w, length - r), (cx, 0, -(length - r) / 2), (0, 0, 0)),
                ("cylinder", (r, w), (cx, 0, -(length - r)), (math.pi / 2, 0, 0))]
    if shape == "tapered":
        upper = 0.6 * length
        tip_w = w * p["taper"]
        return [("box", (t, w, upper), (cx, 0, -upper / 2), (0, 0, 0)),
                ("box", (t, tip_w, length - upper), (cx, 0, -(upper + length) / 2), (0, 0, 0))]
    if shape == "padded":
        pt = p["pad_thickness"]
        pl = min(0.5 * length, 0.03)
        return [("box", (t, w, length), (cx, 0, -length / 2), (0, 0, 0)),
                ("box", (pt, w, pl), (-sign * pt / 2, 0, -(length - pl / 2)), (0, 0, 0))]
    return [("box", (t, w, length), (cx, 0, -length / 2), (0, 0, 0))]


def _finger_mass(shapes) -> float:
    vol = sum((np.prod(s) if k == "box" else math.pi * s[0] ** 2 * s[1]) for k, s, _, _ in shapes)
    return max(float(vol * FINGER_DENSITY), 0.01)


def _palm(b: _Builder, p: dict, half_x: float, half_y: float) -> None:
    h = p["palm_height"]
    b.link("palm", [("box", (2 * half_x, 2 * half_y, h), (0, 0, h / 2), (0, 0, 0))], PALM_MASS)


def _tcp_depth(length: float) -> float:
    """TCP depth below the palm: the pad centre, at most 2 cm above the fingertips."""
    return length - min(0.02, length / 3.0)


def _parallel_jaw(p: dict, name: str) -> tuple[ET.Element, dict]:
    b = _Builder(name)
    length, t, w, a = p["finger_length"], p["finger_thickness"], p["finger_width"], p["aperture"]
    _palm(b, p, a / 2 + t + 0.005, w / 2 + 0.005)
    pad = p["pad_thickness"] if p["pad_shape"] == "padded" else 0.0
    closed, opened = -pad, a / 2
    for side, sign in (("left", -1.0), ("right", 1.0)):
        shapes = _finger_shapes(p, length, sign)
        b.link(f"finger_{side}", shapes, _finger_mass(shapes))
        mimic = ("finger_left_joint", 1.0, 0.0) if side == "right" else None
        b.joint(f"finger_{side}_joint", "prismatic", "palm", f"finger_{side}", axis=(sign, 0, 0),
                limits=(closed, opened), effort=p["force"], velocity=p["max_velocity"], mimic=mimic)
    spec = {
        "family": "2-finger",
        "drive_joints": [{"name": "finger_left_joint", "open": opened, "closed": closed}],
        "couplings": ([{"joint": "finger_right_joint", "driver": "finger_left_joint", "mode": "target"}]
                      if p["closing_law"] == "independent" else []),
        "tcp": {"position": [0.0, 0.0, -_tcp_depth(length)], "approach": [0, 0, -1], "closing": [1, 0, 0]},
    }
    return b.robot, spec


def _hinge_angles(length: float, hinge: float, aperture: float) -> tuple[float, float]:
    """Closed (tips meet at the centre line) and open (tips ``aperture`` apart) hinge angles, rad."""
    closed = math.asin(min(hinge / length, 0.99))
    opened = -math.asin(min(max(aperture / 2 - hinge, 0.0) / length, 0.99))
    return closed, opened


def _revolute(p: dict, name: str) -> tuple[ET.Element, dict]:
    b = _Builder(name)
    length, h, a = p["finger_length"], p["hinge_offset"], p["aperture"]
    _palm(b, p, h + p["finger_thickness"] + 0.01, p["finger_width"] / 2 + 0.005)
    closed, opened = _hinge_angles(length, h, a)
    for side, sign in (("left", -1.0), ("right", 1.0)):
        shapes = _finger_shapes(p, length, sign)
        b.link(f"finger_{side}", shapes, _finger_mass(shapes))
        mimic = ("finger_left_joint", 1.0, 0.0) if side == "right" else None
        b.joint(f"finger_{side}_joint", "revolute", "palm", f"finger_{side}", xyz=(sign * h, 0, 0),
                axis=(0, sign, 0), limits=(opened, closed), effort=p["force"], velocity=p["max_velocity"], mimic=mimic)
    spec = {
        "family": "2-finger",
        "drive_joints": [{"name": "finger_left_joint", "open": opened, "closed": closed}],
        "couplings": ([{"joint": "finger_right_joint", "driver": "finger_left_joint", "mode": "target"}]
                      if p["closing_law"] == "independent" else []),
        "tcp": {"position": [0.0, 0.0, -_tcp_depth(length)], "approach": [0, 0, -1], "closing": [1, 0, 0]},
    }
    return b.robot, spec


def _mounts(layout: str, h: float, pair: float) -> list[tuple[float, float, float]]:
    """(x, y, yaw) of each finger mount; each mount's +x points to where its finger closes."""
    if layout == "radial":
        return [(h * math.cos(a), h * math.sin(a), a + math.pi) for a in (0.0, 2 * math.pi / 3, 4 * math.pi / 3)]
    if layout == "opposed":
        return [(h, 0.0, math.pi), (-h, pair, 0.0), (-h, -pair, 0.0)]
    return [(-h, 0.0, 0.0), (h, 0.0, math.pi)]


def _three_finger(p: dict, name: str) -> tuple[ET.Element, dict]:
    b = _Builder(name)
    length, h, a = p["finger_length"], p["hinge_offset"], p["aperture"]
    half = h + p["finger_thickness"] + 0.01
    _palm(b, p, half, max(half, p["pair_offset"] + p["finger_width"] / 2 + 0.005))
    closed, opened = _hinge_angles(length, h, a)
    spread = p["spread"] == "coupled"
    k = (p["spread_open"] - p["spread_closed"]) / (opened - closed)
    off = p["spread_closed"] - k * closed
    for i, (x, y, yaw) in enumerate(_mounts(p["layout"], h, p["pair_offset"])):
        parent = "palm"
        if spread and i > 0:
            sgn = 1.0 if i == 1 else -1.0
            b.link(f"mount_{i}", [("cylinder", (0.006, 0.004), (0, 0, -0.002), (0, 0, 0))], 0.01)
            b.joint(f"spread_{i}_joint", "revolute", "palm", f"mount_{i}", xyz=(x, y, 0), rpy=(0, 0, yaw), axis=(0, 0, 1),
                    limits=(-0.6, 0.6), effort=p["force"], velocity=p["max_velocity"],
                    mimic=("finger_0_joint", sgn * k, sgn * off))
            parent, xyz, rpy = f"mount_{i}", (0, 0, 0), (0, 0, 0)
        else:
            xyz, rpy = (x, y, 0), (0, 0, yaw)
        shapes = _finger_shapes(p, length, -1.0)
        b.link(f"finger_{i}", shapes, _finger_mass(shapes))
        b.joint(f"finger_{i}_joint", "revolute", parent, f"finger_{i}", xyz=xyz, rpy=rpy, axis=(0, -1, 0),
                limits=(opened, closed), effort=p["force"], velocity=p["max_velocity"],
                mimic=("finger_0_joint", 1.0, 0.0) if i > 0 else None)
    spec = {
        "family": "3-finger",
        "drive_joints": [{"name": "finger_0_joint", "open": opened, "closed": closed}],
        "couplings": [{"joint": f"finger_{i}_joint", "driver": "finger_0_joint", "mode": "target"} for i in (1, 2)],
        "tcp": {"position": [0.0, 0.0, -_tcp_depth(length)], "approach": [0, 0, -1], "closing": [1, 0, 0]},
    }
    return b.robot, spec


def _underactuated(p: dict, name: str) -> tuple[ET.Element, dict]:
    b = _Builder(name)
    l1, l2, h, a, r = p["proximal_length"], p["distal_length"], p["hinge_offset"], p["aperture"], p["curl_ratio"]
    n = int(p["fingers"])
    half = h + p["finger_thickness"] + 0.01
    _palm(b, p, half, half if n == 3 else p["finger_width"] / 2 + 0.005)
    _, opened = _hinge_angles(l1 + l2, h, a)

    def tip_x(phi: float) -> float:
        return l1 * math.sin(phi) + l2 * math.sin(phi + r * (phi - opened))

    lo, hi = opened, math.pi / 2
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if tip_x(mid) < h else (lo, mid)
    closed = (lo + hi) / 2
    couplings = []
    fp = dict(p, pad_shape="flat")
    for i, (x, y, yaw) in enumerate(_mounts("radial" if n == 3 else "pair", h, 0.0)):
        prox = _finger_shapes(fp, l1, -1.0)
        dist = _finger_shapes(dict(fp, pad_shape="rounded"), l2, -1.0)
        b.link(f"proximal_{i}", prox, _finger_mass(prox))
        b.link(f"distal_{i}", dist, _finger_mass(dist))
        b.joint(f"proximal_{i}_joint", "revolute", "palm", f"proximal_{i}", xyz=(x, y, 0), rpy=(0, 0, yaw),
                axis=(0, -1, 0), limits=(opened, closed), effort=p["force"], velocity=p["max_velocity"],
                mimic=("proximal_0_joint", 1.0, 0.0) if i > 0 else None)
        dlim = (0.0, r * (closed - opened) + 1e-3)
        b.joint(f"distal_{i}_joint", "revolute", f"proximal_{i}", f"distal_{i}", xyz=(0, 0, -l1), axis=(0, -1, 0),
                limits=dlim, effort=p["force"] * p["distal_force_ratio"], velocity=p["max_velocity"])
        couplings.append({"joint": f"distal_{i}_joint", "driver": "proximal_0_joint", "multiplier": r,
                          "offset": -r * opened, "mode": "target"})
    spec = {
        "family": "3-finger" if n == 3 else "2-finger",
        "drive_joints": [{"name": "proximal_0_joint", "open": opened, "closed": closed}],
        "couplings": couplings,
        "coupling_force": p["force"] * p["distal_force_ratio"],
        "tcp": {"position": [0.0, 0.0, -_tcp_depth(l1 + l2)], "approach": [0, 0, -1], "closing": [1, 0, 0]},
    }
    return b.robot, spec


_BUILDERS = {"parallel_jaw": _parallel_jaw, "revolute": _revolute, "three_finger": _three_finger,
             "underactuated": _underactuated}


def describe(family: str, p: dict) -> str:
    """One line naming a procedural gripper by its parameters (lengths in mm)."""
    mm = {k: round(v * 1000) for k, v in p.items() if isinstance(v, float) and k not in ("force", "max_velocity")
          and not k.startswith(("spread_", "taper", "curl", "distal_force"))}
    bits = [family] + [f"{k}={v}mm" for k, v in mm.items()]
    bits += [f"{k}={v}" for k, v in p.items() if isinstance(v, (str, int)) and not isinstance(v, bool)]
    return " ".join(bits)


def generate(family: str, seed: int) -> Generated:
    """Build (or reuse from the cache) ``<family>-<seed>`` and check its kinematics.

    Raises GripperSpecError naming the generated spec file and the reason when the gripper is rejected.
    """
    params = sample_params(family, seed)
    name = f"{family}-{seed}"
    robot, spec_fields = _BUILDERS[family](params, name)
    ET.indent(robot)
    urdf_text = ET.tostring(robot, encoding="unicode")
    digest = hashlib.sha1(urdf_text.encode()).hexdigest()[:12]
    folder = cache_root() / "grippers" / "procedural" / f"{name}-{digest}"
    spec_path = folder / f"{name}.yaml"
    if not spec_path.is_file():
        atomic_write_text(folder / "gripper.urdf", urdf_text)
        data = {
            "name": name,
            "split": "train",
            "description": describe(family, params),
            "license": "generated by the project (MIT)",
            "source": "gripper.urdf",
            "cut_link": "palm",
            "friction": 1.0,
            "force": params["force"],
            "max_velocity": params["max_velocity"],
            "params": dict(params, generator=family, seed=int(seed)),
            **spec_fields,
        }
        atomic_write_text(spec_path, yaml.safe_dump(data, sort_keys=False))
    spec = load_spec(spec_path)
    marker = folder / "kinematics.ok"
    if not marker.is_file():
        check_kinematics(spec)
        atomic_write_text(marker, "passed check_kinematics\n")
    return Generated(spec, params)

