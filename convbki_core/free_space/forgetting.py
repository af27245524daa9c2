"""Forgetting what moved: two rules for the voxels of the movable classes (car, person, ...).

Free space empties a voxel once rays cross it, but two kinds of mover evidence are out of
the rays' reach, and the Dirichlet sum keeps them for as long as the drive lasts:

1. **A return that contradicts a mover.** A truck drives down a lane; the car behind it
   arrives in voxels that still hold the truck's evidence, and the query of the car's returns
   answers "truck" until the car has out-counted it. A road point where a bus stood meets
   the same. A movable class is the state of a voxel at one time, not what the voxel is, so
   a return of another class in it can say that the object has gone. For each voxel v holding
   this scan's returns, with F[c, v] their class evidence, before the scan's update:

       if  m = argmax_{c >= 1} alpha[c, v]  is a movable class, v holds class evidence
       (sum_{c >= 1} alpha[c, v] > C_1 a0), argmax_c F[c, v] != m, and
       either no return of this scan within ``contradiction_radius`` (horizontally) of v is
       of a movable class, or v is empty space (alpha[0, v] > 1/2 of its concentration):
           alpha[c, v] <- a0   for c = 1 .. C-1        (class 0, the free evidence, is kept)

   The radius tells label noise from change. Segmentation networks call a parked van "car"
   in one scan and "other-vehicle" in the next, a truck's box "building" here and there:
   while the object is in view some of its returns are of a movable class, and a return of
   another class on it is the input's noise, which the paper's sum out-votes. Where no such
   return is near, the object has gone (the road where a car stood), and where rays found the
   voxel empty since, what is there now is new. Static classes keep the paper's sum: a wall
   that the input calls "fence" in one scan is out-voted, not reset.

2. **A mover needs support.** Vehicles and people stand on the ground. Rays cross the lower
   part of the space a bus swept, but no ray passes through its upper part once it has gone
   (the beams above the sensor's height end nowhere, and LiDARs send no return from the
   sky), so the top of the bus would stay. In each column of the window, walking up from
   its bottom, count the empty voxels (class 0 holds more than half of the concentration)
   met since the last occupied voxel of a static class. A voxel of a movable class met when
   that count is at least ``MIN_EMPTY_BELOW`` metres' worth (more than the clearance under a
   parked car, which the rays under it find empty), that this scan's class evidence did not
   reach, is a trail and becomes empty space:

       alpha[0, v] <- max(alpha[0, v], sum_{c >= 1} alpha[c, v] + 1)

   A mover that is there is seen (its voxels receive this scan's evidence) and stays; a
   parked car out of view stands on the road with a voxel or two of empty clearance under
   its body, too little to float. The rule reads the emptiness the rays left up to the previous scan (it
   runs between this scan's update, which marks what the scan reached, and its rays), so a
   trail goes one scan after the space under it was found empty.

Both run only with free space (class 0 holds the rays' evidence) and only for the classes a
label map marks as movable. Like clamping, they are not sums: maps made with them merge as
evidence, and the merge differs from mapping the whole drive where one part's rays would
have emptied what the other part saw (the docs measure it). The rule of 2 reads whole
columns, so the mapper keeps, per column of the window, whether it may hold a movable
voxel (flagged around every voxel to which this scan brings movable evidence, and where the
window brought in voxels from the store); a column found without one is unflagged, so the
rule visits only where movers have been. A column whose movers are all empty keeps a mark of
its own and is visited again only when this scan's evidence made one of them occupied (the
spread of a static return can), which leaves the same map as visiting every column.
"""

from __future__ import annotations

import numpy as np
import torch

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.geometry.volume import SparseVolume, unravel_linear
from convbki_core.memory.window import CHANGED, EVIDENCE, TOUCHED, class_bits

if HAVE_NUMBA:
    from convbki_core.compiled import get_num_threads, njit, prange

