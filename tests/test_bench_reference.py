"""The benchmark's same-run baseline (tests/bench/reference.py) computes what the model computes:
the public code's per-opening, per-rotation loop gives the scores of ``predict``, and its training
step the loss and gradients of ``forward_train``, so the timings compare like with like."""

import importlib.util
from pathlib import Path

import pytest
import torch

from test_network import SMALL as SMALL_GRIDS

from common.config import load_config
from common.network import build_model

SMALL = SMALL_GRIDS + ["model.rotations=8"]
"""The network tests' small grids (32 x 32 x 16 scene cells, 16 x 16 x 8 gripper cells), R = 8."""

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def reference():
    path = Path(__file__).resolve().parent / "bench" / "reference.py"
    spec = importlib.util.spec_from_file_location("bench_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def scene_and_gripper(cfg, batch: int, openings: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    X, Y, Z = cfg.scene_grid.shape
    height = torch.randint(0, Z // 2, (batch, X, Y), generator=gen).float()
    z = torch.arange(Z).float().view(1, 1, 1, Z)
    tsdf = ((z - height[..., None]) / 3.0).clamp(-1, 1)
    obstacle = (torch.rand(tsdf.shape, generator=gen) < 0.1).float()
    scene = torch.stack([tsdf, obstacle], dim=1)
    grip = torch.rand((openings, 2, *cfg.gripper_grid.shape), generator=gen) * 2 - 1
    return scene, grip


@pytest.mark.parametrize("variant", ["adagrasp", "init-only"])
def test_reference_loop_scores_equal_predict(reference, variant):
    cfg = load_config("default", SMALL + [f"model.variant={variant}"])
    torch.manual_seed(0)
    model = build_model(cfg).train()
    scene, grip = scene_and_gripper(cfg, 4, 3, seed=1)
    with torch.no_grad():
        model.forward_train(scene, grip[[0, 1, 2, 0]], torch.tensor([0, 1, 2, 3]))  # non-trivial BN statistics
    model.eval()
    ref = reference.reference_copy(model)
    assert ref.scene_encoder.conv3d[0].conv.weight.is_contiguous()
    assert not model.scene_encoder.conv3d[0].conv.weight.is_contiguous()  # the model runs channels-last
    got = reference.reference_predict(ref, scene[:1], grip)
    want = model.predict(scene[:1], [grip])[0]
    assert got.shape == want.shape == (3, 8, 32, 32)
    assert float((got - want).abs().max()) <= 1e-4
    assert float(got.std()) > 1e-3  # the maps are not constant


def test_reference_training_step_equals_forward_train(reference):
    """In float64: in float32 the two orders of the same sums differ by up to 1% in the first
    layers' gradients (rounding through train-mode batch norm), which would hide a real bug."""
    cfg = load_config("default", SMALL)
    torch.manual_seed(0)
    model = build_model(cfg).double().train()
    ref = reference.reference_copy(model)
    scene, grip = (t.double() for t in scene_and_gripper(cfg, 4, 4, seed=2))
    action = torch.tensor([[3, 5, 0, 0], [10, 20, 3, 1], [16, 16, 6, 2], [30, 1, 7, 3]])
    label = torch.tensor([1, 0, 1, 0])
    logits = model.forward_train(scene, grip, action[:, 2])
    loss = model.loss(logits, action, label)
    loss.backward()
    before = ref.dec_out.weight.detach().clone()
    step = reference.reference_train_step_fn(ref, lr=5e-4)
    ref_loss = step(scene, grip, action, label)
    assert abs(ref_loss - float(loss.detach())) <= 1e-6
    for (name, p), q in zip(model.named_parameters(), ref.parameters()):
        assert q.grad is not None, name
        assert float((p.grad - q.grad).abs().max()) <= 1e-5 * max(1.0, float(p.grad.abs().max())), name
    assert not torch.equal(before, ref.dec_out.weight)  # the step updated the weights
