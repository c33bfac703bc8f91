"""Augmentation keeps the scene and the executed action consistent."""

import math

import numpy as np
import torch

from learner.augment import augment_batch, rotate_shift_scene

R = 16


def _blob(vol: torch.Tensor, channel: int, i: float, j: float) -> None:
    """Write a 3x3 blob of ones into all z of vol[channel] (X, Y, Z) around cell (i, j)."""
    ii, jj = int(round(i)), int(round(j))
    vol[channel, ii - 1 : ii + 2, jj - 1 : jj + 2, :] = 1.0


def _peak(vol: torch.Tensor, channel: int) -> np.ndarray:
    """Value-weighted centroid (i, j) of vol[channel] at z = 0."""
    plane = vol[channel, :, :, 0].numpy()
    ii, jj = np.nonzero(plane > 1e-6)
    w = plane[ii, jj]
    return np.array([(ii * w).sum() / w.sum(), (jj * w).sum() / w.sum()])


def test_action_follows_scene_rotation_and_shift():
    gen = torch.Generator().manual_seed(3)
    nx = ny = 48
    for trial in range(12):
        i, j, k = 20 + trial % 5, 26 - trial % 4, trial % R
        scene = torch.zeros(1, 2, nx, ny, 4)
        _blob(scene[0], 0, i, j)  # the grasp cell
        theta = 2 * math.pi * k / R
        _blob(scene[0], 1, i + 8 * math.cos(theta), j + 8 * math.sin(theta))  # marks the yaw direction
        action = torch.tensor([[i, j, k, 2]])
        out, out_action = augment_batch(scene, action, R, prob=1.0, generator=gen)
        ni, nj, nk, ns = out_action[0].tolist()
        assert ns == 2
        grasp = _peak(out[0], 0)
        assert np.abs(grasp - [ni, nj]).max() <= 1.0
        marker = _peak(out[0], 1)
        theta2 = 2 * math.pi * nk / R
        expected = np.array([ni + 8 * math.cos(theta2), nj + 8 * math.sin(theta2)])
        assert np.abs(marker - expected).max() <= 1.5, (marker, expected)


def test_identity_transform_is_exact():
    scene = torch.rand(2, 2, 16, 16, 3)
    out = rotate_shift_scene(scene, torch.zeros(2), torch.zeros(2, 2))
    assert torch.allclose(out, scene, atol=1e-6)


def test_prob_zero_leaves_batch_unchanged():
    gen = torch.Generator().manual_seed(0)
    scene = torch.rand(4, 2, 16, 16, 3)
    action = torch.tensor([[1, 2, 3, 0]] * 4)
    out, out_action = augment_batch(scene, action, R, prob=0.0, generator=gen)
    assert torch.equal(out, scene) and torch.equal(out_action, action)


def test_augmentation_with_probability_one_rotates_and_shifts_the_batch():
    """With augment_prob 1 the batch is transformed (an augmentation that returned its input
    unchanged would pass the consistency tests above): rotations spread over 0..R-1, most cells
    move, the scene changes and the opening index stays."""
    gen = torch.Generator().manual_seed(0)
    scene = torch.rand(64, 2, 48, 48, 4)
    action = torch.tensor([[24, 24, 0, 1]] * 64)
    out, out_action = augment_batch(scene, action, R, prob=1.0, generator=gen)
    assert len(set(out_action[:, 2].tolist())) >= 12
    assert (out_action[:, :2] != action[:, :2]).any(1).float().mean() > 0.5
    assert not torch.equal(out, scene) and torch.equal(out_action[:, 3], action[:, 3])
