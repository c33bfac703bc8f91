"""The AdaGrasp network: batched inference against the per-rotation loop, shapes at both scales,
the loss's gradient, rotation conventions (90-degree equivariance of the argmax, the gripper's
yaw on a hand-built scene, the decoder's centring), the correlation methods, the kernel cache,
config errors."""

import math

import numpy as np
import pytest
import torch

from common.config import load_config
from common.network import (
    SUCCESS,
    NetworkConfigError,
    _upsample,
    build_model,
    count_parameters,
    rotation_taps,
)

SMALL = [
    "scene_grid.x_range=[-0.064, 0.064]",
    "scene_grid.y_range=[-0.064, 0.064]",
    "scene_grid.z_range=[0.0, 0.064]",
    "gripper_grid.shape=[16, 16, 8]",
]
"""A 32 x 32 x 16 scene grid at 4 mm and a 16 x 16 x 8 gripper grid at 8 mm: fast, same architecture."""


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def small_model(*overrides: str, seed: int = 0):
    cfg = load_config("default", SMALL + list(overrides))
    torch.manual_seed(seed)
    return cfg, build_model(cfg).eval()


def random_scene(cfg, seed: int) -> torch.Tensor:
    """(1, 2, X, Y, Z) float32: TSDF of a few boxes on the table (1 free, -1 inside), an obstacle channel."""
    rng = np.random.default_rng(seed)
    X, Y, Z = cfg.scene_grid.shape
    height = np.zeros((X, Y))
    for _ in range(4):
        i, j = rng.integers(2, X - 8, size=2)
        w, d = rng.integers(2, 7, size=2)
        height[i : i + w, j : j + d] = rng.integers(2, Z - 2)
    z = np.arange(Z)[None, None, :]
    tsdf = np.clip((z - height[:, :, None]) / 3.0, -1.0, 1.0)
    obstacle = ((tsdf < 0) & (rng.random((X, Y, 1)) < 0.3)).astype(np.float64)
    return torch.from_numpy(np.stack([tsdf, obstacle])[None].astype(np.float32))


