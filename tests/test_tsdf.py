"""Cameras and TSDF fusion against an analytic scene: a sphere resting on the table.

Depth images are ray-cast analytically (first hit of the sphere or the plane z = 0), fused, and
compared with the scene's exact signed distance ``min(|p - c| - r, z)``.

The projective TSDF stores the distance along the optical axis, which equals the true distance
only where the surface faces the camera; near silhouettes and in occlusion shadows it is
known to differ (Curless & Levoy). The checks therefore look at voxels whose nearest surface
point every camera sees, with one voxel of clearance from the sphere's occluding contour, at an
incidence angle below a bound stated per check.
"""

from __future__ import annotations

import numpy as np
import pytest

from common.camera import (
    Intrinsics,
    depth_from_opengl_zbuffer,
    fit_intrinsics,
    look_at,
    opengl_view_matrix,
    ring_cameras,
    scene_cameras,
    top_down_camera,
)
from common.config import SceneGridConfig, load_config
from common.geometry import Transform, voxel_centers
from common.tsdf import ObservationFuser, TSDFVolume, fuse_observation, heightmap_from_tsdf

CENTRE = np.array([0.013, -0.021, 0.03])
"""Sphere centre (m, world); off the voxel lattice on purpose."""
RADIUS = 0.03
"""Sphere radius (m); the sphere touches the table."""


def raycast(intrinsics: Intrinsics, T_world_cam: Transform, centre=CENTRE, radius=RADIUS):
    """Depth (H, W) float32 m along the optical axis of the first hit of sphere or table (inf if
    none), and (H, W) bool True where the sphere is hit first."""
    rays = intrinsics.pixel_rays() @ T_world_cam.rotation.T  # world directions, unit camera z
    o = T_world_cam.translation
    oc = o - centre
    a = np.einsum("hwc,hwc->hw", rays, rays)
    b = rays @ oc
    disc = b * b - a * (oc @ oc - radius * radius)
    s_sphere = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)
    s_sphere = np.where(s_sphere > 0, s_sphere, np.inf)
    with np.errstate(divide="ignore"):
        s_table = np.where(rays[..., 2] < 0, -o[2] / rays[..., 2], np.inf)
    return np.minimum(s_sphere, s_table).astype(np.float32), s_sphere < s_table


def scene_sdf(points: np.ndarray, centre=CENTRE, radius=RADIUS):
    """Signed distance (...,) of sphere + table, nearest surface points (..., 3) and normals (..., 3)."""
    d = points - centre
    nd = np.linalg.norm(d, axis=-1, keepdims=True)
    sphere = nd[..., 0] - radius
    on_sphere = sphere < points[..., 2]
    q = np.where(on_sphere[..., None], centre + radius * d / nd, points * np.array([1.0, 1.0, 0.0]))
    n = np.where(on_sphere[..., None], d / nd, np.array([0.0, 0.0, 1.0]))
    return np.minimum(sphere, points[..., 2]), q, n


def clear_view(eye: np.ndarray, q: np.ndarray, n: np.ndarray, clearance: float, centre=CENTRE, radius=RADIUS):
    """(...,) bool: surface point q (normal n) faces ``eye`` and, if on the table, the segment
    eye -> q passes the sphere with ``clearance`` m to spare; also returns cos(incidence)."""
    to_eye = eye - q
    cos = np.einsum("...c,...c->...", to_eye, n) / np.linalg.norm(to_eye, axis=-1)
    seg = q - eye
    t = np.clip(np.einsum("...c,c->...", -seg, eye - centre) / np.einsum("...c,...c->...", seg, seg), 0.0, 1.0)
    miss = np.linalg.norm(eye + t[..., None] * seg - centre, axis=-1) >= radius + clearance
    on_table = q[..., 2] < 1e-9
    return (cos > 0) & (~on_table | miss), cos


def fuse_sphere(grid: SceneGridConfig, cameras):
    depths, masks = zip(*(raycast(k, t) for k, t in cameras))
    obs = fuse_observation(grid, list(depths), cameras, list(masks))
    points = voxel_centers(grid.origin, grid.voxel_size, grid.shape)
    sdf, q, n = scene_sdf(points)
    seen = np.ones(sdf.shape, dtype=bool)
    cos_min = np.ones(sdf.shape)
    for _, T_world_cam in cameras:
        vis, cos = clear_view(T_world_cam.translation, q, n, grid.voxel_size)
        seen &= vis
        cos_min = np.minimum(cos_min, cos)
    return obs, sdf, seen, cos_min


