"""The public AdaGrasp implementation's compute schedule on this project's layers: a same-run baseline.

The public code (Xu et al., ICRA 2021) scores a scene by looping over openings and rotations:
for every opening it encodes the gripper again, and for every rotation it turns the scene with
``grid_sample`` (trilinear, border), encodes it from scratch, correlates it with that opening's
kernel, decodes the map and turns it back with ``grid_sample``; every layer runs on its own
(convolution, then batch norm, then ReLU) in torch's default contiguous layout. Its training
step runs the batch's executed rotations through the same path and back-propagates.

This module runs that schedule with the layers of an :class:`common.network.AdaGraspNet` (so the
same weights and the same convolutions), on a copy of the model in the contiguous layout, so that
``tests/bench/bench_model.py --reference`` can time the public schedule and ours in one run and
report ratios. It is a lower bound on the public code's cost, not the public code: the
correlation here is the model's own method, and its decoder is the project's. The scores equal
:meth:`AdaGraspNet.predict`'s (tests/test_bench_reference.py), so both sides compute the same thing.

Use::

    ref = reference_copy(model)                    # contiguous layout, same weights
    probs = reference_predict(ref, scene, grip)    # (S, R, X, Y), as model.predict(scene, [grip])[0]
    step = reference_train_step_fn(ref, lr)        # step(scene_b, grip_b, action_b, label_b) -> loss
"""

from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F

from common.network import SUCCESS, AdaGraspNet, ConvBlock, Encoder, ResBlock2D, _upsample


def reference_copy(model: AdaGraspNet) -> AdaGraspNet:
    """A copy of ``model`` with every weight in torch's default contiguous layout."""
    return copy.deepcopy(model).to(memory_format=torch.contiguous_format)


def _block(blk: ConvBlock, x: torch.Tensor, residual: torch.Tensor | None = None) -> torch.Tensor:
    """Convolution, batch norm, residual add and ReLU as separate operations."""
    y = blk.conv(x)
    if blk.norm is not None:
        y = blk.norm(y)
    if residual is not None:
        y = y + residual
    return F.relu(y) if blk.relu else y


def _res(rb: ResBlock2D, x: torch.Tensor) -> torch.Tensor:
    return _block(rb.conv2, _block(rb.conv1, x), residual=x)


def _encode(enc: Encoder, x: torch.Tensor) -> torch.Tensor:
    """:meth:`Encoder.forward` layer by layer on contiguous (B, C, X, Y, Z) input -> (B, C', Fx, Fy)."""
    for blk in enc.conv3d:
        x = _block(blk, x)
    b, c, fx, fy, fz = x.shape
    y = x.permute(0, 4, 1, 2, 3).reshape(b, fz * c, fx, fy)  # channel z * C + c, as the model folds z
    y = _block(enc.fold, y)
    for rb in enc.res:
        y = _res(rb, y)
    return _block(enc.out, y)


def _decode(model: AdaGraspNet, x: torch.Tensor) -> torch.Tensor:
    """:meth:`AdaGraspNet.decode` layer by layer: maps (M, C, Lx, Ly) -> logits (M, 2, X, Y)."""
    y = _res(model.dec_res0, _block(model.dec_in, x))
    corners = model.corners
    for conv, res in zip(model.dec_up, model.dec_res):
        y = _res(res, _upsample(_block(conv, y), corners))
        corners = False
    if corners:
        y = F.avg_pool2d(y, 2, stride=1)
    return model.dec_out(y)


