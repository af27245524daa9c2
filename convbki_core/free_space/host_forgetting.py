"""The movers' rules on a host window (numpy arrays): the numpy rules, the reference and the
path without numba, and their compiled twins, which leave the same window and column flags.

Rule 1 (a return contradicts a mover): ``_contradicted_numpy``, compiled with the flags around
movable evidence in one pass (``_contradicted_and_flag_numba``). Rule 2 (a mover needs
support): ``_unsupported_numpy`` over the flagged columns at once, ``_unsupported_numba`` a
column at a time. The rules themselves, and why, are ``forgetting``'s docstring; the torch
rules are in ``device_forgetting``. Every path sums the classes in the same order
(``_occupied_sum``), so that all take the same decision at a tie.
"""

from __future__ import annotations

import numpy as np
import torch

from convbki_core.compiled import HAVE_NUMBA
from convbki_core.memory.window import CHANGED, EVIDENCE, TOUCHED

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange

FREE_CLASS = 0
# Bits of ``MoverForgetting.columns``: the column may hold a movable voxel (the support rule
# visits it); a movable return of this scan lies within the kernel's reach of it; the column
# holds only movers the rays or the rule emptied (the compiled rule visits it when this scan's
# evidence reached one of its voxels: nothing else can make them occupied again).
_FLAGGED, _NEAR_MOVERS, _EMPTIED = 1, 2, 4
EMPTY_SHARE = 0.5  # a voxel is empty space when class 0 holds more than this share of its concentration


def _empty_at(alpha, physical: np.ndarray) -> np.ndarray:
    """(M,) bool: the voxels at ``physical`` are empty space (class 0 holds more than
    ``EMPTY_SHARE`` of their concentration), in the order the compiled rule sums them."""
    x, y, z = physical.T
    if isinstance(alpha, torch.Tensor):
        index = torch.as_tensor(physical, device=alpha.device)
        values = alpha[:, index[:, 0], index[:, 1], index[:, 2]]
        rest = _occupied_sum(values[1:])
        return (values[FREE_CLASS] > EMPTY_SHARE * (values[FREE_CLASS] + rest)).cpu().numpy()
    values = alpha[:, x, y, z]
    return values[FREE_CLASS] > np.float32(EMPTY_SHARE) * (values[FREE_CLASS] + _occupied_sum(values[1:]))


def _contradicted_numpy(alpha, physical, seen, movable, prior) -> int:
    x, y, z = physical.T
    values = alpha[:, x, y, z]  # (C, M)
    occupied = values[1:]
    held = occupied.argmax(axis=0) + 1
    has_evidence = _occupied_sum(occupied) > np.float32(prior) * np.float32(occupied.shape[0]) * np.float32(1 + 1e-6)
    reset = movable[held] & has_evidence & (seen != held)
    if reset.any():
        alpha[1:, x[reset], y[reset], z[reset]] = prior
    return int(reset.sum())


def _occupied_sum(occupied):
    """The classes 1 .. C-1 of voxels summed one class after another, in float32 (numpy or
    torch): the order the compiled rule adds them in, so that every path takes the same
    decision at a voxel whose free share is a tie."""
    total = occupied[0].clone() if isinstance(occupied, torch.Tensor) else occupied[0].copy()
    for row in occupied[1:]:
        total += row
    return total


def _unsupported_numpy(alpha, mask, origin, movable, columns, prior, min_empty) -> int:
    """The rule of 2 over the flagged columns, vectorised across them (the no-numba path)."""
    xs, ys = np.nonzero(columns)
    if not len(xs):
        return 0
    size_z = mask.shape[2]
    near = (columns[xs, ys] & _NEAR_MOVERS) != 0
    empty_below = np.zeros(len(xs), np.int64)  # empty voxels met since the last static one
    on_ground = np.zeros(len(xs), bool)  # the voxel just below is occupied by a static class
    still_movable = np.zeros(len(xs), bool)  # an occupied mover stays in the column
    emptied = np.zeros(len(xs), bool)  # a mover the rays or the rule emptied stays in the column
    count = 0
    for step in range(size_z):
        z = (origin[2] + step) % size_z
        marks = mask[xs, ys, z]
        values = alpha[:, xs, ys, z]
        evident = (marks & EVIDENCE) != 0
        occupied = values[1:]
        rest = _occupied_sum(occupied)
        empty = evident & (values[FREE_CLASS] > EMPTY_SHARE * (values[FREE_CLASS] + rest))
        # A voxel whose classes all hold the prior has no most likely class: it is not a mover.
        mover_held = movable[occupied.argmax(axis=0) + 1] & (occupied.max(axis=0) > prior)
        is_movable = evident & ~empty & mover_held
        trail = is_movable & (empty_below >= min_empty) & ((marks & TOUCHED) == 0)
        fringe = is_movable & ~trail & on_ground & ~near & ((marks & TOUCHED) != 0)
        if fringe.any():  # reached by the ground's spread, no mover near: the rays decide
            mask[xs[fringe], ys[fringe], z] &= np.uint8(0xFF & ~TOUCHED)
        if trail.any():
            alpha[FREE_CLASS, xs[trail], ys[trail], z] = np.maximum(values[FREE_CLASS, trail], rest[trail] + 1.0)
            mask[xs[trail], ys[trail], z] |= np.uint8(CHANGED)
            count += int(trail.sum())
        still_movable |= is_movable & ~trail
        # An emptied mover keeps the column in view (later spread can make it occupied again).
        emptied |= trail | (evident & empty & mover_held)
        empty_below = np.where(evident & ~empty & ~is_movable, 0, empty_below + empty)
        on_ground = evident & ~empty & ~is_movable
    columns[xs[still_movable], ys[still_movable]] |= np.uint8(_FLAGGED)
    columns[xs[~still_movable], ys[~still_movable]] = np.where(emptied[~still_movable], _EMPTIED, 0)
    return count


