"""Gripper specs: any URDF / SDF / MJCF hand plus a small YAML spec, never Python of its own.

A spec names the model file, the link to cut at, the drive joints with their open and
closed values, couplings (URDF ``<mimic>`` is read automatically), the tool-centre point
(TCP) and approach axis, friction and force. ``opening`` in [0, 1] maps linearly from the
closed (0) to the open (1) joint values. A global ``scale`` multiplies the whole hand.

TCP frame (used everywhere a gripper pose is given): origin at the grasp centre between the
finger pads; z = -approach (the fingers point along -z), x = the closing direction of the
first finger. ``T_world_tcp`` with identity rotation is a top-down grasp closing along world x.

Usage::

    spec = get_gripper("wsg_50")                 # registered name
    spec = get_gripper("parallel_jaw-3")         # procedural family + seed
    spec = get_gripper("path/to/my_hand.yaml")   # any spec file
    for s in list_grippers(split="test"): ...
    mesh = posed_meshes(spec, scale=1.0, opening=0.5)   # trimesh in the TCP frame, metres
    model = GripperModel(spec, scale=1.1)               # FK + collision parts, reused by the encoder
"""

from __future__ import annotations

import copy
import hashlib
import importlib.resources
import importlib.util
import io
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from common.files import atomic_write_text
from common.geometry import Transform
from common.gripper_formats import (
    MOVABLE_TYPES,
    FormatError,
    extract_subtree,
    freeze_joints,
    inertia_from_collision,
    joint_table,
    links_and_joints,
    load_robot_xml,
    read_mimics,
    resolve_meshes,
    scale_robot,
)

FAMILIES = ("2-finger", "3-finger", "multi")
"""Gripper families by number of fingers."""
SPLITS = ("train", "test")
"""Data splits; every real gripper is in the test split."""
COUPLING_MODES = ("mimic", "measured", "target")
"""How a coupled joint follows its driver in PyBullet. mimic: a JOINT_GEAR constraint (rigid,
two-way linkage); measured: a per-step position target at the driver's measured position;
target: a per-step position target at the driver's commanded target (adaptive fingers)."""
FORMAT_VERSION = "9"
"""Bumped whenever the processed-URDF layout changes, so cached files are rebuilt."""
CACHE_ENV = "ADAGRASP_CACHE"
"""Environment variable that overrides the user cache directory."""
MIN_APERTURE_CHANGE = 0.005
"""Metres (at scale 1): the aperture must change at least this much from closed to open."""
CLOSED_APERTURE = 0.003
"""Metres (at scale 1): apertures below this count as closed (tips touching or crossing) in the monotonic check."""


class GripperSpecError(ValueError):
    """A gripper spec or its model is wrong; the message is one line naming the file and the field."""


