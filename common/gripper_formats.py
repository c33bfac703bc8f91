"""Robot description files -> one clean URDF tree for a gripper.

The gripper library reads URDF, SDF and MJCF; this module turns any of them into a URDF
element tree, cuts the hand off an arm, freezes joints the spec does not drive, makes mesh
paths absolute, and scales the whole model. Usage::

    robot = load_robot_xml(path)                      # URDF, SDF (.sdf) or MJCF (.xml)
    robot = extract_subtree(robot, "panda_hand")      # cut link becomes the root
    robot = freeze_joints(robot, keep={"j1", "j2"}, hold={})
    resolve_meshes(robot, path, mesh_cache_dir)
    robot = scale_robot(robot, 1.1)
    ET.ElementTree(robot).write(out_path)

Every failure raises :class:`FormatError` with a one-line message (the caller prefixes the
file and the spec field).
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
import uuid
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np


class FormatError(ValueError):
    """A robot description cannot be read or transformed; the message is one line."""


MOVABLE_TYPES = ("revolute", "continuous", "prismatic")
"""URDF joint types that move (one degree of freedom)."""


# --------------------------------------------------------------------------------------
# small math helpers
# --------------------------------------------------------------------------------------


def rpy_to_matrix(rpy) -> np.ndarray:
    """(3, 3) rotation of URDF roll-pitch-yaw (fixed axes x, y, z), radians."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_rpy(m: np.ndarray) -> np.ndarray:
    """URDF roll-pitch-yaw (3,) radians of a (3, 3) rotation."""
    sp = -float(np.clip(m[2, 0], -1.0, 1.0))
    if abs(sp) > 1 - 1e-9:
        r = math.atan2(-m[1, 2], m[1, 1])
        return np.array([r, math.copysign(math.pi / 2, sp), 0.0])
    return np.array([math.atan2(m[2, 1], m[2, 2]), math.asin(sp), math.atan2(m[1, 0], m[0, 0])])


def quat_wxyz_to_matrix(q) -> np.ndarray:
    """(3, 3) rotation of a (w, x, y, z) quaternion."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(np.asarray(q, dtype=np.float64))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _floats(text: str | None, n: int, what: str, default=None) -> np.ndarray:
    if text is None:
        if default is None:
            raise FormatError(f"{what}: missing")
        return np.asarray(default, dtype=np.float64)
    try:
        vals = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise FormatError(f"{what}: expected {n} numbers, got {text!r}") from None
    if vals.shape != (n,) or not np.all(np.isfinite(vals)):
        raise FormatError(f"{what}: expected {n} finite numbers, got {text!r}")
    return vals


def _number(text: str | None, what: str, default: float | None = None) -> float:
    """One number of the file (``default`` where absent), or FormatError naming ``what``."""
    if text is None:
        if default is None:
            raise FormatError(f"{what}: missing")
        return float(default)
    try:
        return float(text)
    except (TypeError, ValueError):
        raise FormatError(f"{what}: expected a number, got {text!r}") from None


def _text(el: ET.Element | None, what: str) -> str:
    """The stripped text of element ``el``, or FormatError naming ``what`` when it is absent or empty."""
    if el is None or el.text is None or not el.text.strip():
        raise FormatError(f"{what}: missing")
    return el.text.strip()


def _number_text(el: ET.Element | None, what: str) -> str:
    """The text of element ``el``, checked to be a number (kept as written)."""
    text = _text(el, what)
    _number(text, what)
    return text


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def origin_matrix(elem: ET.Element | None, what: str = "origin") -> np.ndarray:
    """(4, 4) transform of a URDF ``<origin>`` element (identity if absent)."""
    m = np.eye(4)
    if elem is None:
        return m
    m[:3, :3] = rpy_to_matrix(_floats(elem.get("rpy"), 3, f"{what} rpy", (0, 0, 0)))
    m[:3, 3] = _floats(elem.get("xyz"), 3, f"{what} xyz", (0, 0, 0))
    return m


def set_origin(parent: ET.Element, m: np.ndarray) -> None:
    """Write (4, 4) transform ``m`` as the ``<origin>`` child of ``parent``."""
    o = parent.find("origin")
    if o is None:
        o = ET.Element("origin")
        parent.insert(0, o)
    o.set("xyz", _fmt(m[:3, 3]))
    o.set("rpy", _fmt(matrix_to_rpy(m[:3, :3])))


# --------------------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------------------


def load_robot_xml(path: Path) -> ET.Element:
    """Parse a URDF, SDF or MJCF file into a URDF ``<robot>`` element.

    Mesh filenames stay as written; :func:`resolve_meshes` makes them absolute.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"file not found: {path}")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise FormatError(f"not valid XML ({e})") from None
    if root.tag == "robot":
        return root
    if root.tag == "sdf":
        return sdf_to_urdf(root, path)
    if root.tag == "mujoco":
        return mjcf_to_urdf(root, path)
    raise FormatError(f"unknown robot format: root element <{root.tag}> (expected robot, sdf or mujoco)")