FREE_CLASS = 0
# Bits of ``MoverForgetting.columns``: the column may hold a movable voxel (the support rule
# visits it); a movable return of this scan lies within the kernel's reach of it; the column
# holds only movers the rays or the rule emptied (the compiled rule visits it when this scan's
# evidence reached one of its voxels: nothing else can make them occupied again).
_FLAGGED, _NEAR_MOVERS, _EMPTIED = 1, 2, 4
# Metres of empty space under a movable voxel that make it float: rays that pass under a parked
# car (its ground clearance) find a voxel or two empty, the space a bus has left far more.
MIN_EMPTY_BELOW = 0.6
EMPTY_SHARE = 0.5  # a voxel is empty space when class 0 holds more than this share of its concentration


class MoverForgetting:
    """The two rules for one mapper's window (``RollingWindow``: numpy arrays, or
    ``TorchWindow``: torch tensors); ``movable_classes`` of the label map, ``reach`` the
    kernel's half width in voxels (how far a return's evidence spreads)."""

    def __init__(self, movable_classes, num_classes: int, prior: float, dims: np.ndarray, reach: int,
                 resolution: float, near_radius: float = 0.0):
        self.movable = np.zeros(num_classes, np.bool_)
        self.movable[list(movable_classes)] = True
        self.movable[FREE_CLASS] = False
        # Columns (in voxels, each way) around this scan's movable returns where no voxel is reset:
        # the object is in view there, so a return of another class on it is a label, not a change.
        # -1: no such condition.
        self.near = int(np.ceil(near_radius / resolution - 1e-9)) if near_radius > 0 else -1
        self._near_columns = np.zeros(tuple(np.asarray(dims, np.int64)[:2]), np.bool_)
        self.movable_bits = class_bits(np.flatnonzero(self.movable))
        self.prior = float(prior)
        self.dims = np.asarray(dims, np.int64)
        self.reach = int(reach)
        # Empty voxels a movable voxel needs below it to float (more than a car's ground clearance).
        self.min_empty = max(1, int(np.ceil(MIN_EMPTY_BELOW / resolution - 1e-9)))
        # Per torus column: it may hold a voxel of a movable class (the rule of 2 visits it).
        self.columns = np.zeros(tuple(self.dims[:2]), np.uint8)
        self.origin: np.ndarray | None = None
        self.reset_voxels = 0  # totals over the drive, for reports
        self.emptied_voxels = 0

    @property
    def active(self) -> bool:
        return bool(self.movable.any())

    def clear(self) -> None:
        self.columns[:] = 0
        self.origin = None

    def warm_up(self, scratch) -> None:
        """Both rules on a copy of these rules over the scratch window (``parts.Scratch``), with
        the scan's evidence in it and window moves along every axis in between."""
        # Every class movable (class 0 never is), so that the rules find voxels to act on.
        small = MoverForgetting(np.arange(len(self.movable)), len(self.movable), self.prior, scratch.geometry.dims,
                                self.reach, scratch.geometry.resolution)
        small.near = self.near
        window = scratch.window
        for origin in (scratch.origin, *scratch.origins()):
            window.move_to(origin)
            small.window_moved(origin, window.mask)
            small.contradicted(scratch.volume, window)
            small.unsupported(window)

    # -- 1. returns that contradict a mover ----------------------------------------------------
    def contradicted(self, volume: SparseVolume, window) -> int:
        """Reset the class evidence of the voxels of this scan's returns (``volume``) whose
        movable class they contradict; flag the columns around movable evidence. Call after the
        window moved to the scan's origin and before the update."""
        self.columns &= np.uint8(_FLAGGED | _EMPTIED)  # the movable returns near a column are this scan's
        if not volume.num_voxels:
            return 0
        if HAVE_NUMBA and not isinstance(window.alpha, torch.Tensor):
            # One compiled pass: the voxels' places in the torus, the classes the scan saw there,
            # the reset, and the flags around movable evidence.
            held_by_column, movable_bits = self._class_bits(window)
            with parallel_region():
                count = int(_contradicted_and_flag_numba(
                    window.alpha, volume.linear, np.asarray(volume.dims, np.int64),
                    np.asarray(volume.origin, np.int64), self.dims, volume.features, self.movable,
                    np.float32(self.prior), self.columns, self.reach, held_by_column, movable_bits, self.near,
                    self._near_columns))
            self.reset_voxels += count
            return count
        physical = np.mod(unravel_linear(volume.linear, volume.dims) + volume.origin, self.dims)
        seen = volume.features.argmax(axis=1)
        if self.near >= 0:  # near this scan's movable returns, only voxels that rays found empty
            self._near_columns[:] = False
            self._mark_around(self._near_columns, physical[self.movable[seen]], self.near, True)
            candidates = ~self._near_columns[physical[:, 0], physical[:, 1]] | _empty_at(window.alpha, physical)
            physical_tried, seen_tried = physical[candidates], seen[candidates]
        else:
            physical_tried, seen_tried = physical, seen
        if isinstance(window.alpha, torch.Tensor):
            count = _contradicted_torch(window.alpha, physical_tried, seen_tried, self.movable, self.prior)
        else:
            count = _contradicted_numpy(window.alpha, physical_tried, seen_tried, self.movable, self.prior)
        # Any movable evidence, also in a voxel whose returns are mostly static: its spread can
        # make a neighbour's most likely class a movable one.
        self._flag_around(physical[volume.features[:, self.movable].max(axis=1) > 0], _FLAGGED)
        self._flag_around(physical[self.movable[seen]], _FLAGGED | _NEAR_MOVERS)
        self.reset_voxels += count
        return count

    def _class_bits(self, window) -> tuple[np.ndarray, np.uint64]:
        """The window's ``classes_by_column`` (asked for here, so the window keeps it from now
        on) and the bits of the movable classes; with no such bits, every bit set (every class
        run is read)."""
        held_by_column = window.classes_by_column()
        if held_by_column is None:
            return np.full((1, 1), np.iinfo(np.uint64).max, np.uint64), np.uint64(0)
        return held_by_column, self.movable_bits

    def _flag_around(self, physical: np.ndarray, bits: int) -> None:
        self._mark_around(self.columns, physical, self.reach, np.uint8(bits))

    def _mark_around(self, target: np.ndarray, physical: np.ndarray, reach: int, value) -> None:
        """``target[x, y] |= value`` for every column within ``reach`` columns (each way, on the
        torus) of the voxels ``physical`` (M, 3)."""
        if not len(physical):
            return
        columns = np.unique(physical[:, 0] * self.dims[1] + physical[:, 1])
        x, y = columns // self.dims[1], columns % self.dims[1]
        steps = np.arange(-reach, reach + 1)
        xs = np.mod(x[:, None, None] + steps[None, :, None], self.dims[0])
        ys = np.mod(y[:, None, None] + steps[None, None, :], self.dims[1])
        target[np.broadcast_to(xs, (len(x), len(steps), len(steps))).reshape(-1),
               np.broadcast_to(ys, (len(x), len(steps), len(steps))).reshape(-1)] |= value

    def window_moved(self, origin: np.ndarray, mask) -> None:
        """The window now starts at global ``origin``: the columns it brought in (new x or y
        rows; every column holding evidence when it moved along z, whose new layer came from
        the store) may hold movers seen before."""
        origin = np.asarray(origin, np.int64)
        if self.origin is None:  # a new window (or one loaded from a map file): look everywhere once
            self.columns[:] = _FLAGGED
        elif not np.array_equal(origin, self.origin):
            for axis in (0, 1, 2):
                shift = int(origin[axis] - self.origin[axis])
                if shift:
                    rows = np.arange(min(abs(shift), int(self.dims[axis])))
                    new = (origin[axis] + (self.dims[axis] - 1 - rows if shift > 0 else rows)) % self.dims[axis]
                    if axis == 0:
                        self.columns[new, :] |= _FLAGGED
                    elif axis == 1:
                        self.columns[:, new] |= _FLAGGED
                    elif isinstance(mask, np.ndarray):
                        # Only a column whose entering layers hold evidence can have gained a
                        # movable voxel (an unflagged column held none).
                        self.columns |= ((mask[:, :, new] & EVIDENCE) != 0).any(axis=2).astype(np.uint8)
        self.origin = origin.copy()

    # -- 2. a mover needs support --------------------------------------------------------------
    def unsupported(self, window) -> int:
        """Empty the movable voxels of the flagged columns that float over empty space and this
        scan's evidence did not reach. Call after the update (the ``TOUCHED`` bits set) and
        before free space (which clears them)."""
        if isinstance(window.alpha, torch.Tensor):
            near = torch.as_tensor((self.columns & _NEAR_MOVERS) != 0, device=window.alpha.device)
            count = _unsupported_torch(window.alpha, window.mask, window.origin, self.movable, self.prior, near,
                                       self.min_empty)
        elif HAVE_NUMBA:
            with parallel_region():
                # The flagged columns as one list, so that the threads share them evenly (movers
                # gather in a few rows of the window).
                flagged = np.flatnonzero(self.columns).astype(np.int64)
                threads = min(get_num_threads(), max(1, len(flagged)))
                held_by_column, movable_bits = self._class_bits(window)
                count = int(_unsupported_numba(window.alpha, window.mask, np.asarray(window.origin, np.int64),
                                               self.movable, self.columns, flagged, np.float32(self.prior),
                                               self.min_empty, threads, held_by_column, movable_bits != 0))
        else:
            count = _unsupported_numpy(window.alpha, window.mask, np.asarray(window.origin, np.int64),
                                       self.movable, self.columns, np.float32(self.prior), self.min_empty)
        self.emptied_voxels += count
        return count


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


