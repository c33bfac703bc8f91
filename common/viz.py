"""Pictures of score maps and chosen grasps, as RGB arrays (for PNG files and TensorBoard).

Every function returns an (H, W, 3) uint8 image drawn with matplotlib's Agg canvas (no pyplot,
no global figure state). Maps are drawn in the world frame seen from above: x to the right,
y up (``imshow(map.T, origin="lower")``).

- :func:`score_maps_image`: the paper's figure style -- per opening a row of three of the R
  rotations (the best one and two spread evenly around the circle), each the score map over the
  heightmap with the gripper's closing direction drawn, its maximum in the title; the best
  rotation is framed in red and its best cell marked.
- :func:`grasp_image`: the heightmap with the chosen grasp: the gripper's footprint (cells of the
  gripper TSDF below zero at the chosen opening, projected down, turned by the yaw and moved to
  the TCP; white, and orange for the part at or below the TCP), the TCP (+) and the closing
  direction (red line).

Usage::

    img = score_maps_image(probs[g], obs.heightmap, cfg, openings)        # (H, W, 3) uint8
    save_png(img, "figs/scores.png"); writer.add_image("scores", img, step, dataformats="HWC")
    img = grasp_image(obs.heightmap, cfg, choice, encoding[choice.action[3]])
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from common.config import Config
from common.geometry import cell_to_world, rotation_angle


def _render(fig: Figure) -> np.ndarray:
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[:, :, :3])


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an (H, W, 3) uint8 image as PNG (parent folders created); returns the path."""
    from PIL import Image

    assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8, (image.shape, image.dtype)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)
    return path


def _extent(cfg: Config) -> tuple[float, float, float, float]:
    g = cfg.scene_grid
    return (g.x_range[0], g.x_range[1], g.y_range[0], g.y_range[1])