def links_and_joints(robot: ET.Element) -> tuple[dict[str, ET.Element], dict[str, ET.Element]]:
    """Name -> element maps of the links and joints of a URDF tree (link masses checked)."""
    links = {}
    for link in robot.findall("link"):
        name = link.get("name")
        if not name:
            raise FormatError("a <link> has no name")
        mass = link.find("inertial/mass")
        if mass is not None:
            _number(mass.get("value"), f"link {name}: inertial mass")
        links[name] = link
    joints = {}
    for joint in robot.findall("joint"):
        name = joint.get("name")
        if not name:
            raise FormatError("a <joint> has no name")
        for tag in ("parent", "child"):
            el = joint.find(tag)
            if el is None or el.get("link") not in links:
                raise FormatError(f"joint {name}: {tag} link {None if el is None else el.get('link')!r} does not exist")
        joints[name] = joint
    return links, joints


def joint_table(robot: ET.Element) -> dict[str, dict]:
    """Per joint: type, parent, child, lower, upper (None where absent)."""
    _, joints = links_and_joints(robot)
    out = {}
    for name, j in joints.items():
        lim = j.find("limit")
        lo, hi = (None if lim is None or lim.get(key) is None else _number(lim.get(key), f"joint {name}: limit {key}")
                  for key in ("lower", "upper"))
        out[name] = {
            "type": j.get("type"),
            "parent": j.find("parent").get("link"),
            "child": j.find("child").get("link"),
            "lower": lo,
            "upper": hi,
        }
    return out


def read_mimics(robot: ET.Element) -> list[tuple[str, str, float, float]]:
    """``<mimic>`` couplings as (joint, driver joint, multiplier, offset)."""
    out = []
    for j in robot.findall("joint"):
        m = j.find("mimic")
        if m is not None:
            name = j.get("name")
            out.append((name, m.get("joint"), _number(m.get("multiplier"), f"joint {name}: mimic multiplier", 1.0),
                        _number(m.get("offset"), f"joint {name}: mimic offset", 0.0)))
    return out


# --------------------------------------------------------------------------------------
# transforms of the tree
# --------------------------------------------------------------------------------------


def extract_subtree(robot: ET.Element, base_link: str) -> ET.Element:
    """A new URDF tree with ``base_link`` as root and every link below it."""
    links, joints = links_and_joints(robot)
    if base_link not in links:
        raise FormatError(f"link {base_link!r} does not exist (links: {', '.join(sorted(links))})")
    children: dict[str, list[ET.Element]] = {}
    for j in joints.values():
        children.setdefault(j.find("parent").get("link"), []).append(j)
    keep_links, keep_joints, stack = [base_link], [], [base_link]
    while stack:
        for j in children.get(stack.pop(), []):
            child = j.find("child").get("link")
            if child in keep_links:  # a tree reaches every link once
                raise FormatError(f"joint {j.get('name')!r}: link {child!r} is reached twice below {base_link!r} "
                                  "(a closed chain or a link with two parents; URDF describes trees)")
            keep_joints.append(j.get("name"))
            keep_links.append(child)
            stack.append(child)
    out = ET.Element("robot", {"name": robot.get("name", "gripper")})
    for name in keep_links:
        out.append(copy.deepcopy(links[name]))
    for name in keep_joints:
        out.append(copy.deepcopy(joints[name]))
    for j in out.findall("joint"):
        m = j.find("mimic")
        if m is not None and m.get("joint") not in keep_joints:
            j.remove(m)
    return out