def random_gripper(cfg, n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.rand((n, 2, *cfg.gripper_grid.shape), generator=gen) * 2 - 1


def loop_probs(model, scene, gripper) -> torch.Tensor:
    """(S, R, X, Y) by one forward_train call per opening and rotation."""
    R = model.rotations
    out = torch.zeros(gripper.shape[0], R, *model.scene_shape[:2], device=model.device)
    with torch.no_grad():
        for s in range(gripper.shape[0]):
            for k in range(R):
                logits = model.forward_train(scene, gripper[s : s + 1], torch.tensor([k]))
                out[s, k] = torch.softmax(logits, dim=1)[0, SUCCESS]
    return out


@pytest.mark.parametrize(
    "overrides",
    [
        (),
        ("model.correlation=grouped",),
        ("model.variant=init-only", "model.scene_chunk=3", "model.decoder_chunk=5"),
        ("model.rotate=kernel",),
        ("model.variant=scene-only",),
    ],
)
def test_batched_predict_equals_loop(overrides):
    cfg, model = small_model("model.rotations=8", *overrides)
    scene = random_scene(cfg, 1)
    grippers = [random_gripper(cfg, 3, 2), random_gripper(cfg, 2, 3)]
    probs = model.predict(scene, grippers, keys=["a", "b"])
    assert probs.shape == (2, 3, 8, 32, 32) and probs.dtype == torch.float32
    for g, enc in enumerate(grippers):
        ref = loop_probs(model, scene, enc)
        assert float((probs[g, : enc.shape[0]] - ref).abs().max()) <= 1e-5
    assert float(probs[1, 2].abs().max()) == 0.0  # padded opening
    if cfg.model.variant == "scene-only":
        assert torch.equal(probs[0, 0], probs[1, 1])
    else:
        assert float((probs[0, 0] - probs[0, 1]).abs().max()) > 1e-4  # the gripper matters


def test_default_scale_shapes_and_batched_subset(default_cfg):
    torch.manual_seed(0)
    model = build_model(default_cfg).eval()
    assert model.feature_shape == (48, 48) and model.kernel_size == 32 and model.lattice0 == (49, 49)
    scene = random_scene(default_cfg, 0)
    gripper = random_gripper(default_cfg, 2, 0)
    probs = model.predict(scene[0], [gripper])
    assert probs.shape == (1, 2, 16, 96, 96)
    assert 0.0 <= float(probs.min()) and float(probs.max()) <= 1.0
    with torch.no_grad():
        for s, k in ((0, 0), (1, 5), (0, 11)):
            logits = model.forward_train(scene, gripper[s : s + 1], torch.tensor([k]))
            ref = torch.softmax(logits, dim=1)[0, SUCCESS]
            assert float((probs[0, s, k] - ref).abs().max()) <= 1e-5
    assert count_parameters(model) > 0


def test_paper_scale_training_shapes(paper_cfg):
    torch.manual_seed(0)
    model = build_model(paper_cfg)
    assert model.feature_shape == (48, 48) and model.kernel_size == 32 and model.lattice0 == (49, 49)
    scene = torch.zeros(1, 2, 192, 192, 64)
    gripper = torch.zeros(1, 2, 64, 64, 32)
    model.train()
    logits = model.forward_train(scene, gripper, torch.tensor([3]))
    assert logits.shape == (1, 2, 192, 192)


@pytest.mark.slow
def test_paper_scale_predict_shape(paper_cfg):
    torch.manual_seed(0)
    model = build_model(paper_cfg).eval()
    probs = model.predict(torch.zeros(2, 192, 192, 64), [torch.zeros(5, 2, 64, 64, 32)])
    assert probs.shape == (1, 5, 16, 192, 192)


def test_gradient_only_from_executed_action():
    cfg, model = small_model()
    model.train()
    scene = torch.cat([random_scene(cfg, 4), random_scene(cfg, 5)])
    gripper = random_gripper(cfg, 2, 6)
    action = torch.tensor([[3, 7, 2, 0], [20, 11, 9, 1]])
    logits = model.forward_train(scene, gripper, action[:, 2])
    logits.retain_grad()
    loss = model.loss(logits, action, torch.tensor([True, False]))
    loss.backward()
    grad = logits.grad
    mask = torch.zeros_like(grad, dtype=torch.bool)
    mask[0, :, 3, 7] = True
    mask[1, :, 20, 11] = True
    assert float(grad[~mask].abs().max()) == 0.0
    assert float(grad[mask].abs().min()) > 0.0
    # success pushes the success logit up, failure pushes it down (gradient descent)
    assert grad[0, SUCCESS, 3, 7] < 0 and grad[1, SUCCESS, 20, 11] > 0
    for name in ("scene_encoder.conv3d.0.conv.weight", "gripper_encoder.conv3d.0.conv.weight", "dec_out.weight"):
        assert float(dict(model.named_parameters())[name].grad.abs().sum()) > 0.0, name
    # the loss is the paper's: softmax cross-entropy of the two logits at the executed cell
    picked = torch.stack([logits[0, :, 3, 7], logits[1, :, 20, 11]]).detach()
    expected = -(torch.log_softmax(picked, dim=1)[[0, 1], [1, 0]]).mean()
    assert abs(float(loss.detach()) - float(expected)) < 1e-6


def test_rotating_the_scene_90_degrees_rotates_the_best_grasp():
    """Untrained, seeded model on a square grid: rot90 of the scene moves the argmax to the rotated
    cell and rotation k + R/4."""
    cfg, model = small_model(
        "scene_grid.x_range=[-0.096, 0.096]", "scene_grid.y_range=[-0.096, 0.096]", seed=3
    )
    scene = random_scene(cfg, 11)
    gripper = random_gripper(cfg, 2, 12)
    R, N = model.rotations, cfg.scene_grid.shape[0]
    probs = model.predict(scene, [gripper])[0]
    flat = probs.flatten()
    top2 = torch.topk(flat, 2).values
    assert float(top2[0] - top2[1]) > 1e-4, "argmax is not unique enough for this test"
    s, k, i, j = np.unravel_index(int(flat.argmax()), probs.shape)
    turned = torch.from_numpy(np.ascontiguousarray(np.rot90(scene.numpy(), 1, axes=(2, 3))))
    probs2 = model.predict(turned, [gripper])[0]
    s2, k2, i2, j2 = np.unravel_index(int(probs2.argmax()), probs2.shape)
    assert s2 == s and k2 == (k + R // 4) % R
    # world (x, y) -> (-y, x) about the centre: cell (i, j) -> (N - 1 - j, i), exactly (a quarter
    # turn of a square grid moves cells onto cells: a score map shifted by one cell fails here)
    assert (i2, j2) == (N - 1 - j, i)
    assert abs(float(probs2[s2, k2, i2, j2]) - float(probs[s, k, i, j])) < 1e-5


@pytest.mark.parametrize("rotate", ["scene", "kernel"])
def test_yaw_convention_on_a_hand_built_scene(monkeypatch, rotate):
    """With the learned layers replaced by occupancy sums, rotation k's best cell is the TCP that
    puts the gripper's finger (at +x of the TCP) on the block at yaw theta_k (x turned towards y)."""
    cfg, model = small_model(
        "scene_grid.x_range=[-0.128, 0.128]",
        "scene_grid.y_range=[-0.128, 0.128]",
        "model.rotations=4",
        f"model.rotate={rotate}",
    )
    X, Y, Z = cfg.scene_grid.shape  # 64 x 64 x 16 at 4 mm; features 32 x 32 at 8 mm
    C = model.channels

    def scene_features(scene, theta=None):
        if theta is not None:
            scene = model.rotate_scene(scene, theta)
        occ = (scene[:, :1] < 0).float().sum(dim=-1)  # (B, 1, X, Y)
        return torch.nn.functional.avg_pool2d(occ, 2).repeat(1, C, 1, 1)

    def gripper_features(gripper):
        return (gripper[:, :1] < 0).float().sum(dim=-1).repeat(1, C, 1, 1)

    def decode(x):
        y = _upsample(x.sum(dim=1, keepdim=True), model.corners)
        return torch.cat([-y, y], dim=1)

    monkeypatch.setattr(model, "encode_scene", scene_features)
    monkeypatch.setattr(model, "encode_gripper", gripper_features)
    monkeypatch.setattr(model, "decode", decode)
    # block: scene cells 40..41 along x and 20..21 along y = feature cell (20, 10)
    scene = torch.ones(1, 2, X, Y, Z)
    scene[0, 0, 40:42, 20:22, :4] = -1.0
    scene[0, 1] = 0.0
    # gripper: one occupied 8 mm cell, (14, 7) of 16: its centre is (+6.5, -0.5) cells from the TCP
    gripper = torch.ones(1, 2, 16, 16, 8)
    gripper[0, 0, 14, 7, :] = -1.0
    probs = model.predict(scene, [gripper])[0, 0]  # (R, X, Y)
    block = np.array([41.0, 21.0])  # centre, in scene cells from the grid corner
    finger = np.array([6.5, -0.5]) * 2.0  # in scene cells
    for k in range(4):
        theta = 2 * math.pi * k / 4
        rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
        tcp = block - rot @ finger
        # the TCP falls on a cell corner: the best cells are exactly the four cells around it
        best = {tuple(c) for c in np.argwhere(probs[k].numpy() >= float(probs[k].max()) - 1e-6)}
        corner = np.rint(tcp).astype(int)
        assert np.allclose(tcp, corner), tcp
        around = {(corner[0] - di, corner[1] - dj) for di in (0, 1) for dj in (0, 1)}
        assert best == around, (k, sorted(best), tcp)


@pytest.mark.parametrize("variant", ["adagrasp", "scene-only"])
def test_decoder_with_mirror_symmetric_kernels_commutes_with_a_mirror(variant):
    """With every decoder kernel made mirror-symmetric, the decoder must commute with mirroring its
    input along x and along y: its output grid is centred on the correlation lattice (corner or
    centre samples), so a score map shifted by a cell, or padded on one side only, fails here."""
    cfg, model = small_model(f"model.variant={variant}", seed=6)
    assert model.corners == (variant == "adagrasp")
    decoder = [model.dec_in, model.dec_res0, *model.dec_up, *model.dec_res, model.dec_out]
    with torch.no_grad():
        for m in (m for part in decoder for m in part.modules()):
            if isinstance(m, torch.nn.Conv2d):
                w = m.weight
                w.copy_((w + w.flip(-1) + w.flip(-2) + w.flip(-1, -2)) / 4)
        gen = torch.Generator().manual_seed(6)
        maps = torch.rand(3, model.channels, *model.lattice0, generator=gen)
        out = model.decode(maps)
        assert out.shape == (3, 2, *model.scene_shape[:2])
        for dim in (2, 3):
            mirrored = model.decode(maps.flip(dim))
            assert float((mirrored - out.flip(dim)).abs().max()) < 1e-4 * float(out.abs().max()), dim


def test_rotation_taps_quarter_turn_is_exact():
    rng = np.random.default_rng(0)
    img = rng.random((7, 7)).astype(np.float32)
    idx, w = rotation_taps(math.pi / 2, 7, 7)
    out = (img.reshape(-1)[idx] * w).sum(-1).reshape(7, 7)
    # out(q) = in(R q): content turns by -90 degrees, i.e. np.rot90 with k = -1
    np.testing.assert_allclose(out, np.rot90(img, -1), atol=1e-6)


def test_correlation_methods_agree_and_place_the_tcp():
    cfg, model = small_model()
    gen = torch.Generator().manual_seed(0)
    feats = torch.rand(3, model.channels, 16, 16, generator=gen)
    kernels = torch.rand(4, model.channels, 16, 16, generator=gen)
    model.correlation = "fft"
    a = model.cross_correlate(feats, kernels, "all")
    m_a = model.cross_correlate(feats, kernels[:3], "matched")
    model.correlation = "grouped"
    b = model.cross_correlate(feats, kernels, "all")
    m_b = model.cross_correlate(feats, kernels[:3], "matched")
    assert a.shape == (3, 4, model.channels, 17, 17)
    assert float((a - b).abs().max()) < 1e-5 and float((m_a - m_b).abs().max()) < 1e-5
    assert float((m_a[1] - a[1, 1]).abs().max()) < 1e-5
    # a single feature at cell p and a single kernel cell a: the output sits at o = p + K // 2 - a
    f = torch.zeros(1, model.channels, 16, 16)
    f[0, :, 5, 9] = 1.0
    k = torch.zeros(1, model.channels, 16, 16)
    k[0, :, 11, 3] = 1.0
    for method in ("fft", "grouped"):
        model.correlation = method
        out = model.cross_correlate(f, k, "all")[0, 0, 0]
        assert tuple(np.unravel_index(int(out.argmax()), out.shape)) == (5 + 8 - 11, 9 + 8 - 3)


def test_kernel_cache_follows_weights_version(monkeypatch):
    cfg, model = small_model()
    scene = random_scene(cfg, 0)
    gripper = random_gripper(cfg, 2, 0)
    calls = []
    original = model.encode_gripper
    monkeypatch.setattr(model, "encode_gripper", lambda g: calls.append(1) or original(g))
    p1 = model.predict(scene, [gripper], keys=["g"])
    p2 = model.predict(scene, [gripper], keys=["g"])
    assert len(calls) == 1 and torch.equal(p1, p2)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    state["gripper_encoder.out.conv.weight"].mul_(-1.0)
    model.set_weights(state, version=7)
    p3 = model.predict(scene, [gripper], keys=["g"])
    assert len(calls) == 2 and float((p3 - p1).abs().max()) > 1e-4
    model.train()
    with pytest.raises(RuntimeError, match="eval"):
        model.predict(scene, [gripper])


def test_bad_grids_raise_one_line_errors():
    with pytest.raises(NetworkConfigError, match="gripper_grid.shape") as e:
        small_model("gripper_grid.shape=[16, 8, 8]")
    assert "\n" not in str(e.value)
    with pytest.raises(NetworkConfigError, match="scene_grid.voxel_size"):
        cfg = load_config("default", SMALL + ["scene_grid.voxel_size=0.008", "model.feature_cell=0.024"])
        build_model(cfg)
    cfg, model = small_model()
    with pytest.raises(AssertionError, match="scene"):
        model.predict(torch.zeros(1, 2, 8, 8, 8), [random_gripper(cfg, 1, 0)])


def test_checkpoint_round_trip_keeps_weights_variant_and_config(tmp_path):
    from common.checkpoint import CheckpointError, load_checkpoint, read_checkpoint, save_checkpoint

    cfg, model = small_model("model.variant=init-only", "model.rotations=8", "learner.lr=0.001", seed=4)
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.learner.lr)
    scene = random_scene(cfg, 0)
    logits = model.forward_train(scene, random_gripper(cfg, 1, 0), torch.tensor([2]))
    model.loss(logits, torch.tensor([[5, 6, 2, 0]]), torch.tensor([1])).backward()
    optimizer.step()  # weights and batch-norm statistics now differ from the initialisation
    model.eval()
    path = save_checkpoint(tmp_path / "ck" / "latest.pt", model, cfg, step=17, version=5, epsilon=0.4,
                           optimizer=optimizer, extra={"note": "x"})
    loaded, ckpt = load_checkpoint(path)
    assert ckpt.variant == "init-only" and loaded.variant == "init-only"
    assert ckpt.cfg == cfg and ckpt.step == 17 and ckpt.version == 5 and ckpt.epsilon == 0.4
    assert ckpt.extra == {"note": "x"} and loaded.weights_version == 5 and not loaded.training
    ref, got = model.state_dict(), loaded.state_dict()
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)
    fresh = torch.optim.Adam(loaded.parameters(), lr=cfg.learner.lr)
    fresh.load_state_dict(ckpt.optimizer)
    gripper = random_gripper(cfg, 2, 1)
    assert torch.equal(model.predict(scene, [gripper]), loaded.predict(scene, [gripper]))
    # damaged or inconsistent files: one line naming the file and the key, nothing half-written
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    for target, needle in ((bad, "not a readable checkpoint"), (tmp_path / "none.pt", "not found")):
        with pytest.raises(CheckpointError, match=needle) as e:
            read_checkpoint(target)
        assert "\n" not in str(e.value) and str(target) in str(e.value)
    state = torch.load(path, weights_only=True)
    state["variant"] = "adagrasp"
    torch.save(state, tmp_path / "mismatch.pt")
    with pytest.raises(CheckpointError, match="variant"):
        read_checkpoint(tmp_path / "mismatch.pt")
    state["variant"] = "init-only"
    state["config"]["model"]["rotations"] = 0
    torch.save(state, tmp_path / "badcfg.pt")
    with pytest.raises(CheckpointError, match="model.rotations"):
        read_checkpoint(tmp_path / "badcfg.pt")
    state["config"]["model"]["rotations"] = 8
    del state["model"]["dec_out.weight"]
    torch.save(state, tmp_path / "partial.pt")
    with pytest.raises(CheckpointError, match="model: weights do not fit"):
        load_checkpoint(tmp_path / "partial.pt")
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == ["latest.pt"]


