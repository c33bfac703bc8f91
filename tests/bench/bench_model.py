"""Benchmark of the AdaGrasp network: inference per scene and training step, at both scales.

Prints ONE JSON line of medians over ``--repeats`` timed runs (after one warm-up run):

- ``params``: trainable parameters (the same at both scales);
- ``infer_default_s`` / ``infer_paper_s``: seconds per scene for 1 gripper x 5 openings x 16
  rotations with ``model.rotate=scene`` (the paper's method), gripper kernels cached (as actors
  run it); ``gripper_kernels_default_s`` / ``_paper_s``: encoding the 5 kernels once;
- ``infer_default_kernel_s`` / ``infer_paper_kernel_s``: the same with ``model.rotate=kernel``;
- ``infer_paper_g5_s``: the paper-scale scene for 5 grippers x 5 openings x 16 rotations at once
  (divide by 5 for seconds per gripper);
- ``train_step_default_s`` / ``train_step_paper_s``: one batch-8 step (forward of each sample's
  executed rotation, loss, backward, Adam);
- ``learner_step_default_s`` / ``learner_step_paper_s``: one :meth:`learner.learner.Learner.train`
  step as the learner runs it (batch moved to the device, rotation/shift augmentation there,
  the step, scores back to the replay), fed one fixed batch held in memory
  (:class:`replay.synthetic.FixedBatchReplay`) instead of the Zarr replay, so that replay reads
  are not part of the figure (tests/bench/bench_replay.py has those);
- ``kernel_rotation_consistency``: accuracy proxy of the kernel-rotation option on an untrained
  seeded model (see :func:`rotation_consistency`), per mode: mean |p(rot90 scene, k + R/4) -
  rot90(p(scene, k))| and the fraction of (opening, rotation) maps whose maximum is reached
  within one cell of where the original map's argmax cell turns to;
- ``train_step_paper_frozen_stem_s``: the paper-scale step with ``model.train_stem=false``;
- ``learner_step_precision_default`` / ``_paper`` (with ``--precision``): the learner step with
  ``learner.precision`` fp32 and bf16 (bfloat16 autocast), timed alternately in one process:
  ``fp32_s``, ``bf16_s``, ``speedup``;
- ``speed_option_accuracy`` (with ``--accuracy-steps N``): the paper's model and both speed
  options trained N steps on the same synthetic grasping task (:func:`synth_accuracy`) and
  scored on held-out scenes;
- ``*_gflop`` and ``*_gflop_per_s`` (with ``--flops``): convolution GFLOP per call of the
  inference and training-step figures (:func:`count_gflop`) and the rate the timed median
  implies, to compare with what the machine can do;
- ``reference`` (with ``--reference``): the public AdaGrasp code's compute schedule on the same
  layers and weights (tests/bench/reference.py: per opening the gripper encoded again, per
  rotation the scene turned by ``grid_sample`` and encoded again, each layer on its own in the
  contiguous layout) against this project's path, timed alternately in one process (the order
  swaps every round, since the second place of a pair runs a few per cent faster here): per
  figure ``ours_s``, ``reference_s`` and ``speedup`` = reference / ours, for inference
  (1 gripper x 5 openings x R rotations, ``infer_default`` / ``infer_paper``) and the batch-8
  training step (``train_step_default`` / ``train_step_paper``); ``max_abs_diff_default``, the
  largest difference of the two paths' probabilities for the timed default-scale scene;
  ``wgrad_chunking_paper``: the paper-scale training step with the 3-D weight gradients taken in
  chunks of samples (``common.network._WGRAD_MAX_ELEMENTS``, the default) against one call for
  the whole batch, alternately (``chunked_s``, ``whole_batch_s``, ``ratio``);
- ``threads``: torch intra-op threads; ``device`` (``--device``; on CUDA every timed run ends
  with a device synchronisation, and ``gpu``, ``torch``, the TF32 settings, the peak allocated
  memory ``cuda_peak_gib`` and ``cuda_cpu_max_abs_diff_default``, the largest difference between
  the default model's probabilities on the GPU and on the CPU for the same scene, are added);
  ``process_env``: whether the process ran with
  the allocator settings every launcher process gets (``--process-env`` applies
  ``common.runtime.apply_process_env`` before torch loads: transparent huge pages and glibc
  keeping freed buffers, so large activations are not faulted in and zeroed again every step);
  ``load_avg``: the machine's 1-minute load average before and after (the figures are only
  comparable on an otherwise idle machine).

Usage::

    python tests/bench/bench_model.py                 # both scales, 3 repeats
    python tests/bench/bench_model.py --repeats 5 --threads 2 --process-env --skip-paper-train
    python tests/bench/bench_model.py --device cuda --repeats 10 --set model.scene_chunk=1
    python tests/bench/bench_model.py --repeats 3 --threads 2 --process-env --skip-kernel --flops
    python tests/bench/bench_model.py --repeats 3 --threads 2 --process-env --skip-kernel --reference
    python tests/bench/bench_model.py --repeats 5 --threads 1 --process-env --skip-kernel --skip-paper --precision
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.runtime import apply_process_env  # noqa: E402

if __name__ == "__main__" and "--process-env" in sys.argv:
    apply_process_env()  # before torch allocates anything

import numpy as np  # noqa: E402
import torch  # noqa: E402

from common.config import load_config  # noqa: E402
from common.network import build_model, count_parameters  # noqa: E402
from learner.learner import Learner, precision_autocast  # noqa: E402
from replay.synthetic import FixedBatchReplay, random_actions  # noqa: E402
from reference import reference_copy, reference_predict, reference_train_step_fn  # noqa: E402


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


def timed(fn, device: torch.device) -> float:
    """Wall seconds of one call of ``fn``; on CUDA the call ends with a synchronisation, so
    queued kernels are inside the figure."""
    t0 = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - t0


def median_time(fn, repeats: int, device: torch.device) -> float:
    """Median of :func:`timed` over ``repeats`` runs after one warm-up."""
    timed(fn, device)
    return statistics.median([timed(fn, device) for _ in range(repeats)])


def paired_medians(a, b, repeats: int, device: torch.device) -> tuple[float, float]:
    """Median wall seconds of ``a`` and of ``b``, timed alternately after one warm-up each; the
    order swaps every round (a b, b a, ...), so neither gains from always running second."""
    timed(a, device)
    timed(b, device)
    ta, tb = [], []
    for r in range(repeats):
        if r % 2 == 0:
            ta.append(timed(a, device))
            tb.append(timed(b, device))
        else:
            tb.append(timed(b, device))
            ta.append(timed(a, device))
    return statistics.median(ta), statistics.median(tb)


def bench_reference(cfg, repeats: int, device: torch.device, train: bool = True, diff: bool = False) -> dict:
    """This project's inference and training step against the public code's schedule
    (tests/bench/reference.py) on the same weights, scene and batch: ``{figure: {ours_s,
    reference_s, speedup}}``, plus ``max_abs_diff`` of the two inference results if ``diff``."""
    torch.manual_seed(0)
    model = build_model(cfg).to(device).eval()
    ref = reference_copy(model).eval()
    scene = scene_of(cfg, 1, 0).to(device)
    grip = gripper_of(cfg, 5, 0).to(device)
    ours = lambda: model.predict(scene, [grip], keys=["bench"])  # noqa: E731 (kernels cached, as actors run it)
    theirs = lambda: reference_predict(ref, scene, grip)  # noqa: E731
    out = {}
    if diff:
        out["max_abs_diff"] = float((ours()[0] - theirs()).abs().max())
    a, b = paired_medians(ours, theirs, repeats, device)
    out["infer"] = {"ours_s": a, "reference_s": b, "speedup": b / a}
    if train:
        torch.manual_seed(0)
        ref_step = reference_train_step_fn(reference_copy(build_model(cfg).to(device)).train(), cfg.learner.lr)
        B = cfg.learner.batch_size
        scenes, grips = scene_of(cfg, B, 1).to(device), gripper_of(cfg, B, 1).to(device)
        gen = torch.Generator().manual_seed(0)

        def theirs_step():
            action = random_actions(B, cfg.scene_grid.shape[:2], cfg.model.rotations, 0, gen).to(device)
            ref_step(scenes, grips, action, (torch.arange(B, device=device) % 2))

        a, b = paired_medians(train_step_fn(cfg, device), theirs_step, repeats, device)
        out["train_step"] = {"ours_s": a, "reference_s": b, "speedup": b / a}
    return out


def bench_wgrad_chunking(cfg, repeats: int, device: torch.device) -> dict:
    """The training step with chunked 3-D weight gradients (the default) against whole-batch ones."""
    import common.network as network

    chunked, whole_step = train_step_fn(cfg, device), train_step_fn(cfg, device)
    limit = network._WGRAD_MAX_ELEMENTS

    def whole():
        network._WGRAD_MAX_ELEMENTS = 2**62
        try:
            whole_step()
        finally:
            network._WGRAD_MAX_ELEMENTS = limit

    a, b = paired_medians(chunked, whole, repeats, device)
    return {"chunked_s": a, "whole_batch_s": b, "ratio": b / a}


def infer_fns(cfg, device: torch.device, grippers: int = 1):
    """(one scene's inference for ``grippers`` x 5 openings x R rotations with cached kernels,
    encoding one gripper's 5 kernels), as the bench times them."""
    torch.manual_seed(0)
    model = build_model(cfg).to(device).eval()
    scene = scene_of(cfg, 1, 0).to(device)
    grips = [gripper_of(cfg, 5, g).to(device) for g in range(grippers)]
    keys = [f"bench{g}" for g in range(grippers)]
    return (lambda: model.predict(scene, grips, keys=keys)), (lambda: model.gripper_kernels(grips[0]))


def bench_infer(cfg, repeats: int, device: torch.device, grippers: int = 1) -> tuple[float, float]:
    """(seconds per scene for ``grippers`` x 5 openings x R rotations, seconds to encode 5 kernels)."""
    infer, kernels = infer_fns(cfg, device, grippers)
    kernel_s = median_time(kernels, repeats, device)
    return median_time(infer, repeats, device), kernel_s


def count_gflop(fn) -> float:
    """GFLOP of the convolutions one call of ``fn`` runs (torch's FlopCounterMode; 1 multiply-add
    = 2 FLOP; FFTs, resampling and element-wise work are not counted). Counted on the plain
    convolution path: the fused oneDNN calls of CPU inference run the same convolutions but are
    invisible to the counter."""
    from torch.utils.flop_counter import FlopCounterMode

    import common.network as network

    fused, network._FUSED = network._FUSED, None
    try:
        with FlopCounterMode(display=False) as counter:
            fn()
    finally:
        network._FUSED = fused
    return counter.get_total_flops() / 1e9


def learner_step_fn(cfg, device: torch.device):
    """One :meth:`Learner.train` step on a fixed batch (augmentation probability as configured)."""
    B = cfg.learner.batch_size
    gen = torch.Generator().manual_seed(2)
    action = random_actions(B, cfg.scene_grid.shape[:2], cfg.model.rotations, cfg.scene_grid.shape[0] // 4, gen)
    replay = FixedBatchReplay(scene_of(cfg, B, 2), gripper_of(cfg, B, 2), action, (torch.arange(B) % 2).float())
    torch.manual_seed(0)
    learner = Learner(cfg, replay, device=device, seed=0)
    return lambda: learner.train(1)


def bench_learner(cfg, repeats: int, device: torch.device) -> float:
    """Seconds per :meth:`Learner.train` step (:func:`learner_step_fn`)."""
    return median_time(learner_step_fn(cfg, device), repeats, device)


def bench_precision(cfg, repeats: int, device: torch.device) -> dict:
    """The learner step (:func:`learner_step_fn`) with ``learner.precision`` fp32 and bf16, timed
    alternately: ``fp32_s``, ``bf16_s`` and ``speedup`` = fp32 / bf16."""
    fns = {}
    for precision in ("fp32", "bf16"):
        c = copy.deepcopy(cfg)
        c.learner.precision = precision
        fns[precision] = learner_step_fn(c, device)
    a, b = paired_medians(fns["fp32"], fns["bf16"], repeats, device)
    return {"fp32_s": a, "bf16_s": b, "speedup": a / b}


def cuda_cpu_diff(cfg, device: torch.device) -> float:
    """Largest |p_gpu - p_cpu| over the default model's maps of one scene (1 gripper x 5 openings)."""
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    scene, grip = scene_of(cfg, 1, 0), gripper_of(cfg, 5, 0)
    cpu = model.predict(scene, [grip])
    gpu = model.to(device).predict(scene.to(device), [grip.to(device)]).cpu()
    return float((gpu - cpu).abs().max())


def bench_train(cfg, repeats: int, device: torch.device) -> float:
    """Seconds per batch-B training step (:func:`train_step_fn`)."""
    return median_time(train_step_fn(cfg, device), repeats, device)


def train_step_fn(cfg, device: torch.device):
    """One training step as the bench times it: forward of each sample's executed rotation,
    loss, backward, Adam; random scenes and actions, alternating labels."""
    torch.manual_seed(0)
    model = build_model(cfg).to(device).train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.learner.lr)
    B = cfg.learner.batch_size
    scene = scene_of(cfg, B, 1).to(device)
    grip = gripper_of(cfg, B, 1).to(device)
    gen = torch.Generator().manual_seed(0)

    def step():
        action = random_actions(B, cfg.scene_grid.shape[:2], cfg.model.rotations, 0, gen)
        label = torch.arange(B) % 2
        logits = model.forward_train(scene, grip, action[:, 2].to(device))
        loss = model.loss(logits, action, label)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


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


# ---------------------------------------------------------------------------------------
# Accuracy of the kernel-rotation option on a synthetic grasping task
# ---------------------------------------------------------------------------------------

SYNTH = [
    "scene_grid.x_range=[-0.064, 0.064]",
    "scene_grid.y_range=[-0.064, 0.064]",
    "scene_grid.z_range=[0.0, 0.064]",
    "gripper_grid.shape=[16, 16, 8]",
    "model.rotations=8",
]
"""Synthetic task grid: 32 x 32 x 16 scene cells at 4 mm, 16 x 16 x 8 gripper cells at 8 mm, R = 8."""
SYNTH_APERTURES = (0.03, 0.06)
"""Finger gaps (m) of the synthetic parallel-jaw gripper at its two openings."""


def synth_gripper(cfg) -> torch.Tensor:
    """(2, 2, gX, gY, gZ) float32 TSDF-like encoding of a parallel-jaw gripper: two 8 mm fingers
    along x at +-gap/2 (below the TCP) and a palm above, at each aperture; channel 1 closed."""
    g = cfg.gripper_grid
    gx, gy, gz = g.shape
    pts_x = (np.arange(gx) + 0.5 - gx / 2) * g.voxel_size
    pts_y = (np.arange(gy) + 0.5 - gy / 2) * g.voxel_size
    pts_z = (np.arange(gz) + 0.5) * g.voxel_size - g.tcp_height
    X, Y, Z = np.meshgrid(pts_x, pts_y, pts_z, indexing="ij")

    def vol(gap):
        finger = (np.abs(np.abs(X) - gap / 2 - 0.004) <= 0.004) & (np.abs(Y) <= 0.012) & (Z <= 0.0)
        palm = (np.abs(X) <= gap / 2 + 0.008) & (np.abs(Y) <= 0.012) & (Z > 0.0)
        return np.where(finger | palm, -1.0, 1.0)

    closed = vol(0.0)
    return torch.from_numpy(np.stack([np.stack([vol(a), closed]) for a in SYNTH_APERTURES]).astype(np.float32))


def synth_scene(cfg, rng) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """One random box (yaw any, 8-40 mm sides, 20-50 mm tall) near the centre.

    Returns the scene (1, 2, X, Y, Z) float32, labels (S, R, X, Y) bool -- a grasp succeeds when
    the TCP is over the box (2 mm inside its outline) and both jaws, at +-gap/2 along the
    closing direction, clear the box by 2 mm -- and the cells within 16 mm of the box (X, Y)
    bool, where the hard failures are."""
    from scipy.ndimage import binary_dilation

    grid = cfg.scene_grid
    X, Y, Z = grid.shape
    v = grid.voxel_size
    length, width = rng.uniform(0.008, 0.040, size=2)
    height = rng.uniform(0.02, 0.05)
    yaw = rng.uniform(0, np.pi)
    cx, cy = rng.uniform(-0.03, 0.03, size=2)
    xs = grid.x_range[0] + (np.arange(X) + 0.5) * v
    ys = grid.y_range[0] + (np.arange(Y) + 0.5) * v
    px, py = np.meshgrid(xs - cx, ys - cy, indexing="ij")
    u = np.cos(yaw) * px + np.sin(yaw) * py
    w = -np.sin(yaw) * px + np.cos(yaw) * py
    inside = (np.abs(u) <= length / 2) & (np.abs(w) <= width / 2)
    heights = np.where(inside, height, 0.0)
    zs = grid.z_range[0] + (np.arange(Z) + 0.5) * v
    tsdf = np.clip((zs[None, None, :] - heights[:, :, None]) / grid.truncation, -1, 1)
    scene = torch.from_numpy(np.stack([tsdf, np.zeros_like(tsdf)])[None].astype(np.float32))
    core = (np.abs(u) <= length / 2 - 0.002) & (np.abs(w) <= width / 2 - 0.002)
    R = cfg.model.rotations
    labels = np.zeros((len(SYNTH_APERTURES), R, X, Y), dtype=bool)
    for k in range(R):
        theta = 2 * np.pi * k / R
        delta = theta - yaw
        across = abs(length * np.cos(delta)) + abs(width * np.sin(delta))  # box width across the jaws
        offset = np.abs(np.cos(theta) * px + np.sin(theta) * py)  # TCP from the box centre along the jaws
        for s, gap in enumerate(SYNTH_APERTURES):
            labels[s, k] = core & (across / 2 + offset < gap / 2 - 0.002)
    near = binary_dilation(inside, iterations=4)
    return scene, labels, near


SPEED_OPTIONS = {
    "scene": ["model.decoder_width=64"],
    "kernel": ["model.decoder_width=64", "model.rotate=kernel"],
    "frozen_stem": ["model.decoder_width=64", "model.train_stem=false"],
    "decoder32": ["model.decoder_width=32"],
    "decoder32_bf16": ["model.decoder_width=32", "learner.precision=bf16"],
}
"""The reference model (the paper's scene rotation, 64-channel decoder) and the speed options,
compared by :func:`synth_accuracy`."""


def synth_accuracy(
    steps: int, eval_scenes: int = 30, seeds: int = 3, options: list[str] | None = None, device: str = "cpu"
) -> dict:
    """:func:`synth_accuracy_one` for seeds 0..seeds-1: per option the mean and per-seed metrics."""
    options = list(SPEED_OPTIONS) if options is None else options
    runs = [synth_accuracy_one(steps, eval_scenes, seed, options, device) for seed in range(seeds)]
    out = {"steps": steps, "eval_scenes": eval_scenes, "seeds": seeds, "grid": runs[0]["grid"]}
    for mode in options:
        out[mode] = {
            key: float(np.mean([r[mode][key] for r in runs])) for key in ("top1", "balanced_acc", "train_s")
        }
        out[mode]["balanced_acc_per_seed"] = [round(r[mode]["balanced_acc"], 4) for r in runs]
    return out


def synth_accuracy_one(steps: int, eval_scenes: int, seed: int, options: list[str], device: str = "cpu") -> dict:
    """Train the paper's model and each speed option on the same synthetic data; held-out metrics.

    Each step: batch 8, half successes and half failures drawn from the label maps of fresh
    scenes (the paper's balanced sampling), Adam at the paper's learning rate. Metrics on
    ``eval_scenes`` held-out scenes: ``top1``, the fraction whose best-scored grasp over the
    cells near the box is a success; ``balanced_acc``, mean of the accuracies on successes and
    on failures near the box (threshold 0.5)."""
    out = {"steps": steps, "eval_scenes": eval_scenes, "grid": "32x32x16 @ 4 mm, R=8"}
    for mode in options:
        cfg = load_config("default", SYNTH + SPEED_OPTIONS[mode])
        torch.manual_seed(seed)
        model = build_model(cfg).to(device).train()
        opt = torch.optim.Adam(model.parameters(), lr=cfg.learner.lr)
        grip = synth_gripper(cfg).to(device)
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        for _ in range(steps):
            scenes, grips, actions, labels = [], [], [], []
            while len(scenes) < 8:
                scene, lab, near = synth_scene(cfg, rng)
                want = len(scenes) % 2 == 0
                cand = np.argwhere(lab if want else ~lab & near)
                if len(cand) == 0:
                    continue
                s, k, i, j = cand[rng.integers(len(cand))]
                scenes.append(scene)
                grips.append(grip[s : s + 1])
                actions.append((i, j, k, s))
                labels.append(int(want))
            action = torch.tensor(actions, device=device)
            with precision_autocast(torch.device(device), cfg.learner.precision):
                logits = model.forward_train(torch.cat(scenes).to(device), torch.cat(grips), action[:, 2])
                loss = model.loss(logits, action, torch.tensor(labels, device=device))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize(device)
        train_s = time.perf_counter() - t0
        model.eval()
        erng = np.random.default_rng(10_000 + seed)
        top1, acc_pos, acc_neg = [], [], []
        for _ in range(eval_scenes):
            scene, lab, near = synth_scene(cfg, erng)
            probs = model.predict(scene.to(device), [grip])[0].cpu().numpy()  # (S, R, X, Y)
            region = np.broadcast_to(near, probs.shape)
            best = np.unravel_index(int(np.argmax(np.where(region, probs, -1))), probs.shape)
            top1.append(bool(lab[best]))
            if lab.any():
                acc_pos.append(float((probs[lab] > 0.5).mean()))
            neg = region & ~lab
            acc_neg.append(float((probs[neg] <= 0.5).mean()))
        out[mode] = {
            "top1": float(np.mean(top1)),
            "balanced_acc": 0.5 * (float(np.mean(acc_pos)) + float(np.mean(acc_neg))),
            "train_s": train_s,
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu", help="torch device of the timed runs: cpu | cuda | cuda:N")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override applied to both scales (repeatable), e.g. model.scene_chunk=16")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--skip-paper", action="store_true", help="skip every paper-scale measurement")
    ap.add_argument("--skip-paper-train", action="store_true", help="skip the paper-scale training step")
    ap.add_argument("--skip-kernel", action="store_true", help="skip the kernel-rotation option")
    ap.add_argument("--flops", action="store_true",
                    help="also count the convolution GFLOP of each timed figure and the GFLOP/s it ran at")
    ap.add_argument("--process-env", action="store_true",
                    help="run with the launcher's allocator settings (common/runtime.py), applied before torch loads")
    ap.add_argument("--reference", action="store_true",
                    help="also time the public code's schedule (tests/bench/reference.py) against ours, alternately")
    ap.add_argument("--precision", action="store_true",
                    help="also time the learner step with learner.precision fp32 against bf16, alternately")
    ap.add_argument("--accuracy-steps", type=int, default=0,
                    help="train scene- and kernel-rotation models this many steps on the synthetic task (0: skip)")
    ap.add_argument("--accuracy-seeds", type=int, default=3, help="seeds of the synthetic accuracy comparison")
    ap.add_argument("--only-accuracy", action="store_true", help="run only the synthetic accuracy comparison")
    ap.add_argument("--options", default=",".join(SPEED_OPTIONS),
                    help=f"comma-separated options of the accuracy comparison (of {', '.join(SPEED_OPTIONS)})")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    options = [o for o in args.options.split(",") if o]
    unknown = sorted(set(options) - set(SPEED_OPTIONS))
    if unknown:
        ap.error(f"--options: unknown {unknown}; known: {list(SPEED_OPTIONS)}")
    if args.only_accuracy:
        acc = synth_accuracy(args.accuracy_steps or 300, seeds=args.accuracy_seeds, options=options, device=args.device)
        print(json.dumps({"speed_option_accuracy": acc}))
        return 0
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        ap.error(f"--device {args.device}: torch {torch.__version__} sees no CUDA device")

    def config(name: str, *extra: str):
        return load_config(name, list(args.set) + list(extra))

    default = config("default")
    paper = config("paper")
    n = args.repeats
    out = {
        "params": count_parameters(build_model(default)),
        "threads": torch.get_num_threads(),
        "device": str(device),
        "overrides": list(args.set),
        "process_env": args.process_env,
        "load_avg_before": os.getloadavg()[0],
    }
    if device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
        out["torch"] = torch.__version__
        out["cudnn_allow_tf32"] = torch.backends.cudnn.allow_tf32
        out["matmul_allow_tf32"] = torch.backends.cuda.matmul.allow_tf32
        out["cuda_cpu_max_abs_diff_default"] = cuda_cpu_diff(default, device)
    out["infer_default_s"], out["gripper_kernels_default_s"] = bench_infer(default, n, device)
    out["train_step_default_s"] = bench_train(default, n, device)
    out["learner_step_default_s"] = bench_learner(default, n, device)
    if not args.skip_kernel:
        out["infer_default_kernel_s"] = bench_infer(config("default", "model.rotate=kernel"), n, device)[0]
    if not args.skip_paper:
        out["infer_paper_s"], out["gripper_kernels_paper_s"] = bench_infer(paper, n, device)
        out["infer_paper_g5_s"] = bench_infer(paper, n, device, grippers=5)[0]
        if not args.skip_kernel:
            out["infer_paper_kernel_s"] = bench_infer(config("paper", "model.rotate=kernel"), n, device)[0]
        if not args.skip_paper_train:
            out["train_step_paper_s"] = bench_train(paper, n, device)
            out["learner_step_paper_s"] = bench_learner(paper, n, device)
            out["train_step_paper_frozen_stem_s"] = bench_train(config("paper", "model.train_stem=false"), n, device)
    if args.precision:
        out["learner_step_precision_default"] = bench_precision(default, n, device)
        if not args.skip_paper and not args.skip_paper_train:
            out["learner_step_precision_paper"] = bench_precision(paper, n, device)
    if args.reference:
        ref = bench_reference(default, n, device, diff=True)
        out["reference"] = {"max_abs_diff_default": ref.pop("max_abs_diff")}
        out["reference"].update({f"{k}_default": v for k, v in ref.items()})
        if not args.skip_paper:
            ref = bench_reference(paper, n, device, train=not args.skip_paper_train)
            out["reference"].update({f"{k}_paper": v for k, v in ref.items()})
            if not args.skip_paper_train and device.type == "cpu":
                out["reference"]["wgrad_chunking_paper"] = bench_wgrad_chunking(paper, n, device)
    if device.type == "cuda":
        out["cuda_peak_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
    if args.flops:
        def warmed(infer):
            infer()  # fills the gripper kernel cache, as the timed runs' warm-up does
            return infer

        counted = {
            "infer_default": warmed(infer_fns(default, device)[0]),
            "train_step_default": train_step_fn(default, device),
        }
        if not args.skip_paper:
            counted["infer_paper"] = warmed(infer_fns(paper, device)[0])
            if not args.skip_paper_train:
                counted["train_step_paper"] = train_step_fn(paper, device)
        for name, fn in counted.items():
            out[f"{name}_gflop"] = count_gflop(fn)
            out[f"{name}_gflop_per_s"] = out[f"{name}_gflop"] / out[f"{name}_s"]
    if not args.skip_kernel:
        out["kernel_rotation_consistency"] = rotation_consistency(None)
    if args.accuracy_steps > 0:
        out["speed_option_accuracy"] = synth_accuracy(
            args.accuracy_steps, seeds=args.accuracy_seeds, options=options, device=args.device
        )
    out["load_avg_after"] = os.getloadavg()[0]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
