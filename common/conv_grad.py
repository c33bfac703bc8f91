"""Weight gradient of strided 3-D convolutions by slab-wise im2col and one matrix product per slab.

On CPUs without AVX-512, oneDNN (torch's CPU convolution library) computes the weight gradient
of a 3-D convolution with its generic im2col + GEMM fallback, which is slow for the encoders'
stride-2 layers (docs/RESULTS.md, "Where the time goes on two cores"). Here the output is cut
into slabs of a few depth rows, each slab's input patches are gathered into a buffer that stays
in cache, and the gradient accumulates one matrix product per slab. The input gradient still
comes from the library. Same sums as the library up to float rounding (tests/test_network.py);
tests/bench/bench_model.py times the training step both ways in the same run.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

SLAB_MIN_CHANNELS = 16
"""Input channels below which the library's kernel stays (with few channels each patch row is
short and gathering it costs more than the library's fallback)."""

SLAB_BYTES = 4 << 20
"""Target size (bytes) of one slab's patch buffer: a few MB, so it stays in the last-level cache."""


def conv3d_weight_grad(
    x: torch.Tensor, grad_out: torch.Tensor, kernel: int, stride: int, padding: int, slab_bytes: int = SLAB_BYTES
) -> torch.Tensor:
    """Gradient of a 3-D convolution's weight (cubic kernel, one group, no dilation).

    x: (B, Cin, D, H, W) float32, the convolution's input, any memory format.
    grad_out: (B, Cout, D', H', W') float32, the gradient of its output.
    Returns (Cout, Cin, k, k, k) float32 in channels-last-3d memory format (as the encoders'
    weights), the sum over the batch.
    """
    if x.dim() != 5 or grad_out.dim() != 5 or x.shape[0] != grad_out.shape[0]:
        raise ValueError(f"conv3d_weight_grad: x {tuple(x.shape)} and grad_out {tuple(grad_out.shape)} are not 5-D batches")
    b, cin, d, h, w = x.shape
    cout, do, ho, wo = grad_out.shape[1:]
    k, s, p = int(kernel), int(stride), int(padding)
    expect = tuple((n + 2 * p - k) // s + 1 for n in (d, h, w))
    if expect != (do, ho, wo):
        raise ValueError(f"conv3d_weight_grad: grad_out spatial shape {(do, ho, wo)}, expected {expect}")
    cl = torch.channels_last_3d
    xl = x.contiguous(memory_format=cl).permute(0, 2, 3, 4, 1)  # (B, D, H, W, Cin) contiguous
    gl = grad_out.contiguous(memory_format=cl).permute(0, 2, 3, 4, 1)  # (B, D', H', W', Cout)
    hp, wp = h + 2 * p, w + 2 * p
    taps = k * k * cin
    rows = max(1, min(do, slab_bytes // (ho * wo * k * taps * x.element_size())))
    slab = x.new_zeros(s * (rows - 1) + k, hp, wp, cin)  # padded input rows of one slab
    cols = x.new_empty(rows * ho * wo, k * taps)  # its patches, one row per output cell
    grad = x.new_zeros(cout, k * taps)  # columns ordered (kd, kh, kw, cin)
    sd, sh, sw = hp * wp * cin, wp * cin, cin
    for i in range(b):
        for a in range(0, do, rows):
            m = min(rows, do - a)
            first = s * a - p  # input depth row of the slab's first row (may be padding)
            count = s * (m - 1) + k
            lo, hi = max(first, 0), min(first + count, d)
            if lo > first:
                slab[: lo - first].zero_()
            slab[lo - first : hi - first, p : p + h, p : p + w] = xl[i, lo:hi]
            if hi - first < count:
                slab[hi - first : count].zero_()
            patches = slab.as_strided((m, ho, wo, k, k, k, cin), (s * sd, s * sh, s * sw, sd, sh, sw, 1))
            c = cols[: m * ho * wo]
            c.view(m, ho, wo, k, k, k, cin).copy_(patches)
            grad.addmm_(gl[i, a : a + m].reshape(-1, cout).t(), c)
    return grad.view(cout, k, k, k, cin).permute(0, 4, 1, 2, 3)


class _Conv3dSlabGrad(torch.autograd.Function):
    """conv3d whose backward takes the weight gradient from ``conv3d_weight_grad``."""

    @staticmethod
    def forward(ctx, x, weight, bias, stride: int, padding: int):
        ctx.save_for_backward(x, weight)
        ctx.stride, ctx.padding, ctx.has_bias = stride, padding, bias is not None
        return F.conv3d(x, weight, bias, stride, padding)

    @staticmethod
    def backward(ctx, grad_out):
        x, weight = ctx.saved_tensors
        s, p = ctx.stride, ctx.padding
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            grad_x = torch.ops.aten.convolution_backward(
                grad_out, x, weight, None, [s] * 3, [p] * 3, [1] * 3, False, [0] * 3, 1, [True, False, False]
            )[0]
        if ctx.needs_input_grad[1]:
            grad_w = conv3d_weight_grad(x, grad_out, weight.shape[-1], s, p)
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_b = grad_out.sum((0, 2, 3, 4))
        return grad_x, grad_w, grad_b, None, None


def conv3d_slab_grad(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int, padding: int) -> torch.Tensor:
    """``F.conv3d(x, weight, bias, stride, padding)`` (cubic kernel, one group) whose weight
    gradient is computed by ``conv3d_weight_grad``."""
    return _Conv3dSlabGrad.apply(x, weight, bias, int(stride), int(padding))