def test_fused_inference_kernels_match_the_plain_path(monkeypatch):
    """CPU inference fuses bias, ReLU and residual adds into oneDNN convolutions; the plain path
    (batch norm folded, separate ReLU) gives the same probabilities."""
    import common.network as network

    if network._FUSED is None:
        pytest.skip("this torch build has no fused oneDNN convolution")
    cfg, model = small_model("model.rotations=4")
    scene = random_scene(cfg, 2)
    gripper = random_gripper(cfg, 2, 3)
    fused = model.predict(scene, [gripper])
    monkeypatch.setattr(network, "_FUSED", None)
    plain = model.predict(scene, [gripper])
    assert float((fused - plain).abs().max()) <= 1e-5
    # and the training path (batch statistics) is untouched: train-mode forward needs gradients
    model.train()
    logits = model.forward_train(scene, gripper[:1], torch.tensor([1]))
    assert logits.requires_grad


def test_chunked_weight_gradient_of_3d_convolutions_matches_the_batch(monkeypatch):
    """Large 3-D batches take their weight gradients in chunks of samples on the CPU (oneDNN
    falls back to a slow kernel above 2**28 input elements); the gradients stay the same. The
    chunk limit is lowered so that the small model's 5-sample batch splits into 2 + 2 + 1 at the
    first layer and into other sizes further down. In float64: in float32 the two summation
    orders already differ by about 1% in the first layer's gradient (rounding amplified through
    train-mode batch norm), which would hide a real bug."""
    import common.network as network

    cfg, model = small_model("model.rotations=8", seed=3)
    model.double().train()
    scenes = torch.cat([random_scene(cfg, s) for s in range(5)]).double()
    grippers = random_gripper(cfg, 5, 4).double()
    k = torch.tensor([0, 3, 5, 6, 7])
    action = torch.tensor([[3, 4, 0, 0], [10, 20, 3, 1], [16, 16, 5, 2], [30, 1, 6, 3], [0, 31, 7, 4]])
    label = torch.tensor([1, 0, 1, 0, 1])
    calls = []
    original = network._Conv3dChunkedWeightGrad.apply

    def grads(limit: int) -> dict:
        monkeypatch.setattr(network, "_WGRAD_MAX_ELEMENTS", limit)
        model.zero_grad(set_to_none=True)
        loss = model.loss(model.forward_train(scenes, grippers, k), action, label)
        loss.backward()
        return {n: p.grad.clone() for n, p in model.named_parameters()}

    def counted(*args):
        calls.append(args[-1])
        return original(*args)

    monkeypatch.setattr(network._Conv3dChunkedWeightGrad, "apply", counted)
    whole = grads(2**40)
    assert calls == []
    per_sample = 2 * 32 * 32 * 16
    chunked = grads(2 * per_sample)
    assert calls and calls[0] == 2  # the scene's first layer: chunks of two samples
    for name, g in whole.items():
        assert float((chunked[name] - g).abs().max()) <= 1e-9 * max(1.0, float(g.abs().max())), name


