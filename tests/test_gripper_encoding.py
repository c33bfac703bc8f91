"""Gripper TSDF encodings: exact geometry, agreement with a TSDF fused from rendered depth, caching."""

from __future__ import annotations

import warnings

import numpy as np
import pybullet as p
import pytest
import trimesh

from actors.bullet_gripper import BulletGripper
from common.camera import Intrinsics, depth_from_opengl_zbuffer, look_at, opengl_view_matrix
from common.config import GripperGridConfig
from common.geometry import Transform
from common.gripper import GripperModel, get_gripper
from common.gripper_encoding import (
    SAMPLES_PER_VOXEL,
    GripperEncoder,
    _GripperField,
    _PartField,
    encode_gripper,
    grid_points,
    gripper_key,
)
from common.tsdf import TSDFVolume


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("ADAGRASP_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))


def _per_view_distances(spec, opening: float, grid: GripperGridConfig, views: int = 42) -> np.ndarray:
    """(V, gX, gY, gZ) float64 metres: projective TSDF of the posed gripper fused from each rendered
    depth view on its own (common.tsdf.TSDFVolume), NaN where a view did not update the voxel."""
    c = p.connect(p.DIRECT)
    try:
        g = BulletGripper(c, spec, 1.0, visual_from_collision=True)
        g.reset(Transform.identity(), opening)
        ext = np.array(grid.shape) * grid.voxel_size
        origin = np.array([-ext[0] / 2, -ext[1] / 2, -grid.tcp_height])
        centre = origin + ext / 2
        w = 256
        f = w / 2 / np.tan(np.radians(22))
        K = Intrinsics(w, w, f, f, (w - 1) / 2, (w - 1) / 2)
        near, far = 0.05, 2.0
        proj = K.opengl_projection(near, far, 0.0).T.ravel().tolist()
        dirs = [[0, 1e-3, 1.0], [0, 1e-3, -1.0]]
        for el in (-60, -30, 0, 30, 60):
            for az in range(0, 360, 45):
                e, a = np.radians(el), np.radians(az + (22.5 if el in (-30, 30) else 0))
                dirs.append([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        out = []
        for d in dirs[:views]:
            T = look_at(centre + 0.55 * np.asarray(d), centre, up=(0, 0, 1) if abs(d[2]) < 0.99 else (1, 0, 0))
            img = p.getCameraImage(w, w, opengl_view_matrix(T).T.ravel().tolist(), proj,
                                   renderer=p.ER_TINY_RENDERER, physicsClientId=c)
            vol = TSDFVolume(origin, grid.voxel_size, grid.shape, grid.truncation)
            vol.integrate(depth_from_opengl_zbuffer(np.reshape(img[3], (w, w)), near, far), K, T)
            v = vol.tsdf().astype(np.float64) * grid.truncation
            v[vol.weight() == 0] = np.nan
            out.append(v)
        return np.stack(out)
    finally:
        p.disconnect(physicsClientId=c)


@pytest.mark.parametrize("name", ["parallel_jaw-0", "three_finger-1", "panda_hand", "xarm_gripper"])
def test_encoding_matches_tsdf_fused_from_rendered_depth(name):
    """Within one voxel of the rendered reference in the truncation band.

    Reference per voxel: the nearest surface any view saw in front of it (min over views of the
    projective distance, an upper bound of the true distance); inside voxels must not be seen as
    free space by any view.
    """
    grid = GripperGridConfig()
    spec = get_gripper(name)
    vals = _per_view_distances(spec, 0.6, grid)
    enc = encode_gripper(spec, 1.0, 0.6, grid)[0].astype(np.float64) * grid.truncation
    vox = grid.voxel_size
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nanmin(np.where(vals >= 0, vals, np.nan), axis=0)
        seen_free = np.nanmax(vals, axis=0)
    surface = np.isfinite(ref) & (ref < vox / 2)
    assert surface.sum() > 100
    assert np.mean(np.abs(enc[surface]) <= vox) >= 0.99
    band = (enc > 0) & (enc < grid.truncation) & np.isfinite(ref)
    assert np.mean(enc[band] <= ref[band] + vox) >= 0.99
    assert np.mean(np.abs(enc[band] - ref[band]) <= vox) >= 0.85
    inside = (enc < -vox / 2) & np.isfinite(seen_free)
    assert inside.sum() > 20
    assert np.mean(seen_free[inside] <= vox) >= 0.99


@pytest.mark.parametrize("name", ["panda_hand", "pr2_gripper", pytest.param("g1_three_finger", marks=pytest.mark.slow)])
def test_mesh_distance_close_to_exact_signed_distance(name):
    """Nearest-sample distances against trimesh's exact signed distance to the same hulls."""
    grid = GripperGridConfig()
    field = _GripperField(get_gripper(name), grid)
    got = field.sdf(0.5).ravel().astype(np.float64)
    pts = grid_points(grid).reshape(-1, 3)
    band = np.abs(got) < grid.truncation * 0.9
    exact = np.full(band.sum(), np.inf)
    for part, T in field.model.posed_parts(0.5):
        m = part.mesh.copy()
        m.apply_transform(T)
        exact = np.minimum(exact, -trimesh.proximity.signed_distance(m, pts[band]))
    err = np.abs(got[band] - exact)
    assert np.median(err) < 1e-3
    assert np.percentile(err, 99) < 0.5 * grid.voxel_size
    assert np.mean((np.sign(got[band]) == np.sign(exact)) | (np.abs(exact) < 1e-3)) > 0.995


@pytest.mark.parametrize("name", ["underactuated-0", "panda_hand", "xarm_gripper"])
def test_field_at_any_scale_matches_the_scaled_gripper(name):
    """One field built at scale 1 (mesh parts tabulated once) against the exact per-part distance of
    the gripper loaded at each scale; the scales run large to small, so the tables must widen."""
    grid = GripperGridConfig()
    spec = get_gripper(name)
    field = _GripperField(spec, grid)
    pts = grid_points(grid).reshape(-1, 3)
    trunc = grid.truncation
    errs = []
    for scale, opening in ((1.2, 1.0), (0.9, 0.4), (0.6, 0.7)):
        got = field.sdf(opening, scale).ravel().astype(np.float64)
        exact = np.full(len(pts), trunc)
        for part, T in GripperModel(spec, scale).posed_parts(opening):
            local = (pts - T[:3, 3]) @ T[:3, :3]
            part_field = _PartField(part, grid.voxel_size / SAMPLES_PER_VOXEL, grid.voxel_size)
            exact = np.minimum(exact, part_field.exact(local, trunc))
        band = np.abs(exact) < 0.9 * trunc
        assert band.sum() > 200
        errs.append(np.abs(got[band] - exact[band]) / grid.voxel_size)
    err = np.concatenate(errs)
    if name.startswith("underactuated"):
        assert err.max() < 1e-4
    else:
        assert np.median(err) < 0.06
        assert np.percentile(err, 99) < 0.4


def test_primitive_encoding_is_exact_for_a_box_finger():
    """A parallel jaw's pad face sits exactly where the kinematics put it."""
    grid = GripperGridConfig()
    spec = get_gripper("parallel_jaw-0")
    assert spec.params["pad_shape"] == "flat"
    enc = encode_gripper(spec, 1.0, 1.0, grid)[0] * grid.truncation
    pts = grid_points(grid)
    half_gap = GripperModel(spec).aperture(1.0) / 2
    k = int(np.argmin(np.abs(pts[0, 0, :, 2])))
    centre_line = (np.abs(pts[..., 1]) < grid.voxel_size) & (np.arange(grid.shape[2]) == k)
    between = centre_line & (np.abs(pts[..., 0]) < half_gap)
    assert np.allclose(enc[between], half_gap - np.abs(pts[..., 0][between]), atol=1e-5)


def test_encoding_shape_range_sign_and_frame():
    grid = GripperGridConfig(shape=(32, 32, 16), voxel_size=0.008)
    enc = encode_gripper(get_gripper("wsg_50"), 1.0, 1.0, grid)
    assert enc.shape == (2, 32, 32, 16) and enc.dtype == np.float32
    assert enc.min() == -1.0 or enc.min() < 0 and enc.max() == 1.0
    assert np.all(np.abs(enc) <= 1.0)
    open_, closed = enc
    # fingers point down: occupied voxels below the TCP exist, and the open fingers are wider apart
    occ_open = np.argwhere(open_ < 0)
    occ_closed = np.argwhere(closed < 0)
    assert occ_open[:, 2].min() * grid.voxel_size < grid.tcp_height
    assert np.ptp(occ_open[:, 0]) > np.ptp(occ_closed[:, 0])
    # closing along x: the open gap is along x, not y
    assert np.ptp(occ_open[:, 0]) > np.ptp(occ_open[:, 1])


def test_paper_grid_and_scale():
    grid = GripperGridConfig(shape=(64, 64, 32), voxel_size=0.004)
    spec = get_gripper("three_finger-2")
    a = encode_gripper(spec, 0.8, 1.0, grid)
    b = encode_gripper(spec, 1.2, 1.0, grid)
    assert a.shape == (2, 64, 64, 32)
    assert (a[0] < 0).sum() < (b[0] < 0).sum()


def test_encoder_caches_in_memory_and_on_disk(tmp_path):
    grid = GripperGridConfig()
    spec = get_gripper("revolute-3")
    enc = GripperEncoder(grid, cache_dir=tmp_path)
    x = enc.encode(spec, 1.1, (0.5, 1.0))
    assert x.shape == (2, 2, *grid.shape) and x.dtype == np.float32
    assert np.array_equal(x[0, 1], x[1, 1])
    assert np.allclose(x[1], encode_gripper(spec, 1.1, 1.0, grid), atol=1e-6)
    files = sorted(tmp_path.rglob("*.npy"))
    assert len(files) == 3
    again = GripperEncoder(grid, cache_dir=tmp_path).encode(spec, 1.1, (1.0, 0.5))
    assert np.array_equal(again[0], x[1]) and np.array_equal(again[1], x[0])
    np.save(files[0], np.zeros(3, dtype=np.float32))
    healed = GripperEncoder(grid, cache_dir=tmp_path).encode(spec, 1.1, (0.5, 1.0))
    assert np.array_equal(healed, x)
    with pytest.raises(ValueError):
        enc.encode(spec, 1.1, (1.5,))


def test_gripper_key():
    assert gripper_key("wsg_50", 1.1, (0.5, 1.0)) == "wsg_50@1.1000:0.5000,1.0000"
    assert gripper_key("a", 1.0, (0.5,)) != gripper_key("a", 1.0, (0.6,))
