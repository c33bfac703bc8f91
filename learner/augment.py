"""Training-time augmentation: a random rotation about z and a random shift of the scene,
applied consistently to the scene volume and the executed action.

Rotations are multiples of 2 pi / R so the rotation index of the action stays exact
(k' = (k + m) mod R); shifts are whole cells. Call loop::

    scene, action = augment_batch(scene, action, rotations=16, prob=0.7, generator=g)
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def _transform_cells(ij: torch.Tensor, angle: torch.Tensor, shift: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """Rotate cells (B, 2) float about ``center`` (2,) by ``angle`` (B,) rad, then shift (B, 2) cells."""
    c, s = torch.cos(angle), torch.sin(angle)
    d = ij - center
    rotated = torch.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], dim=1)
    return rotated + center + shift


def rotate_shift_scene(scene: torch.Tensor, angle: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Rotate each scene about the grid centre by ``angle`` (B,) rad (counter-clockwise about +z,
    in the (x, y) = (axis 0, axis 1) plane), then shift it by ``shift`` (B, 2) float cells.

    scene: (B, C, X, Y, Z) float32 volumes; returns the same shape. Samples outside the grid
    replicate the border (table level for a tabletop scene).
    """
    assert scene.ndim == 5, scene.shape
    b, ch, nx, ny, nz = scene.shape
    center = torch.tensor([(nx - 1) / 2.0, (ny - 1) / 2.0], dtype=scene.dtype, device=scene.device)
    ii, jj = torch.meshgrid(
        torch.arange(nx, dtype=scene.dtype, device=scene.device),
        torch.arange(ny, dtype=scene.dtype, device=scene.device),
        indexing="ij",
    )
    out_ij = torch.stack([ii, jj], dim=-1).reshape(1, -1, 2).expand(b, -1, -1)
    # Source cell of each output cell: the inverse transform.
    c, s = torch.cos(-angle)[:, None], torch.sin(-angle)[:, None]
    d = out_ij - center - shift[:, None, :]
    src_i = c * d[..., 0] - s * d[..., 1] + center[0]
    src_j = s * d[..., 0] + c * d[..., 1] + center[1]
    # grid_sample on (B, C*Z, H=X, W=Y): grid[..., 0] indexes W (our j), grid[..., 1] indexes H (our i).
    grid = torch.stack([src_j / (ny - 1) * 2 - 1, src_i / (nx - 1) * 2 - 1], dim=-1).reshape(b, nx, ny, 2)
    flat = scene.permute(0, 1, 4, 2, 3).reshape(b, ch * nz, nx, ny)
    out = F.grid_sample(flat, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(b, ch, nz, nx, ny).permute(0, 1, 3, 4, 2).contiguous()


def augment_batch(
    scene: torch.Tensor,
    action: torch.Tensor,
    rotations: int,
    prob: float,
    generator: torch.Generator,
    max_shift_cells: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Randomly rotate and shift a batch, keeping scene and action consistent.

    scene: (B, C, X, Y, Z) float32; action: (B, 4) int64 (i, j, k, s) with i along x, j along y.
    Each sample is augmented with probability ``prob`` by a rotation of m * 2 pi / R (m uniform
    in 0..R-1) and a whole-cell shift of up to ``max_shift_cells`` (default X // 8) per axis,
    redrawn (up to 8 times, else left as it is) until the executed cell stays inside the grid.
    Returns new tensors; the inputs are not modified.
    """
    assert scene.ndim == 5 and action.shape == (scene.shape[0], 4), (scene.shape, action.shape)
    b, _, nx, ny, _ = scene.shape
    max_shift = nx // 8 if max_shift_cells is None else max_shift_cells
    center = torch.tensor([(nx - 1) / 2.0, (ny - 1) / 2.0])
    apply = torch.rand(b, generator=generator) < prob
    m = torch.zeros(b, dtype=torch.int64)
    shift = torch.zeros(b, 2)
    new_ij = action[:, :2].float().clone()
    for n in torch.nonzero(apply).flatten().tolist():
        for _ in range(8):
            m_n = int(torch.randint(rotations, (1,), generator=generator))
            s_n = torch.randint(-max_shift, max_shift + 1, (2,), generator=generator).float()
            angle = torch.tensor([2 * math.pi * m_n / rotations])
            ij = _transform_cells(action[n : n + 1, :2].float(), angle, s_n[None], center)[0]
            ij_round = torch.round(ij)
            if 0 <= ij_round[0] < nx and 0 <= ij_round[1] < ny:
                m[n], shift[n], new_ij[n] = m_n, s_n, ij_round
                break
    if not bool((m != 0).any() or (shift != 0).any()):
        return scene.clone(), action.clone()
    angle = 2 * math.pi * m.to(scene.dtype) / rotations
    out_scene = rotate_shift_scene(scene, angle.to(scene.device), shift.to(scene.device, scene.dtype))
    out_action = action.clone()
    out_action[:, 0:2] = new_ij.to(torch.int64)
    out_action[:, 2] = (action[:, 2] + m) % rotations
    return out_scene, out_action
