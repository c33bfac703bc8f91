"""The network, the learner and checkpoints on a CUDA device (skipped where torch sees none):
batched inference against the per-rotation loop and against the CPU, a learner step against the
same step on the CPU, and a CPU checkpoint loaded onto the GPU.

TF32 is switched off inside these tests so that the GPU computes in full float32 and the
tolerances of the CPU tests apply; the benchmark (tests/bench/bench_model.py --device cuda)
reports the GPU-CPU difference under torch's default settings."""

import pytest
import torch

from common.config import load_config
from replay.synthetic import FixedBatchReplay, random_actions
from test_network import SMALL, loop_probs, random_gripper, random_scene, small_model

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.fixture(autouse=True)
def full_float32():
    before = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = before


@pytest.mark.parametrize(
    "overrides",
    [(), ("model.correlation=grouped",), ("model.rotate=kernel",), ("model.variant=scene-only",)],
)
def test_cuda_predict_equals_loop_and_cpu(overrides):
    cfg, model = small_model("model.rotations=8", *overrides)
    scene = random_scene(cfg, 1)
    grippers = [random_gripper(cfg, 3, 2), random_gripper(cfg, 2, 3)]
    on_cpu = model.predict(scene, grippers, keys=["a", "b"])
    model.cuda()
    probs = model.predict(scene.cuda(), [g.cuda() for g in grippers], keys=["a", "b"])
    assert probs.device.type == "cuda" and probs.shape == (2, 3, 8, 32, 32)
    for g, enc in enumerate(grippers):
        ref = loop_probs(model, scene.cuda(), enc.cuda())
        assert float((probs[g, : enc.shape[0]] - ref).abs().max()) <= 1e-5
    assert float((probs.cpu() - on_cpu).abs().max()) <= 1e-4


def fixed_replay(cfg) -> FixedBatchReplay:
    """One batch of seeded random scenes, grippers and actions, alternating labels."""
    B = cfg.learner.batch_size
    gen = torch.Generator().manual_seed(5)
    action = random_actions(B, cfg.scene_grid.shape[:2], cfg.model.rotations, 8, gen)
    scene = torch.cat([random_scene(cfg, b) for b in range(B)])
    gripper = torch.cat([random_gripper(cfg, 1, b) for b in range(B)])
    return FixedBatchReplay(scene, gripper, action, (torch.arange(B) % 2).float())


def learner_step(cfg, device: str):
    """One Learner.train step from a fixed batch (seeded): (loss, scores, Adam's first moments
    (0.1 x the gradient) by name on the CPU, published weights)."""
    from learner.learner import Learner

    torch.manual_seed(3)
    replay = fixed_replay(cfg)
    learner = Learner(cfg, replay, device=device, seed=7)
    loss = learner.train(1).loss
    names = {id(p): n for n, p in learner.model.named_parameters()}
    moments = {names[id(p)]: st["exp_avg"].cpu() for p, st in learner.optimizer.state.items()}
    return loss, replay.scores[0], moments, learner.publish()[1]


def test_cuda_learner_step_matches_cpu():
    """Same seeds, same augmentation draws (every sample rotated and shifted, on the device): the
    GPU learner's loss, replay scores and gradients equal the CPU learner's within float32
    rounding, amplified through training-mode batch norm over 8 samples (measured on an H200:
    loss 4e-5, scores 1.4e-4, gradients 1.3% of the largest apart; a sample augmented
    differently or a missing gradient term moves them by far more); published weights are on
    the CPU.
    Only one step is compared: Adam moves every weight by about lr whatever its gradient's size,
    so gradients near zero whose sign differs between devices make later steps drift apart."""
    cfg = load_config("default", SMALL + ["model.rotations=8", "learner.augment_prob=1.0"])
    cpu_loss, cpu_scores, cpu_moments, _ = learner_step(cfg, "cpu")
    gpu_loss, gpu_scores, gpu_moments, gpu_state = learner_step(cfg, "cuda")
    assert abs(cpu_loss - gpu_loss) <= 5e-4, (cpu_loss, gpu_loss)
    assert float(abs(cpu_scores - gpu_scores).max()) <= 1e-3, (cpu_scores, gpu_scores)
    assert cpu_moments.keys() == gpu_moments.keys() and len(cpu_moments) > 10
    scale = max(float(m.abs().max()) for m in cpu_moments.values())
    worst = max(float((cpu_moments[k] - gpu_moments[k]).abs().max()) for k in cpu_moments)
    assert scale > 0 and worst <= 5e-2 * scale, (worst, scale)
    assert all(v.device.type == "cpu" for v in gpu_state.values())


def test_cpu_checkpoint_loads_onto_cuda(tmp_path):
    from common.checkpoint import load_checkpoint, save_checkpoint

    cfg, model = small_model("model.rotations=8", seed=2)
    path = save_checkpoint(tmp_path / "latest.pt", model, cfg, step=1, version=3, epsilon=0.5)
    loaded, ckpt = load_checkpoint(path, device="cuda")
    assert loaded.device.type == "cuda" and loaded.weights_version == 3 and ckpt.cfg == cfg
    scene, gripper = random_scene(cfg, 4), random_gripper(cfg, 2, 4)
    ref = model.predict(scene, [gripper])
    got = loaded.predict(scene.cuda(), [gripper.cuda()]).cpu()
    assert float((got - ref).abs().max()) <= 1e-4