def _cameras(cfg, n):
    cfg.sim.cameras = n
    return scene_cameras(cfg.scene_grid, cfg.sim)


# --------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", ["default", "paper"])
@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_cameras_see_whole_workspace_with_tight_images(config, n):
    cfg = load_config(config)
    g = cfg.scene_grid
    cams = _cameras(cfg, n)
    assert len(cams) == n
    corners = np.array([[x, y, z] for x in g.x_range for y in g.y_range for z in g.z_range])
    for k, T_world_cam in cams:
        p = T_world_cam.inverse().apply(corners)
        u = k.fx * p[:, 0] / p[:, 2] + k.cx
        v = k.fy * p[:, 1] / p[:, 2] + k.cy
        assert np.all(p[:, 2] > 0)
        assert u.min() >= -0.5 and u.max() <= k.width - 0.5
        assert v.min() >= -0.5 and v.max() <= k.height - 0.5
        # tight: the box spans all but at most one pixel of the image in each direction
        assert u.max() - u.min() > k.width - 2 and v.max() - v.min() > k.height - 2
        # about one pixel per voxel at the look-at point
        dist = np.linalg.norm(T_world_cam.translation - np.array([0.0, 0.0, 0.0 if n == 1 else np.mean(g.z_range)]))
        assert k.fx == pytest.approx(dist * cfg.sim.image_pixels_per_voxel / g.voxel_size, rel=1e-9)


def test_top_down_camera_one_pixel_per_voxel_on_table():
    cfg = load_config("default")
    k, T = top_down_camera(cfg.scene_grid, 0.6, 1.0)
    assert np.allclose(T.rotation[:, 2], [0, 0, -1])  # looks straight down
    # two table points one voxel apart along x land one pixel apart
    p = T.inverse().apply(np.array([[0.0, 0.0, 0.0], [cfg.scene_grid.voxel_size, 0.0, 0.0]]))
    du = k.fx * (p[1, 0] / p[1, 2] - p[0, 0] / p[0, 2])
    assert du == pytest.approx(1.0)
    assert (k.width, k.height) == (124, 124)


def test_ring_cameras_evenly_spread_and_aimed_at_centre():
    g = SceneGridConfig()
    for n in (2, 3, 4):
        cams = ring_cameras(g, n, radius=0.45, height=0.6, pixels_per_voxel=1.0)
        az = sorted(np.mod(np.arctan2(t.translation[1], t.translation[0]), 2 * np.pi) for _, t in cams)
        assert np.allclose(np.diff(az + [az[0] + 2 * np.pi]), 2 * np.pi / n)
        for k, t in cams:
            assert np.hypot(*t.translation[:2]) == pytest.approx(0.45)
            assert t.translation[2] == pytest.approx(0.6)
            c = t.inverse().apply(np.array([0.0, 0.0, np.mean(g.z_range)]))
            assert np.allclose(c[:2], 0.0, atol=1e-12)  # centre on the optical axis


def test_look_at_is_opencv_convention():
    T = look_at(eye=(1.0, 0.0, 0.0), target=(0.0, 0.0, 0.0))
    p = T.inverse().apply(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1], [0.0, 0.1, 0.0]]))
    assert p[0] == pytest.approx([0.0, 0.0, 1.0])  # target straight ahead
    assert p[1][1] < 0  # world up appears up in the image (negative y)
    assert p[2][0] > 0  # world +y is to the right when looking along -x
    assert np.allclose(T.rotation @ T.rotation.T, np.eye(3)) and np.linalg.det(T.rotation) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 1), (0, 0, 0))
    with pytest.raises(ValueError, match="coincide"):
        look_at((0, 0, 1), (0, 0, 1))