def test_frozen_stem_trains_everything_but_the_first_block():
    cfg, model = small_model("model.train_stem=false")
    model.train()
    stem = model.scene_encoder.conv3d[0]
    before = stem.norm.running_mean.clone()
    scene = random_scene(cfg, 3)
    logits = model.forward_train(scene, random_gripper(cfg, 1, 3), torch.tensor([1]))
    model.loss(logits, torch.tensor([[4, 5, 1, 0]]), torch.tensor([1])).backward()
    assert stem.conv.weight.grad is None and stem.norm.weight.grad is None
    assert float(model.scene_encoder.conv3d[1].conv.weight.grad.abs().sum()) > 0
    assert not torch.equal(stem.norm.running_mean, before)  # batch statistics still tracked
    # the same weights give the same scores whichever way the stem is trained
    _, trained = small_model()
    trained.load_state_dict(model.state_dict())
    model.eval()
    trained.eval()
    grip = random_gripper(cfg, 1, 4)
    assert torch.equal(model.predict(scene, [grip]), trained.predict(scene, [grip]))


def test_shipped_models_load_by_name(tmp_path, monkeypatch):
    import common.checkpoint as ck

    cfg, model = small_model(seed=2)
    ck.save_checkpoint(tmp_path / "tiny-net" / "checkpoint.pt", model.eval(), cfg, step=3, version=2)
    monkeypatch.setattr(ck, "shipped_models_dir", lambda: tmp_path)
    loaded, ckpt = ck.load_checkpoint("model:tiny-net")
    assert ckpt.step == 3 and all(torch.equal(v, loaded.state_dict()[k]) for k, v in model.state_dict().items())
    with pytest.raises(ck.CheckpointError, match="known: tiny-net") as e:
        ck.read_checkpoint("model:nope")
    assert "\n" not in str(e.value) and "model:nope" in str(e.value)


