"""The AdaGrasp network (Xu et al., ICRA 2021): scene and gripper encoders, cross-correlation, decoder.

Layout (both scales come from the config; ``model.feature_cell`` is where the two meet)::

    scene (B, 2, X, Y, Z)  -> rotated about z by theta_k (bilinear, border)
        -> 3-D conv 2->16 -> 3-D conv 16->32 -> 3-D conv 32->64 (stride 2 from the second layer
           until the feature cell is reached) -> z folded into channels -> 1x1 conv -> 64
        -> 2 residual blocks (64) -> 3x3 conv -> C = model.channels (16) on the (Fx, Fy) feature grid
    gripper (N, 2, gX, gY, gZ) (channel 0 = TSDF at the initial opening, 1 = closed; init-only
        reads channel 0) -> 3-D conv ->16 -> 3-D conv 16->64 (stride 2 until the feature cell)
        -> z folded -> 1x1 conv -> 2 residual blocks -> 3x3 conv -> kernel (N, C, K, K)
    cross-correlation: each channel of the scene features with the same channel of the kernel
        (depthwise), divided by K * K; an even K puts the kernel's TCP on a cell corner, so the
        result lives on the (Fx + 1, Fy + 1) lattice of feature-cell corners
    decoder: conv C->D (D = model.decoder_width, 64), residual block, then per factor 2 of
        feature_cell / voxel_size a conv (to D / 2 at the last), an exact bilinear resampling onto
        the centres of cells half the size and a residual block;
        a 1x1 conv gives two logits per scene cell (channel 0 = failure, 1 = success)
    -> rotated back by -theta_k -> logits (B, 2, X, Y) on the scene grid

Rotation convention: the score at scene cell (i, j) of rotation k is the grasp whose TCP is at
the centre of cell (i, j) with yaw theta_k = 2 pi k / R about +z, i.e. the gripper's own x axis
(axis 0 of its grid) turned from world x towards world y by theta_k. Rotations are about the
grid centre in cell units, so multiples of 90 degrees map cells onto cells exactly. The
encoders' stride-2 convs (3 x 3, padding 1) centre output cell o on input cell 2o rather than on
the middle of the two cells it covers, half an input cell off per such layer. The scene and
gripper encoders shift by different amounts when their voxel sizes differ; the net offset is
the same at every rotation with ``rotate: scene`` (the scene is turned before it is encoded),
so training absorbs it.

Variants (``model.variant``): ``adagrasp`` (open + closed gripper TSDF), ``init-only`` (open
only), ``scene-only`` (no gripper: the scene features go straight to the decoder; every gripper
and opening gets the same map). ``model.rotate``: ``scene`` (the paper: the scene is re-encoded
once per rotation) or ``kernel`` (a speed option: the scene is encoded once and the gripper
kernel, zero-padded to hold any rotation, is rotated instead; the scene features are not
rotation equivariant, so its scores differ from ``scene``). ``model.train_stem = false`` (a
training speed option) keeps the scene encoder's first conv block (2 -> 16 channels at full
resolution, with its batch-norm affine) at its initialisation, which skips its backward pass.

Inference (:meth:`AdaGraspNet.predict`) encodes the scene once per rotation (``model.scene_chunk``
rotations per batch; by default 1 on the CPU and all on a GPU) and shares it across every
opening of every gripper; gripper kernels are cached per (key, weights version); the
correlation of all rotations with all kernels is one call (``model.correlation``: ``fft``, or
``grouped`` -- one grouped convolution, slower on CPU for 32 x 32 kernels); the maps are decoded
``model.decoder_chunk`` at a time (by default 16 on the CPU, 256 on a GPU). Implementation:
3-D activations are channels-last (oneDNN's fast layout), rotations are a 4-tap bilinear gather
(``embedding_bag``) that writes that layout directly, and on CPU in eval mode each conv runs with
its batch norm folded in and its bias, ReLU and residual add fused (oneDNN ``_convolution_pointwise``).
Training (:meth:`AdaGraspNet.forward_train`) evaluates only each sample's executed rotation and
opening, as the paper does; on the CPU a 3-D layer whose batch input exceeds 2**27 elements takes
its weight gradient in chunks of samples (oneDNN's fast kernel stops at 2**28; ``_WGRAD_MAX_ELEMENTS``).

Use::

    model = build_model(cfg).eval()
    probs = model.predict(scene, [enc_a, enc_b], keys=["a", "b"])  # (G, S_max, R, X, Y)
    model.train()
    logits = model.forward_train(scene_b, gripper_b, k_b)          # (B, 2, X, Y)
    loss = model.loss(logits, action_b, label_b)
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from common.config import Config, GripperGridConfig, ModelConfig, SceneGridConfig

SUCCESS = 1
"""Index of the success logit along the logits' channel axis (0 is failure)."""
VARIANTS = ("adagrasp", "init-only", "scene-only")
"""Model variants (``model.variant``)."""
_KERNEL_CACHE_SIZE = 64
"""Gripper kernel sets kept per model (least recently used dropped first)."""
_TAPS_CACHE_SIZE = 96
"""Rotation sampling tables kept per model (R rotations and their inverses on two grids fit)."""
_CPU_SCENE_CHUNK, _CPU_DECODER_CHUNK = 1, 16
"""Inference batching on the CPU when ``model.scene_chunk`` / ``model.decoder_chunk`` is 0: one
rotated scene and 16 score maps per batch (larger batches run no faster on a few cores and need
more memory)."""
_GPU_DECODER_CHUNK = 256
"""Score maps decoded per batch on a GPU when ``model.decoder_chunk`` is 0 (a GPU encodes all
rotations of the scene in one batch)."""


