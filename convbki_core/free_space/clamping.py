"""Clamping: a voxel's concentrations stay updatable where the rays say the world changed.

The Dirichlet update is a sum, so a voxel where a car stood for a few seconds holds thousands
of units of "car" evidence; the rays that later cross the empty voxel add about one unit per
return behind it, and would need thousands of scans to win it back. OctoMap meets the same
problem in occupancy mapping with its clamping policy: a voxel's belief is held within bounds
so that a bounded number of contrary observations can overturn it. Here the bound is on the
total concentration: when free evidence arrives at a voxel whose concentrations sum to more
than ``limit``, the evidence above the prior (the free one included) is scaled down so that
they sum to ``limit``, with ``a0`` the prior and C the classes:

    alpha[c, v] <- a0 + (alpha[c, v] - a0) * (limit - C a0) / (sum_c alpha[c, v] - C a0)

Scaling keeps the ratios between the classes' evidence, so the expected class: the map reads
the same at that moment, only later evidence weighs more against the old. It keeps the prior
too: every concentration stays at or above it, as in a map built by sums alone, so maps made
with clamping merge as evidence (``map_tool merge``: the prior counted once, the evidence of
each map added; see the docs for how that differs from mapping the whole drive at once).

It is applied where a ray first contradicts a voxel: when the voxel takes free evidence while
its free concentration is still below one unit (``FIRST_CONTRADICTION``), i.e. the rays had
not yet found it empty. A mover's voxels are clamped by the first rays through them once it
has gone, and then lose to the rays that follow. Voxels that are never contradicted keep the
paper's exact sum. Reading a voxel's C concentrations costs C scattered reads, so the check
is made once per contradiction, not on every ray: most voxels that take free evidence take
it scan after scan (the air that rays cross near surfaces).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from convbki_core.compiled import HAVE_NUMBA

if HAVE_NUMBA:
    from convbki_core.compiled import njit

DEFAULT_LIMIT = 300.0
# A voxel whose free concentration is below this is seen empty for the first time (the prior
# is far below one unit, one ray adds one).
FIRST_CONTRADICTION = 1.0


def check_limit(limit: float) -> float:
    """The clamping limit as a float: 0 turns clamping off, otherwise it must be positive
    and finite. Raises ValueError with one line otherwise."""
    value = float(limit)
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"max_concentration must be 0 (off) or a positive number, got {limit!r}")
    return value


def first_contradiction(before: np.ndarray) -> np.ndarray:
    """Whether voxels whose free concentration was ``before`` as they took free evidence are
    contradicted for the first time (and so checked for clamping)."""
    return before < FIRST_CONTRADICTION


def clamp_numpy(alpha: np.ndarray, voxels: tuple[np.ndarray, np.ndarray, np.ndarray], before: np.ndarray,
                limit: float, prior: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clamp, in place, the voxels ``voxels`` (x, y, z index arrays into ``alpha`` (C, X, Y, Z))
    that have just taken free evidence; ``before`` their free concentrations before it;
    ``prior`` the map's prior concentration, which clamping keeps. Returns the voxels scaled."""
    if limit <= 0 or len(voxels[0]) == 0:
        return tuple(np.zeros(0, np.int64) for _ in range(3))
    check = first_contradiction(before)
    x, y, z = (axis[check] for axis in voxels)
    column = alpha[:, x, y, z]
    total = np.zeros(column.shape[1], np.float32)
    for row in column:  # class by class, as the compiled pass sums
        total += row
    over = total > limit
    floor = np.float32(prior)
    base = np.float32(alpha.shape[0]) * floor
    scale = (np.float32(limit) - base) / (total[over] - base)
    alpha[:, x[over], y[over], z[over]] = floor + (column[:, over] - floor) * scale
    return x[over], y[over], z[over]


if HAVE_NUMBA:

    @njit(nogil=True, inline="always")
    def evidence_scale(total, limit, prior, classes):  # pragma: no cover - compiled
        """(the prior as float32, the factor of the evidence above it) that bring a voxel's
        concentrations summing to ``total`` down to ``limit``."""
        floor = np.float32(prior)
        base = np.float32(classes) * floor
        return floor, (np.float32(limit) - base) / (total - base)

    @njit(nogil=True, inline="always")
    def clamp_voxel(alpha, x, y, z, before, limit, prior):  # pragma: no cover - compiled; tested against numpy
        """The clamping of one voxel that has just taken free evidence (``before``: its free
        concentration before it); ``limit`` <= 0: off. Returns whether it was scaled."""
        if limit <= 0 or before >= FIRST_CONTRADICTION:
            return False
        total = np.float32(0.0)
        for c in range(alpha.shape[0]):
            total += alpha[c, x, y, z]
        if total > limit:
            floor, scale = evidence_scale(total, limit, prior, alpha.shape[0])
            for c in range(alpha.shape[0]):
                alpha[c, x, y, z] = floor + (alpha[c, x, y, z] - floor) * scale
            return True
        return False


def clamp_torch(alpha: torch.Tensor, before: torch.Tensor, limit: float, prior: float) -> None:
    """The same on a device window, just after its free evidence was added: ``before``
    (X, Y, Z) the free concentrations before it (the voxels whose free concentration changed
    are those that took free evidence)."""
    if limit <= 0:
        return
    check = (alpha[0] != before) & (before < FIRST_CONTRADICTION)
    index = torch.nonzero(check, as_tuple=True)
    if index[0].numel() == 0:
        return
    column = alpha[:, index[0], index[1], index[2]]
    total = torch.zeros(column.shape[1], dtype=alpha.dtype, device=alpha.device)
    for row in column:
        total += row
    over = total > limit
    floor = torch.tensor(prior, dtype=alpha.dtype, device=alpha.device)
    base = torch.tensor(alpha.shape[0], dtype=alpha.dtype, device=alpha.device) * floor
    scale = (torch.tensor(limit, dtype=alpha.dtype, device=alpha.device) - base) / (total[over] - base)
    alpha[:, index[0][over], index[1][over], index[2][over]] = floor + (column[:, over] - floor) * scale