def test_every_shipped_model_loads():
    from common.checkpoint import load_checkpoint, shipped_models_dir

    names = sorted(p.parent.name for p in shipped_models_dir().glob("*/checkpoint.pt"))
    for name in names:
        model, ckpt = load_checkpoint(f"model:{name}")
        assert not model.training and (shipped_models_dir() / name / "config.yaml").is_file()


def test_folded_batch_norm_follows_weight_edits():
    """Eval-mode inference keeps each conv's folded batch norm between calls; editing a weight
    in place, giving it new storage or loading new weights must refold it."""
    cfg, model = small_model("model.rotations=4", seed=5)
    scene = random_scene(cfg, 5)
    grip = random_gripper(cfg, 2, 5)

    def fresh_probs():
        _, fresh = small_model("model.rotations=4", seed=6)
        fresh.load_state_dict(model.state_dict())
        return fresh.eval().predict(scene, [grip])

    before = model.predict(scene, [grip])
    assert torch.equal(before, model.predict(scene, [grip]))
    with torch.no_grad():
        model.scene_encoder.conv3d[1].norm.running_var.mul_(4.0)
    edited = model.predict(scene, [grip])
    assert float((edited - before).abs().max()) > 1e-4 and torch.equal(edited, fresh_probs())
    weight = model.dec_res0.conv1.conv.weight
    weight.data = -weight.data.clone()
    replaced = model.predict(scene, [grip])
    assert float((replaced - edited).abs().max()) > 1e-4 and torch.equal(replaced, fresh_probs())
    _, other = small_model("model.rotations=4", seed=7)
    model.load_state_dict(other.state_dict())
    assert torch.equal(model.predict(scene, [grip]), other.eval().predict(scene, [grip]))