def test_pybullet_render_matches_intrinsics():
    """The OpenGL helpers reproduce the pinhole model in PyBullet's DIRECT renderer to float
    precision (tilted and rolled cameras, off-centre principal points)."""
    pybullet = pytest.importorskip("pybullet")
    g = SceneGridConfig()
    client = pybullet.connect(pybullet.DIRECT)
    try:
        table = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=[1, 1, 0.001], physicsClientId=client)
        pybullet.createMultiBody(0, -1, table, basePosition=[0, 0, -0.001], physicsClientId=client)
        near, far = 0.05, 2.0
        for up in [(0, 0, 1), (0, 1, 0), (1, 1, 1)]:
            T = look_at((0.45, 0.1, 0.6), (0.0, 0.0, 0.06), up)
            k = fit_intrinsics(g, T, 175.0)
            _, _, _, zbuf, _ = pybullet.getCameraImage(
                k.width,
                k.height,
                opengl_view_matrix(T).T.ravel().tolist(),
                k.opengl_projection(near, far).T.ravel().tolist(),
                renderer=pybullet.ER_TINY_RENDERER,
                physicsClientId=client,
            )
            depth = depth_from_opengl_zbuffer(np.reshape(zbuf, k.shape), near, far)
            ref, _ = raycast(k, T, radius=0.0)
            assert np.abs(depth - ref).max() < 1e-4, up
    finally:
        pybullet.disconnect(client)


# --------------------------------------------------------------------------------------
# TSDF against the analytic sphere
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", ["default", "paper"])
@pytest.mark.parametrize("n", [1, 4])
def test_tsdf_matches_analytic_sphere(config, n):
    cfg = load_config(config)
    g = cfg.scene_grid
    v, trunc = g.voxel_size, g.truncation
    obs, sdf, seen, cos_min = fuse_sphere(g, _cameras(cfg, n))
    est = obs.tsdf * trunc
    assert obs.tsdf.min() >= -1.0 and obs.tsdf.max() <= 1.0
    # Distance within one voxel: one top-down camera, the whole band (but its last voxel, where
    # nearest-pixel rounding decides whether a voxel is updated at all), surfaces within 20 deg
    # of facing the camera; four oblique cameras (incidence 40-50 deg), 1.5 voxels of the surface.
    if n == 1:
        near = seen & (cos_min >= np.cos(np.radians(20))) & (np.abs(sdf) <= trunc - v)
    else:
        near = seen & (cos_min >= np.cos(np.radians(45))) & (np.abs(sdf) <= 1.5 * v)
    assert near.sum() > 5000
    err = np.abs(est - sdf)[near]
    assert err.max() <= v, f"max error {err.max() / v:.2f} voxels"
    # Sign: every visible surface within 60 deg of facing the cameras, every voxel whose distance
    # along the view ray (about |sdf| / cos) lies in the band but its ends.
    band = seen & (cos_min >= np.cos(np.radians(60))) & (np.abs(sdf) >= v) & (np.abs(sdf) <= (trunc - v) * cos_min)
    assert band.sum() > 5000
    assert np.all(np.sign(est[band]) == np.sign(sdf[band]))
    # Inside the sphere well beyond the band: never observed, reads +1 (documented choice).
    deep = sdf < -(trunc + 2 * v)
    assert deep.any() and np.all(obs.tsdf[deep] == 1.0)


@pytest.mark.parametrize("config", ["default", "paper"])
@pytest.mark.parametrize("n", [1, 4])
def test_heightmap_of_sphere_top(config, n):
    cfg = load_config(config)
    g = cfg.scene_grid
    cams = _cameras(cfg, n)
    obs, *_ = fuse_sphere(g, cams)
    xy = voxel_centers(g.origin, g.voxel_size, g.shape)[:, :, 0, :2]
    rho = np.linalg.norm(xy - CENTRE[:2], axis=-1)
    top = rho <= RADIUS / 2
    truth = CENTRE[2] + np.sqrt(np.maximum(RADIUS**2 - rho**2, 0.0))
    assert top.sum() > 10
    assert np.abs(obs.heightmap[top] - truth[top]).max() <= g.voxel_size
    far = rho > RADIUS + 3 * g.truncation
    assert np.all(obs.heightmap[far] == 0.0)
    assert obs.valid.mean() > 0.99


