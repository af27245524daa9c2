"""Clamping where free evidence arrives: the rule, its three implementations, its limits."""

import numpy as np
import pytest
import torch

from convbki_core.compiled import HAVE_NUMBA
from convbki_core.free_space.clamping import check_limit, clamp_numpy, clamp_torch, first_contradiction


def _window(seed: int, classes: int = 6, dims=(5, 4, 3)):
    rng = np.random.default_rng(seed)
    alpha = np.full((classes, *dims), 1e-3, np.float32)
    # a mix: heavy voxels (a mover stood there), light ones, and some near the limit
    scale = rng.choice([1.0, 50.0, 5000.0], size=dims)
    alpha += (rng.random((classes, *dims)) * scale).astype(np.float32)
    # free concentrations from none to a few rays' worth: some cross a power of two, some not
    alpha[0] = (1e-3 + rng.random(dims) * rng.choice([0.0, 4.0, 40.0], size=dims)).astype(np.float32)
    before = alpha[0].copy()
    added = rng.integers(0, 9, size=dims).astype(np.float32)
    alpha[0] += added
    takes = added > 0
    return alpha, before, takes


PRIOR = 1e-3


def _expected(alpha: np.ndarray, before: np.ndarray, takes: np.ndarray, limit: float) -> np.ndarray:
    """The rule written out voxel by voxel: the evidence above the prior scaled so that the
    concentrations sum to the limit."""
    out = alpha.copy()
    prior = np.float32(PRIOR)
    base = np.float32(alpha.shape[0]) * prior
    for x, y, z in zip(*np.nonzero(takes)):
        if before[x, y, z] >= 1.0:
            continue
        total = np.float32(0)
        for c in range(alpha.shape[0]):
            total = np.float32(total + alpha[c, x, y, z])
        if total > limit:
            scale = (np.float32(limit) - base) / (total - base)
            out[:, x, y, z] = prior + (alpha[:, x, y, z] - prior) * scale
    return out


def test_a_voxel_is_checked_when_first_contradicted():
    before = np.array([1e-3, 0.5, 0.999, 1.0, 7.0], np.float32)
    assert first_contradiction(before).tolist() == [True, True, True, False, False]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numpy_clamps_by_the_rule(seed):
    alpha, before, takes = _window(seed)
    expected = _expected(alpha, before, takes, 300.0)
    got = alpha.copy()
    clamp_numpy(got, np.nonzero(takes), before[takes], 300.0, PRIOR)
    np.testing.assert_array_equal(got, expected)
    changed = (got != alpha).any(axis=0)
    assert changed.any() and not changed.all()  # the case exercises both branches
    sums = got.sum(axis=0)
    assert np.all(sums[changed] <= 300.0 * (1 + 1e-5))
    # Scaling keeps the expected class of every clamped voxel, and the prior: no concentration
    # falls below it, so the map's files still merge as sums of evidence.
    assert np.array_equal(got.argmax(axis=0), alpha.argmax(axis=0))
    assert got.min() >= np.float32(PRIOR)
    heavy = changed & (alpha.sum(axis=0) > 1000)
    evidence, kept = alpha[:, heavy] - np.float32(PRIOR), got[:, heavy] - np.float32(PRIOR)
    np.testing.assert_allclose(kept / kept.sum(axis=0), evidence / evidence.sum(axis=0), rtol=1e-3, atol=1e-6)


def test_torch_equals_numpy():
    alpha, before, takes = _window(3)
    expected = alpha.copy()
    clamp_numpy(expected, np.nonzero(takes), before[takes], 300.0, PRIOR)
    tensor = torch.as_tensor(alpha.copy())
    clamp_torch(tensor, torch.as_tensor(before), 300.0, PRIOR)
    np.testing.assert_array_equal(tensor.numpy(), expected)


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba not installed")
def test_compiled_equals_numpy():
    from numba import njit

    from convbki_core.free_space.clamping import clamp_voxel

    @njit
    def clamp_all(alpha, voxels, before, limit, prior):
        for i in range(voxels.shape[0]):
            clamp_voxel(alpha, voxels[i, 0], voxels[i, 1], voxels[i, 2], before[i], limit, prior)

    alpha, before, takes = _window(4)
    expected = alpha.copy()
    clamp_numpy(expected, np.nonzero(takes), before[takes], 300.0, PRIOR)
    got = alpha.copy()
    clamp_all(got, np.argwhere(takes), before[takes], 300.0, PRIOR)
    np.testing.assert_array_equal(got, expected)


def test_off_and_below_the_limit_change_nothing():
    alpha, before, takes = _window(5)
    for limit in (0.0, 1e9):
        got = alpha.copy()
        clamp_numpy(got, np.nonzero(takes), before[takes], limit, PRIOR)
        np.testing.assert_array_equal(got, alpha)


def test_a_bounded_number_of_rays_empties_a_long_stay():
    """A voxel with 8000 units of "car": without clamping 3 rays a scan need thousands of
    scans to make it free; clamped at 300 it turns free after about 300 / 3 scans."""
    def scans_to_free(limit: float) -> int:
        alpha = np.zeros((3, 1, 1, 1), np.float32)
        alpha[:, 0, 0, 0] = [1e-3, 8000.0, 2.0]
        for scan in range(1, 5000):
            before = alpha[0].copy()
            alpha[0] += 3.0
            clamp_numpy(alpha, (np.zeros(1, int),) * 3, before.reshape(-1), limit, PRIOR)
            if alpha[:, 0, 0, 0].argmax() == 0:
                return scan
        return 5000

    assert scans_to_free(0.0) > 2000
    assert 80 < scans_to_free(300.0) < 120


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_bad_limits_are_refused(bad):
    with pytest.raises(ValueError, match="max_concentration"):
        check_limit(bad)