def _joint_motion(joint: ET.Element, q: float) -> np.ndarray:
    axis = _floats(joint.find("axis").get("xyz") if joint.find("axis") is not None else None, 3, "axis", (1, 0, 0))
    axis = axis / max(np.linalg.norm(axis), 1e-12)
    m = np.eye(4)
    if joint.get("type") == "prismatic":
        m[:3, 3] = axis * q
    else:
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        m[:3, :3] = np.eye(3) + math.sin(q) * k + (1 - math.cos(q)) * k @ k
    return m


def freeze_joints(robot: ET.Element, keep: set[str], hold: dict[str, float]) -> ET.Element:
    """Make every movable joint not in ``keep`` fixed, at ``hold[name]`` (default 0)."""
    out = copy.deepcopy(robot)
    for j in out.findall("joint"):
        name = j.get("name")
        if j.get("type") in MOVABLE_TYPES and name not in keep:
            q = float(hold.get(name, 0.0))
            set_origin(j, origin_matrix(j.find("origin")) @ _joint_motion(j, q))
            j.set("type", "fixed")
            for tag in ("axis", "limit", "mimic", "dynamics", "calibration", "safety_controller"):
                for el in j.findall(tag):
                    j.remove(el)
    for tag in ("transmission", "gazebo", "material"):
        for el in out.findall(tag):
            out.remove(el)
    return out


def resolve_mesh_path(filename: str, source: Path) -> Path:
    """Absolute path of a mesh referenced from ``source`` (``package://``, ``file://`` or relative)."""
    name = filename
    for scheme in ("file://",):
        if name.startswith(scheme):
            name = name[len(scheme):]
    candidates: list[Path] = []
    if name.startswith("package://"):
        rest = name[len("package://"):]
        pkg, _, tail = rest.partition("/")
        for d in [source.parent, *source.parent.parents]:
            candidates += [d / rest, d / tail] if d.name != pkg else [d / tail]
    else:
        p = Path(name)
        candidates.append(p if p.is_absolute() else source.parent / p)
    for c in candidates:
        if c.is_file():
            return c.resolve()
    raise FormatError(f"mesh {filename!r} not found next to {source.name} or in any parent package folder")


def _binary_stl(path: Path) -> bool:
    """True for a binary STL (84 header bytes and 50 per triangle, as its count says): PyBullet
    reads those, while an ASCII STL loads there as a 2 mm box without an error."""
    size = path.stat().st_size
    if size < 84:
        return False
    with open(path, "rb") as f:
        f.seek(80)
        triangles = int.from_bytes(f.read(4), "little")
    return size == 84 + 50 * triangles


def resolve_meshes(robot: ET.Element, source: Path, mesh_cache: Path) -> None:
    """Make mesh filenames absolute in place; convert formats PyBullet cannot read (all but OBJ and
    binary STL) to OBJ in ``mesh_cache``."""
    import trimesh

    for mesh in robot.iter("mesh"):
        fn = mesh.get("filename")
        if not fn:
            raise FormatError("a <mesh> has no filename")
        path = resolve_mesh_path(fn, source)
        if path.suffix.lower() != ".obj" and not (path.suffix.lower() == ".stl" and _binary_stl(path)):
            digest = hashlib.sha1(str(path).encode() + str(path.stat().st_mtime_ns).encode()).hexdigest()[:16]
            out = mesh_cache / f"{path.stem}-{digest}.obj"
            if not out.exists():
                try:
                    tm = trimesh.load(path, force="mesh")
                except Exception as e:  # noqa: BLE001 - any loader failure is reported as one line
                    raise FormatError(f"mesh {fn!r} cannot be read ({type(e).__name__}: {e})") from None
                mesh_cache.mkdir(parents=True, exist_ok=True)
                tmp = out.with_name(f"{out.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp.obj")  # one per writer
                tm.export(tmp)
                tmp.replace(out)
            path = out
        mesh.set("filename", str(path))


