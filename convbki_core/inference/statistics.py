"""Dirichlet statistics of a voxel's concentration parameters (paper Eq. 2).

For alpha (..., C) with eta = sum_c alpha_c: the expected class probability is
p_c = alpha_c / eta and its variance p_c (1 - p_c) / (1 + eta).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region


@dataclass
class DirichletStats:
    """Per voxel: expected class, its expected probability and the variance of that probability."""

    label: np.ndarray  # (N,) int64 arg-max class
    confidence: np.ndarray  # (N,) float32 E[theta_label]
    variance: np.ndarray  # (N,) float32 V[theta_label]


def dirichlet_statistics(alpha: np.ndarray) -> DirichletStats:
    """Statistics of concentration rows ``alpha`` (N, C), computed in float32 (maps hold millions of rows)."""
    alpha = np.asarray(alpha)
    if alpha.ndim != 2:
        raise ValueError(f"alpha must be (N, C), got shape {alpha.shape}")
    alpha = alpha.astype(np.float32, copy=False)
    if HAVE_NUMBA and alpha.shape[0]:
        label = np.empty(alpha.shape[0], np.int64)
        expected = np.empty(alpha.shape[0], np.float32)
        variance = np.empty(alpha.shape[0], np.float32)
        with parallel_region():
            _rows_numba(np.ascontiguousarray(alpha), label, expected, variance)
        return DirichletStats(label, expected, variance)
    label = alpha.argmax(axis=1) if alpha.shape[0] else np.zeros(0, np.int64)
    total = alpha.sum(axis=1, dtype=np.float32)
    top = alpha[np.arange(alpha.shape[0]), label]
    with np.errstate(invalid="ignore", divide="ignore"):
        expected = np.where(total > 0, top / total, np.float32(0.0)).astype(np.float32)
    variance = expected * (np.float32(1.0) - expected) / (np.float32(1.0) + total)
    return DirichletStats(label.astype(np.int64), expected, variance.astype(np.float32))


if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange

    @njit(nogil=True, inline="always")
    def voxel_statistics(values):  # pragma: no cover - compiled
        """(expected class, its expected probability, its variance) of one voxel's concentrations,
        summed in class order in float32: the one definition every compiled output shares, so
        the map, its updates and its records agree to the bit."""
        best = 0
        top = values[0]
        total = np.float32(0.0)
        for c in range(values.shape[0]):
            value = values[c]
            total += value
            if value > top:
                top = value
                best = c
        expected = top / total if total > 0 else np.float32(0.0)
        return best, expected, expected * (np.float32(1.0) - expected) / (np.float32(1.0) + total)

    @njit(parallel=True, nogil=True)
    def _rows_numba(alpha, label, expected, variance):  # pragma: no cover - compiled
        for row in prange(alpha.shape[0]):
            label[row], expected[row], variance[row] = voxel_statistics(alpha[row])