def cache_root() -> Path:
    """User cache directory of the project (``$ADAGRASP_CACHE`` overrides it)."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("adagrasp-scale"))


# --------------------------------------------------------------------------------------
# spec records
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DriveJoint:
    """A motor-driven joint: value at opening 0 (closed) and 1 (open), at scale 1 (m or rad)."""

    name: str
    open: float
    closed: float
    prismatic: bool


@dataclass(frozen=True)
class Coupling:
    """``joint = multiplier * driver + offset`` at scale 1 (m or rad; the multiplier in the joint's
    unit per the driver's)."""

    joint: str
    driver: str
    multiplier: float
    offset: float
    mode: str
    prismatic: bool
    """The joint slides (its positions scale with the gripper)."""
    from_mimic: bool
    """Read from the file's ``<mimic>`` (not declared by the spec)."""
    driver_prismatic: bool
    """The driver slides."""

    def ratio(self, scale: float) -> float:
        """d joint / d driver on a gripper at ``scale``: a slider following a hinge moves ``scale``
        times as far per radian, a hinge following a slider turns as far per scaled metre."""
        return self.multiplier * (scale if self.prismatic else 1.0) / (scale if self.driver_prismatic else 1.0)

    def value(self, q_driver: float, scale: float) -> float:
        """The joint's position (m or rad) with the driver at ``q_driver`` (m or rad) at ``scale``."""
        return self.ratio(scale) * q_driver + self.offset * (scale if self.prismatic else 1.0)


@dataclass(frozen=True)
class GripperSpec:
    """A gripper: processed URDF (scale 1) plus how to drive it. All vectors in the cut (base) link frame."""

    name: str
    """Unique name (registered name or ``<family>-<seed>`` for procedural grippers)."""
    family: str
    """2-finger | 3-finger | multi."""
    split: str
    """train | test."""
    urdf: Path
    """Processed URDF at scale 1 (cut, frozen, absolute mesh paths) in the user cache."""
    spec_path: Path
    """The YAML spec file."""
    source: Path
    """The original model file (URDF, SDF or MJCF)."""
    cut_link: str
    """Root link of the hand (the base the virtual arm carries)."""
    drive_joints: tuple[DriveJoint, ...]
    """Motor-driven joints."""
    couplings: tuple[Coupling, ...]
    """Joints that follow a driver (from ``<mimic>`` and from the spec)."""
    finger_links: tuple[str, ...]
    """Links moved by drive or coupled joints."""
    tcp_position: tuple[float, float, float]
    """TCP position in the base frame, metres at scale 1."""
    approach_axis: tuple[float, float, float]
    """Unit direction the fingers point (the grasp approach direction), base frame."""
    closing_axis: tuple[float, float, float]
    """Unit direction along which the first finger closes, base frame (x of the TCP frame)."""
    tcp_estimated: bool
    """True when the spec left the TCP out and it was estimated from the finger geometry."""
    friction: float
    """Lateral friction coefficient of every gripper link."""
    force: float
    """Maximum force (N, prismatic) or torque (N m, revolute) of each drive motor."""
    coupling_force: float
    """Maximum force / torque of each coupled joint's motor."""
    max_velocity: float
    """Maximum joint speed of the drive motors (m/s or rad/s at scale 1)."""
    base_force: float
    """Maximum force (N; N m on yaw) of the virtual-arm motors that move the base when no force is given."""
    aperture_band: float
    """Metres at scale 1: finger geometry up to this far above the TCP counts for the aperture."""
    description: str = ""
    """One line about the gripper (procedural grippers list their parameters)."""
    license: str = ""
    """Licence of the model and meshes."""
    params: dict = field(default_factory=dict, compare=False, hash=False)
    """Generator parameters of a procedural gripper (empty for real ones)."""

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Every movable joint: drives first, then coupled joints."""
        return tuple(d.name for d in self.drive_joints) + tuple(c.joint for c in self.couplings)

    def T_base_tcp(self, scale: float = 1.0) -> Transform:
        """TCP frame in the base (cut link) frame at ``scale``."""
        z = -np.asarray(self.approach_axis, dtype=np.float64)
        x = np.asarray(self.closing_axis, dtype=np.float64)
        x = x - z * float(x @ z)
        x /= np.linalg.norm(x)
        return Transform(np.stack([x, np.cross(z, x), z], axis=1), np.asarray(self.tcp_position) * scale)


def joint_positions(spec: GripperSpec, opening: float, scale: float = 1.0) -> dict[str, float]:
    """Joint values (m or rad) of every movable joint at ``opening`` in [0, 1] and ``scale``."""
    if not 0.0 <= opening <= 1.0:
        raise ValueError(f"opening must lie in [0, 1], got {opening}")
    q = {}
    for d in spec.drive_joints:
        q[d.name] = (d.closed + opening * (d.open - d.closed)) * (scale if d.prismatic else 1.0)
    pending = list(spec.couplings)
    while pending:
        rest = []
        for c in pending:
            if c.driver in q:
                q[c.joint] = c.value(q[c.driver], scale)
            else:
                rest.append(c)
        if len(rest) == len(pending):
            raise GripperSpecError(f"{spec.spec_path}: couplings: cycle or missing driver among {[c.joint for c in rest]}")
        pending = rest
    return q


# --------------------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------------------

_SPEC_KEYS = {
    "name", "family", "split", "description", "license", "source", "cut_link", "drive_joints", "couplings",
    "hold_joints", "tcp", "friction", "force", "coupling_force", "max_velocity", "base_force", "aperture_band",
    "params", "base_mass", "inertia",
}


def _package_dir(package: str, where: str) -> Path:
    spec = importlib.util.find_spec(package)
    if spec is None:
        raise GripperSpecError(f"{where}: package {package!r} is not installed (pip install it)")
    if spec.submodule_search_locations:
        return Path(list(spec.submodule_search_locations)[0])
    return Path(spec.origin).parent


def _resolve_source(raw, spec_path: Path) -> Path:
    where = f"{spec_path}: source"
    if isinstance(raw, str):
        p = Path(raw)
        p = p if p.is_absolute() else spec_path.parent / p
    elif isinstance(raw, dict) and set(raw) <= {"package", "path"} and "path" in raw:
        base = _package_dir(str(raw["package"]), where) if "package" in raw else spec_path.parent
        p = base / str(raw["path"])
    else:
        raise GripperSpecError(f"{where}: expected a path or {{package: NAME, path: PATH}}, got {raw!r}")
    if not p.is_file():
        raise GripperSpecError(f"{where}: model file not found: {p}")
    return p.resolve()


def _num(data: dict, key: str, where: str, default: float | None = None) -> float:
    """A finite number ``data[key]``; ``where`` is "file: field" and the key is appended."""
    if key not in data:
        if default is None:
            raise GripperSpecError(f"{where}.{key}: missing")
        return float(default)
    v = data[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise GripperSpecError(f"{where}.{key}: expected a number, got {v!r}")
    return float(v)


def _vec3(v, where: str, unit: bool) -> tuple[float, float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 3 or not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in v
    ):
        raise GripperSpecError(f"{where}: expected 3 numbers, got {v!r}")
    a = np.asarray(v, dtype=np.float64)
    if unit:
        n = np.linalg.norm(a)
        if n < 1e-9:
            raise GripperSpecError(f"{where}: must not be the zero vector")
        a = a / n
    return (float(a[0]), float(a[1]), float(a[2]))


def _set_base_mass(robot: ET.Element, cut_link: str, mass: float) -> None:
    """Give the root link ``mass`` kg and the inertia of a 6 cm cube of that mass (at its old centre of mass)."""
    link = next(l for l in robot.findall("link") if l.get("name") == cut_link)
    inertial = link.find("inertial")
    if inertial is None:
        inertial = ET.SubElement(link, "inertial")
    for tag in ("mass", "inertia"):
        for el in inertial.findall(tag):
            inertial.remove(el)
    i = mass * 0.06**2 / 6
    ET.SubElement(inertial, "mass", {"value": f"{mass:.6g}"})
    ET.SubElement(inertial, "inertia", {"ixx": f"{i:.6g}", "iyy": f"{i:.6g}", "izz": f"{i:.6g}",
                                        "ixy": "0", "ixz": "0", "iyz": "0"})


def _processed_urdf(spec_path: Path, text: str, source: Path, cut_link: str, keep: set[str], hold: dict,
                    base_mass: float | None, inertia: str = "file") -> Path:
    """Cut, freeze and resolve the source model once; cached by content."""
    st = source.stat()
    key = hashlib.sha1(
        f"{FORMAT_VERSION}|{text}|{source}|{st.st_mtime_ns}|{st.st_size}".encode()
    ).hexdigest()[:16]
    out = cache_root() / "grippers" / "urdf" / f"{spec_path.stem}-{key}" / "gripper.urdf"
    if out.is_file():
        return out
    try:
        robot = load_robot_xml(source)
        robot = extract_subtree(robot, cut_link)
    except FormatError as e:
        field_name = "cut_link" if "does not exist" in str(e) and "link" in str(e) and "joint" not in str(e) else "source"
        raise GripperSpecError(f"{spec_path}: {field_name}: {source.name}: {e}") from None
    try:
        robot = freeze_joints(robot, keep, hold)
        # the spec's couplings (which took in every <mimic>) move the joints; a <mimic> left in the
        # file would make the kinematic model (yourdfpy honours it) disagree with PyBullet (which does not)
        for joint in robot.findall("joint"):
            for mimic in joint.findall("mimic"):
                joint.remove(mimic)
        if base_mass is not None:
            _set_base_mass(robot, cut_link, base_mass)
        resolve_meshes(robot, source, out.parent / "meshes")
        if inertia == "geometry":
            inertia_from_collision(robot)
        links_and_joints(robot)
    except FormatError as e:
        raise GripperSpecError(f"{spec_path}: source: {source.name}: {e}") from None
    ET.indent(robot)
    atomic_write_text(out, ET.tostring(robot, encoding="unicode"))
    return out


def _moving_couplings(couplings: list[Coupling], drive_names: set[str]) -> tuple[list[Coupling], list[Coupling]]:
    """Split ``couplings`` (order kept) into those that move (their driver is a drive joint or,
    along a chain, follows one) and those that follow a frozen joint."""
    moving = set(drive_names)
    while True:
        more = {c.joint for c in couplings if c.driver in moving} - moving
        if not more:
            return [c for c in couplings if c.joint in moving], [c for c in couplings if c.joint not in moving]
        moving |= more


def _on_cycle(joint: str, follows: dict[str, str]) -> bool:
    """Whether following drivers (``follows``: joint -> driver) from ``joint`` comes back to it."""
    seen, j = set(), follows.get(joint)
    while j is not None and j not in seen:
        if j == joint:
            return True
        seen.add(j)
        j = follows.get(j)
    return False


def _descendant_links(robot_joints: dict[str, dict], joints: set[str]) -> tuple[str, ...]:
    children: dict[str, list[str]] = {}
    for info in robot_joints.values():
        children.setdefault(info["parent"], []).append(info["child"])
    out: list[str] = []
    stack = [robot_joints[j]["child"] for j in joints]
    while stack:
        link = stack.pop()
        if link not in out:
            out.append(link)
            stack.extend(children.get(link, []))
    return tuple(sorted(out))


def load_spec(path: str | Path) -> GripperSpec:
    """Read and validate a gripper spec YAML; build (or reuse) its processed URDF.

    Raises GripperSpecError with one line naming the file and the field.
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise GripperSpecError(f"{path}: spec file not found")
    text = path.read_text()
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise GripperSpecError(f"{path}:{where}: not valid YAML ({getattr(e, 'problem', e)})") from None
    if not isinstance(data, dict):
        raise GripperSpecError(f"{path}: expected a mapping at the top level")
    unknown = set(data) - _SPEC_KEYS
    if unknown:
        raise GripperSpecError(f"{path}: {sorted(unknown)[0]}: unknown field (known: {', '.join(sorted(_SPEC_KEYS))})")
    for key in ("name", "family", "split", "source", "cut_link", "drive_joints"):
        if key not in data:
            raise GripperSpecError(f"{path}: {key}: missing")
    name = data["name"]
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.\-]+", name):
        raise GripperSpecError(f"{path}: name: expected letters, digits, '_', '-', '.', got {name!r}")
    if data["family"] not in FAMILIES:
        raise GripperSpecError(f"{path}: family: expected one of {list(FAMILIES)}, got {data['family']!r}")
    if data["split"] not in SPLITS:
        raise GripperSpecError(f"{path}: split: expected one of {list(SPLITS)}, got {data['split']!r}")
    source = _resolve_source(data["source"], path)
    cut_link = data["cut_link"]
    if not isinstance(cut_link, str):
        raise GripperSpecError(f"{path}: cut_link: expected a link name, got {cut_link!r}")

    try:
        raw_robot = extract_subtree(load_robot_xml(source), cut_link)
    except FormatError as e:
        field_name = "cut_link" if str(e).startswith(f"link {cut_link!r}") else "source"
        raise GripperSpecError(f"{path}: {field_name}: {source.name}: {e}") from None
    try:
        table = joint_table(raw_robot)
        mimics = read_mimics(raw_robot)
    except FormatError as e:
        raise GripperSpecError(f"{path}: source: {source.name}: {e}") from None
    movable = {n for n, j in table.items() if j["type"] in MOVABLE_TYPES}

    drives_raw = data["drive_joints"]
    if not isinstance(drives_raw, list) or not drives_raw:
        raise GripperSpecError(f"{path}: drive_joints: expected a non-empty list")
    drives = []
    for i, d in enumerate(drives_raw):
        where = f"{path}: drive_joints[{i}]"
        if not isinstance(d, dict) or set(d) - {"name", "open", "closed"} or "name" not in d:
            raise GripperSpecError(f"{where}: expected {{name, open, closed}}, got {d!r}")
        jn = d["name"]
        if not isinstance(jn, str):
            raise GripperSpecError(f"{where}.name: expected a joint name, got {jn!r}")
        if jn not in table:
            raise GripperSpecError(f"{where}.name: joint {jn!r} does not exist below {cut_link} in {source.name}")
        if jn not in movable:
            raise GripperSpecError(f"{where}.name: joint {jn!r} is {table[jn]['type']}, not movable")
        lo, hi = _num(d, "open", where), _num(d, "closed", where)
        if abs(lo - hi) < 1e-9:
            raise GripperSpecError(f"{where}.open: equals closed ({lo}); the opening would not move the joint")
        jl, ju = table[jn]["lower"], table[jn]["upper"]
        if table[jn]["type"] != "continuous" and jl is not None and ju is not None:
            for key, v in (("open", lo), ("closed", hi)):
                if not jl - 1e-6 <= v <= ju + 1e-6:
                    raise GripperSpecError(f"{where}.{key}: {v} outside the joint limits [{jl}, {ju}] of {jn}")
        drives.append(DriveJoint(jn, lo, hi, table[jn]["type"] == "prismatic"))
    drive_names = {d.name for d in drives}

    couplings: list[Coupling] = []
    for jn, driver, mult, off in mimics:
        if jn in drive_names or jn not in movable:  # a driven or fixed joint follows nothing
            continue
        couplings.append(Coupling(jn, driver, mult, off, "mimic", table[jn]["type"] == "prismatic", True,
                                  table[driver]["type"] == "prismatic"))
    declared: dict[str, int] = {}
    for i, c in enumerate(data.get("couplings") or []):
        where = f"{path}: couplings[{i}]"
        if not isinstance(c, dict) or set(c) - {"joint", "driver", "multiplier", "offset", "mode"} or not {"joint", "driver"} <= set(c):
            raise GripperSpecError(f"{where}: expected {{joint, driver, multiplier, offset, mode}}, got {c!r}")
        for key in ("joint", "driver"):
            if not isinstance(c[key], str):
                raise GripperSpecError(f"{where}.{key}: expected a joint name, got {c[key]!r}")
            if c[key] not in movable:
                raise GripperSpecError(f"{where}.{key}: joint {c[key]!r} does not exist or is not movable in {source.name}")
        mode = c.get("mode", "mimic")
        if mode not in COUPLING_MODES:
            raise GripperSpecError(f"{where}.mode: expected one of {list(COUPLING_MODES)}, got {mode!r}")
        couplings = [k for k in couplings if k.joint != c["joint"]]
        couplings.append(Coupling(c["joint"], c["driver"], _num(c, "multiplier", where, 1.0), _num(c, "offset", where, 0.0),
                                  mode, table[c["joint"]]["type"] == "prismatic", False,
                                  table[c["driver"]]["type"] == "prismatic"))
        declared[c["joint"]] = i
    for c in couplings:
        if c.joint in drive_names:
            raise GripperSpecError(f"{path}: couplings: joint {c.joint!r} is also a drive joint")

    hold = data.get("hold_joints") or {}
    if not isinstance(hold, dict):
        raise GripperSpecError(f"{path}: hold_joints: expected a mapping joint -> value")
    for jn, v in hold.items():
        if jn not in table:
            raise GripperSpecError(f"{path}: hold_joints.{jn}: joint does not exist in {source.name}")
        if jn not in movable:
            raise GripperSpecError(f"{path}: hold_joints.{jn}: the joint is {table[jn]['type']}; only movable joints are held")
        _num(hold, jn, f"{path}: hold_joints")
    held = {k: float(v) for k, v in hold.items()}

    couplings, frozen = _moving_couplings(couplings, drive_names)
    for c in frozen:
        if not c.from_mimic:
            raise GripperSpecError(f"{path}: couplings[{declared[c.joint]}].driver: joint {c.driver!r} is neither "
                                   "driven nor coupled to a drive joint, so it is frozen")
    moving = drive_names | {c.joint for c in couplings}
    for jn in hold:
        if jn in moving:
            raise GripperSpecError(f"{path}: hold_joints.{jn}: the joint is driven or coupled to a drive joint, "
                                   "so it moves; only frozen joints are held")
    # a <mimic> of a frozen joint is frozen too, where its <mimic> puts it (hold_joints may say
    # otherwise); the joints of a <mimic> cycle that no drive joint enters stay at 0
    pending = [c for c in frozen if c.joint not in held]
    while pending:
        follows = {c.joint: c.driver for c in pending}
        ready = [c for c in pending if c.driver not in follows]
        for c in ready:
            held[c.joint] = c.value(held.get(c.driver, 0.0), 1.0)
        if not ready:  # every driver waits: each chain ends in a cycle
            held.update({j: 0.0 for j in follows if _on_cycle(j, follows)})
        pending = [c for c in pending if c.joint not in held]

    base_mass = _scalar(data, "base_mass", path, 1.0) if "base_mass" in data else None
    inertia = data.get("inertia", "file")
    if inertia not in ("file", "geometry"):
        raise GripperSpecError(f"{path}: inertia: expected file or geometry, got {inertia!r}")
    urdf = _processed_urdf(path, text, source, cut_link, moving, held, base_mass, inertia)
    finger_links = _descendant_links(table, moving)

    friction = _scalar(data, "friction", path, 1.0)
    force = _scalar(data, "force", path, 20.0)
    coupling_force = _scalar(data, "coupling_force", path, force)
    max_velocity = _scalar(data, "max_velocity", path, 0.5)
    base_force = _scalar(data, "base_force", path, 300.0)
    aperture_band = _scalar(data, "aperture_band", path, 0.03)

    tcp = data.get("tcp")
    estimated = tcp is None
    if tcp is not None:
        if not isinstance(tcp, dict) or set(tcp) - {"position", "approach", "closing"} or not {"position", "approach"} <= set(tcp):
            raise GripperSpecError(f"{path}: tcp: expected {{position, approach, closing}}, got {tcp!r}")
        tcp_pos = _vec3(tcp["position"], f"{path}: tcp.position", unit=False)
        approach = _vec3(tcp["approach"], f"{path}: tcp.approach", unit=True)
        closing = _vec3(tcp.get("closing", _any_perpendicular(approach)), f"{path}: tcp.closing", unit=True)
        if abs(float(np.dot(approach, closing))) > 0.99:
            raise GripperSpecError(f"{path}: tcp.closing: must not be parallel to tcp.approach")
    else:
        tcp_pos, approach, closing = (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)

    spec = GripperSpec(
        name=name,
        family=data["family"],
        split=data["split"],
        urdf=urdf,
        spec_path=path,
        source=source,
        cut_link=cut_link,
        drive_joints=tuple(drives),
        couplings=tuple(couplings),
        finger_links=finger_links,
        tcp_position=tcp_pos,
        approach_axis=approach,
        closing_axis=closing,
        tcp_estimated=estimated,
        friction=friction,
        force=force,
        coupling_force=coupling_force,
        max_velocity=max_velocity,
        base_force=base_force,
        aperture_band=aperture_band,
        description=str(data.get("description", "")),
        license=str(data.get("license", "")),
        params=dict(data.get("params") or {}),
    )
    joint_positions(spec, 1.0)
    if estimated:
        spec = _with_estimated_tcp(spec)
    return spec