def shown_rotations(best_k: int, rotations: int) -> list[int]:
    """Three rotation indices, sorted: ``best_k`` and two more spread evenly around the circle."""
    return sorted({int(best_k) % rotations, (best_k + rotations // 3) % rotations, (best_k + 2 * rotations // 3) % rotations})


def score_maps_image(
    probs: np.ndarray,
    heightmap: np.ndarray,
    cfg: Config,
    openings: tuple[float, ...] | None = None,
    mask: np.ndarray | None = None,
    title: str = "",
) -> np.ndarray:
    """Score maps of one gripper: probs (S, R, X, Y) float in [0, 1] (or (R, X, Y) for one opening),
    heightmap (X, Y) float32 m, optional valid mask (X, Y) bool (invalid cells are greyed)."""
    probs = np.asarray(probs, dtype=np.float32)
    if probs.ndim == 3:
        probs = probs[None]
    S, R, X, Y = probs.shape
    assert heightmap.shape == (X, Y), (heightmap.shape, probs.shape)
    shown = probs if mask is None else np.where(mask, probs, 0.0)
    s_best, k_best, i_best, j_best = np.unravel_index(int(np.argmax(shown)), shown.shape)
    ks = shown_rotations(k_best, R)
    ext = _extent(cfg)
    top = max(float(heightmap.max()), 1e-3)
    half = 0.25 * min(ext[1] - ext[0], ext[3] - ext[2])
    centre = np.array([(ext[0] + ext[1]) / 2, (ext[2] + ext[3]) / 2])
    fig = Figure(figsize=(3.0 * len(ks), 2.9 * S + (0.4 if title else 0.0)), dpi=80)
    axes = fig.subplots(S, len(ks), squeeze=False)
    for s in range(S):
        for col, k in enumerate(ks):
            ax = axes[s, col]
            ax.imshow(heightmap.T, origin="lower", extent=ext, cmap="gray", vmin=-top, vmax=top, interpolation="nearest")
            m = np.ma.masked_where(~mask, shown[s, k]) if mask is not None else shown[s, k]
            ax.imshow(m.T, origin="lower", extent=ext, cmap="jet", vmin=0.0, vmax=1.0, alpha=0.55, interpolation="nearest")
            theta = rotation_angle(k, R)
            d = half * np.array([np.cos(theta), np.sin(theta)])
            ax.plot([centre[0] - d[0], centre[0] + d[0]], [centre[1] - d[1], centre[1] + d[1]], color="white", lw=1.0, ls="--")
            best = s == s_best and k == k_best
            opening = "" if openings is None else f"opening {openings[s]:.3f}, "
            ax.set_title(f"{opening}k={k} ({np.degrees(theta):.1f} deg)\nmax {float(shown[s, k].max()):.3f}", fontsize=8,
                         color="red" if best else "black")
            if best:
                xy = cell_to_world(cfg.scene_grid, i_best, j_best)
                ax.plot([xy[0]], [xy[1]], marker="x", color="red", ms=9, mew=2)
                for spine in ax.spines.values():
                    spine.set_color("red")
                    spine.set_linewidth(3)
            ax.set_xticks([])
            ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return _render(fig)


def gripper_footprint(encoding: np.ndarray, cfg: Config, below_tcp: bool = False) -> np.ndarray:
    """(P, 2) float64 TCP-frame (x, y) metres of the gripper-grid columns with a voxel inside the
    gripper (only voxels at or below the TCP if ``below_tcp``: the fingertips);
    ``encoding``: (2, gX, gY, gZ) or (gX, gY, gZ) float32 TSDF (channel 0 used)."""
    enc = np.asarray(encoding)
    vol = enc[0] if enc.ndim == 4 else enc
    gx, gy, gz = vol.shape
    grid = cfg.gripper_grid
    v = grid.voxel_size
    inside = vol < 0
    if below_tcp:
        inside = inside & ((np.arange(gz) + 0.5) * v - grid.tcp_height <= 0)[None, None, :]
    ii, jj = np.nonzero(inside.any(axis=2))
    return np.stack([(ii + 0.5 - gx / 2) * v, (jj + 0.5 - gy / 2) * v], axis=-1)


def grasp_image(
    heightmap: np.ndarray,
    cfg: Config,
    choice,
    encoding: np.ndarray | None = None,
    title: str = "",
) -> np.ndarray:
    """The heightmap (X, Y) float32 m with a grasp (``common.policy.GraspChoice``: position (3,)
    world m, yaw, opening, score) and, given the gripper encoding at the chosen opening
    ((2, gX, gY, gZ) float32), its footprint."""
    ext = _extent(cfg)
    fig = Figure(figsize=(4.4, 4.0), dpi=80)
    ax = fig.subplots()
    im = ax.imshow(heightmap.T, origin="lower", extent=ext, cmap="viridis", vmin=0.0, interpolation="nearest")
    fig.colorbar(im, ax=ax, fraction=0.046, label="height (m)")
    x, y = float(choice.position[0]), float(choice.position[1])
    c, s = np.cos(choice.yaw), np.sin(choice.yaw)
    rot = np.array([[c, -s], [s, c]])
    if encoding is not None:
        v = cfg.gripper_grid.voxel_size
        for below, colour, alpha in ((False, "white", 0.35), (True, "orange", 0.8)):
            for px, py in gripper_footprint(encoding, cfg, below_tcp=below):
                corner = rot @ np.array([px - v / 2, py - v / 2]) + (x, y)
                ax.add_patch(Rectangle(corner, v, v, angle=np.degrees(choice.yaw), color=colour, alpha=alpha, lw=0))
    d = rot @ np.array([0.03, 0.0])
    ax.plot([x - d[0], x + d[0]], [y - d[1], y + d[1]], color="red", lw=1.5, marker="o", ms=3)
    ax.plot([x], [y], marker="+", color="red", ms=10, mew=2)
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    label = f"score {choice.score:.3f}, opening {choice.opening:.3f}, yaw {np.degrees(choice.yaw):.1f} deg"
    ax.set_title(f"{title}\n{label}" if title else label, fontsize=8)
    fig.tight_layout()
    return _render(fig)