def test_checkpoints_run_with_batching_chosen_for_the_device(tmp_path):
    from common.checkpoint import load_checkpoint, save_checkpoint

    cfg, model = small_model("model.rotations=4", "model.scene_chunk=3", "model.decoder_chunk=5", seed=8)
    save_checkpoint(tmp_path / "c.pt", model, cfg, step=1, version=1)
    loaded, ckpt = load_checkpoint(tmp_path / "c.pt")
    assert (loaded.scene_chunk, loaded.decoder_chunk) == (0, 0)
    assert (ckpt.cfg.model.scene_chunk, ckpt.cfg.model.decoder_chunk) == (3, 5)
    chosen, _ = load_checkpoint(tmp_path / "c.pt", scene_chunk=2, decoder_chunk=7)
    assert (chosen.scene_chunk, chosen.decoder_chunk) == (2, 7)
    scene, grip = random_scene(cfg, 8), random_gripper(cfg, 2, 8)
    reference = model.predict(scene, [grip])
    for other in (loaded, chosen):
        assert float((other.predict(scene, [grip]) - reference).abs().max()) <= 1e-5
    with pytest.raises(ValueError, match="scene_chunk"):
        load_checkpoint(tmp_path / "c.pt", scene_chunk=-1)


def test_chunked_weight_gradient_under_bf16_autocast_matches_the_plain_convolution(monkeypatch):
    """learner.precision=bf16 on the CPU at paper scale takes the chunked weight-gradient path
    (its saved float32 input met a bfloat16 gradient: a dtype error at the first step). Under
    autocast it computes what the plain convolution computes, up to bfloat16 rounding, and the
    weights' gradients stay float32."""
    import common.network as network

    cfg, model = small_model("model.rotations=8", seed=3)
    model.train()
    scenes = torch.cat([random_scene(cfg, s) for s in range(3)])
    grippers = random_gripper(cfg, 3, 4)
    k, action, label = torch.tensor([0, 3, 5]), torch.tensor([[3, 4, 0, 0], [10, 20, 3, 1], [16, 16, 5, 2]]), \
        torch.tensor([1, 0, 1])

    def grads(limit: int) -> dict:
        monkeypatch.setattr(network, "_WGRAD_MAX_ELEMENTS", limit)
        model.zero_grad(set_to_none=True)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loss = model.loss(model.forward_train(scenes, grippers, k), action, label)
        loss.backward()
        return {n: p.grad.clone() for n, p in model.named_parameters()}

    whole = grads(2**40)
    chunked = grads(2 * 32 * 32 * 16)
    for name, g in whole.items():
        assert chunked[name].dtype == torch.float32, name
        scale = max(1e-6, float(g.abs().max()))
        assert float((chunked[name] - g).abs().max()) <= 0.05 * scale, name
