"""TSDF fusion timings at the default (96 x 96 x 32, 4 mm) and paper (192 x 192 x 64, 2 mm) grids.

Depth images of a 3 cm sphere on the table are ray-cast analytically for the configured cameras
(scene_cameras). Prints ONE JSON line of medians in seconds:

- ``project_{scale}_s``: voxel -> pixel projection of one camera (done once per fixed camera)
- ``integrate_{scale}_s``: fusing one camera's depth + obstacle mask with a cached projection
- ``integrate_uncached_{scale}_s``: ``TSDFVolume.integrate`` (projection included), per camera
- ``integrate_torch_{scale}_s``: the same cached kernel written in torch (CPU, 1 thread), for
  the numpy-vs-torch comparison
- ``fuse_{n}cam_{scale}_s``: ``ObservationFuser.fuse`` (n images -> tsdf, obstacle, heightmap, valid)

Usage: ``python tests/bench/bench_tsdf.py [--repeats N]``
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from common.camera import Intrinsics, scene_cameras
from common.config import load_config
from common.geometry import Transform
from common.tsdf import ObservationFuser, TSDFVolume, VoxelProjection

SPHERE_CENTRE = np.array([0.013, -0.021, 0.03])
SPHERE_RADIUS = 0.03


def sphere_depth(k: Intrinsics, T_world_cam: Transform) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 depth (m) of a sphere on the table z = 0, and (H, W) bool sphere mask."""
    rays = k.pixel_rays() @ T_world_cam.rotation.T
    oc = T_world_cam.translation - SPHERE_CENTRE
    a = np.einsum("hwc,hwc->hw", rays, rays)
    b = rays @ oc
    disc = b * b - a * (oc @ oc - SPHERE_RADIUS**2)
    s_sphere = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)
    with np.errstate(divide="ignore"):
        s_table = np.where(rays[..., 2] < 0, -T_world_cam.translation[2] / rays[..., 2], np.inf)
    return np.minimum(s_sphere, s_table).astype(np.float32), s_sphere < s_table


def median_time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def torch_integrate(depth: np.ndarray, mask: np.ndarray, proj: VoxelProjection, trunc: float, state: list):
    """The cached integration kernel in torch; ``state`` = [sum, weight, obstacle_sum, band_weight]."""
    d = torch.from_numpy(np.append(np.nan_to_num(depth, nan=-1e30, posinf=-1e30).ravel(), -1e30).astype(np.float32))
    m = torch.from_numpy(np.append(mask.ravel(), False).astype(np.float32))
    pix = torch.from_numpy(proj.pixel.astype(np.int32))
    z = torch.from_numpy(proj.z_cam)

    def run():
        diff = torch.index_select(d, 0, pix) - z
        upd = diff >= -trunc
        band = upd & (diff <= trunc)
        dist = torch.clamp(diff * (1.0 / trunc), max=1.0) * upd
        state[0].add_(dist)
        state[1].add_(upd)
        state[3].add_(band)
        state[2].add_(torch.index_select(m, 0, pix) * band)

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    torch.set_num_threads(1)
    out: dict[str, float] = {}
    for scale in ("default", "paper"):
        cfg = load_config(scale)
        g = cfg.scene_grid
        for n in (1, 4):
            cfg.sim.cameras = n
            cams = scene_cameras(g, cfg.sim)
            images = [sphere_depth(k, t) for k, t in cams]
            depths = [d for d, _ in images]
            masks = [m for _, m in images]
            fuser = ObservationFuser(g, cams)
            out[f"fuse_{n}cam_{scale}_s"] = median_time(lambda: fuser.fuse(depths, masks), args.repeats)
            if n == 4:  # per-camera timings over the ring's first camera
                k, t = cams[0]
                vol = TSDFVolume(g.origin, g.voxel_size, g.shape, g.truncation)
                proj = fuser.projections[0]
                out[f"project_{scale}_s"] = median_time(lambda: vol.project(k, t), max(3, args.repeats // 3))
                out[f"integrate_{scale}_s"] = median_time(
                    lambda: vol.integrate_projected(depths[0], proj, masks[0]), args.repeats
                )
                out[f"integrate_uncached_{scale}_s"] = median_time(
                    lambda: vol.integrate(depths[0], k, t, masks[0]), max(3, args.repeats // 3)
                )
                state = [torch.zeros(proj.z_cam.shape[0]) for _ in range(4)]
                out[f"integrate_torch_{scale}_s"] = median_time(
                    torch_integrate(depths[0], masks[0], proj, g.truncation, state), args.repeats
                )
    print(json.dumps({k: round(v, 5) for k, v in sorted(out.items())}))


if __name__ == "__main__":
    main()