_WGRAD_MAX_ELEMENTS = 2**27
"""Largest input (elements) of one weight-gradient call of a 3-D convolution on the CPU; larger
batches are cut into chunks of whole samples. oneDNN 3.x falls back to im2col + GEMM for the
weight gradient of a channels-last 3-D convolution whose input exceeds 2**28 elements: on two
AVX-512 cores the paper-scale 16 -> 32 layer (8 x 16 x 192 x 192 x 64) took 0.68 s for the
whole batch and 0.26-0.29 s in chunks of 1-4 samples (7 samples were still fast, 8 not); the
other layers are below the limit (docs/RESULTS.md, "Speed of the network")."""

_FUSED = getattr(torch.ops.mkldnn, "_convolution_pointwise", None) if torch.backends.mkldnn.is_available() else None
"""oneDNN convolution with a fused bias, ReLU and residual add (CPU inference only), if this torch has it."""


class NetworkConfigError(ValueError):
    """The grids and the model config do not fit together; the message names the field."""


# --------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------


class _Conv3dChunkedWeightGrad(torch.autograd.Function):
    """``F.conv3d(x, weight, None, stride, padding)`` whose weight gradient is summed over
    chunks of ``chunk`` samples (see ``_WGRAD_MAX_ELEMENTS``); the input gradient is one call.

    Under CPU autocast (``learner.precision=bf16``) it does what autocast does for a convolution:
    input and weight are cast to the autocast dtype, which the backward pass computes in; the
    weight gradient is summed in float32 and both gradients come back in their inputs' dtypes."""

    @staticmethod
    def forward(ctx, x, weight, stride, padding, chunk):
        ctx.dtypes = (x.dtype, weight.dtype)
        if torch.is_autocast_enabled("cpu"):
            low = torch.get_autocast_dtype("cpu")
            x, weight = x.to(low), weight.to(low)
        ctx.save_for_backward(x, weight)
        ctx.conf = (list(stride), list(padding), int(chunk))
        with torch.autocast("cpu", enabled=False):
            return F.conv3d(x, weight, None, stride, padding)

    @staticmethod
    def backward(ctx, grad_out):
        x, weight = ctx.saved_tensors
        stride, padding, chunk = ctx.conf
        grad_out = grad_out.to(x.dtype)
        args = (None, stride, padding, [1, 1, 1], False, [0, 0, 0], 1)
        grad_x = grad_w = None
        if ctx.needs_input_grad[0]:
            grad_x = torch.ops.aten.convolution_backward(grad_out, x, weight, *args, [True, False, False])[0]
            grad_x = grad_x.to(ctx.dtypes[0])
        if ctx.needs_input_grad[1]:
            for i in range(0, x.shape[0], chunk):
                part = torch.ops.aten.convolution_backward(
                    grad_out[i : i + chunk], x[i : i + chunk], weight, *args, [False, True, False]
                )[1].to(torch.promote_types(ctx.dtypes[1], torch.float32))
                grad_w = part if grad_w is None else grad_w.add_(part)
            grad_w = grad_w.to(ctx.dtypes[1])
        return grad_x, grad_w, None, None, None


