"""Gripper TSDF encodings on the gripper grid, computed from the URDF geometry and cached.

Pipeline: forward kinematics (yourdfpy) -> posed collision parts -> signed distance at every
voxel centre -> distance / truncation clipped to [-1, 1]. Sign convention as the scene TSDF:
positive in free space, negative inside the gripper.

Signed distance per part, evaluated only on the grid block that the part's posed bounding box
(plus the truncation distance) covers, combined by a minimum over parts:

- boxes, spheres, cylinders: exact analytic distance;
- meshes, as their convex hulls (what PyBullet collides): distance to the nearest of dense
  surface samples (spacing a third of a voxel, KD-tree in the part frame), signed by that
  sample's face normal, or by the exact convex inside test where the normal is ambiguous (near
  edges and corners) or no sample lies within the truncation. This is tabulated once per part
  on a lattice one voxel apart; an encoding interpolates the table trilinearly (within 0.31
  voxel of the direct evaluation at the 99th percentile on the real grippers).

Everything is built once per gripper and grid at scale 1: a gripper at scale ``s`` is the same
gripper scaled uniformly about its TCP, so its field is ``s * field_1(p / s)``. A new (scale,
opening) costs forward kinematics and interpolation (milliseconds; tests/bench/bench_grippers.py).

Grid frame: the TCP frame at yaw 0 (fingers along -z, closing along x); voxel (i, j, k) has its
centre at ``((i + 0.5 - gX / 2) v, (j + 0.5 - gY / 2) v, (k + 0.5) v - tcp_height)``.

Usage::

    enc = GripperEncoder(cfg.gripper_grid)                  # memory + disk cache
    x = enc.encode(spec, scale=1.1, openings=(0.5, 1.0))    # (S, 2, gX, gY, gZ) float32
    key = gripper_key(spec.name, 1.1, (0.5, 1.0))           # the replay's table key
    one = encode_gripper(spec, 1.0, 0.75, cfg.gripper_grid) # (2, gX, gY, gZ), no cache
"""

from __future__ import annotations

import hashlib
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
import trimesh
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from common.config import GripperGridConfig
from common.gripper import GripperModel, GripperSpec, _sample_surface, cache_root

ENCODING_VERSION = "3"
"""Bumped when the encoding changes, so disk caches are not reused across versions."""
SAMPLES_PER_VOXEL = 3.0
"""Mesh surface samples per voxel edge (sample spacing = voxel_size / this)."""
KD_EPS = 0.1
"""Approximate nearest-sample search: the sample found is within (1 + KD_EPS) of the nearest
(below 1 mm difference on the real grippers at the default grid; 1.6x faster)."""
LATTICE_PER_VOXEL = 1.0
"""Mesh parts' tabulated distance: lattice points per grid voxel edge."""


def grid_points(grid: GripperGridConfig) -> np.ndarray:
    """(gX, gY, gZ, 3) float64 voxel centres in the TCP frame, metres."""
    gx, gy, gz = grid.shape
    v = grid.voxel_size
    axes = [(np.arange(gx) + 0.5 - gx / 2) * v, (np.arange(gy) + 0.5 - gy / 2) * v, (np.arange(gz) + 0.5) * v - grid.tcp_height]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def gripper_key(name: str, scale: float, openings: tuple[float, ...]) -> str:
    """Key of one gripper encoding set, e.g. ``wsg_50@1.1000:0.5000,1.0000`` (name, scale, openings)."""
    return f"{name}@{float(scale):.4f}:" + ",".join(f"{float(o):.4f}" for o in openings)


def _box_sdf(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(p) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    return outside + np.minimum(q.max(axis=-1), 0.0)


def _cylinder_sdf(p: np.ndarray, r: float, half_len: float) -> np.ndarray:
    d = np.stack([np.hypot(p[:, 0], p[:, 1]) - r, np.abs(p[:, 2]) - half_len], axis=-1)
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0)


