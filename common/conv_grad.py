"""Convolution weight gradients by slab-wise im2col and one matrix product per slab.

On CPUs without AVX-512, oneDNN (torch's CPU convolution library) computes the weight gradient
of a strided 3-D convolution with its generic im2col + GEMM fallback, and that of a wide 2-D
3x3 convolution several times slower than the forward pass (docs/RESULTS.md, "Where the time
goes on two cores"). Here the output is cut
into slabs of a few depth rows, each slab's input patches are gathered into a buffer that stays
in cache, and the gradient accumulates one matrix product per slab. The input gradient still
comes from the library. Same sums as the library up to float rounding (tests/test_network.py);
tests/bench/bench_model.py times the training step both ways in the same run.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

SLAB_BYTES = 4 << 20
"""Target size (bytes) of one slab's patch buffer: a few MB, so it stays in the last-level cache."""


def slab_pays(dim: int, cin: int, kernel: int, stride: int) -> bool:
    """Whether the slab weight gradient beats the library's for this convolution on the CPU.

    Measured on the 2-core AVX2 machine, one thread, CPU seconds against the library's kernel:
    3-D stride 2 with 16 or 32 input channels 1.3-1.8x faster, 3-D stride 1 slower (0.4-0.8x:
    the library is fast there); 2-D 3x3 with 32 or 64 input channels 1.1-2.6x faster (the most
    at 192 x 192), with 16 input channels 0.8-1.0x.
    """
    if dim == 3:
        return stride == 2 and cin >= 16
    return dim == 2 and kernel == 3 and cin >= 32


def _triple(v, dim: int, fill: int) -> tuple[int, int, int]:
    """(D, H, W) values of a per-dimension argument; a 2-D one gets ``fill`` as its last."""
    v = (int(v),) * dim if isinstance(v, int) else tuple(int(a) for a in v)
    return v + (fill,) if dim == 2 else v


def conv_weight_grad(x: torch.Tensor, grad_out: torch.Tensor, kernel, stride, padding, slab_bytes: int = SLAB_BYTES) -> torch.Tensor:
    """Gradient of a 2-D or 3-D convolution's weight (one group, no dilation).

    x: (B, Cin, D, H, W) or (B, Cin, H, W) float32, the convolution's input, any memory format.
    grad_out: (B, Cout, D', H', W') or (B, Cout, H', W') float32, the gradient of its output.
    kernel, stride, padding: an int or one value per spatial dimension.
    Returns (Cout, Cin, *kernel) float32 in channels-last memory format (as the encoders'
    3-D weights), the sum over the batch. Slabs run along the first spatial dimension.
    """
    dim = x.dim() - 2
    if dim not in (2, 3) or grad_out.dim() != x.dim() or x.shape[0] != grad_out.shape[0]:
        raise ValueError(f"conv_weight_grad: x {tuple(x.shape)} and grad_out {tuple(grad_out.shape)} are not 2-D or 3-D batches")
    (kd, kh, kw), (s1, s2, s3), (p1, p2, p3) = (_triple(a, dim, f) for a, f in ((kernel, 1), (stride, 1), (padding, 0)))
    sizes, out_sizes = tuple(x.shape[2:]), tuple(grad_out.shape[2:])
    expect = tuple((n + 2 * p - k) // s + 1 for n, k, s, p in zip(sizes, (kd, kh, kw), (s1, s2, s3), (p1, p2, p3)))
    if expect[:dim] != out_sizes:
        raise ValueError(f"conv_weight_grad: grad_out spatial shape {out_sizes}, expected {expect[:dim]}")
    b, cin, cout = x.shape[0], x.shape[1], grad_out.shape[1]
    if dim == 2:  # (B, C, H, W) as (B, C, H, W, 1); channels-last memory is the same
        x, grad_out = (t.contiguous(memory_format=torch.channels_last).unsqueeze(-1) for t in (x, grad_out))
    d, h, w = x.shape[2:]
    do, ho, wo = grad_out.shape[2:]
    cl = torch.channels_last_3d
    xl = x.contiguous(memory_format=cl).permute(0, 2, 3, 4, 1)  # (B, D, H, W, Cin) contiguous
    gl = grad_out.contiguous(memory_format=cl).permute(0, 2, 3, 4, 1)  # (B, D', H', W', Cout)
    hp, wp = h + 2 * p2, w + 2 * p3
    taps = kd * kh * kw * cin
    rows = max(1, min(do, slab_bytes // (ho * wo * taps * x.element_size())))
    slab = x.new_zeros(s1 * (rows - 1) + kd, hp, wp, cin)  # padded input rows of one slab
    cols = x.new_empty(rows * ho * wo, taps)  # its patches, one row per output cell
    grad = x.new_zeros(cout, taps)  # columns ordered (kd, kh, kw, cin)
    sd, sh, sw = hp * wp * cin, wp * cin, cin
    for i in range(b):
        for a in range(0, do, rows):
            m = min(rows, do - a)
            first = s1 * a - p1  # input row of the slab's first row (may be padding)
            count = s1 * (m - 1) + kd
            lo, hi = max(first, 0), min(first + count, d)
            if lo > first:
                slab[: lo - first].zero_()
            slab[lo - first : hi - first, p2 : p2 + h, p3 : p3 + w] = xl[i, lo:hi]
            if hi - first < count:
                slab[hi - first : count].zero_()
            patches = slab.as_strided((m, ho, wo, kd, kh, kw, cin), (s1 * sd, s2 * sh, s3 * sw, sd, sh, sw, 1))
            c = cols[: m * ho * wo]
            c.view(m, ho, wo, kd, kh, kw, cin).copy_(patches)
            grad.addmm_(gl[i, a : a + m].reshape(-1, cout).t(), c)
    grad = grad.view(cout, kd, kh, kw, cin).permute(0, 4, 1, 2, 3)
    return grad[..., 0] if dim == 2 else grad


class _SlabGradConv(torch.autograd.Function):
    """2-D or 3-D convolution whose backward takes the weight gradient from ``conv_weight_grad``."""

    @staticmethod
    def forward(ctx, x, weight, bias, stride: tuple, padding: tuple):
        ctx.save_for_backward(x, weight)
        ctx.stride, ctx.padding, ctx.has_bias = stride, padding, bias is not None
        return (F.conv3d if x.dim() == 5 else F.conv2d)(x, weight, bias, stride, padding)

    @staticmethod
    def backward(ctx, grad_out):
        x, weight = ctx.saved_tensors
        s, p = ctx.stride, ctx.padding
        n = x.dim() - 2
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            grad_x = torch.ops.aten.convolution_backward(
                grad_out, x, weight, None, list(s), list(p), [1] * n, False, [0] * n, 1, [True, False, False]
            )[0]
        if ctx.needs_input_grad[1]:
            grad_w = torch.empty_like(weight).copy_(conv_weight_grad(x, grad_out, tuple(weight.shape[2:]), s, p))
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_b = grad_out.sum([0, *range(2, n + 2)])
        return grad_x, grad_w, grad_b, None, None


def conv_slab_grad(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride, padding) -> torch.Tensor:
    """``F.conv2d`` / ``F.conv3d(x, weight, bias, stride, padding)`` (one group, no dilation) whose
    weight gradient is computed by ``conv_weight_grad``; stride and padding are tuples."""
    return _SlabGradConv.apply(x, weight, bias, tuple(stride), tuple(padding))
