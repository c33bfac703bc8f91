"""Benchmark of the AdaGrasp network: inference per scene and training step, at both scales.

Prints ONE JSON line of medians over ``--repeats`` timed runs (after one warm-up run):

- ``params``: trainable parameters (the same at both scales);
- ``infer_default_s`` / ``infer_paper_s``: seconds per scene for 1 gripper x 5 openings x 16
  rotations with ``model.rotate=scene`` (the paper's method), gripper kernels cached (as actors
  run it); ``gripper_kernels_default_s`` / ``_paper_s``: encoding the 5 kernels once;
- ``infer_default_kernel_s`` / ``infer_paper_kernel_s``: the same with ``model.rotate=kernel``;
- ``train_step_default_s`` / ``train_step_paper_s``: one batch-8 step (forward of each sample's
  executed rotation, loss, backward, Adam);
- ``kernel_rotation_consistency``: accuracy proxy of the kernel-rotation option on an untrained
  seeded model (see :func:`rotation_consistency`), per mode: mean |p(rot90 scene, k + R/4) -
  rot90(p(scene, k))| and the fraction of (opening, rotation) maps whose maximum is reached
  within one cell of where the original map's argmax cell turns to;
- ``threads``: torch intra-op threads; ``device``.

Usage::

    python tests/bench/bench_model.py                 # both scales, 3 repeats
    python tests/bench/bench_model.py --repeats 5 --threads 2 --skip-paper-train
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.config import load_config  # noqa: E402
from common.network import build_model, count_parameters  # noqa: E402


def scene_of(cfg, batch: int, seed: int) -> torch.Tensor:
    """(batch, 2, X, Y, Z) float32 TSDF of random boxes on the table, empty obstacle channel."""
    rng = np.random.default_rng(seed)
    X, Y, Z = cfg.scene_grid.shape
    out = np.zeros((batch, 2, X, Y, Z), dtype=np.float32)
    z = np.arange(Z)[None, None, :]
    for b in range(batch):
        h = np.zeros((X, Y))
        for _ in range(5):
            i, j = rng.integers(X // 4, 3 * X // 4, size=2)
            w, d = rng.integers(X // 24, X // 8, size=2)
            h[i : i + w, j : j + d] = rng.integers(Z // 8, Z // 2)
        out[b, 0] = np.clip((z - h[:, :, None]) / 5.0, -1, 1)
    return torch.from_numpy(out)


def gripper_of(cfg, n: int, seed: int) -> torch.Tensor:
    """(n, 2, gX, gY, gZ) float32: two finger blocks and a palm, fingers further apart per opening."""
    gx, gy, gz = cfg.gripper_grid.shape
    out = np.ones((n, 2, gx, gy, gz), dtype=np.float32)
    for s in range(n):
        for c, gap in ((0, gx // 8 + s * gx // 16), (1, gx // 16)):
            lo, hi = gx // 2 - gap, gx // 2 + gap
            out[s, c, lo - gx // 16 : lo, gy // 2 - gy // 8 : gy // 2 + gy // 8, : gz // 2] = -1
            out[s, c, hi : hi + gx // 16, gy // 2 - gy // 8 : gy // 2 + gy // 8, : gz // 2] = -1
            out[s, c, lo - gx // 16 : hi + gx // 16, gy // 2 - gy // 8 : gy // 2 + gy // 8, gz // 2 :] = -1
    return torch.from_numpy(out)


def median_time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_infer(cfg, repeats: int) -> tuple[float, float]:
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    scene = scene_of(cfg, 1, 0)
    grip = gripper_of(cfg, 5, 0)
    kernels = median_time(lambda: model.gripper_kernels(grip), repeats)
    per_scene = median_time(lambda: model.predict(scene, [grip], keys=["bench"]), repeats)
    return per_scene, kernels


def bench_train(cfg, repeats: int) -> float:
    torch.manual_seed(0)
    model = build_model(cfg).train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.learner.lr)
    B = cfg.learner.batch_size
    scene = scene_of(cfg, B, 1)
    grip = gripper_of(cfg, B, 1)
    gen = torch.Generator().manual_seed(0)
    X, Y, _ = cfg.scene_grid.shape

    def step():
        k = torch.randint(cfg.model.rotations, (B,), generator=gen)
        action = torch.stack([torch.randint(X, (B,), generator=gen), torch.randint(Y, (B,), generator=gen), k], dim=1)
        label = torch.arange(B) % 2
        logits = model.forward_train(scene, grip, k)
        loss = model.loss(logits, action, label)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return median_time(step, repeats)


def rotation_consistency(cfg, seeds: int = 2) -> dict:
    """How far the scores are from turning with the scene, for an untrained seeded model.

    For a scene and the scene turned by 90 degrees about the grid centre (exact on the grid),
    the maps of rotation k + R/4 of the turned scene should be the maps of rotation k turned by
    90 degrees. ``scene`` rotation satisfies this by construction (up to rounding); ``kernel``
    rotation only as far as the features are rotation equivariant."""
    out = {}
    for mode in ("scene", "kernel"):
        diffs, hits, total = [], 0, 0
        for seed in range(seeds):
            torch.manual_seed(seed)
            c = load_config("default", [f"model.rotate={mode}"]) if cfg is None else cfg
            c.model.rotate = mode
            model = build_model(c).eval()
            scene = scene_of(c, 1, 10 + seed)
            grip = gripper_of(c, 2, 0)
            p = model.predict(scene, [grip])[0].numpy()  # (S, R, X, Y)
            turned = torch.from_numpy(np.ascontiguousarray(np.rot90(scene.numpy(), 1, axes=(2, 3))))
            q = model.predict(turned, [grip])[0].numpy()
            R, N = p.shape[1], p.shape[2]
            for s in range(p.shape[0]):
                for k in range(R):
                    expect = np.rot90(p[s, k], 1)
                    got = q[s, (k + R // 4) % R]
                    diffs.append(float(np.abs(got - expect).mean()))
                    i, j = np.unravel_index(int(np.argmax(p[s, k])), p[s, k].shape)
                    i2, j2 = N - 1 - j, i  # where that cell goes when the scene turns
                    near = got[max(i2 - 1, 0) : i2 + 2, max(j2 - 1, 0) : j2 + 2].max()
                    hits += int(near >= got.max() - 1e-6)
                    total += 1
        out[mode] = {"mean_abs_diff": float(np.mean(diffs)), "argmax_follows": hits / total}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--skip-paper", action="store_true", help="skip every paper-scale measurement")
    ap.add_argument("--skip-paper-train", action="store_true", help="skip the paper-scale training step")
    ap.add_argument("--skip-kernel", action="store_true", help="skip the kernel-rotation option")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    default = load_config("default")
    paper = load_config("paper")
    out = {"params": count_parameters(build_model(default)), "threads": torch.get_num_threads(), "device": "cpu"}
    out["infer_default_s"], out["gripper_kernels_default_s"] = bench_infer(default, args.repeats)
    out["train_step_default_s"] = bench_train(default, args.repeats)
    if not args.skip_kernel:
        out["infer_default_kernel_s"] = bench_infer(load_config("default", ["model.rotate=kernel"]), args.repeats)[0]
    if not args.skip_paper:
        out["infer_paper_s"], out["gripper_kernels_paper_s"] = bench_infer(paper, args.repeats)
        if not args.skip_kernel:
            out["infer_paper_kernel_s"] = bench_infer(load_config("paper", ["model.rotate=kernel"]), args.repeats)[0]
        if not args.skip_paper_train:
            out["train_step_paper_s"] = bench_train(paper, args.repeats)
    if not args.skip_kernel:
        out["kernel_rotation_consistency"] = rotation_consistency(None)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