def _collision_mesh(col: ET.Element, what: str):
    """trimesh of one <collision> element in its link frame (meshes as their convex hull, as
    PyBullet collides them), or None for geometry without volume."""
    import trimesh

    geom = col.find("geometry")
    shape = None if geom is None or len(geom) == 0 else geom[0]
    if shape is None:
        return None
    if shape.tag == "box":
        tm = trimesh.creation.box(extents=_floats(shape.get("size"), 3, f"{what} box size"))
    elif shape.tag == "sphere":
        tm = trimesh.creation.icosphere(2, _number(shape.get("radius"), f"{what} sphere radius", 0))
    elif shape.tag == "cylinder":
        tm = trimesh.creation.cylinder(_number(shape.get("radius"), f"{what} cylinder radius", 0),
                                       _number(shape.get("length"), f"{what} cylinder length", 0), sections=24)
    elif shape.tag == "mesh":
        try:
            tm = trimesh.load(shape.get("filename"), force="mesh")
        except Exception as e:  # noqa: BLE001 - any loader failure is reported as one line
            raise FormatError(f"{what}: mesh {shape.get('filename')!r} cannot be read ({type(e).__name__})") from None
        tm.apply_scale(np.broadcast_to(_floats(shape.get("scale"), 3, f"{what} mesh scale", (1, 1, 1)), (3,)))
        tm = tm.convex_hull if len(tm.faces) else None
    else:
        return None
    if tm is None or tm.volume <= 1e-12:
        return None
    tm.apply_transform(origin_matrix(col.find("origin"), f"{what} origin"))
    return tm


def inertia_from_collision(robot: ET.Element) -> list[str]:
    """Replace each link's inertial by that of its collision geometry at the link's own mass.

    The geometry is taken as one solid of uniform density (convex hulls of meshes, primitives as
    given); the mass stays what the file says. For models whose files carry placeholder inertias
    (for example 1 kg m^2 on a 20 g finger, which makes fingers sluggish under their motors).
    Returns the names of the links changed; links without mass or collision volume keep theirs.
    """
    changed = []
    for link in robot.findall("link"):
        name = link.get("name")
        inertial = link.find("inertial")
        mass_el = None if inertial is None else inertial.find("mass")
        mass = 0.0 if mass_el is None else _number(mass_el.get("value"), f"link {name}: inertial mass", 0)
        meshes = [m for c in link.findall("collision") if (m := _collision_mesh(c, f"link {name} collision")) is not None]
        if mass <= 0 or not meshes:
            continue
        volumes = np.array([m.volume for m in meshes])
        com = sum(v * m.center_mass for v, m in zip(volumes, meshes)) / volumes.sum()
        tensor = np.zeros((3, 3))
        for v, m in zip(volumes, meshes):
            d = m.center_mass - com
            part_mass = mass * v / volumes.sum()
            # inertia of the part about its centre at unit density, scaled to its mass, moved to the link's COM
            tensor += m.moment_inertia / m.mass * part_mass + part_mass * (d @ d * np.eye(3) - np.outer(d, d))
        for el in list(inertial):
            if el.tag in ("origin", "inertia"):
                inertial.remove(el)
        ET.SubElement(inertial, "origin", {"xyz": _fmt(com), "rpy": "0 0 0"})
        keys = (("ixx", 0, 0), ("ixy", 0, 1), ("ixz", 0, 2), ("iyy", 1, 1), ("iyz", 1, 2), ("izz", 2, 2))
        ET.SubElement(inertial, "inertia", {k: f"{tensor[a, b]:.9g}" for k, a, b in keys})
        changed.append(name)
    return changed