def _sample_positions(theta: torch.Tensor, nx: int, ny: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised sample positions (T, nx, ny) along axes 0 and 1 of a turn by ``theta`` (T,) rad
    about the grid centre, with the convention of :func:`common.network.rotation_taps`."""
    c = torch.cos(theta).view(-1, 1, 1)
    s = torch.sin(theta).view(-1, 1, 1)
    hx, hy = (nx - 1) / 2.0, (ny - 1) / 2.0
    ci = (torch.arange(nx, dtype=torch.float64) - hx).view(1, -1, 1)
    cj = (torch.arange(ny, dtype=torch.float64) - hy).view(1, 1, -1)
    si = (c * ci - s * cj) / hx
    sj = (s * ci + c * cj) / hy
    return si, sj


def rotate_volume(x: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """(B, C, X, Y, Z) turned about z by ``theta`` (T,) float64 rad with ``grid_sample`` (border);
    B == T, or B == 1 for T turns of one volume -> (T, C, X, Y, Z), contiguous."""
    b, c, nx, ny, nz = x.shape
    si, sj = _sample_positions(theta, nx, ny)
    t = si.shape[0]
    z = torch.linspace(-1.0, 1.0, nz, dtype=torch.float64).view(1, 1, 1, nz).expand(t, nx, ny, nz)
    # grid_sample reads (x, y, z) = (last, middle, first) spatial axes of the input.
    grid = torch.stack([z, sj[..., None].expand_as(z), si[..., None].expand_as(z)], dim=-1)
    src = x.expand(t, -1, -1, -1, -1) if b == 1 else x
    return F.grid_sample(src, grid.to(x.device, x.dtype), mode="bilinear", padding_mode="border", align_corners=True)


def rotate_maps(x: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """(B, C, X, Y) turned by ``theta`` (B,) float64 rad with ``grid_sample`` (border)."""
    b, c, nx, ny = x.shape
    si, sj = _sample_positions(theta, nx, ny)
    grid = torch.stack([sj, si], dim=-1)
    return F.grid_sample(x, grid.to(x.device, x.dtype), mode="bilinear", padding_mode="border", align_corners=True)


def _gripper_input(model: AdaGraspNet, grip: torch.Tensor) -> torch.Tensor:
    return grip[:, :1] if model.variant == "init-only" else grip


@torch.no_grad()
def reference_predict(ref: AdaGraspNet, scene: torch.Tensor, grip: torch.Tensor) -> torch.Tensor:
    """Success probabilities (S, R, X, Y) of one scene (1, 2, X, Y, Z) for one gripper's encodings
    (S, 2, gX, gY, gZ), by the public code's loop: per opening the kernel, per rotation the scene
    turned, encoded and decoded on its own. ``ref`` (from :func:`reference_copy`) in eval mode."""
    assert not ref.training and ref.variant != "scene-only", (ref.training, ref.variant)
    assert scene.dim() == 5 and scene.shape[0] == 1, tuple(scene.shape)
    R = ref.rotations
    thetas = torch.arange(R, dtype=torch.float64) * (2.0 * math.pi / R)
    out = scene.new_zeros(grip.shape[0], R, *scene.shape[2:4])
    for s in range(grip.shape[0]):
        kernel = _encode(ref.gripper_encoder, _gripper_input(ref, grip[s : s + 1]))
        for k in range(R):
            th = thetas[k : k + 1]
            feats = _encode(ref.scene_encoder, rotate_volume(scene, th))
            logits = rotate_maps(_decode(ref, ref.cross_correlate(feats, kernel, "matched")), -th)
            out[s, k] = torch.softmax(logits, dim=1)[0, SUCCESS]
    return out


def reference_train_step_fn(ref: AdaGraspNet, lr: float):
    """``step(scene, grip, action, label) -> loss``: one training step of ``ref`` (train mode) as
    the public code takes it: the batch's scenes (B, 2, X, Y, Z) turned by their executed
    rotations ``action[:, 2]`` with ``grid_sample``, encoded, correlated with the kernels of
    ``grip`` (B, 2, gX, gY, gZ), decoded, turned back; the loss of :meth:`AdaGraspNet.loss`,
    backward, Adam at ``lr``."""
    opt = torch.optim.Adam(ref.parameters(), lr=lr)

    def step(scene: torch.Tensor, grip: torch.Tensor, action: torch.Tensor, label: torch.Tensor) -> float:
        theta = action[:, 2].double() * (2.0 * math.pi / ref.rotations)
        kernels = _encode(ref.gripper_encoder, _gripper_input(ref, grip))
        feats = _encode(ref.scene_encoder, rotate_volume(scene, theta))
        logits = rotate_maps(_decode(ref, ref.cross_correlate(feats, kernels, "matched")), -theta)
        loss = ref.loss(logits, action, label)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return float(loss.detach())

    return step