def _scalar(data: dict, key: str, path: Path, default: float) -> float:
    if key not in data:
        return float(default)
    v = data[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
        raise GripperSpecError(f"{path}: {key}: expected a positive number, got {v!r}")
    return float(v)


def _any_perpendicular(a) -> list[float]:
    a = np.asarray(a)
    x = np.cross(a, [0.0, 1.0, 0.0]) if abs(a[1]) < 0.9 else np.cross(a, [1.0, 0.0, 0.0])
    return list(x / np.linalg.norm(x))


def _with_estimated_tcp(spec: GripperSpec) -> GripperSpec:
    """Estimate TCP, approach and closing axes from the finger geometry at opening 1 (scale 1).

    approach = from the base origin towards the centroid of the finger geometry; the TCP lies
    on that line, ``min(0.02, 0.3 * finger extent)`` behind the farthest finger point;
    closing = from the TCP towards the first finger's centroid, perpendicular to approach.
    """
    from dataclasses import replace

    model = GripperModel(replace(spec, tcp_estimated=False), 1.0, frame="base")
    pts = model.finger_points_posed(1.0)
    if not pts:
        raise GripperSpecError(f"{spec.spec_path}: tcp: cannot estimate the TCP: the fingers have no collision geometry")
    allp = np.concatenate(list(pts.values()))
    c = allp.mean(axis=0)
    if np.linalg.norm(c) < 1e-6:
        raise GripperSpecError(f"{spec.spec_path}: tcp: cannot estimate the approach axis (finger centroid at the base origin); give tcp")
    a = c / np.linalg.norm(c)
    proj = allp @ a
    extent = proj.max() - proj.min()
    depth = proj.max() - min(0.02, 0.3 * extent)
    lateral = c - a * float(c @ a)
    tcp = lateral + a * depth
    first = pts[spec.finger_links[0]].mean(axis=0) - tcp
    first -= a * float(first @ a)
    closing = first / np.linalg.norm(first) if np.linalg.norm(first) > 1e-6 else np.asarray(_any_perpendicular(a))
    return replace(
        spec,
        tcp_position=tuple(float(v) for v in tcp),
        approach_axis=tuple(float(v) for v in a),
        closing_axis=tuple(float(v) for v in closing),
        tcp_estimated=True,
    )


# --------------------------------------------------------------------------------------
# registry
# --------------------------------------------------------------------------------------


def assets_dir() -> Path:
    """The packaged ``assets/grippers`` folder."""
    return Path(str(importlib.resources.files("assets") / "grippers"))


def registered_spec_paths() -> dict[str, Path]:
    """Name -> spec file of every gripper shipped under assets/grippers/real (file stem = name)."""
    return {p.stem: p for p in sorted((assets_dir() / "real").glob("*.yaml"))}


def get_gripper(name_or_path: str) -> GripperSpec:
    """A registered name, a procedural ``<family>-<seed>`` name, or a path to a spec YAML."""
    from common import gripper_procedural

    s = str(name_or_path)
    if s.endswith((".yaml", ".yml")) or os.sep in s:
        return load_spec(Path(s))
    reg = registered_spec_paths()
    if s in reg:
        return load_spec(reg[s])
    m = re.fullmatch(r"([a-z_]+)-(\d+)", s)
    if m and m.group(1) in gripper_procedural.FAMILY_NAMES:
        return gripper_procedural.generate(m.group(1), int(m.group(2))).spec
    raise GripperSpecError(
        f"{s}: unknown gripper (registered: {', '.join(reg)}; procedural: "
        f"{', '.join(f + '-<seed>' for f in gripper_procedural.FAMILY_NAMES)}; or a path to a spec YAML)"
    )


def list_grippers(split: str | None = None, family: str | None = None) -> list[GripperSpec]:
    """Registered real grippers plus the procedural catalogue (assets/grippers/catalog.yaml)."""
    from common import gripper_procedural

    if split is not None and split not in SPLITS:
        raise GripperSpecError(f"split: expected one of {list(SPLITS)}, got {split!r}")
    if family is not None and family not in FAMILIES:
        raise GripperSpecError(f"family: expected one of {list(FAMILIES)}, got {family!r}")
    specs = [load_spec(p) for p in registered_spec_paths().values()]
    specs += [get_gripper(n) for n in gripper_procedural.catalog_names()]
    return [s for s in specs if (split is None or s.split == split) and (family is None or s.family == family)]


# --------------------------------------------------------------------------------------
# scaled URDFs and geometry
# --------------------------------------------------------------------------------------


SCALE_RANGE = (0.05, 20.0)
"""Global gripper scales the processed URDFs are made for."""


def check_scale(scale: float, flag: str = "scale") -> None:
    """ValueError in one line naming ``flag`` unless ``scale`` lies in SCALE_RANGE (NaN does not)."""
    lo, hi = SCALE_RANGE
    if not lo <= scale <= hi:
        raise ValueError(f"{flag}: expected a value in [{lo:g}, {hi:g}], got {scale}")


def scaled_urdf(spec: GripperSpec, scale: float, visual_from_collision: bool = False) -> ET.Element:
    """Root of the processed URDF scaled by ``scale``, built in memory; nothing is written.

    Training draws a new scale every episode, so a file per scale would pile up in the cache
    (two small files an episode). Mesh filenames in the processed URDF are absolute, so the tree
    loads from any folder. With ``visual_from_collision`` every visual is replaced by the link's
    collision geometry (renders then show exactly what collides, as the encoding does); the hulls
    this needs are cached in the processed URDF's folder.
    """
    check_scale(scale)
    robot = ET.parse(spec.urdf).getroot()
    if visual_from_collision:
        for link in robot.findall("link"):
            for v in link.findall("visual"):
                link.remove(v)
            for c in link.findall("collision"):
                v = copy.deepcopy(c)
                v.tag = "visual"
                for mesh in v.iter("mesh"):
                    sc = mesh.get("scale", "1 1 1")
                    mesh.set("filename", str(_hull_file(Path(mesh.get("filename")), sc, spec.urdf.parent / "hulls")))
                    mesh.set("scale", "1 1 1")
                link.append(v)
    try:
        return scale_robot(robot, scale)
    except FormatError as e:
        raise GripperSpecError(f"{spec.spec_path}: source: {spec.urdf.name}: {e}") from None


def _hull_file(mesh_path: Path, scale_attr: str, folder: Path) -> Path:
    """OBJ of the convex hull of a mesh file scaled by ``scale_attr`` ("sx sy sz"); cached in ``folder``."""
    import trimesh

    key = hashlib.sha1(f"{mesh_path}|{scale_attr}".encode()).hexdigest()[:12]
    out = folder / f"{mesh_path.stem}-{key}.obj"
    if not out.is_file():
        tm = trimesh.load(mesh_path, force="mesh")
        tm.apply_scale(np.broadcast_to(np.array([float(v) for v in scale_attr.split()]), (3,)))
        folder.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.stem}.{os.getpid()}.tmp.obj")
        tm.convex_hull.export(tmp)
        os.replace(tmp, out)
    return out