def scale_robot(robot: ET.Element, s: float) -> ET.Element:
    """The model scaled by ``s`` about the root frame: geometry, frames, prismatic limits, inertia.
    ``<mimic>`` elements are left as they are (processed URDFs have none; couplings scale through
    ``Coupling.value``)."""
    out = copy.deepcopy(robot)
    if s == 1.0:
        return out
    for origin in out.iter("origin"):
        if origin.get("xyz") is not None:
            origin.set("xyz", _fmt(_floats(origin.get("xyz"), 3, "origin xyz") * s))
    for box in out.iter("box"):
        box.set("size", _fmt(_floats(box.get("size"), 3, "box size") * s))
    for tag in ("cylinder", "sphere", "capsule"):
        for el in out.iter(tag):
            for key in ("radius", "length"):
                if el.get(key) is not None:
                    el.set(key, f"{_number(el.get(key), f'{tag} {key}') * s:.9g}")
    for mesh in out.iter("mesh"):
        mesh.set("scale", _fmt(_floats(mesh.get("scale"), 3, "mesh scale", (1, 1, 1)) * s))
    for inertia in out.iter("inertia"):
        for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"):
            if inertia.get(key) is not None:
                inertia.set(key, f"{_number(inertia.get(key), f'inertia {key}') * s * s:.9g}")
    for j in out.findall("joint"):
        if j.get("type") == "prismatic":
            lim = j.find("limit")
            where = f"joint {j.get('name')}"
            if lim is not None:
                for key in ("lower", "upper", "velocity"):
                    if lim.get(key) is not None:
                        lim.set(key, f"{_number(lim.get(key), f'{where}: limit {key}') * s:.9g}")
    return out


# --------------------------------------------------------------------------------------
# SDF -> URDF
# --------------------------------------------------------------------------------------


def _pose(elem: ET.Element | None, what: str) -> np.ndarray:
    m = np.eye(4)
    if elem is None or elem.find("pose") is None or not (elem.find("pose").text or "").strip():
        return m
    v = _floats(elem.find("pose").text, 6, f"{what} pose")
    m[:3, :3] = rpy_to_matrix(v[3:])
    m[:3, 3] = v[:3]
    return m


def _sdf_geometry(geom: ET.Element, what: str) -> ET.Element:
    out = ET.Element("geometry")
    if geom.find("box") is not None:
        size = _floats(_text(geom.find("box/size"), f"{what} box size"), 3, f"{what} box size")
        ET.SubElement(out, "box", {"size": _fmt(size)})
    elif geom.find("cylinder") is not None:
        c = geom.find("cylinder")
        ET.SubElement(out, "cylinder", {"radius": _number_text(c.find("radius"), f"{what} cylinder radius"),
                                        "length": _number_text(c.find("length"), f"{what} cylinder length")})
    elif geom.find("sphere") is not None:
        ET.SubElement(out, "sphere", {"radius": _number_text(geom.find("sphere/radius"), f"{what} sphere radius")})
    elif geom.find("mesh") is not None:
        m = geom.find("mesh")
        scale = _floats(m.find("scale").text if m.find("scale") is not None else None, 3, f"{what} scale", (1, 1, 1))
        ET.SubElement(out, "mesh", {"filename": _text(m.find("uri"), f"{what} mesh uri"), "scale": _fmt(scale)})
    else:
        raise FormatError(f"{what}: unsupported SDF geometry {[c.tag for c in geom]}")
    return out