@pytest.mark.parametrize("n", [1, 4])
def test_obstacle_channel(n):
    cfg = load_config("default")
    g = cfg.scene_grid
    obs, sdf, seen, cos_min = fuse_sphere(g, _cameras(cfg, n))
    points = voxel_centers(g.origin, g.voxel_size, g.shape)
    dist_sphere = np.linalg.norm(points - CENTRE, axis=-1) - RADIUS
    # voxels within a voxel of the sphere's upper half (away from the table contact), where it
    # faces every camera (the oblique ring sees even the sphere's top at 40-50 deg)
    facing = np.cos(np.radians(45 if n == 1 else 70))
    on_sphere = seen & (np.abs(dist_sphere) <= g.voxel_size) & (cos_min >= facing) & (points[..., 2] > CENTRE[2])
    assert on_sphere.sum() > 50
    assert obs.obstacle[on_sphere].min() >= 0.99
    table_far = (np.linalg.norm(points[..., :2] - CENTRE[:2], axis=-1) > RADIUS + 3 * g.truncation) & (
        points[..., 2] < g.truncation
    )
    assert np.all(obs.obstacle[table_far] == 0.0)
    assert obs.obstacle.min() >= 0.0 and obs.obstacle.max() <= 1.0


def test_fuser_reuse_equals_one_off_fusion():
    cfg = load_config("default")
    cams = _cameras(cfg, 3)
    depths, masks = zip(*(raycast(k, t) for k, t in cams))
    fuser = ObservationFuser(cfg.scene_grid, cams)
    first = fuser.fuse(depths, masks)
    again = fuser.fuse(depths, masks)
    once = fuse_observation(cfg.scene_grid, list(depths), cams, list(masks))
    for a in (again, once):
        for name in ("tsdf", "obstacle", "heightmap", "valid"):
            assert np.array_equal(getattr(first, name), getattr(a, name)), name


def test_vectorised_integration_equals_per_voxel_loop():
    """The vectorised kernel against a plain Curless-Levoy running average, voxel by voxel, with
    arbitrary intrinsics (fx != fy, off-centre), poses and depth images with holes."""
    rng = np.random.default_rng(7)
    origin, voxel, shape, trunc = np.array([-0.05, -0.04, 0.0]), 0.01, (9, 8, 6), 0.025
    vol = TSDFVolume(origin, voxel, shape, trunc)
    ref_tsdf = np.ones(shape)
    ref_w = np.zeros(shape)
    ref_obs, ref_ow = np.zeros(shape), np.zeros(shape)
    centres = voxel_centers(origin, voxel, shape)
    for eye in ([0.3, 0.1, 0.4], [-0.2, -0.25, 0.3]):
        T = look_at(eye, [0.0, 0.0, 0.03], up=(0.3, 1.0, 1.0))
        k = Intrinsics(width=23, height=17, fx=31.0, fy=27.0, cx=9.3, cy=10.1)
        depth = rng.uniform(0.3, 0.6, size=k.shape).astype(np.float32)
        depth[rng.random(k.shape) < 0.1] = np.nan
        depth[rng.random(k.shape) < 0.1] = 0.0
        depth[rng.random(k.shape) < 0.05] = np.inf
        mask = rng.random(k.shape) < 0.5
        vol.integrate(depth, k, T, mask)
        cam = T.inverse()
        for idx in np.ndindex(*shape):
            x, y, z = cam.apply(centres[idx])
            if z <= 0:
                continue
            u, r = int(np.rint(k.fx * x / z + k.cx)), int(np.rint(k.fy * y / z + k.cy))
            if not (0 <= u < k.width and 0 <= r < k.height):
                continue
            d = float(depth[r, u])
            if not (np.isfinite(d) and d > 0) or d - z < -trunc:
                continue
            dist = min(1.0, (d - z) / trunc)
            ref_tsdf[idx] = (ref_tsdf[idx] * ref_w[idx] + dist) / (ref_w[idx] + 1) if ref_w[idx] else dist
            ref_w[idx] += 1
            if d - z <= trunc:
                ref_obs[idx] = (ref_obs[idx] * ref_ow[idx] + mask[r, u]) / (ref_ow[idx] + 1)
                ref_ow[idx] += 1
    assert ref_w.sum() > 50 and ref_ow.sum() > 20  # the loop exercised both branches
    assert np.allclose(vol.tsdf(), ref_tsdf, atol=1e-5)
    assert np.array_equal(vol.weight(), ref_w)
    assert np.allclose(vol.obstacle(), ref_obs, atol=1e-6)


