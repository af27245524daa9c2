"""Which classes each column of the window holds: a bit per class, kept current by the window.

Readers that go through every column of the window (the planner's costmap, the movers'
rules) need not read a class's run of a column when all of it holds the prior, and most runs
do: a column holds evidence of a few classes. Once asked for (``classes_by_column``), the window keeps per
column a bit per class that may be above the prior there, a superset kept current from what
can raise a class: a scan's class evidence reaches the columns within the kernel's half-width
of its occupied voxels (``note_scan``), and voxels come back from the store. Everything else
that writes concentrations only adds empty-space evidence (class 0, whose run is always read),
scales the evidence above the prior, or resets classes to the prior.

Here the bits themselves: classes as the bits of a uint64, the classes a window's columns
hold, and the columns a scan's classes reach, each in numpy and compiled.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.geometry.grid import unravel_linear

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange

# The most classes whose runs ``classes_by_column`` keeps a bit for (one uint64 per column).
MAX_CLASS_BITS = 64


def class_bits(classes) -> np.uint64:
    """Classes (each below ``MAX_CLASS_BITS``) as the bits of one uint64, as ``classes_by_column`` keeps them."""
    bits = np.uint64(0)
    for c in classes:
        bits |= np.uint64(1) << np.uint64(int(c))
    return bits


def row_class_bits(held: np.ndarray) -> np.ndarray:
    """(n,) uint64: per row of ``held`` (n, C) bool, bit c set where column c is true."""
    bits = np.uint64(1) << np.arange(held.shape[1], dtype=np.uint64)
    return np.bitwise_or.reduce(np.where(held, bits, np.uint64(0)), axis=1)


def classes_held(alpha: np.ndarray, prior: float) -> np.ndarray:
    """(X, Y) uint64: per column of ``alpha`` (C, X, Y, Z), bit c set where class c holds
    anything but ``prior`` in the column."""
    prior = np.float32(prior)
    if HAVE_NUMBA:
        with parallel_region():
            return _classes_held_numba(alpha, prior)
    held = np.zeros(alpha.shape[1:3], np.uint64)
    for c in range(alpha.shape[0]):
        held |= (alpha[c] != prior).any(axis=2).astype(np.uint64) << np.uint64(c)
    return held


def _note_scan_classes(linear: np.ndarray, features: np.ndarray, origin: np.ndarray, dims: np.ndarray, half: int,
                       held: np.ndarray, scratch: np.ndarray) -> None:
    """Set in ``held`` (X, Y, physical columns) the bits of the classes with evidence in each
    occupied voxel (``linear`` window-linear indices from ``origin``, ``features`` (M, C)) over
    the window's columns within ``half`` of it (the update writes nothing outside the window);
    ``scratch`` (2, X, Y) uint64 zeros, left zero."""
    if HAVE_NUMBA:
        with parallel_region():
            # Separate kernels: each step reads what the previous one wrote in other rows.
            voxel_bits = _voxel_class_bits(np.ascontiguousarray(features))
            _scan_columns(linear, voxel_bits, int(dims[1]), int(dims[2]), scratch[0])
            _spread_along_y(scratch[0], half, scratch[1])
            _spread_along_x(scratch[1], half, int(origin[0] % dims[0]), int(origin[1] % dims[1]), held)
            scratch[1].fill(0)
        return
    voxel_bits = row_class_bits(features != 0)
    local = unravel_linear(linear, dims)
    scan = np.zeros((int(dims[0]) + 2 * half, int(dims[1]) + 2 * half), np.uint64)  # local, with a margin
    np.bitwise_or.at(scan, (local[:, 0] + half, local[:, 1] + half), voxel_bits)
    spread = np.zeros_like(scan)
    for shift in range(-half, half + 1):
        spread |= np.roll(scan, shift, axis=1)
    grown = np.zeros_like(scan)
    for shift in range(-half, half + 1):
        grown |= np.roll(spread, shift, axis=0)
    inside = grown[half:half + int(dims[0]), half:half + int(dims[1])]
    held[np.ix_(np.arange(origin[0], origin[0] + dims[0]) % dims[0],
                np.arange(origin[1], origin[1] + dims[1]) % dims[1])] |= inside


if HAVE_NUMBA:

    @njit(parallel=True, nogil=True)
    def _classes_held_numba(alpha, prior):  # pragma: no cover - compiled
        classes, size_x, size_y, size_z = alpha.shape
        held = np.zeros((size_x, size_y), np.uint64)
        for x in prange(size_x):
            for c in range(classes):
                bit = np.uint64(1) << np.uint64(c)
                for y in range(size_y):
                    for z in range(size_z):
                        if alpha[c, x, y, z] != prior:
                            held[x, y] |= bit
                            break
        return held

    @njit(parallel=True, nogil=True)
    def _voxel_class_bits(features):  # pragma: no cover - compiled
        rows, classes = features.shape
        voxel_bits = np.zeros(rows, np.uint64)
        for row in prange(rows):
            bits = np.uint64(0)
            for c in range(classes):
                if features[row, c] != 0:
                    bits |= np.uint64(1) << np.uint64(c)
            voxel_bits[row] = bits
        return voxel_bits

    @njit(nogil=True)
    def _scan_columns(linear, voxel_bits, size_y, size_z, scan):  # pragma: no cover - compiled
        """The scan's columns in window-local order (local x, y from the origin)."""
        for row in range(linear.shape[0]):
            rest = linear[row] // size_z
            scan[rest // size_y, rest % size_y] |= voxel_bits[row]

    @njit(parallel=True, nogil=True)
    def _spread_along_y(scan, half, spread):  # pragma: no cover - compiled
        """``spread`` |= ``scan`` grown by ``half`` along y; ``scan`` left zero."""
        size_x, size_y = scan.shape
        for x in prange(size_x):
            for y in range(size_y):
                bits = scan[x, y]
                if bits == 0:
                    continue
                scan[x, y] = 0
                for near in range(max(0, y - half), min(size_y, y + half + 1)):
                    spread[x, near] |= bits

    @njit(parallel=True, nogil=True)
    def _spread_along_x(spread, half, start_x, start_y, held):  # pragma: no cover - compiled
        """``held`` (physical columns, local column 0 at ``start_x``, ``start_y``) |= ``spread``
        grown by ``half`` along x."""
        size_x, size_y = spread.shape
        for x in prange(size_x):
            physical_x = start_x + x - size_x if start_x + x >= size_x else start_x + x
            for y in range(size_y):
                bits = np.uint64(0)
                for near in range(max(0, x - half), min(size_x, x + half + 1)):
                    bits |= spread[near, y]
                if bits != 0:
                    physical_y = start_y + y - size_y if start_y + y >= size_y else start_y + y
                    held[physical_x, physical_y] |= bits