def sdf_to_urdf(root: ET.Element, path: Path) -> ET.Element:
    """Convert the first ``<model>`` of an SDF file (link poses in the model frame) to URDF."""
    model = root.find(".//model")
    if model is None:
        raise FormatError("SDF file has no <model>")
    robot = ET.Element("robot", {"name": model.get("name", path.stem)})
    poses: dict[str, np.ndarray] = {}
    for link in model.findall("link"):
        name = link.get("name")
        poses[name] = _pose(link, f"link {name}")
        out = ET.SubElement(robot, "link", {"name": name})
        inertial = link.find("inertial")
        if inertial is not None:
            oi = ET.SubElement(out, "inertial")
            set_origin(oi, _pose(inertial, f"link {name} inertial"))
            mass = inertial.find("mass")
            ET.SubElement(oi, "mass", {"value": _number_text(mass, f"link {name}: inertial mass") if mass is not None else "0.1"})
            ine = inertial.find("inertia")
            vals = {k: (_number_text(ine.find(k), f"link {name}: inertia {k}") if ine is not None and ine.find(k) is not None
                        else "0") for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
            ET.SubElement(oi, "inertia", vals)
        for tag in ("visual", "collision"):
            for el in link.findall(tag):
                geom = el.find("geometry")
                if geom is None:
                    raise FormatError(f"link {name}: {tag} has no geometry")
                oe = ET.SubElement(out, tag)
                set_origin(oe, _pose(el, f"link {name} {tag}"))
                oe.append(_sdf_geometry(geom, f"link {name} {tag}"))
    for joint in model.findall("joint"):
        name = joint.get("name")
        parent, child = _text(joint.find("parent"), f"joint {name}: parent"), _text(joint.find("child"), f"joint {name}: child")
        if parent not in poses or child not in poses:
            raise FormatError(f"joint {name}: parent {parent!r} or child {child!r} is not a link of the model")
        if not np.allclose(_pose(joint, f"joint {name}"), np.eye(4)):
            raise FormatError(f"joint {name}: a non-zero joint <pose> is not supported")
        jtype = joint.get("type")
        if jtype not in ("fixed", "revolute", "prismatic", "continuous"):
            raise FormatError(f"joint {name}: unsupported SDF joint type {jtype!r}")
        oj = ET.SubElement(robot, "joint", {"name": name, "type": jtype})
        ET.SubElement(oj, "parent", {"link": parent})
        ET.SubElement(oj, "child", {"link": child})
        set_origin(oj, np.linalg.inv(poses[parent]) @ poses[child])
        axis = joint.find("axis")
        if jtype != "fixed" and axis is not None:
            xyz = _floats(axis.find("xyz").text, 3, f"joint {name} axis")
            upm = axis.find("use_parent_model_frame")
            if upm is not None and upm.text.strip() in ("1", "true"):
                xyz = poses[child][:3, :3].T @ xyz
            ET.SubElement(oj, "axis", {"xyz": _fmt(xyz)})
            lim = axis.find("limit")
            if lim is not None:
                attrs = {k: _text(lim.find(k), f"joint {name}: limit {k}")
                         for k in ("lower", "upper", "effort", "velocity") if lim.find(k) is not None}
                for k, v in attrs.items():
                    _number(v, f"joint {name}: limit {k}")
                ET.SubElement(oj, "limit", attrs)
    return robot


# --------------------------------------------------------------------------------------
# MJCF -> URDF
# --------------------------------------------------------------------------------------


class _MjcfDefaults:
    """MJCF default classes: class name -> tag -> attributes (inherited from parent classes)."""

    def __init__(self, root: ET.Element) -> None:
        self.classes: dict[str, dict[str, dict[str, str]]] = {}
        top = root.find("default")
        self._walk(top, "main", {}) if top is not None else self.classes.setdefault("main", {})

    def _walk(self, elem: ET.Element, name: str, inherited: dict[str, dict[str, str]]) -> None:
        own = {tag: dict(attrs) for tag, attrs in inherited.items()}
        for child in elem:
            if child.tag != "default":
                own.setdefault(child.tag, {}).update(child.attrib)
        self.classes[name] = own
        for child in elem.findall("default"):
            self._walk(child, child.get("class", name), own)

    def attrs(self, elem: ET.Element, childclass: str) -> dict[str, str]:
        cls = elem.get("class", childclass)
        if cls not in self.classes:
            raise FormatError(f"<{elem.tag} class={cls!r}>: unknown default class")
        out = dict(self.classes[cls].get(elem.tag, {}))
        out.update(elem.attrib)
        return out


def _mj_frame(attrs: dict[str, str], what: str, angle_deg: bool) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = _floats(attrs.get("pos"), 3, f"{what} pos", (0, 0, 0))
    if "quat" in attrs:
        m[:3, :3] = quat_wxyz_to_matrix(_floats(attrs["quat"], 4, f"{what} quat"))
    elif "euler" in attrs:
        e = _floats(attrs["euler"], 3, f"{what} euler")
        e = np.deg2rad(e) if angle_deg else e
        m[:3, :3] = rpy_to_matrix(e)
    elif "axisangle" in attrs:
        v = _floats(attrs["axisangle"], 4, f"{what} axisangle")
        ang = math.radians(v[3]) if angle_deg else v[3]
        k = v[:3] / np.linalg.norm(v[:3])
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        m[:3, :3] = np.eye(3) + math.sin(ang) * kx + (1 - math.cos(ang)) * kx @ kx
    return m


def mjcf_to_urdf(root: ET.Element, path: Path) -> ET.Element:
    """Convert an MJCF model (bodies, hinge/slide joints, primitive and mesh geoms) to URDF.

    A geom collides when its resolved ``contype`` or ``conaffinity`` is non-zero; geoms that
    do not collide become visuals. Capsules become a cylinder and two spheres.
    """
    compiler = root.find("compiler")
    angle_deg = compiler is None or compiler.get("angle", "degree") == "degree"
    meshdir = path.parent / (compiler.get("meshdir", "") if compiler is not None else "")
    defaults = _MjcfDefaults(root)
    meshes: dict[str, tuple[str, np.ndarray]] = {}
    for m in root.iter("mesh"):
        if m.get("file") is None:
            continue
        name = m.get("name") or Path(m.get("file")).stem
        attrs = defaults.attrs(m, "main")
        meshes[name] = (str((meshdir / m.get("file")).resolve()), _floats(attrs.get("scale"), 3, f"mesh {name} scale", (1, 1, 1)))
    world = root.find("worldbody")
    bodies = world.findall("body") if world is not None else []
    if len(bodies) != 1:
        raise FormatError(f"MJCF worldbody must hold exactly one root body, found {len(bodies)}")
    robot = ET.Element("robot", {"name": root.get("model", path.stem)})

    def add_geoms(link: ET.Element, body: ET.Element, childclass: str, T_link_body: np.ndarray) -> None:
        for g in body.findall("geom"):
            a = defaults.attrs(g, childclass)
            what = f"geom {g.get('name', '')} of body {body.get('name')}"
            gtype = a.get("type", "sphere")
            collides = _number(a.get("contype"), f"{what} contype", 1) != 0 or (
                _number(a.get("conaffinity"), f"{what} conaffinity", 1) != 0)
            tag = "collision" if collides else "visual"
            T = T_link_body @ _mj_frame(a, what, angle_deg)
            size = [_number(v, f"{what} size") for v in a.get("size", "0").split()]
            parts: list[tuple[np.ndarray, ET.Element]] = []
            if "fromto" in a and gtype in ("capsule", "cylinder"):
                ft = _floats(a["fromto"], 6, f"{what} fromto")
                p0, p1 = ft[:3], ft[3:]
                d = p1 - p0
                length = float(np.linalg.norm(d))
                z = d / length
                x = np.cross(z, [1, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1, 0])
                x /= np.linalg.norm(x)
                R = np.stack([x, np.cross(z, x), z], axis=1)
                Tl = np.eye(4)
                Tl[:3, :3], Tl[:3, 3] = R, (p0 + p1) / 2
                T = T_link_body @ Tl
                size = [size[0], length / 2]
            if gtype == "mesh":
                if a.get("mesh") not in meshes:
                    raise FormatError(f"{what}: mesh {a.get('mesh')!r} is not a file mesh asset")
                fn, sc = meshes[a["mesh"]]
                parts.append((T, ET.Element("mesh", {"filename": fn, "scale": _fmt(sc)})))
            elif gtype == "box":
                parts.append((T, ET.Element("box", {"size": _fmt(np.array(size[:3]) * 2)})))
            elif gtype == "sphere":
                parts.append((T, ET.Element("sphere", {"radius": f"{size[0]:.9g}"})))
            elif gtype in ("cylinder", "capsule"):
                r, h = size[0], size[1]
                parts.append((T, ET.Element("cylinder", {"radius": f"{r:.9g}", "length": f"{2 * h:.9g}"})))
                if gtype == "capsule":
                    for sgn in (-1, 1):
                        Ts = np.eye(4)
                        Ts[2, 3] = sgn * h
                        parts.append((T @ Ts, ET.Element("sphere", {"radius": f"{r:.9g}"})))
            elif gtype == "plane":
                continue
            else:
                raise FormatError(f"{what}: unsupported geom type {gtype!r}")
            for Tp, shape in parts:
                el = ET.SubElement(link, tag)
                set_origin(el, Tp)
                ET.SubElement(el, "geometry").append(shape)

    def add_body(body: ET.Element, parent: str | None, T_parent_body: np.ndarray, childclass: str) -> None:
        name = body.get("name")
        if not name:
            raise FormatError("an MJCF body has no name")
        childclass = body.get("childclass", childclass)
        joints = [j for j in body.findall("joint") if defaults.attrs(j, childclass).get("type", "hinge") != "free"]
        if len(joints) > 1:
            raise FormatError(f"body {name}: {len(joints)} joints in one body are not supported")
        T_link_body = np.eye(4)
        if parent is not None:
            oj_name = f"{name}_fixed"
            jtype, ja = "fixed", {}
            T_origin = T_parent_body
            if joints:
                ja = defaults.attrs(joints[0], childclass)
                oj_name = joints[0].get("name", f"{name}_joint")
                jtype = {"hinge": "revolute", "slide": "prismatic"}.get(ja.get("type", "hinge"))
                if jtype is None:
                    raise FormatError(f"joint {oj_name}: unsupported MJCF joint type {ja.get('type')!r}")
                anchor = np.eye(4)
                anchor[:3, 3] = _floats(ja.get("pos"), 3, f"joint {oj_name} pos", (0, 0, 0))
                T_origin = T_parent_body @ anchor
                T_link_body = np.linalg.inv(anchor)
            oj = ET.SubElement(robot, "joint", {"name": oj_name, "type": jtype})
            ET.SubElement(oj, "parent", {"link": parent})
            ET.SubElement(oj, "child", {"link": name})
            set_origin(oj, T_origin)
            if jtype != "fixed":
                ET.SubElement(oj, "axis", {"xyz": _fmt(_floats(ja.get("axis"), 3, f"joint {oj_name} axis", (0, 0, 1)))})
                rng = ja.get("range")
                if rng is None:
                    raise FormatError(f"joint {oj_name}: no range")
                lo, hi = _floats(rng, 2, f"joint {oj_name} range")
                if angle_deg and jtype == "revolute":
                    lo, hi = math.radians(lo), math.radians(hi)
                ET.SubElement(oj, "limit", {"lower": f"{lo:.9g}", "upper": f"{hi:.9g}", "effort": "10", "velocity": "2"})
        link = ET.SubElement(robot, "link", {"name": name})
        inertial = body.find("inertial")
        if inertial is not None:
            a = inertial.attrib
            oi = ET.SubElement(link, "inertial")
            Ti = T_link_body @ _mj_frame(a, f"body {name} inertial", angle_deg)
            if "fullinertia" in a:
                v = _floats(a["fullinertia"], 6, f"body {name} fullinertia")
                full = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
            else:
                full = np.diag(_floats(a.get("diaginertia"), 3, f"body {name} diaginertia", (1e-6, 1e-6, 1e-6)))
            inertia = Ti[:3, :3] @ full @ Ti[:3, :3].T
            Tp = np.eye(4)
            Tp[:3, 3] = Ti[:3, 3]
            set_origin(oi, Tp)
            ET.SubElement(oi, "mass", {"value": f"{max(_number(a.get('mass'), f'body {name} mass', 0.01), 1e-3):.9g}"})
            diag = np.maximum(np.diag(inertia), 1e-8)
            ET.SubElement(oi, "inertia", {"ixx": f"{diag[0]:.9g}", "iyy": f"{diag[1]:.9g}", "izz": f"{diag[2]:.9g}",
                                          "ixy": f"{inertia[0, 1]:.9g}", "ixz": f"{inertia[0, 2]:.9g}", "iyz": f"{inertia[1, 2]:.9g}"})
        if inertial is None:
            oi = ET.SubElement(link, "inertial")
            ET.SubElement(oi, "mass", {"value": "0.001"})
            ET.SubElement(oi, "inertia", {"ixx": "1e-8", "iyy": "1e-8", "izz": "1e-8", "ixy": "0", "ixz": "0", "iyz": "0"})
        add_geoms(link, body, childclass, T_link_body)
        for child in body.findall("body"):
            add_body(child, name, T_link_body @ _mj_frame(child.attrib, f"body {child.get('name')}", angle_deg), childclass)

    add_body(bodies[0], None, np.eye(4), "main")
    return robot