def test_no_return_pixels_update_nothing():
    cfg = load_config("default")
    cams = _cameras(cfg, 2)
    holes = [np.full(k.shape, fill, dtype=np.float32) for (k, _), fill in zip(cams, (np.nan, 0.0))]
    obs = fuse_observation(cfg.scene_grid, holes, cams)
    assert np.all(obs.tsdf == 1.0) and np.all(obs.obstacle == 0.0)
    assert not obs.valid.any() and np.all(obs.heightmap == 0.0)
    inf = [np.full(k.shape, np.inf, dtype=np.float32) for k, _ in cams]
    vol = TSDFVolume(cfg.scene_grid.origin, cfg.scene_grid.voxel_size, cfg.scene_grid.shape, cfg.scene_grid.truncation)
    vol.integrate(inf[0], *cams[0])
    assert np.all(vol.weight() == 0)


def test_heightmap_column_full_and_crossing_interpolation():
    g = SceneGridConfig(voxel_size=0.004)
    nx, ny, nz = g.shape
    zc = (np.arange(nz) + 0.5) * g.voxel_size
    surface = 0.0213
    tsdf = np.clip((zc - surface) / g.truncation, -1, 1).astype(np.float32) * np.ones((nx, ny, 1), np.float32)
    tsdf[0, 0, :] = -1.0  # a column filled to the top
    tsdf[1, 1, :] = 1.0  # nothing but free space
    h = heightmap_from_tsdf(tsdf, g)
    assert h[0, 0] == pytest.approx(g.z_range[1])
    assert h[1, 1] == 0.0
    assert h[5, 5] == pytest.approx(surface, abs=1e-6)


# --------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------


def _one_line(excinfo, *words):
    msg = str(excinfo.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg


def test_bad_inputs_raise_one_clear_line():
    cfg = load_config("default")
    g = cfg.scene_grid
    (k, T), = _cameras(cfg, 1)
    vol = TSDFVolume(g.origin, g.voxel_size, g.shape, g.truncation)
    good = np.ones(k.shape, np.float32)
    with pytest.raises(ValueError) as e:
        vol.integrate(np.ones((k.height + 1, k.width), np.float32), k, T)
    _one_line(e, "depth", str(k.shape))
    with pytest.raises(ValueError) as e:
        vol.integrate(np.ones(k.shape, np.int32), k, T)
    _one_line(e, "depth", "dtype")
    with pytest.raises(ValueError) as e:
        vol.integrate(good, k, T, obstacle_mask=np.ones((3, 3), bool))
    _one_line(e, "obstacle_mask", "shape")
    with pytest.raises(ValueError) as e:
        vol.integrate(good, k, T, obstacle_mask=np.ones(k.shape, np.float32))
    _one_line(e, "obstacle_mask", "bool")
    with pytest.raises(TypeError) as e:
        vol.integrate(good, k, T.as_matrix())
    _one_line(e, "T_world_cam", "Transform")
    with pytest.raises(ValueError) as e:
        fuse_observation(g, [good, good], [(k, T)])
    _one_line(e, "depths", "1")
    with pytest.raises(ValueError) as e:
        fuse_observation(g, [good], [(k, T)], obstacle_masks=[])
    _one_line(e, "obstacle_masks")
    with pytest.raises(ValueError) as e:
        fuse_observation(g, [], [])
    _one_line(e, "cameras")
    with pytest.raises(ValueError) as e:
        TSDFVolume(g.origin, g.voxel_size, (96, 96), g.truncation)
    _one_line(e, "shape")
    with pytest.raises(ValueError) as e:
        TSDFVolume(g.origin, -1.0, g.shape, g.truncation)
    _one_line(e, "voxel_size")
    with pytest.raises(ValueError) as e:
        TSDFVolume(g.origin, g.voxel_size, g.shape, 0.0)
    _one_line(e, "truncation")
    with pytest.raises(ValueError) as e:
        heightmap_from_tsdf(np.ones((4, 4, 4), np.float32), g)
    _one_line(e, "tsdf", str(g.shape))
    small = TSDFVolume(g.origin, g.voxel_size, (8, 8, 8), g.truncation)
    with pytest.raises(ValueError) as e:
        vol.integrate_projected(good, small.project(k, T))
    _one_line(e, "projection")
    with pytest.raises(ValueError) as e:
        Intrinsics(width=0, height=10, fx=1.0, fy=1.0, cx=0.0, cy=0.0)
    _one_line(e, "width")
    with pytest.raises(ValueError) as e:
        top_down_camera(g, height=0.1, pixels_per_voxel=1.0)
    _one_line(e, "camera_height")
