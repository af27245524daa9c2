"""The ground's surface: which voxels of the window hold it, so that free space leaves them.

A voxel holds the surface when its most likely occupied class (the arg-max over classes
1..C-1) is a ground class of the label map (``ground_classes``) and its ground evidence
(those classes' concentrations above the prior) is not below that of the voxel under it nor
of the one over it; why such a voxel takes no free evidence is the free-space update's third
condition (``update``).

Which voxels hold the surface is kept as a bit of the window's mask (``GROUND``), derived
again, a column at a time, where a voxel's classes changed (``RECLASSED``: this scan's class
evidence reached it, it came back from the store, it was clamped, or the window moved along z
past its neighbour); a pass reads only the runs the window's per-column class bits say are
held (``classes_by_column``).

``ground_marks`` is the rule for a whole window (numpy, and torch for the device window);
the compiled pass keeps the bits up to date (``_derive_ground``), and the numpy pass of the
update derives them everywhere (``_set_ground``).
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA
from convbki_core.memory.window import EVIDENCE, GROUND, RECLASSED

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange

    # Bytes, so that the mask's update stays in bytes and vectorises.
    _GROUND_BYTE = np.uint8(GROUND)
    _RECLASSED_BYTE = np.uint8(RECLASSED)


def ground_marks(alpha, ground_bits: np.uint64, origin_z: int, prior: float):
    """Per voxel of the torus window ``alpha`` (C, X, Y, Z), numpy or torch, whose z origin is
    ``origin_z``: whether it holds the ground's surface (the module's docstring): its first
    arg-max over classes 1..C-1 is one of ``ground_bits``, and its ground evidence g (the
    ground classes' concentrations above ``prior``, summed in class order in float64) is not
    below that of the voxel under it nor of the one over it (0 beyond the window)."""
    classes = [c for c in range(alpha.shape[0]) if (int(ground_bits) >> c) & 1]
    best = alpha[1:].argmax(0) + 1
    bottom = int(origin_z) % alpha.shape[3]
    if isinstance(best, np.ndarray):
        is_ground = ((np.uint64(ground_bits) >> best.astype(np.uint64)) & np.uint64(1)).astype(bool)
        evidence = np.zeros(alpha.shape[1:])
        for c in classes:
            evidence += alpha[c].astype(np.float64) - np.float64(np.float32(prior))
        local = np.roll(evidence, -bottom, axis=2)  # global order along z
        below, above = np.zeros_like(local), np.zeros_like(local)
        below[:, :, 1:], above[:, :, :-1] = local[:, :, :-1], local[:, :, 1:]
        return is_ground & np.roll((local >= below) & (local >= above), bottom, axis=2)
    import torch

    table = torch.tensor([(int(ground_bits) >> c) & 1 for c in range(alpha.shape[0])], dtype=torch.bool,
                         device=alpha.device)
    evidence = torch.zeros(alpha.shape[1:], dtype=torch.float64, device=alpha.device)
    for c in classes:
        evidence += alpha[c].double() - float(np.float32(prior))
    local = torch.roll(evidence, -bottom, dims=2)
    below, above = torch.zeros_like(local), torch.zeros_like(local)
    below[:, :, 1:], above[:, :, :-1] = local[:, :, :-1], local[:, :, 1:]
    return table[best] & torch.roll((local >= below) & (local >= above), bottom, dims=2)


def _set_ground(mask: np.ndarray, ground: np.ndarray) -> None:
    mask[...] = np.where(ground, mask | np.uint8(GROUND), mask & np.uint8(0xFF & ~GROUND))


if HAVE_NUMBA:

    @njit(parallel=True, nogil=True)
    def _derive_ground(alpha, mask, classes, read_all, ground_bits, prior, origin_z):  # pragma: no cover
        """``ground_marks`` as the ``GROUND`` bits of every column holding a voxel with
        ``RECLASSED`` (a voxel's classes, and so its own bit and its neighbours', changed since
        they were derived); clears ``RECLASSED``. Reads, per column, only the class runs its
        bits in ``classes`` (X, Y) say are held (all with ``read_all``): a run not held is at
        the prior, as every concentration is at least the prior, so the arg-max is the same and
        the run adds exactly 0 to the ground evidence."""
        size_x, size_y, size_z = mask.shape
        bottom = origin_z % size_z
        top = (bottom + size_z - 1) % size_z
        prior64 = np.float64(prior)
        for x in prange(size_x):
            best = np.empty(size_z, np.float32)
            arg = np.empty(size_z, np.int64)
            evidence = np.empty(size_z)
            for y in range(size_y):
                stale = np.uint8(0)
                for z in range(size_z):
                    stale |= mask[x, y, z] & _RECLASSED_BYTE
                if stale == 0:
                    continue
                held = classes[x, y] if not read_all else np.uint64(0)
                best[:] = prior
                arg[:] = 1
                evidence[:] = 0.0
                for c in range(1, alpha.shape[0]):
                    if not read_all and ((held >> np.uint64(c)) & np.uint64(1)) == 0:
                        continue
                    counts = ((ground_bits >> np.uint64(c)) & np.uint64(1)) != 0
                    for z in range(size_z):
                        value = alpha[c, x, y, z]
                        if value > best[z]:
                            best[z] = value
                            arg[z] = c
                        if counts:
                            evidence[z] += np.float64(value) - prior64
                for z in range(size_z):
                    below = 0.0 if z == bottom else evidence[z - 1 if z > 0 else size_z - 1]
                    above = 0.0 if z == top else evidence[z + 1 if z + 1 < size_z else 0]
                    m = mask[x, y, z] & ~_RECLASSED_BYTE
                    if ((m & EVIDENCE) and ((ground_bits >> np.uint64(arg[z])) & np.uint64(1))
                            and evidence[z] >= below and evidence[z] >= above):
                        m |= _GROUND_BYTE
                    else:
                        m &= ~_GROUND_BYTE
                    mask[x, y, z] = m