def _contradicted_torch(alpha, physical, seen, movable, prior) -> int:
    index = torch.as_tensor(physical, device=alpha.device)
    x, y, z = index[:, 0], index[:, 1], index[:, 2]
    occupied = alpha[1:, x, y, z]
    held = occupied.argmax(dim=0) + 1
    limit = float(np.float32(prior) * np.float32(occupied.shape[0]) * np.float32(1 + 1e-6))
    has_evidence = _occupied_sum(occupied) > limit
    seen_t = torch.as_tensor(seen, device=alpha.device)
    reset = torch.as_tensor(movable, device=alpha.device)[held] & has_evidence & (seen_t != held)
    alpha[1:, x, y, z] = torch.where(reset, float(prior), occupied)  # no read of the device before the end
    return int(torch.count_nonzero(reset))


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


def _unsupported_torch(alpha, mask, origin, movable, prior, near, min_empty) -> int:
    """The rule of 2 over every column of a device window at once (whole-window operations, no
    loop over its layers). Each layer's decision reads only what the layers under it were
    before the rule changed anything, so the walk up a column becomes two scans along z: the
    empty voxels met since the last static one are a running count less its value where that
    static voxel stands; a voxel stands on the ground where the one under it is static."""
    size_z = mask.shape[2]
    device = alpha.device
    evident = (mask & EVIDENCE) != 0
    rest = _occupied_sum(alpha[1:])
    free = alpha[FREE_CLASS]
    empty = evident & (free > EMPTY_SHARE * (free + rest))
    best, held = alpha[1:].max(dim=0)
    is_movable = evident & ~empty & torch.as_tensor(movable, device=device)[held + 1] & (best > prior)
    static = evident & ~empty & ~is_movable
    # Along each column from its bottom layer (the torus turned), then back.
    layer = torch.arange(size_z, device=device)
    up, down = (layer + int(origin[2])) % size_z, (layer - int(origin[2])) % size_z
    static_up, empties = static[:, :, up], empty[:, :, up].to(torch.int64)
    under = torch.cumsum(empties, dim=2) - empties  # empty voxels below each layer
    last_static = torch.cummax(torch.where(static_up, layer, -1), dim=2).values
    below = torch.nn.functional.pad(last_static[:, :, :-1], (1, 0), value=-1)  # the last static one under it
    empty_below = (under - torch.gather(under, 2, below + 1))[:, :, down]
    on_ground = torch.nn.functional.pad(static_up[:, :, :-1], (1, 0), value=False)[:, :, down]
    touched = (mask & TOUCHED) != 0
    trail = is_movable & (empty_below >= min_empty) & ~touched
    fringe = is_movable & ~trail & on_ground & ~near[:, :, None] & touched
    mask &= ~(fringe.to(torch.uint8) * TOUCHED)
    mask |= trail.to(torch.uint8) * CHANGED
    alpha[FREE_CLASS] = torch.where(trail, torch.maximum(free, rest + 1.0), free)
    return int(torch.count_nonzero(trail))


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
