"""Pinhole cameras that see the scene grid with as few pixels as the grid needs.

Camera frame: OpenCV convention, x right, y down, z forward along the optical axis; pixel
(u, v) = (column, row) has its centre at integer coordinates, so the image spans
u in [-0.5, W - 0.5]. A camera pose is ``T_world_cam`` (maps camera-frame points to world).

Field of view: each camera's focal length is set by the resolution the grid needs,
``f = distance * pixels_per_voxel / voxel_size`` where ``distance`` is the depth of the
look-at point (the table centre for the top-down camera), so one pixel covers about one
voxel there. The image is then cropped to the tightest rectangle that holds the projection
of the whole workspace box (x_range x y_range x z_range, table to grid top) -- the principal
point moves off-centre where the box projects asymmetrically. The field of view is therefore
the smallest one that sees every voxel, and the pixel count the smallest that gives every
voxel its own pixel at the table (top-down at 0.6 m: a 44 degree square field of view,
124 x 124 px on the default grid, 246 x 246 on the paper grid; ring cameras 129 x 97 and
256 x 192). Each voxel reads its nearest pixel, so a coarser image would leave neighbouring
voxels reading the same pixel, and a finer one costs render time for sub-voxel detail.

Usage::

    cams = scene_cameras(cfg.scene_grid, cfg.sim)            # [(Intrinsics, T_world_cam), ...]
    for K, T_world_cam in cams:
        view = opengl_view_matrix(T_world_cam)                   # (4, 4), for a renderer
        proj = K.opengl_projection(near=0.1, far=2.0)            # (4, 4)
        # PyBullet: getCameraImage(K.width, K.height, view.T.ravel(), proj.T.ravel(), ...)
        depth = depth_from_opengl_zbuffer(zbuffer, near=0.1, far=2.0)   # (H, W) m
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.config import SceneGridConfig, SimConfig
from common.geometry import Transform


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; OpenCV camera frame (x right, y down, z forward)."""

    width: int
    """Image width in pixels (columns)."""
    height: int
    """Image height in pixels (rows)."""
    fx: float
    """Focal length along u, pixels."""
    fy: float
    """Focal length along v, pixels."""
    cx: float
    """Principal point u (column coordinate, pixel centres at integers)."""
    cy: float
    """Principal point v (row coordinate, pixel centres at integers)."""

    def __post_init__(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height or self.width < 1 or self.height < 1:
            raise ValueError(f"Intrinsics.width/height: expected positive integers, got {self.width} x {self.height}")
        if not (self.fx > 0 and self.fy > 0 and math.isfinite(self.fx) and math.isfinite(self.fy)):
            raise ValueError(f"Intrinsics.fx/fy: expected positive finite focal lengths, got {self.fx}, {self.fy}")
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ValueError(f"Intrinsics.cx/cy: expected finite principal point, got {self.cx}, {self.cy}")

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (H, W) of depth images taken with these intrinsics."""
        return (int(self.height), int(self.width))

    def matrix(self) -> np.ndarray:
        """(3, 3) float64 camera matrix K, pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) float64 camera-frame ray of every pixel centre, scaled to z = 1 (so a point at
        depth d along the optical axis is ``d * ray``)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)

    def opengl_projection(self, near: float, far: float, sample_offset: float = 0.0) -> np.ndarray:
        """(4, 4) float64 OpenGL projection matrix (row-major) that renders exactly these intrinsics.

        ``sample_offset`` is where a renderer samples inside each pixel, in pixels from the pixel's
        lower-left corner in window coordinates: 0.0 for PyBullet's TinyRenderer (the DIRECT-mode
        renderer samples pixel corners; checked against analytic ray casting in the tests), 0.5
        for renderers that sample pixel centres. Assumes the renderer returns row 0 at the top of
        the image (PyBullet does). For PyBullet's column-major ``projectionMatrix`` pass
        ``m.T.ravel()``.
        """
        if not 0 < near < far:
            raise ValueError(f"opengl_projection: expected 0 < near < far, got near={near}, far={far}")
        w, h, o = float(self.width), float(self.height), float(sample_offset)
        return np.array(
            [
                [2 * self.fx / w, 0.0, 1.0 - 2 * (self.cx + o) / w, 0.0],
                [0.0, 2 * self.fy / h, 2 * (self.cy + 1.0 - o) / h - 1.0, 0.0],
                [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
                [0.0, 0.0, -1.0, 0.0],
            ]
        )


def opengl_view_matrix(T_world_cam: Transform) -> np.ndarray:
    """(4, 4) float64 OpenGL view matrix (row-major; world -> OpenGL eye: x right, y up, z back)."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    return flip @ T_world_cam.inverse().as_matrix()


def depth_from_opengl_zbuffer(zbuffer: np.ndarray, near: float, far: float) -> np.ndarray:
    """Metric depth along the optical axis (H, W) float32 m from an OpenGL z-buffer in [0, 1].

    Pixels at the far plane (no geometry) become ``inf`` (no return).
    """
    zb = np.asarray(zbuffer, dtype=np.float64)
    depth = far * near / (far - (far - near) * zb)
    depth[zb >= 1.0] = np.inf
    return depth.astype(np.float32)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> Transform:
    """``T_world_cam`` of a camera at ``eye`` (3,) m whose optical axis points at ``target`` (3,) m.

    OpenCV frame: z along the view direction, x to the image right, y down; ``up`` (3,) is the
    world direction that appears upward in the image. Raises ValueError if ``eye == target`` or
    ``up`` is parallel to the view direction.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError(f"look_at: eye and target coincide at {eye.tolist()}")
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9 * max(np.linalg.norm(up), 1e-300):
        raise ValueError(f"look_at: up {up.tolist()} is parallel to the view direction {z.tolist()}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Transform(np.stack([x, y, z], axis=1), eye)


def _workspace_corners(grid: SceneGridConfig) -> np.ndarray:
    """(8, 3) float64 world corners of the workspace box, metres."""
    xs, ys, zs = grid.x_range, grid.y_range, grid.z_range
    return np.array([[x, y, z] for x in xs for y in ys for z in zs], dtype=np.float64)


def _workspace_centre(grid: SceneGridConfig) -> np.ndarray:
    return np.array([np.mean(grid.x_range), np.mean(grid.y_range), np.mean(grid.z_range)])


def fit_intrinsics(grid: SceneGridConfig, T_world_cam: Transform, focal: float) -> Intrinsics:
    """Tightest intrinsics with focal length ``focal`` (pixels) whose image holds the workspace box.

    The principal point is placed so that the extreme projected corners land on the centres of
    the first and last pixel rows and columns.
    """
    pts = T_world_cam.inverse().apply(_workspace_corners(grid))
    if np.any(pts[:, 2] <= 1e-6):
        raise ValueError("fit_intrinsics: T_world_cam: part of the workspace lies behind the camera")
    u = focal * pts[:, 0] / pts[:, 2]
    v = focal * pts[:, 1] / pts[:, 2]
    width = int(math.ceil(u.max() - u.min() - 1e-9)) + 1
    height = int(math.ceil(v.max() - v.min() - 1e-9)) + 1
    return Intrinsics(width=width, height=height, fx=focal, fy=focal, cx=float(-u.min()), cy=float(-v.min()))


def _check_pixels_per_voxel(pixels_per_voxel: float) -> None:
    if not pixels_per_voxel > 0:
        raise ValueError(f"sim.image_pixels_per_voxel: expected > 0, got {pixels_per_voxel}")


def top_down_camera(grid: SceneGridConfig, height: float, pixels_per_voxel: float) -> tuple[Intrinsics, Transform]:
    """Camera above the workspace centre at ``height`` m over the table, looking straight down.

    Image right = world +x, image down = world -y. One pixel spans ``voxel_size / pixels_per_voxel``
    on the table.
    """
    _check_pixels_per_voxel(pixels_per_voxel)
    if not height > grid.z_range[1]:
        raise ValueError(f"sim.camera_height: {height} m must exceed the grid top z = {grid.z_range[1]} m")
    centre = _workspace_centre(grid)
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    T_world_cam = Transform(rotation, np.array([centre[0], centre[1], height]))
    distance = height - grid.z_range[0]
    focal = distance * pixels_per_voxel / grid.voxel_size
    return fit_intrinsics(grid, T_world_cam, focal), T_world_cam


def ring_cameras(
    grid: SceneGridConfig, n: int, radius: float, height: float, pixels_per_voxel: float
) -> list[tuple[Intrinsics, Transform]]:
    """``n`` cameras at ``height`` m and horizontal ``radius`` m from the workspace centre, at
    azimuths 2 pi k / n (k = 0 on +x), each looking at the centre of the workspace box.

    One pixel spans ``voxel_size / pixels_per_voxel`` at the look-at point (perpendicular to the
    view ray; the table is foreshortened along the radial direction).
    """
    _check_pixels_per_voxel(pixels_per_voxel)
    if not 1 <= n:
        raise ValueError(f"sim.cameras: ring needs at least 1 camera, got {n}")
    if not radius > 0:
        raise ValueError(f"sim.camera_ring_radius: expected > 0, got {radius}")
    centre = _workspace_centre(grid)
    cams = []
    for k in range(n):
        azimuth = 2.0 * math.pi * k / n
        eye = np.array([centre[0] + radius * math.cos(azimuth), centre[1] + radius * math.sin(azimuth), height])
        T_world_cam = look_at(eye, centre)
        focal = float(np.linalg.norm(centre - eye)) * pixels_per_voxel / grid.voxel_size
        cams.append((fit_intrinsics(grid, T_world_cam, focal), T_world_cam))
    return cams


def scene_cameras(grid: SceneGridConfig, sim: SimConfig) -> list[tuple[Intrinsics, Transform]]:
    """The configured cameras: 1 -> top-down, 2..4 -> a ring (``sim.cameras``)."""
    if sim.cameras == 1:
        return [top_down_camera(grid, sim.camera_height, sim.image_pixels_per_voxel)]
    if 2 <= sim.cameras <= 4:
        return ring_cameras(grid, sim.cameras, sim.camera_ring_radius, sim.camera_height, sim.image_pixels_per_voxel)
    raise ValueError(f"sim.cameras: expected 1..4, got {sim.cameras}")