@dataclass
class Part:
    """One collision element of a link, in the link frame."""

    link: str
    T_link_part: np.ndarray
    """(4, 4) float64 pose of the element in its link frame (metres)."""
    kind: str
    """box | sphere | cylinder | mesh."""
    size: np.ndarray
    """box: half extents (3,); sphere: (radius,); cylinder: (radius, half length); mesh: unused."""
    mesh: object = None
    """trimesh.Trimesh in the part frame: the convex hull for meshes (PyBullet collides a moving
    body's meshes as their convex hulls), a triangulation for primitives."""


class GripperModel:
    """Forward kinematics (yourdfpy) and collision parts of one gripper at one scale.

    ``frame="tcp"`` (default) expresses every pose in the TCP frame, ``"base"`` in the cut link frame.
    """

    def __init__(self, spec: GripperSpec, scale: float = 1.0, frame: str = "tcp") -> None:
        import trimesh
        import yourdfpy

        self.spec, self.scale = spec, float(scale)
        text = ET.tostring(scaled_urdf(spec, scale), encoding="utf-8")
        try:
            self.urdf = yourdfpy.URDF.load(io.BytesIO(text), build_scene_graph=True, load_meshes=False,
                                           build_collision_scene_graph=False, load_collision_meshes=False)
        except Exception as e:  # noqa: BLE001 - report any parser failure as one line
            raise GripperSpecError(f"{spec.spec_path}: source: URDF cannot be loaded ({type(e).__name__}: {e})") from None
        self.base = self.urdf.base_link
        T = spec.T_base_tcp(scale) if frame == "tcp" else Transform.identity()
        self.T_frame_base = T.inverse().as_matrix()
        self.parts: list[Part] = []
        for link in self.urdf.robot.links:
            for col in link.collisions:
                g = col.geometry
                T_lp = np.asarray(col.origin if col.origin is not None else np.eye(4), dtype=np.float64)
                if g.box is not None:
                    half = np.asarray(g.box.size, dtype=np.float64) / 2
                    part = Part(link.name, T_lp, "box", half, trimesh.creation.box(extents=half * 2))
                elif g.sphere is not None:
                    r = float(g.sphere.radius)
                    part = Part(link.name, T_lp, "sphere", np.array([r]), trimesh.creation.icosphere(2, r))
                elif g.cylinder is not None:
                    r, h = float(g.cylinder.radius), float(g.cylinder.length)
                    part = Part(link.name, T_lp, "cylinder", np.array([r, h / 2]), trimesh.creation.cylinder(r, h, sections=24))
                elif g.mesh is not None:
                    try:
                        tm = trimesh.load(g.mesh.filename, force="mesh")
                    except Exception as e:  # noqa: BLE001
                        raise GripperSpecError(
                            f"{spec.spec_path}: source: mesh {g.mesh.filename} cannot be read ({type(e).__name__})"
                        ) from None
                    if len(tm.faces) == 0:
                        raise GripperSpecError(f"{spec.spec_path}: source: mesh {g.mesh.filename} has no faces")
                    sc = np.asarray(g.mesh.scale if g.mesh.scale is not None else [1, 1, 1], dtype=np.float64)
                    tm.apply_scale(np.broadcast_to(sc, (3,)))
                    if not np.all(np.isfinite(tm.vertices)):
                        raise GripperSpecError(f"{spec.spec_path}: source: mesh {g.mesh.filename} has non-finite vertices")
                    part = Part(link.name, T_lp, "mesh", np.zeros(0), tm.convex_hull)
                else:
                    continue
                self.parts.append(part)
        self._finger_samples: dict[str, np.ndarray] | None = None

    def link_poses(self, opening: float) -> dict[str, np.ndarray]:
        """(4, 4) float64 pose of every link in the model's frame at ``opening``."""
        q = joint_positions(self.spec, opening, self.scale)
        actuated = set(self.urdf.actuated_joint_names)
        self.urdf.update_cfg({k: v for k, v in q.items() if k in actuated})
        return {
            link: self.T_frame_base @ self.urdf.get_transform(link, self.base)
            for link in self.urdf.link_map
        }

    def posed_parts(self, opening: float) -> list[tuple[Part, np.ndarray]]:
        """Each collision part with its (4, 4) pose in the model's frame."""
        poses = self.link_poses(opening)
        return [(p, poses[p.link] @ p.T_link_part) for p in self.parts]

    def mesh(self, opening: float):
        """All collision geometry posed at ``opening`` as one trimesh (model's frame, metres)."""
        import trimesh

        meshes = []
        for part, T in self.posed_parts(opening):
            m = part.mesh.copy()
            m.apply_transform(T)
            meshes.append(m)
        if not meshes:
            raise GripperSpecError(f"{self.spec.spec_path}: source: the gripper has no collision geometry")
        return trimesh.util.concatenate(meshes)

    def finger_samples(self) -> dict[str, np.ndarray]:
        """Surface sample points (N, 3) float64 of each finger link in its link frame, metres."""
        if self._finger_samples is None:
            out: dict[str, list[np.ndarray]] = {}
            spacing = 0.002 * self.scale
            for p in self.parts:
                if p.link not in self.spec.finger_links:
                    continue
                m = p.mesh
                n = int(np.clip(m.area / spacing**2, 200, 20000))
                pts, _ = _sample_surface(m, n)
                pts = np.concatenate([pts, np.asarray(m.vertices)])
                out.setdefault(p.link, []).append(pts @ p.T_link_part[:3, :3].T + p.T_link_part[:3, 3])
            self._finger_samples = {k: np.concatenate(v) for k, v in out.items()}
        return self._finger_samples

    def finger_points_posed(self, opening: float) -> dict[str, np.ndarray]:
        """Finger surface samples (N, 3) per finger link in the model's frame at ``opening``."""
        poses = self.link_poses(opening)
        return {k: v @ poses[k][:3, :3].T + poses[k][:3, 3] for k, v in self.finger_samples().items()}

    def sweep_depth(self, min_aperture: float = 0.0, steps: int = 21, max_opening: float = 1.0) -> float:
        """Metres the finger geometry reaches below the TCP (along the approach) at its lowest over
        the openings up to ``max_opening`` whose aperture is at least ``min_aperture`` (m): a TCP
        held this high above a table keeps the fingers off it while they close from ``max_opening``
        on an object that wide. Needs frame="tcp"."""
        lowest = 0.0
        for o in np.linspace(0.0, max_opening, steps):
            pts = self.finger_points_posed(float(o))
            allp = np.concatenate(list(pts.values()))
            if o < max_opening and aperture_from_points(allp, self.spec.aperture_band * self.scale) < min_aperture:
                continue
            lowest = min(lowest, float(allp[:, 2].min()))
        return -lowest

    def aperture(self, opening: float) -> float:
        """Finger aperture (m) at ``opening``: see :func:`aperture_from_points`. Needs frame="tcp"."""
        pts = self.finger_points_posed(opening)
        return aperture_from_points(np.concatenate(list(pts.values())), self.spec.aperture_band * self.scale)