class _PartField:
    """Signed distance of one collision part in its own frame, at gripper scale 1."""

    def __init__(self, part, spacing: float, lattice: float) -> None:
        self.kind, self.size = part.kind, part.size
        m = part.mesh
        self.lo_bound, self.hi_bound = np.asarray(m.bounds[0], dtype=np.float64), np.asarray(m.bounds[1], dtype=np.float64)
        self.corners = np.array([[x, y, z] for x in m.bounds[:, 0] for y in m.bounds[:, 1] for z in m.bounds[:, 2]])
        self.lattice = lattice
        self.table: np.ndarray | None = None
        self.pad = 0.0
        if part.kind == "mesh":
            n = int(np.clip(m.area / spacing**2, 500, 400_000))
            pts, faces = _sample_surface(m, n)
            self.tree = cKDTree(pts)
            self.sample_normals = np.asarray(m.face_normals)[faces]
            snap = spacing / 2
            coarse = trimesh.convex.convex_hull(np.unique(np.round(np.asarray(m.vertices) / snap), axis=0) * snap)
            normals = np.asarray(coarse.face_normals)
            offsets = np.einsum("ij,ij->i", normals, np.asarray(coarse.triangles)[:, 0])
            planes = np.unique(np.round(np.column_stack([normals, offsets]), 6), axis=0)
            self.normals, self.offsets = planes[:, :3], planes[:, 3]
            self.spacing = spacing

    def exact(self, p: np.ndarray, bound: float) -> np.ndarray:
        """(N,) signed distance (m) of points (N, 3) in the part frame, clipped to +-``bound``; negative inside.

        Meshes are convex hulls. Magnitude: distance to the nearest surface sample. Sign: from that
        sample's face normal when the offset points clearly along or against it; otherwise (and
        for points with no sample within ``bound``) from the convex inside test (largest
        face-plane distance, which inside is also the distance) on the hull of the vertices
        snapped to half the sample spacing (a few hundred planes instead of thousands); points
        outside the hull's bounding box are outside without a test.
        """
        if self.kind == "box":
            return np.clip(_box_sdf(p, self.size), -bound, bound)
        if self.kind == "sphere":
            return np.clip(np.linalg.norm(p, axis=-1) - self.size[0], -bound, bound)
        if self.kind == "cylinder":
            return np.clip(_cylinder_sdf(p, self.size[0], self.size[1]), -bound, bound)
        d, idx = self.tree.query(p, k=1, distance_upper_bound=bound, eps=KD_EPS)
        found = np.isfinite(d)
        idx[~found] = 0
        along = np.einsum("ij,ij->i", p - self.tree.data[idx], self.sample_normals[idx])
        sure = found & ((np.abs(along) > 0.5 * d) | (d < self.spacing))
        in_box = np.all((p >= self.lo_bound) & (p <= self.hi_bound), axis=1)
        out = np.where(in_box & (along < 0.0), -d, np.where(found, d, bound))
        unsure = ~sure & in_box
        if unsure.any():
            plane = (p[unsure] @ self.normals.T - self.offsets).max(axis=1)
            mag = np.where(found[unsure], d[unsure], bound)
            out[unsure] = np.where(plane <= 0.0, np.maximum(plane, -mag), mag)
        return np.clip(out, -bound, bound)

    def _build_table(self, pad: float) -> None:
        """Tabulate :meth:`exact` on a lattice (spacing ``self.lattice``) over the bounds +- ``pad``."""
        lo = self.lo_bound - pad
        n = np.ceil((self.hi_bound + pad - lo) / self.lattice).astype(int) + 1
        axes = [lo[a] + np.arange(n[a]) * self.lattice for a in range(3)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        self.table = self.exact(pts, pad).reshape(n).astype(np.float32)
        self.table_lo, self.pad = lo, pad

    def sdf(self, p: np.ndarray, bound: float) -> np.ndarray:
        """(N,) signed distance (m) of points (N, 3) in the part frame, clipped to +-``bound``; negative inside.

        Primitives: exact. Meshes: trilinear interpolation of :meth:`exact` tabulated once on a
        lattice around the part (one grid voxel apart), which reaches ``bound`` plus two lattice
        steps beyond the part (rebuilt wider when a smaller gripper scale asks for more); points
        off the lattice are at least that far away.
        """
        if self.kind != "mesh":
            return self.exact(p, bound)
        need = bound + 2 * self.lattice
        if self.table is None or self.pad < need:
            self._build_table(1.25 * max(need, self.pad))
        coords = ((p - self.table_lo) / self.lattice).T
        out = map_coordinates(self.table, coords, order=1, mode="constant", cval=self.pad, prefilter=False)
        return np.clip(out.astype(np.float64), -bound, bound)


def _part_identity(part) -> bytes:
    """Digest of a part's geometry in its own frame: mirrored fingers built from one mesh share a field."""
    h = hashlib.sha1(f"{part.kind}|{np.asarray(part.size).tobytes().hex()}".encode())
    h.update(np.ascontiguousarray(part.mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(part.mesh.faces, dtype=np.int64).tobytes())
    return h.digest()


class _GripperField:
    """Signed distance field of one gripper on one grid, at any scale and opening.

    Built once per gripper at scale 1: every gripper scale is the same geometry scaled uniformly
    about the TCP (joint origins, prismatic travel and meshes alike), so the field at scale ``s``
    is ``s * field_1(p / s)``; forward kinematics per opening.
    """

    def __init__(self, spec: GripperSpec, grid: GripperGridConfig) -> None:
        self.model = GripperModel(spec, 1.0)
        self.grid = grid
        self.points = grid_points(grid)
        self.lo = self.points[0, 0, 0]
        spacing = grid.voxel_size / SAMPLES_PER_VOXEL
        lattice = grid.voxel_size / LATTICE_PER_VOXEL
        shared: dict[bytes, _PartField] = {}
        self.fields = []
        for part in self.model.parts:
            key = _part_identity(part)
            if key not in shared:
                shared[key] = _PartField(part, spacing, lattice)
            self.fields.append(shared[key])

    def sdf(self, opening: float, scale: float = 1.0) -> np.ndarray:
        """(gX, gY, gZ) float32 signed distance (m) clipped to +-truncation, TCP frame, gripper at ``scale``."""
        g, trunc, v = self.grid, self.grid.truncation, self.grid.voxel_size
        s = float(scale)
        out = np.full(g.shape, trunc, dtype=np.float64)
        for (part, T), field in zip(self.model.posed_parts(opening), self.fields):
            R, t = T[:3, :3], s * T[:3, 3]
            corners = s * (field.corners @ R.T) + t
            i0 = np.floor((corners.min(axis=0) - trunc - self.lo) / v).astype(int)
            i1 = np.ceil((corners.max(axis=0) + trunc - self.lo) / v).astype(int) + 1
            i0 = np.clip(i0, 0, g.shape)
            i1 = np.clip(i1, 0, g.shape)
            if np.any(i1 <= i0):
                continue
            sl = tuple(slice(a, b) for a, b in zip(i0, i1))
            pts = self.points[sl].reshape(-1, 3)
            local = ((pts - t) @ R) / s
            block = out[sl]
            np.minimum(block, s * field.sdf(local, trunc * 1.01 / s).reshape(block.shape), out=block)
        np.clip(out, -trunc, trunc, out=out)
        return out.astype(np.float32)


def encode_gripper(spec: GripperSpec, scale: float, opening: float, grid: GripperGridConfig) -> np.ndarray:
    """(2, gX, gY, gZ) float32 TSDF / truncation in [-1, 1] at ``opening`` (channel 0) and closed
    (channel 1); TCP frame at yaw 0, grid centred on the TCP in x, y, TCP ``grid.tcp_height`` above
    the grid bottom, fingers pointing -z; > 0 free space. No cache (see :class:`GripperEncoder`)."""
    field = _GripperField(spec, grid)
    out = np.stack([field.sdf(opening, scale), field.sdf(0.0, scale)]) / np.float32(grid.truncation)
    assert out.shape == (2, *grid.shape) and out.dtype == np.float32, out.shape
    return out


def _grid_tag(grid: GripperGridConfig) -> str:
    return "g{}x{}x{}_v{:.5f}_h{:.5f}_t{:.3f}".format(*grid.shape, grid.voxel_size, grid.tcp_height, grid.truncation_voxels)


def spec_tag(spec: GripperSpec) -> str:
    """Identity of a gripper's geometry and TCP: processed URDF folder (content hash) + TCP fields."""
    text = f"{ENCODING_VERSION}|{spec.urdf}|{spec.tcp_position}|{spec.approach_axis}|{spec.closing_axis}"
    text += "|" + "|".join(f"{d.name}:{d.open}:{d.closed}" for d in spec.drive_joints)
    text += "|" + "|".join(f"{c.joint}:{c.driver}:{c.multiplier}:{c.offset}" for c in spec.couplings)
    return f"{spec.name}-{hashlib.sha1(text.encode()).hexdigest()[:12]}"


class GripperEncoder:
    """Gripper encodings cached in memory (LRU) and on disk, keyed by (gripper, scale, opening, grid).

    Disk cache: ``<cache>/grippers/encodings/<grid>/<gripper>-<hash>/s<scale>_o<opening>.npy``
    (``disk=False`` turns it off). Writes are atomic, so parallel actors may share the folder.
    """

    def __init__(self, grid: GripperGridConfig, disk: bool = True, memory_items: int = 512,
                 cache_dir: Path | None = None) -> None:
        self.grid = grid
        self.disk = disk
        self.memory_items = memory_items
        self.root = (cache_dir or cache_root() / "grippers" / "encodings") / _grid_tag(grid)
        self._memory: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._fields: OrderedDict[str, _GripperField] = OrderedDict()

    def _field(self, spec: GripperSpec) -> _GripperField:
        key = spec_tag(spec)
        if key not in self._fields:
            self._fields[key] = _GripperField(spec, self.grid)
            while len(self._fields) > 8:
                self._fields.popitem(last=False)
        self._fields.move_to_end(key)
        return self._fields[key]

    def _one(self, spec: GripperSpec, scale: float, opening: float) -> np.ndarray:
        """(gX, gY, gZ) float32 TSDF / truncation at one opening (cached)."""
        tag = spec_tag(spec)
        key = (tag, round(float(scale), 6), round(float(opening), 6))
        hit = self._memory.get(key)
        if hit is not None:
            self._memory.move_to_end(key)
            return hit
        path = self.root / tag / f"s{float(scale):.6f}_o{float(opening):.6f}.npy"
        arr = None
        if self.disk and path.is_file():
            try:
                arr = np.load(path)
            except (OSError, ValueError):
                arr = None
            if arr is not None and (arr.shape != self.grid.shape or arr.dtype != np.float32):
                arr = None
        if arr is None:
            arr = self._field(spec).sdf(opening, scale) / np.float32(self.grid.truncation)
            if self.disk:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.npy")
                np.save(tmp, arr)
                os.replace(tmp, path)
        arr.setflags(write=False)
        self._memory[key] = arr
        while len(self._memory) > self.memory_items:
            self._memory.popitem(last=False)
        return arr

    def encode(self, spec: GripperSpec, scale: float, openings: tuple[float, ...]) -> np.ndarray:
        """(S, 2, gX, gY, gZ) float32 TSDF / truncation at each opening (channel 0) and closed (channel 1)."""
        if len(openings) == 0 or any(not 0.0 <= o <= 1.0 for o in openings):
            raise ValueError(f"openings must be a non-empty tuple of values in [0, 1], got {openings}")
        closed = self._one(spec, scale, 0.0)
        out = np.stack([np.stack([self._one(spec, scale, o), closed]) for o in openings])
        assert out.shape == (len(openings), 2, *self.grid.shape) and out.dtype == np.float32, out.shape
        return out