class ConvBlock(nn.Module):
    """Conv (2-D or 3-D) -> optional batch norm -> optional ReLU.

    In eval mode the batch norm is folded into the convolution's weights on the fly (one pass
    over the activations instead of two).
    """

    def __init__(self, dim: int, cin: int, cout: int, kernel: int = 3, stride: int = 1, norm: bool = True, relu: bool = True):
        super().__init__()
        conv = nn.Conv3d if dim == 3 else nn.Conv2d
        self.conv = conv(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=not norm)
        self.norm = (nn.BatchNorm3d if dim == 3 else nn.BatchNorm2d)(cout) if norm else None
        self.relu = relu
        self._fn = F.conv3d if dim == 3 else F.conv2d
        self._fold_src: tuple = ()
        self._fold_versions: tuple = ()
        self._fold: tuple[torch.Tensor, torch.Tensor] | None = None

    def _fold_sources(self) -> tuple[torch.Tensor, ...]:
        bn = self.norm
        extra = () if self.conv.bias is None else (self.conv.bias,)
        return (self.conv.weight, bn.weight, bn.bias, bn.running_mean, bn.running_var, *extra)

    def _folded(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Weight and bias of the convolution with the eval-mode batch norm folded in.

        Without autograd the result is kept until one of its source tensors is replaced (the
        cache holds them, so their identity is a safe key), gets new storage (``.to``, ``.data``
        assignment) or is changed in place (torch counts in-place writes per tensor: optimiser
        steps, ``load_state_dict``, edits under ``no_grad``), so inference folds once per weights.
        """
        cache = not torch.is_grad_enabled()
        if cache:
            src = self._fold_sources()
            versions = tuple((t._version, t.data_ptr(), t.dtype, t.device) for t in src)
            same = len(src) == len(self._fold_src) and all(a is b for a, b in zip(src, self._fold_src))
            if same and versions == self._fold_versions:
                return self._fold
        bn = self.norm
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        bias = bn.bias - bn.running_mean * scale
        if self.conv.bias is not None:
            bias = bias + self.conv.bias * scale
        shape = (-1,) + (1,) * (self.conv.weight.dim() - 1)
        folded = (self.conv.weight * scale.view(shape), bias)
        if cache:
            self._fold_src, self._fold_versions, self._fold = src, versions, folded
        return folded

    def forward(self, x: torch.Tensor, residual: torch.Tensor | None = None) -> torch.Tensor:
        """Conv block of ``x``; with ``residual`` (same shape as the output) the sum conv + residual
        goes through the ReLU (a residual block's tail)."""
        if not self.training and _FUSED is not None and x.device.type == "cpu" and not torch.is_grad_enabled():
            w, b = self._folded() if self.norm is not None else (self.conv.weight, self.conv.bias)
            c = self.conv
            args = (list(c.padding), list(c.stride), list(c.dilation), c.groups)
            if residual is not None:
                return _FUSED.binary(x, residual, w, b, *args, "add", 1.0, "relu" if self.relu else "none", [], "")
            return _FUSED(x, w, b, *args, "relu" if self.relu else "none", [], "")
        if self.norm is not None and not self.training:
            w, b = self._folded()
            c = self.conv
            y = self._fn(x, w, b, c.stride, c.padding, c.dilation, c.groups)
        else:
            y = self._conv_train(x)
            if self.norm is not None:
                y = self.norm(y)
        if residual is not None:
            y = y + residual
        return F.relu(y, inplace=True) if self.relu else y

    def _conv_train(self, x: torch.Tensor) -> torch.Tensor:
        """The convolution with autograd; a large 3-D batch on the CPU takes its weight gradient
        in chunks of samples (``_WGRAD_MAX_ELEMENTS``), the same sums in another order."""
        c = self.conv
        if (
            x.dim() == 5
            and x.device.type == "cpu"
            and c.bias is None
            and c.weight.requires_grad
            and torch.is_grad_enabled()
            and x.numel() > _WGRAD_MAX_ELEMENTS
        ):
            chunk = max(1, _WGRAD_MAX_ELEMENTS // x[0].numel())
            return _Conv3dChunkedWeightGrad.apply(x, c.weight, c.stride, c.padding, chunk)
        return c(x)


class ResBlock2D(nn.Module):
    """Two 3x3 conv + batch norm layers with an identity shortcut, ReLU after the sum."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = ConvBlock(2, channels, channels)
        self.conv2 = ConvBlock(2, channels, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.conv1(x), residual=x)


class Encoder(nn.Module):
    """3-D conv stack down to the feature cell, z folded into channels, 2-D residual blocks.

    Input (B, cin, X, Y, Z) float32 -> (B, cout, X / f, Y / f) with f = 2 ** down.
    """

    def __init__(
        self, cin: int, widths: tuple[int, ...], down: int, depth: int, mid: int, cout: int, fold_act: bool, where: str
    ):
        super().__init__()
        if down >= len(widths):
            raise NetworkConfigError(
                f"{where}.voxel_size: needs {down} stride-2 stages but the encoder has {len(widths) - 1}"
            )
        layers, c = [], cin
        for n, w in enumerate(widths):
            layers.append(ConvBlock(3, c, w, stride=2 if 0 < n <= down else 1))
            c = w
        self.conv3d = nn.Sequential(*layers)
        self.depth = depth
        self.fold = ConvBlock(2, c * depth, mid, kernel=1, norm=fold_act, relu=fold_act)
        self.res = nn.Sequential(ResBlock2D(mid), ResBlock2D(mid))
        self.out = ConvBlock(2, mid, cout, norm=False)
        self.conv3d.to(memory_format=torch.channels_last_3d)

    def forward(self, x: torch.Tensor, train_stem: bool = True) -> torch.Tensor:
        """``train_stem=False`` runs the first conv block without gradients (its weights stay put)."""
        x = x.contiguous(memory_format=torch.channels_last_3d)
        if train_stem:
            y = self.conv3d(x)
        else:
            with torch.no_grad():
                y = self.conv3d[0](x)
            y = self.conv3d[1:](y)
        b, c, fx, fy, fz = y.shape
        assert fz == self.depth, (y.shape, self.depth)
        # (B, Fx, Fy, Fz * C) is a view of the channels-last volume; as (B, Fz * C, Fx, Fy) it is a
        # channels-last image whose channel index is z * C + c.
        y = y.permute(0, 2, 3, 4, 1).reshape(b, fx, fy, fz * c).permute(0, 3, 1, 2)
        return self.out(self.res(self.fold(y)))


def _pow2(ratio: float, where: str) -> int:
    """log2 of an integer power-of-two ratio, or NetworkConfigError naming ``where``."""
    r = int(round(ratio))
    if abs(ratio - r) > 1e-6 or r < 1 or r & (r - 1):
        raise NetworkConfigError(f"{where}: model.feature_cell / voxel_size must be a power of 2, got {ratio:g}")
    return int(math.log2(r))


def _upsample(y: torch.Tensor, corners: bool) -> torch.Tensor:
    """Exact bilinear resampling (M, C, h, w) onto the centres of cells half the size.

    ``corners``: the input samples the corners of n cells (h = n + 1), else their centres (h = n);
    the output samples the centres of the 2n half-size cells (clamped at the border).
    """
    if corners:
        h, w = y.shape[-2:]
        y = F.interpolate(y, size=(2 * h - 1, 2 * w - 1), mode="bilinear", align_corners=True)
        return F.avg_pool2d(y, 2, stride=1)
    return F.interpolate(y, scale_factor=2, mode="bilinear", align_corners=False)


def _fft_size(n: int) -> int:
    """Smallest m >= n whose prime factors are 2, 3 and 5 (fast FFT lengths)."""
    m = n
    while True:
        r = m
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
        m += 1


# --------------------------------------------------------------------------------------
# Rotation about the grid centre
# --------------------------------------------------------------------------------------


def rotation_taps(theta: float, nx: int, ny: int, zeros: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear sampling table of a rotation about the centre of an (nx, ny) grid.

    Output cell (i, j) reads the input at R(theta) (i - cx, j - cy) + (cx, cy), cell units,
    theta in radians counter-clockwise from axis 0 towards axis 1, (cx, cy) = ((nx-1)/2, (ny-1)/2):
    out(q) = in(R(theta) q), i.e. the content turns by -theta. Returns flat source indices
    (nx * ny, 4) int64 and weights (nx * ny, 4) float32. Outside the grid the sample is clamped
    to the border, or is zero if ``zeros``.
    """
    c, s = math.cos(theta), math.sin(theta)
    c, s = (0.0 if abs(c) < 1e-12 else c), (0.0 if abs(s) < 1e-12 else s)
    hx, hy = (nx - 1) / 2.0, (ny - 1) / 2.0
    ci = (np.arange(nx, dtype=np.float64) - hx)[:, None]
    cj = (np.arange(ny, dtype=np.float64) - hy)[None, :]
    si = c * ci - s * cj + hx
    sj = s * ci + c * cj + hy
    if not zeros:
        si, sj = np.clip(si, 0, nx - 1), np.clip(sj, 0, ny - 1)
    i0, j0 = np.floor(si).astype(np.int64), np.floor(sj).astype(np.int64)
    wi, wj = si - i0, sj - j0
    idx, wts = [], []
    for di, dj, w in ((0, 0, (1 - wi) * (1 - wj)), (1, 0, wi * (1 - wj)), (0, 1, (1 - wi) * wj), (1, 1, wi * wj)):
        ii, jj = i0 + di, j0 + dj
        inside = (ii >= 0) & (ii < nx) & (jj >= 0) & (jj < ny)
        idx.append(np.clip(ii, 0, nx - 1) * ny + np.clip(jj, 0, ny - 1))
        wts.append(np.where(inside, w, 0.0))
    return np.stack(idx, -1).reshape(-1, 4), np.stack(wts, -1).reshape(-1, 4).astype(np.float32)


class Rotator:
    """Rotates stacks of (nx, ny) maps whose per-cell values are contiguous rows; caches tables."""

    def __init__(self) -> None:
        self._taps: OrderedDict = OrderedDict()

    def taps(self, theta: float, nx: int, ny: int, zeros: bool, device) -> tuple[torch.Tensor, torch.Tensor]:
        key = (round(float(theta), 12), nx, ny, zeros, str(device))
        hit = self._taps.get(key)
        if hit is None:
            idx, w = rotation_taps(float(theta), nx, ny, zeros)
            hit = (torch.from_numpy(idx.astype(np.int32)).to(device), torch.from_numpy(w).to(device))
            self._taps[key] = hit
            while len(self._taps) > _TAPS_CACHE_SIZE:
                self._taps.popitem(last=False)
        return hit

    def rows(self, table: torch.Tensor, theta, nx: int, ny: int, zeros: bool = False) -> torch.Tensor:
        """Rotate ``table`` (B, nx * ny, D) by ``theta`` (T,) rad, T == B or B == 1 -> (T, nx * ny, D)."""
        b, cells, d = table.shape
        theta = [float(t) for t in torch.as_tensor(theta, dtype=torch.float64).reshape(-1)]
        assert cells == nx * ny and (b == len(theta) or b == 1), (table.shape, len(theta))
        idx, wts = [], []
        for n, t in enumerate(theta):
            i, w = self.taps(t, nx, ny, zeros, table.device)
            idx.append(i + (n * cells if b > 1 else 0))
            wts.append(w)
        out = F.embedding_bag(
            torch.cat(idx), table.reshape(b * cells, d), per_sample_weights=torch.cat(wts).to(table.dtype), mode="sum"
        )
        return out.view(len(theta), cells, d)

    def maps(self, x: torch.Tensor, theta, zeros: bool = False) -> torch.Tensor:
        """Rotate (B, C, nx, ny) ``x`` by ``theta`` (T,) rad: out(q) = x(R q); channels-last result."""
        b, c, nx, ny = x.shape
        table = x.permute(0, 2, 3, 1).reshape(b, nx * ny, c)
        out = self.rows(table, theta, nx, ny, zeros)
        return out.view(-1, nx, ny, c).permute(0, 3, 1, 2)

    def volume(self, x: torch.Tensor, theta) -> torch.Tensor:
        """Rotate (B, C, nx, ny, nz) ``x`` about z by ``theta`` (T,) rad (border); channels-last-3d result."""
        b, c, nx, ny, nz = x.shape
        table = x.permute(0, 2, 3, 4, 1).reshape(b, nx * ny, nz * c)
        out = self.rows(table, theta, nx, ny)
        return out.view(-1, nx, ny, nz, c).permute(0, 4, 1, 2, 3)


# --------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------


class AdaGraspNet(nn.Module):
    """Scores top-down grasps of one or more grippers at R rotations on the scene grid."""

    def __init__(self, model: ModelConfig, scene_grid: SceneGridConfig, gripper_grid: GripperGridConfig):
        super().__init__()
        self.variant = model.variant
        self.rotations = int(model.rotations)
        self.rotate_mode = model.rotate
        self.correlation = model.correlation
        self.channels = int(model.channels)
        self.scene_chunk = int(model.scene_chunk)
        self.decoder_chunk = int(model.decoder_chunk)
        self.train_stem = bool(model.train_stem)
        self.scene_shape = tuple(int(v) for v in scene_grid.shape)
        self.gripper_shape = tuple(int(v) for v in gripper_grid.shape)
        if self.variant not in VARIANTS:
            raise NetworkConfigError(f"model.variant: expected one of {list(VARIANTS)}, got {self.variant!r}")
        if self.correlation not in ("fft", "grouped"):
            raise NetworkConfigError(f"model.correlation: expected fft or grouped, got {self.correlation!r}")
        if self.rotate_mode not in ("scene", "kernel"):
            raise NetworkConfigError(f"model.rotate: expected scene or kernel, got {self.rotate_mode!r}")

        up = _pow2(model.feature_cell / scene_grid.voxel_size, "scene_grid.voxel_size")
        ratio = 2**up
        X, Y, Z = self.scene_shape
        for name, n in (("x_range", X), ("y_range", Y), ("z_range", Z)):
            if n % ratio:
                raise NetworkConfigError(f"scene_grid.{name}: {n} cells is not a multiple of {ratio}")
        self.feature_shape = (X // ratio, Y // ratio)
        self.scene_encoder = Encoder(2, tuple(model.scene_widths), up, Z // ratio, 64, self.channels, True, "scene_grid")

        self.kernel_size = 0
        if self.variant != "scene-only":
            gdown = _pow2(model.feature_cell / gripper_grid.voxel_size, "gripper_grid.voxel_size")
            g = 2**gdown
            gx, gy, gz = self.gripper_shape
            if gx != gy:
                raise NetworkConfigError(f"gripper_grid.shape: x and y must be equal, got {self.gripper_shape}")
            if gx % g or gz % g:
                raise NetworkConfigError(f"gripper_grid.shape: {self.gripper_shape} is not a multiple of {g}")
            cin = 2 if self.variant == "adagrasp" else 1
            self.gripper_encoder = Encoder(cin, tuple(model.gripper_widths), gdown, gz // g, 64, self.channels, False, "gripper_grid")
            self.kernel_size = gx // g

        # An even kernel puts the correlation on cell corners, (Fx + 1, Fy + 1) points; an odd one
        # (or none) on the feature-cell centres. Each decoder stage resamples exactly onto the
        # centres of cells half the size.
        self.corners = self.kernel_size > 0 and self.kernel_size % 2 == 0
        self.lattice0 = tuple(n + 1 if self.corners else n for n in self.feature_shape)

        dw = int(model.decoder_width)
        if dw < 2 or dw % 2:
            raise NetworkConfigError(f"model.decoder_width: expected an even number >= 2, got {model.decoder_width!r}")
        widths = [dw] + [dw] * max(0, up - 1) + ([dw // 2] if up > 0 else [])
        self.dec_in = ConvBlock(2, self.channels, dw, norm=False)
        self.dec_res0 = ResBlock2D(dw)
        self.dec_up = nn.ModuleList(ConvBlock(2, widths[u], widths[u + 1]) for u in range(up))
        self.dec_res = nn.ModuleList(ResBlock2D(widths[u + 1]) for u in range(up))
        self.dec_out = nn.Conv2d(widths[-1], 2, kernel_size=1, bias=False)

        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Conv3d)):
                nn.init.kaiming_normal_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, (nn.BatchNorm2d, nn.BatchNorm3d)):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

        self.weights_version = 0
        """Version of the loaded weights; part of the gripper-kernel cache key."""
        self._kernels: OrderedDict = OrderedDict()
        self._rotator = Rotator()

    # ---------------------------------------------------------------- state and cache

    def clear_cache(self) -> None:
        """Forget cached gripper kernels (needed only after editing weights in place in eval mode)."""
        self._kernels.clear()

    def train(self, mode: bool = True) -> "AdaGraspNet":
        if mode != self.training:
            self.clear_cache()
        return super().train(mode)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        self.clear_cache()
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def set_weights(self, state_dict: dict, version: int) -> None:
        """Load ``state_dict`` and record its ``version`` (the kernel cache is keyed by it)."""
        self.load_state_dict(state_dict)
        self.weights_version = int(version)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    # ---------------------------------------------------------------- pieces

    def _check_scene(self, scene: torch.Tensor) -> None:
        assert scene.dim() == 5 and scene.shape[1] == 2 and tuple(scene.shape[2:]) == self.scene_shape, (
            f"scene: expected (B, 2, {', '.join(map(str, self.scene_shape))}), got {tuple(scene.shape)}"
        )

    def _check_gripper(self, gripper: torch.Tensor) -> None:
        assert gripper.dim() == 5 and gripper.shape[1] == 2 and tuple(gripper.shape[2:]) == self.gripper_shape, (
            f"gripper: expected (N, 2, {', '.join(map(str, self.gripper_shape))}), got {tuple(gripper.shape)}"
        )

    def rotate_scene(self, scene: torch.Tensor, theta) -> torch.Tensor:
        """Scene (B, 2, X, Y, Z) sampled at positions turned by ``theta`` (T,) rad about the grid
        centre (T == B, or B == 1 for T rotations of one scene): the scene as the gripper at yaw
        theta sees it from its own frame."""
        return self._rotator.volume(scene, theta)

    def rotate_maps(self, maps: torch.Tensor, theta, zeros: bool = False) -> torch.Tensor:
        """Maps (B, C, nx, ny) sampled at positions turned by ``theta`` (B,) rad about their centre."""
        return self._rotator.maps(maps, theta, zeros)

    def encode_scene(self, scene: torch.Tensor, theta=None) -> torch.Tensor:
        """Scene (B, 2, X, Y, Z), rotated by ``theta`` (see :meth:`rotate_scene`) unless None -> (T, C, Fx, Fy)."""
        if theta is not None:
            scene = self.rotate_scene(scene, theta)
        return self.scene_encoder(scene, self.train_stem)

    def encode_gripper(self, gripper: torch.Tensor) -> torch.Tensor:
        """Gripper TSDFs (N, 2, gX, gY, gZ) -> kernels (N, C, K, K)."""
        if self.variant == "init-only":
            gripper = gripper[:, :1]
        return self.gripper_encoder(gripper)

    def rotate_kernels(self, kernels: torch.Tensor, theta) -> torch.Tensor:
        """Kernels (N, C, K, K) turned by ``theta`` (N,) rad about their TCP, zero-padded to
        (N, C, K', K') so that every rotation fits (K' keeps K's parity)."""
        k = kernels.shape[-1]
        extra = math.ceil((math.sqrt(2.0) * k - k) / 2.0)
        padded = F.pad(kernels, (extra, extra, extra, extra))
        neg = -torch.as_tensor(theta, dtype=torch.float64).reshape(-1)
        return self.rotate_maps(padded, neg, zeros=True)

    def cross_correlate(self, features: torch.Tensor, kernels: torch.Tensor, pairs: str) -> torch.Tensor:
        """Depthwise correlation of scene features with gripper kernels, divided by K * K.

        ``pairs == "all"``: features (B, C, Fx, Fy) x kernels (N, C, K, K) -> (B, N, C, Lx, Ly).
        ``pairs == "matched"``: features (B, ...) x kernels (B, ...) -> (B, C, Lx, Ly), sample b with kernel b.
        Output o sums kernel cell a times feature o - K // 2 + a (zero outside the grid), so
        L = F + 1 for even K. ``model.correlation`` picks the method: ``grouped`` (one grouped
        convolution) or ``fft`` (the same sums through real FFTs of the zero-padded maps).
        """
        b, c, fx, fy = features.shape
        n, c2, kx, ky = kernels.shape
        assert c2 == c and (pairs == "all" or n == b), (features.shape, kernels.shape, pairs)
        kernels = kernels * (1.0 / (kx * ky))
        px, py = kx // 2, ky // 2
        if self.correlation == "fft":
            sx, sy = _fft_size(fx + kx - 1), _fft_size(fy + ky - 1)
            ff = torch.fft.rfft2(features, s=(sx, sy))
            fk = torch.conj(torch.fft.rfft2(kernels, s=(sx, sy)))
            prod = ff.unsqueeze(1) * fk.unsqueeze(0) if pairs == "all" else ff * fk
            circ = torch.fft.irfft2(prod, s=(sx, sy))  # circ[d] = sum_m f[m + d] k[m], indices mod s
            lx, ly = fx + 2 * px - kx + 1, fy + 2 * py - ky + 1
            return torch.roll(circ, shifts=(px, py), dims=(-2, -1))[..., :lx, :ly]
        if pairs == "all":
            weight = kernels.transpose(0, 1).reshape(c * n, 1, kx, ky)
            out = F.conv2d(features, weight, padding=(px, py), groups=c)
            return out.view(b, c, n, out.shape[-2], out.shape[-1]).transpose(1, 2)
        weight = kernels.reshape(b * c, 1, kx, ky)
        out = F.conv2d(features.reshape(1, b * c, fx, fy), weight, padding=(px, py), groups=b * c)
        return out.view(b, c, out.shape[-2], out.shape[-1])

    def decode(self, x: torch.Tensor) -> torch.Tensor:
        """Correlation maps (M, C, Lx, Ly) -> logits (M, 2, X, Y) on the scene grid, in the maps' frame."""
        y = self.dec_res0(self.dec_in(x.contiguous(memory_format=torch.channels_last)))
        corners = self.corners
        for conv, res in zip(self.dec_up, self.dec_res):
            y = res(_upsample(conv(y), corners))
            corners = False
        if corners:
            y = F.avg_pool2d(y, 2, stride=1)
        return self.dec_out(y)

    # ---------------------------------------------------------------- training

    def forward_train(self, scene: torch.Tensor, gripper: torch.Tensor | None, k) -> torch.Tensor:
        """Logits (B, 2, X, Y) of each sample's own rotation and gripper state only.

        scene: (B, 2, X, Y, Z) float32 (TSDF, obstacle) on the scene grid; gripper:
        (B, 2, gX, gY, gZ) float32 (TSDF at the executed opening, closed), ignored by scene-only;
        k: (B,) int rotation indices.
        """
        self._check_scene(scene)
        b = scene.shape[0]
        k = torch.as_tensor(k).reshape(-1).long()
        assert k.shape == (b,), (tuple(k.shape), b)
        theta = k.cpu().double() * (2.0 * math.pi / self.rotations)
        if self.variant == "scene-only":
            return self.rotate_maps(self.decode(self.encode_scene(scene, theta)), -theta)
        assert gripper is not None and gripper.shape[0] == b, "gripper: one encoding per sample expected"
        self._check_gripper(gripper)
        kernels = self.encode_gripper(gripper)
        if self.rotate_mode == "kernel":
            feats = self.encode_scene(scene)
            return self.decode(self.cross_correlate(feats, self.rotate_kernels(kernels, theta), "matched"))
        feats = self.encode_scene(scene, theta)
        return self.rotate_maps(self.decode(self.cross_correlate(feats, kernels, "matched")), -theta)

    def forward(self, scene: torch.Tensor, gripper: torch.Tensor | None, k) -> torch.Tensor:
        """Same as :meth:`forward_train`."""
        return self.forward_train(scene, gripper, k)

    @staticmethod
    def loss(logits: torch.Tensor, action, label) -> torch.Tensor:
        """Softmax cross-entropy of the executed action's cell (the paper's loss), mean over the batch.

        logits (B, 2, X, Y); action (B, >= 2) int with columns (i, j, ...); label (B,) bool/int/float,
        1 = success.
        """
        b = logits.shape[0]
        action = torch.as_tensor(action, device=logits.device).long()
        assert action.dim() == 2 and action.shape[0] == b and action.shape[1] >= 2, tuple(action.shape)
        label = torch.as_tensor(label, device=logits.device).reshape(-1).long()
        assert label.shape == (b,), tuple(label.shape)
        picked = logits[torch.arange(b, device=logits.device), :, action[:, 0], action[:, 1]]
        return F.cross_entropy(picked, label)

    # ---------------------------------------------------------------- inference

    def gripper_kernels(self, gripper: torch.Tensor, key: str | None = None) -> torch.Tensor:
        """Kernels (S, C, K, K) of one gripper's encodings (S, 2, gX, gY, gZ), cached per
        (key, weights_version) when ``key`` is given."""
        if key is None:
            return self.encode_gripper(gripper)
        cache_key = (key, self.weights_version, str(gripper.device))
        hit = self._kernels.get(cache_key)
        if hit is not None and hit.shape[0] == gripper.shape[0]:
            self._kernels.move_to_end(cache_key)
            return hit
        kernels = self.encode_gripper(gripper)
        self._kernels[cache_key] = kernels
        while len(self._kernels) > _KERNEL_CACHE_SIZE:
            self._kernels.popitem(last=False)
        return kernels

    def _input(self, x, name: str) -> torch.Tensor:
        t = torch.as_tensor(x)
        assert t.dtype == torch.float32, f"{name}: expected float32, got {t.dtype}"
        return t.to(self.device)

    @torch.no_grad()
    def predict(self, scene, grippers: list, keys: list[str] | None = None) -> torch.Tensor:
        """Success probabilities of every opening of every gripper at every rotation and cell.

        scene: (2, X, Y, Z) or (B, 2, X, Y, Z) float32 (tensor or array) on the scene grid.
        grippers: G encodings, each (S_g, 2, gX, gY, gZ) float32 (only S_g is read by scene-only).
        keys: optional G strings naming the encodings; kernels are cached per (key, weights_version),
        so one key must always name the same encoding.
        Returns float32 on the model's device: (G, S_max, R, X, Y) for a 4-D scene or B == 1, else
        (B, G, S_max, R, X, Y); S_max = max S_g, and openings a gripper lacks (s >= S_g) hold
        probability 0, so neither argmax nor proportional sampling picks them. Needs eval mode.
        """
        if self.training:
            raise RuntimeError("predict: call model.eval() first (batch norm must use its running statistics)")
        scene = self._input(scene, "scene")
        squeeze = scene.dim() == 4 or scene.shape[0] == 1
        if scene.dim() == 4:
            scene = scene.unsqueeze(0)
        self._check_scene(scene)
        assert len(grippers) >= 1, "grippers: expected at least one gripper encoding"
        assert keys is None or len(keys) == len(grippers), "keys: one key per gripper expected"
        counts = [int(g.shape[0]) for g in grippers]
        kernels = None
        if self.variant != "scene-only":
            sets = []
            for g, enc in enumerate(grippers):
                enc = self._input(enc, f"grippers[{g}]")
                self._check_gripper(enc)
                sets.append(self.gripper_kernels(enc, None if keys is None else keys[g]))
            kernels = torch.cat(sets)  # (N, C, K, K), N = sum of S_g
        out = []
        for b in range(scene.shape[0]):
            maps = self._maps(scene[b : b + 1], kernels)  # (N or 1, R, X, Y)
            probs = maps.new_zeros(len(grippers), max(counts), *maps.shape[1:])
            start = 0
            for g, cnt in enumerate(counts):
                probs[g, :cnt] = maps if kernels is None else maps[start : start + cnt]
                start += cnt
            out.append(probs)
        return out[0] if squeeze else torch.stack(out)

    def _maps(self, scene: torch.Tensor, kernels: torch.Tensor | None) -> torch.Tensor:
        """Success probabilities (N, R, X, Y) of one scene (1, 2, X, Y, Z) for N kernels, or (1, R, X, Y)
        for scene-only (kernels None)."""
        R = self.rotations
        thetas = torch.arange(R, dtype=torch.float64) * (2.0 * math.pi / R)
        if kernels is not None and self.rotate_mode == "kernel":
            n = kernels.shape[0]
            feats = self.encode_scene(scene)  # (1, C, Fx, Fy)
            rotated = self.rotate_kernels(kernels.repeat(R, 1, 1, 1), thetas.repeat_interleave(n))
            corr = self.cross_correlate(feats, rotated, "all")[0]  # (R * N, C, Lx, Ly), rotation-major
            return self._decode_probs(corr, None).view(R, n, *self.scene_shape[:2]).transpose(0, 1)
        chunks = []
        step = self.scene_chunk or (R if scene.device.type == "cuda" else _CPU_SCENE_CHUNK)
        for r0 in range(0, R, step):
            th = thetas[r0 : r0 + step]
            feats = self.encode_scene(scene, th)  # (r, C, Fx, Fy)
            if kernels is None:
                chunks.append(self._decode_probs(feats, -th).unsqueeze(0))
                continue
            n = kernels.shape[0]
            corr = self.cross_correlate(feats, kernels, "all")  # (r, N, C, Lx, Ly)
            probs = self._decode_probs(corr.flatten(0, 1), -th.repeat_interleave(n))
            chunks.append(probs.view(len(th), n, *probs.shape[1:]).transpose(0, 1))
        return torch.cat(chunks, dim=1)

    def _decode_probs(self, corr: torch.Tensor, back: torch.Tensor | None) -> torch.Tensor:
        """Maps (M, C, Lx, Ly) -> success probabilities (M, X, Y), turned back by ``back`` (M,) rad if given."""
        outs = []
        step = self.decoder_chunk or (_GPU_DECODER_CHUNK if corr.device.type == "cuda" else _CPU_DECODER_CHUNK)
        for m in range(0, corr.shape[0], step):
            logits = self.decode(corr[m : m + step])
            if back is not None:
                logits = self.rotate_maps(logits, back[m : m + step])
            outs.append(torch.softmax(logits, dim=1)[:, SUCCESS])
        return torch.cat(outs)


def build_model(cfg: Config) -> AdaGraspNet:
    """The network for ``cfg`` (model section plus both grids), initialised from torch's global RNG."""
    return AdaGraspNet(cfg.model, cfg.scene_grid, cfg.gripper_grid)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