def _sample_surface(mesh, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic area-weighted surface samples: points (n, 3) and their face indices (n,)."""
    import trimesh

    return trimesh.sample.sample_surface(mesh, n, seed=0)


def aperture_from_points(points_tcp: np.ndarray, band: float) -> float:
    """Aperture (m): the diameter of the widest cylinder about the approach axis (TCP z axis)
    that no finger point enters, counting finger points from the tips up to ``band`` above the TCP.

    ``points_tcp``: (N, 3) float64 finger surface points in the TCP frame, metres.
    Returns +inf when no finger point lies in the band.
    """
    assert points_tcp.ndim == 2 and points_tcp.shape[1] == 3, points_tcp.shape
    sel = points_tcp[points_tcp[:, 2] <= band]
    if len(sel) == 0:
        return float("inf")
    return float(2.0 * np.min(np.hypot(sel[:, 0], sel[:, 1])))


def posed_meshes(spec: GripperSpec, scale: float, opening: float):
    """Collision geometry of the gripper at ``opening`` as one trimesh in the TCP frame (approach -z), metres."""
    return GripperModel(spec, scale).mesh(opening)


def check_kinematics(spec: GripperSpec, scale: float = 1.0, steps: int = 11) -> list[float]:
    """Apertures (m) at ``steps`` openings from 0 to 1; raises GripperSpecError when they do not
    grow monotonically (1 mm tolerance; below CLOSED_APERTURE counts as closed) or the opening
    does not move the fingers."""
    model = GripperModel(spec, scale)
    ap = [model.aperture(o) for o in np.linspace(0.0, 1.0, steps)]
    field_name = f"drive_joints[0].open ({spec.drive_joints[0].name})"
    if not all(np.isfinite(ap)):
        raise GripperSpecError(f"{spec.spec_path}: aperture_band: no finger geometry within the band at some opening")
    if ap[-1] - ap[0] < MIN_APERTURE_CHANGE * scale:
        raise GripperSpecError(
            f"{spec.spec_path}: {field_name}: the opening does not move the fingers (aperture {ap[0]:.4f} -> {ap[-1]:.4f} m)"
        )
    tol = 1e-3 * scale
    floor = CLOSED_APERTURE * scale
    for i in range(1, len(ap)):
        if max(ap[i], floor) < max(ap[i - 1], floor) - tol:
            raise GripperSpecError(
                f"{spec.spec_path}: {field_name}: aperture is not monotonic in the opening "
                f"({ap[i - 1]:.4f} m at {(i - 1) / (steps - 1):.2f} -> {ap[i]:.4f} m at {i / (steps - 1):.2f})"
            )
    return ap
