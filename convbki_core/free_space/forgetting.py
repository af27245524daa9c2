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
from convbki_core.free_space.device_forgetting import _contradicted_torch, _unsupported_torch
from convbki_core.free_space.host_forgetting import (
    _EMPTIED,
    _FLAGGED,
    _NEAR_MOVERS,
    FREE_CLASS,
    _contradicted_numpy,
    _empty_at,
    _unsupported_numpy,
)
from convbki_core.geometry.grid import unravel_linear
from convbki_core.geometry.volume import SparseVolume
from convbki_core.memory.column_classes import class_bits
from convbki_core.memory.window import EVIDENCE

if HAVE_NUMBA:
    from convbki_core.compiled import get_num_threads
    from convbki_core.free_space.host_forgetting import _contradicted_and_flag_numba, _unsupported_numba

# Metres of empty space under a movable voxel that make it float: rays that pass under a parked
# car (its ground clearance) find a voxel or two empty, the space a bus has left far more.
MIN_EMPTY_BELOW = 0.6


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