if HAVE_NUMBA:
    _EVERY_RUN = np.uint64(0xFFFFFFFFFFFFFFFF)  # class bits that read every class

    @njit(nogil=True, inline="always")
    def _holds_movable(alpha, movable, x, y, z, prior, runs):  # pragma: no cover - compiled
        """A movable class of the voxel holds more than the prior (``runs``: the column's class
        bits; a class whose bit is clear holds the prior and is not read)."""
        found = False
        for c in range(1, alpha.shape[0]):
            if movable[c] and (runs >> np.uint64(c)) & np.uint64(1) != 0:
                found |= alpha[c, x, y, z] > prior
        return found

    @njit(nogil=True, inline="always")
    def _occupied_classes(alpha, x, y, z, runs, prior):  # pragma: no cover - compiled
        """(sum, largest, most likely class) of the classes 1 .. C-1 of voxel (x, y, z), summed
        in class order in float32 (the order every path of the rules adds them in); a class
        whose bit in ``runs`` is clear holds the ``prior``, which is added without reading it."""
        held = 1
        best = alpha[1, x, y, z] if (runs >> np.uint64(1)) & np.uint64(1) != 0 else prior
        total = np.float32(0.0)
        for c in range(1, alpha.shape[0]):
            value = alpha[c, x, y, z] if (runs >> np.uint64(c)) & np.uint64(1) != 0 else prior
            total += value
            if value > best:
                best, held = value, c
        return total, best, held

    @njit(nogil=True, inline="always")
    def _reset_if_contradicted(alpha, movable, x, y, z, seen, prior, runs,
                               protected=False):  # pragma: no cover - compiled
        """Reset the classes of voxel (x, y, z) when its most likely class is movable, it holds
        class evidence and this scan saw ``seen`` there, and (``protected``: a movable return of
        this scan is near) it is empty space; returns whether it did. ``runs``: its column's
        class bits (as ``_occupied_classes``)."""
        # No class ever falls below the prior, so a voxel whose movable classes all hold just
        # the prior has a static most likely class, or no evidence: skip its other classes.
        if not _holds_movable(alpha, movable, x, y, z, prior, runs):
            return False
        classes = alpha.shape[0]
        total, _, held = _occupied_classes(alpha, x, y, z, runs, prior)
        if not (movable[held] and total > prior * np.float32(classes - 1) * np.float32(1 + 1e-6) and seen != held):
            return False
        empty = alpha[FREE_CLASS, x, y, z]
        if protected and not empty > np.float32(EMPTY_SHARE) * (empty + total):
            return False
        for c in range(1, classes):
            alpha[c, x, y, z] = prior
        return True

    @njit(nogil=True)
    def _contradicted_numba(alpha, physical, seen, movable, prior):  # pragma: no cover - compiled
        count = 0
        for i in range(physical.shape[0]):
            count += _reset_if_contradicted(alpha, movable, physical[i, 0], physical[i, 1], physical[i, 2], seen[i],
                                            prior, _EVERY_RUN)
        return count

    @njit(parallel=True, nogil=True)
    def _contradicted_and_flag_numba(alpha, linear, volume_dims, volume_origin, dims, features, movable, prior,
                                     columns, reach, held_by_column, movable_bits, near,
                                     near_columns):  # pragma: no cover - compiled
        """``MoverForgetting.contradicted`` in three passes over the scan's voxels (as the numpy
        path: unravel, argmax, ``_flag_around`` twice, the columns near this scan's movable
        returns (``near`` >= 0: within ``near`` columns, into ``near_columns``), and
        ``_contradicted_numpy`` on the voxels of the other columns). The voxels are distinct, so
        the threads never write the same one. ``held_by_column``: the window's class bits per
        column, and ``movable_bits`` the movable classes' (0: no bits, read every voxel): a voxel
        of a column whose movable runs all hold the prior has nothing to reset, and its classes
        are not read."""
        count_voxels, classes = features.shape
        physical = np.empty((count_voxels, 3), np.int64)
        seen_by_voxel = np.empty(count_voxels, np.int64)
        bits = np.zeros(count_voxels, np.uint8)
        reset = np.zeros(count_voxels, np.int64)
        for i in prange(count_voxels):
            rest = linear[i] // volume_dims[2]
            physical[i, 0] = (rest // volume_dims[1] + volume_origin[0]) % dims[0]
            physical[i, 1] = (rest % volume_dims[1] + volume_origin[1]) % dims[1]
            physical[i, 2] = (linear[i] % volume_dims[2] + volume_origin[2]) % dims[2]
            best, seen, evidence = features[i, 0], 0, False
            for c in range(classes):
                value = features[i, c]
                if value > best:
                    best, seen = value, c
                evidence |= movable[c] and value > 0
            seen_by_voxel[i] = seen
            if evidence:
                bits[i] = _FLAGGED
            if movable[seen]:
                bits[i] = _FLAGGED | _NEAR_MOVERS
        size_x, size_y = columns.shape
        if near >= 0:
            near_columns[:, :] = False
        for i in range(count_voxels):
            if bits[i] == 0:
                continue
            for dx in range(-reach, reach + 1):
                x = (physical[i, 0] + dx) % size_x
                for dy in range(-reach, reach + 1):
                    columns[x, (physical[i, 1] + dy) % size_y] |= bits[i]
            if near >= 0 and (bits[i] & _NEAR_MOVERS) != 0:
                near_columns[physical[i, 0], physical[i, 1]] = True  # grown to the radius below
        if near >= 0:
            _grow_on_torus(near_columns, near)
        for i in prange(count_voxels):
            x, y, z = physical[i, 0], physical[i, 1], physical[i, 2]
            runs = _EVERY_RUN if movable_bits == 0 else held_by_column[x, y]
            if (runs & movable_bits) != 0 or movable_bits == 0:
                reset[i] = _reset_if_contradicted(alpha, movable, x, y, z, seen_by_voxel[i], prior, runs,
                                                  near >= 0 and near_columns[x, y])
        return reset.sum()

    @njit(nogil=True)
    def _grow_on_torus(marked, radius):  # pragma: no cover - compiled
        """Every cell within ``radius`` cells (each way: a square, wrapping around) of a marked
        cell becomes marked: a running count along y (each row of x contiguous), then along x
        (whole rows at once); rows of x with no mark near are only cleared."""
        size_x, size_y = marked.shape
        if 2 * radius + 1 >= min(size_x, size_y):  # the square spans the grid: any mark marks it all
            if marked.any():
                marked[:, :] = True
            return
        grown = np.zeros((size_x, size_y), np.int64)
        rows = np.zeros(size_x, np.int64)  # 1 where row x holds a mark
        for x in range(size_x):
            if not marked[x].any():
                continue
            rows[x] = 1
            count = 0
            for dy in range(-radius, radius + 1):
                count += np.int64(marked[x, dy % size_y])
            enter, leave = radius + 1, size_y - radius  # the cells the window gains and loses as y steps on
            for y in range(size_y):
                grown[x, y] = count
                count += np.int64(marked[x, enter]) - np.int64(marked[x, leave])
                enter = enter + 1 if enter + 1 < size_y else 0
                leave = leave + 1 if leave + 1 < size_y else 0
        count = np.zeros(size_y, np.int64)
        near_rows = 0  # rows with a mark within the window along x
        for dx in range(-radius, radius + 1):
            if rows[dx % size_x]:
                count += grown[dx % size_x]
                near_rows += 1
        enter, leave = radius + 1, size_x - radius
        for x in range(size_x):
            if near_rows:
                marked[x] = count > 0
            else:
                marked[x] = False
            if rows[enter]:
                count += grown[enter]
                near_rows += 1
            if rows[leave]:
                count -= grown[leave]
                near_rows -= 1
            enter = enter + 1 if enter + 1 < size_x else 0
            leave = leave + 1 if leave + 1 < size_x else 0

    @njit(nogil=True, inline="always")
    def _reoccupied(alpha, mask, movable, x, y, prior, runs):  # pragma: no cover - compiled
        """A voxel of column (x, y) that this scan's evidence reached is an occupied mover:
        only such a voxel can have changed a column that held emptied movers alone."""
        for z in range(mask.shape[2]):
            if mask[x, y, z] & TOUCHED == 0:
                continue
            rest, best, held = _occupied_classes(alpha, x, y, z, runs, prior)
            free = alpha[0, x, y, z]
            if not free > EMPTY_SHARE * (free + rest) and movable[held] and best > prior:
                return True
        return False

    @njit(parallel=True, nogil=True)
    def _unsupported_numba(alpha, mask, origin, movable, columns, flagged, prior, min_empty, threads,
                           held_by_column, use_bits):  # pragma: no cover - compiled
        """The rule of 2 over the flagged columns; each class's run of a column is read in one
        pass (contiguous in z), as the costmap reads the window. With ``use_bits``, the runs
        whose bit in ``held_by_column`` is clear hold the prior and are not read: the prior is
        added in their place, so the sums are the same."""
        size_y, size_z = mask.shape[1], mask.shape[2]
        classes = alpha.shape[0]
        counts = np.zeros(threads, np.int64)
        for part in prange(threads):
            rest = np.empty(size_z, np.float32)  # sum of the classes 1 .. C-1 per voxel
            best = np.empty(size_z, np.float32)
            held = np.empty(size_z, np.int64)
            for k in range(part, flagged.shape[0], threads):  # interleaved: neighbouring columns on both threads
                x, y = flagged[k] // size_y, flagged[k] % size_y
                runs = held_by_column[x, y] if use_bits else _EVERY_RUN
                if columns[x, y] & _FLAGGED == 0 and not _reoccupied(alpha, mask, movable, x, y, prior, runs):
                    continue  # emptied movers only, and this scan's evidence made none of them occupied
                # A column none of whose voxels holds a movable class above the prior has no
                # voxel for the rule (no class falls below it): its movable runs alone decide.
                found = False
                for c in range(1, classes):
                    if movable[c] and (runs >> np.uint64(c)) & np.uint64(1) != 0:
                        for z in range(size_z):
                            found |= alpha[c, x, y, z] > prior
                if not found:
                    columns[x, y] = 0
                    continue
                first_held = (runs >> np.uint64(1)) & np.uint64(1) != 0
                for z in range(size_z):
                    rest[z] = 0.0
                    best[z] = alpha[1, x, y, z] if first_held else prior
                    held[z] = 1
                for c in range(1, classes):
                    if (runs >> np.uint64(c)) & np.uint64(1) == 0:
                        for z in range(size_z):
                            rest[z] += prior  # the run holds the prior (no class is below it)
                        continue
                    for z in range(size_z):
                        value = alpha[c, x, y, z]
                        rest[z] += value
                        if value > best[z]:
                            best[z] = value
                            held[z] = c
                near = columns[x, y] & _NEAR_MOVERS != 0
                empty_below = 0  # empty voxels met since the last static one
                on_ground = False  # the voxel just below is occupied by a static class
                still_movable = False  # an occupied mover stays in the column
                emptied = False  # a mover the rays or the rule emptied stays in the column
                for step in range(size_z):
                    z = (origin[2] + step) % size_z
                    marks = mask[x, y, z]
                    if marks & EVIDENCE == 0:
                        on_ground = False
                        continue
                    free = alpha[0, x, y, z]
                    if free > EMPTY_SHARE * (free + rest[z]):
                        empty_below += 1
                        on_ground = False
                        # Later evidence (the spread of a static return) can make it occupied,
                        # and a mover, again.
                        emptied |= movable[held[z]] and best[z] > prior
                        continue
                    if not movable[held[z]] or best[z] <= prior:  # static, or no class above the prior
                        empty_below = 0
                        on_ground = True
                        continue
                    if empty_below >= min_empty and marks & TOUCHED == 0:
                        alpha[0, x, y, z] = max(free, rest[z] + np.float32(1.0))
                        mask[x, y, z] = marks | CHANGED
                        counts[part] += 1
                        emptied = True
                    else:
                        if on_ground and not near and marks & TOUCHED != 0:
                            mask[x, y, z] = marks & ~TOUCHED  # the ground's spread only: the rays decide
                        still_movable = True
                    on_ground = False
                if still_movable:
                    columns[x, y] |= _FLAGGED
                else:
                    columns[x, y] = _EMPTIED if emptied else 0
        return counts.sum()
