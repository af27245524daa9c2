"""Free space: evidence that a voxel is empty, from the rays between the sensor and its returns.

A return at range r says the space between the sensor and r is empty (the occupancy heritage
of BKI mapping). Here that evidence enters the same Dirichlet as the classes, in a "free"
category: the concentration of class 0, which inputs never feed (class 0 is the ignored
"unlabeled" class of the label map). For one scan, with G[v] the number of returns whose
ray crosses voxel v before its end voxel,

    alpha_t[0, v] = alpha_{t-1}[0, v] + sum_tap K_free[tap] * G[v - tap]

for every voxel v that already holds evidence and is not reached by this scan's own class
evidence. A voxel whose expected class becomes 0 is empty: it leaves the shown map (and is
sent with label 0 on the map's updates) but keeps its concentrations, so an object that
comes back wins it back by evidence, as anything else would.

Why the two conditions:
* Only voxels with evidence take free evidence: space that is only ever seen empty costs no
  memory (a drive sees millions of such voxels).
* A voxel reached by the scan's own class evidence (the support of the class filters around
  its returns) takes none from that scan: rays that graze a surface at a shallow angle
  (the road ahead, the side of a pole) cross the voxels holding it without the surface
  being gone, and that same scan sees the surface there. A mover's voxels, once it has left,
  receive no class evidence, so the rays that now pass through them empty them.

Rays: returns that fall into the same voxel share one ray, from the sensor to that voxel's
centre, weighted by their number (the evidence sum of the voxel: one per labelled point);
octomap's discretised insertion does the same. Each ray is walked voxel by voxel (the
Amanatides-Woo traversal). Returns beyond the window (far, or above or below it) still say
that the window's part of their ray is empty: they share rays by the boundary voxel where
they leave the window, which those rays cross too.

The compiled pass counts the rays on two cores without sharing a voxel (rays ending on either
side of the sensor's x plane), then each core adds the counts of its own x planes into the map.
"""

from __future__ import annotations

import numpy as np

from convbki_core.native import HAVE_NUMBA
from convbki_core.volume import SparseVolume, unravel_linear
from convbki_core.window import CHANGED, EVIDENCE, TOUCHED

if HAVE_NUMBA:
    import numba
    from numba import njit, prange

FREE_CLASS = 0
_KEEP_UNTOUCHED = 0xFF & ~TOUCHED  # the mask bits left after a scan


def free_taps(free_filter: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The non-zero taps of a free-space filter (f, f, f) as (offsets (T, 3) int64, weights (T,)
    float32); a voxel v receives weight * G[v - offset]."""
    size = free_filter.shape[0]
    half = size // 2
    nonzero = np.argwhere(free_filter > 0)
    # conv3d's tap [i, j, k] carries F[v + (i, j, k) - half] to v; written as v - offset.
    offsets = (half - nonzero).astype(np.int64)
    return np.ascontiguousarray(offsets), np.ascontiguousarray(free_filter[free_filter > 0], np.float32)


def scan_rays(points: np.ndarray, pose: np.ndarray, volume: SparseVolume,
              resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scan's rays as (end voxels (M, 3), weights (M,), through (M,) bool): one per voxel
    holding returns (weighted by their evidence), and one per window voxel where the rays to
    returns beyond the window leave it (``through``: that voxel is crossed too)."""
    ends = unravel_linear(volume.linear, volume.dims) + volume.origin
    weights = ray_weights(volume.features)
    dropped = points[volume.point_linear < 0]
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite points are dropped next
        beyond = (dropped @ pose[:3, :3].T + pose[:3, 3]) / resolution
    beyond = beyond[np.isfinite(beyond).all(axis=1)]
    exits, rays = window_exits(pose[:3, 3] / resolution, beyond, volume.origin, volume.dims)
    through = np.concatenate([np.zeros(len(ends), np.bool_), np.ones(len(exits), np.bool_)])
    return np.concatenate([ends, exits]), np.concatenate([weights, rays]), through


def ray_weights(features: np.ndarray) -> np.ndarray:
    """Rays per occupied voxel: its evidence sum (the number of labelled points in it)."""
    return np.ascontiguousarray(features.sum(axis=1, dtype=np.float32))


def free_space_update(sensor: np.ndarray, occupied: np.ndarray, weights: np.ndarray, offsets: np.ndarray,
                      tap_weights: np.ndarray, origin: np.ndarray, dims: np.ndarray, alpha: np.ndarray,
                      mask: np.ndarray, counts: np.ndarray, through: np.ndarray | None = None) -> int:
    """Add one scan's free-space evidence into the torus window, in place; returns the number
    of voxels whose free concentration grew.

    ``sensor`` (3,) the sensor position in voxel units (global grid, metres / resolution);
    ``occupied`` (M, 3) int64 global indices of the voxels holding the scan's returns, with
    ``weights`` (M,) float32 rays each; ``offsets``/``tap_weights`` from ``free_taps``; the
    window as in ``update.scatter_update``: voxels with ``TOUCHED`` in ``mask`` received
    this scan's class evidence and take no free evidence; the bit is cleared here.
    ``counts``: the scratch of ``scratch_counts``. ``through`` (M,) bool: rays whose return
    lies beyond the window; they end in the window's boundary voxel ``occupied[m]``, which
    they cross too (``window_exits``).
    """
    occupied = np.ascontiguousarray(occupied, np.int64)
    through = np.zeros(len(occupied), np.bool_) if through is None else np.ascontiguousarray(through, np.bool_)
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    sensor = np.ascontiguousarray(sensor, np.float64)
    if HAVE_NUMBA:
        return int(_free_space_numba(sensor, occupied, np.ascontiguousarray(weights, np.float32), through, offsets,
                                     tap_weights, origin, dims, alpha, mask, counts))
    return _free_space_numpy(sensor, occupied, weights, through, offsets, tap_weights, origin, dims, alpha, mask)


def window_exits(sensor: np.ndarray, points: np.ndarray, origin: np.ndarray,
                 dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For returns beyond the window (``points`` (N, 3) in voxel units, finite; those inside
    are skipped): the window voxels where their rays leave it, unique, with the number of
    rays each."""
    sensor = np.ascontiguousarray(sensor, np.float64)
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    if HAVE_NUMBA:
        linear = _exit_linear_numba(np.ascontiguousarray(points, np.float64), sensor, origin, dims)
    else:
        linear = _exit_linear_numpy(np.asarray(points, np.float64), sensor, origin, dims)
    linear, rays = np.unique(linear, return_counts=True)
    local = np.stack(np.unravel_index(linear, tuple(int(d) for d in dims)), axis=1)
    return local + origin, rays.astype(np.float32)


def _exit_linear_numpy(points, sensor, origin, dims) -> np.ndarray:
    outside = ((points < origin) | (points >= origin + dims)).any(axis=1)
    direction = points[outside] - sensor
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(direction > 0, (origin + dims).astype(np.float64), origin.astype(np.float64))
        leave = np.where(direction != 0, (bound - sensor) / direction, np.inf).min(axis=1)
    exits = np.floor(sensor + direction * (leave[:, None] * (1 - 1e-9)))
    local = np.clip(exits, origin, origin + dims - 1).astype(np.int64) - origin
    return (local[:, 0] * dims[1] + local[:, 1]) * dims[2] + local[:, 2]


def count_rays(sensor: np.ndarray, ends: np.ndarray, weights: np.ndarray, through: np.ndarray, dims: np.ndarray,
               counts: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Only the counting half of ``free_space_update``: the rays' counts G (X, Y, Z), torus
    order, in ``counts`` (whose caller zeroes it again); for a window kept elsewhere (on a GPU)."""
    volume, shared_plane = counts
    sensor = np.ascontiguousarray(sensor, np.float64)
    dims = np.ascontiguousarray(dims, np.int64)
    if HAVE_NUMBA:
        _count_rays(sensor, np.ascontiguousarray(ends, np.int64), np.ascontiguousarray(weights, np.float32),
                    np.ascontiguousarray(through, np.bool_), dims, volume, shared_plane)
        volume[int(np.floor(sensor[0])) % int(dims[0])] += shared_plane
        shared_plane[:] = 0.0
        return volume
    for m in range(len(ends)):
        _walk_ray(sensor, ends[m], lambda voxel, w=float(weights[m]): _add(volume, voxel, dims, w), bool(through[m]))
    return volume


def _add(volume: np.ndarray, voxel, dims: np.ndarray, weight: float) -> None:
    volume[tuple(np.mod(voxel, dims))] += weight


def scratch_counts(dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The zeroed scratch ``free_space_update`` counts into (left zeroed): a window-sized count
    volume and one (Y, Z) plane."""
    shape = tuple(int(d) for d in dims)
    return np.zeros(shape, np.float32), np.zeros(shape[1:], np.float32)


def crossed_voxels(start: np.ndarray, end_voxel: np.ndarray, through: bool = False) -> list[tuple[int, int, int]]:
    """The voxels a ray from ``start`` (voxel units) to the centre of ``end_voxel`` passes
    through, in order, the end voxel left out unless ``through`` (the traversal the
    compiled pass runs)."""
    crossed = []
    _walk_ray(np.asarray(start, np.float64), np.asarray(end_voxel, np.int64), crossed.append, through)
    return crossed


def _walk_ray(start, end_voxel, visit, through=False) -> None:
    """Amanatides-Woo: step into the neighbour whose boundary the ray meets first."""
    end = end_voxel + 0.5
    direction = end - start
    voxel = np.floor(start).astype(np.int64)
    steps = int(np.abs(end_voxel - voxel).sum()) + int(through)
    step = np.where(direction > 0, 1, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(direction != 0, np.abs(1.0 / direction), np.inf)
        boundary = np.where(direction > 0, voxel + 1.0, voxel.astype(np.float64))
        t_max = np.where(direction != 0, (boundary - start) / direction, np.inf)
    for _ in range(steps):
        visit((int(voxel[0]), int(voxel[1]), int(voxel[2])))
        axis = int(np.argmin(t_max))
        voxel[axis] += step[axis]
        t_max[axis] += delta[axis]


def _free_space_numpy(sensor, occupied, weights, through, offsets, tap_weights, origin, dims, alpha, mask) -> int:
    """The same pass in Python loops and numpy (the fallback without numba, and a reference)."""
    counts = np.zeros(tuple(int(d) for d in dims), np.float64)

    def count(voxel, weight):
        counts[tuple(np.mod(voxel, dims))] += weight

    for m in range(occupied.shape[0]):
        _walk_ray(sensor, occupied[m], lambda voxel, w=float(weights[m]): count(np.array(voxel), w), bool(through[m]))
    counts = counts.astype(np.float32)
    takes = (mask & EVIDENCE != 0) & (mask & TOUCHED == 0)
    physical = np.argwhere(takes)
    global_index = origin + (physical - origin) % dims
    evidence = np.zeros(len(physical), np.float32)
    for offset, weight in zip(offsets, tap_weights):
        source = global_index - offset
        inside = ((source >= origin) & (source < origin + dims)).all(axis=1)
        source_physical = np.mod(source[inside], dims)
        evidence[inside] += weight * counts[tuple(source_physical.T)]
    grew = evidence > 0
    x, y, z = physical[grew].T
    alpha[FREE_CLASS, x, y, z] += evidence[grew]
    mask[x, y, z] |= np.uint8(CHANGED)
    mask &= np.uint8(_KEEP_UNTOUCHED)
    return int(grew.sum())


if HAVE_NUMBA:

    @njit(cache=True, nogil=True, inline="always")
    def _count_ray(sensor, end_voxel, weight, through, dims, counts, shared_x, shared_plane):  # pragma: no cover
        """Add ``weight`` to the count of every voxel the ray crosses before its end voxel (and
        the end voxel too when ``through``); counts of the physical x plane ``shared_x`` go to
        ``shared_plane`` (Y, Z) instead (-1: none)."""
        vx = np.int64(np.floor(sensor[0]))
        vy = np.int64(np.floor(sensor[1]))
        vz = np.int64(np.floor(sensor[2]))
        dx = end_voxel[0] + 0.5 - sensor[0]
        dy = end_voxel[1] + 0.5 - sensor[1]
        dz = end_voxel[2] + 0.5 - sensor[2]
        steps = abs(end_voxel[0] - vx) + abs(end_voxel[1] - vy) + abs(end_voxel[2] - vz) + (1 if through else 0)
        sx = 1 if dx > 0 else -1
        sy = 1 if dy > 0 else -1
        sz = 1 if dz > 0 else -1
        inf = np.inf
        tdx = abs(1.0 / dx) if dx != 0 else inf
        tdy = abs(1.0 / dy) if dy != 0 else inf
        tdz = abs(1.0 / dz) if dz != 0 else inf
        tx = ((vx + 1.0 if dx > 0 else vx * 1.0) - sensor[0]) / dx if dx != 0 else inf
        ty = ((vy + 1.0 if dy > 0 else vy * 1.0) - sensor[1]) / dy if dy != 0 else inf
        tz = ((vz + 1.0 if dz > 0 else vz * 1.0) - sensor[2]) / dz if dz != 0 else inf
        # Torus positions, advanced with the voxel: no modulo inside the loop.
        px = vx % dims[0]
        py = vy % dims[1]
        pz = vz % dims[2]
        for _ in range(steps):
            if px == shared_x:
                shared_plane[py, pz] += weight
            else:
                counts[px, py, pz] += weight
            # The same choice as numpy's argmin over (tx, ty, tz): the first smallest.
            if tx <= ty and tx <= tz:
                tx += tdx
                px += sx
                if px == dims[0]:
                    px = 0
                elif px < 0:
                    px = dims[0] - 1
            elif ty <= tz:
                ty += tdy
                py += sy
                if py == dims[1]:
                    py = 0
                elif py < 0:
                    py = dims[1] - 1
            else:
                tz += tdz
                pz += sz
                if pz == dims[2]:
                    pz = 0
                elif pz < 0:
                    pz = dims[2] - 1

    @njit(cache=True, parallel=True, nogil=True)
    def _count_rays(sensor, occupied, weights, through, dims, counts, shared_plane):  # pragma: no cover
        """Two threads, no shared voxel: rays that end at or beyond the sensor's x plane only
        visit planes on that side, the others only planes below it; the sensor's own plane,
        which both visit, is counted separately for the second group."""
        sensor_x = np.int64(np.floor(sensor[0]))
        for group in prange(2):
            for m in range(occupied.shape[0]):
                if (occupied[m, 0] >= sensor_x) == (group == 0):
                    _count_ray(sensor, occupied[m], weights[m], through[m], dims, counts,
                               -1 if group == 0 else sensor_x % dims[0], shared_plane)

    @njit(cache=True, parallel=True, nogil=True)
    def _apply_counts(sensor_x, offsets, tap_weights, origin, dims, alpha, mask, counts,
                      shared_plane, parts):  # pragma: no cover - compiled
        """Add the counted rays as free evidence, each thread over its own x planes; clear the
        counts and the ``TOUCHED`` bits on the way."""
        taps = offsets.shape[0]
        centre_only = taps == 1 and offsets[0, 0] == 0 and offsets[0, 1] == 0 and offsets[0, 2] == 0
        if not centre_only:  # the sensor plane's second counts join the rest first
            counts[sensor_x] += shared_plane
            shared_plane[:] = 0.0
        grew = np.zeros(parts, np.int64)
        for part in prange(parts):
            x_begin = dims[0] * part // parts
            x_end = dims[0] * (part + 1) // parts
            found = 0
            for x in range(x_begin, x_end):
                global_x = origin[0] + (x - origin[0]) % dims[0]
                for y in range(dims[1]):
                    global_y = origin[1] + (y - origin[1]) % dims[1]
                    for z in range(dims[2]):
                        marks = mask[x, y, z]
                        evidence = np.float32(0.0)
                        if centre_only:
                            evidence = counts[x, y, z]
                            if x == sensor_x:
                                evidence += shared_plane[y, z]
                            if evidence == 0:
                                if marks & TOUCHED != 0:
                                    mask[x, y, z] = marks & _KEEP_UNTOUCHED
                                continue
                            counts[x, y, z] = 0.0
                            evidence *= tap_weights[0]
                        elif marks & EVIDENCE != 0 and marks & TOUCHED == 0:
                            global_z = origin[2] + (z - origin[2]) % dims[2]
                            for t in range(taps):
                                sx = global_x - offsets[t, 0]
                                sy = global_y - offsets[t, 1]
                                sz = global_z - offsets[t, 2]
                                if (origin[0] <= sx < origin[0] + dims[0] and origin[1] <= sy < origin[1] + dims[1]
                                        and origin[2] <= sz < origin[2] + dims[2]):
                                    evidence += tap_weights[t] * counts[sx % dims[0], sy % dims[1], sz % dims[2]]
                        if marks & EVIDENCE != 0 and marks & TOUCHED == 0 and evidence > 0:
                            alpha[FREE_CLASS, x, y, z] += evidence
                            mask[x, y, z] = marks | CHANGED
                            found += 1
                        elif marks & TOUCHED != 0:
                            mask[x, y, z] = marks & _KEEP_UNTOUCHED
            grew[part] = found
        if centre_only:
            shared_plane[:] = 0.0
        else:  # a tap reads other threads' planes: clear only after every thread has read
            counts[:] = 0.0
        return grew.sum()

    @njit(cache=True, nogil=True)
    def _exit_linear_numba(points, sensor, origin, dims):  # pragma: no cover - compiled; tested against numpy
        """Window-local linear index of the voxel where each outside point's ray leaves the window."""
        out = np.empty(points.shape[0], np.int64)
        count = 0
        for i in range(points.shape[0]):
            outside = False
            for axis in range(3):
                if points[i, axis] < origin[axis] or points[i, axis] >= origin[axis] + dims[axis]:
                    outside = True
            if not outside:
                continue
            leave = np.inf
            for axis in range(3):
                direction = points[i, axis] - sensor[axis]
                if direction > 0:
                    leave = min(leave, (origin[axis] + dims[axis] - sensor[axis]) / direction)
                elif direction < 0:
                    leave = min(leave, (origin[axis] - sensor[axis]) / direction)
            local = np.empty(3, np.int64)
            for axis in range(3):
                position = np.floor(sensor[axis] + (points[i, axis] - sensor[axis]) * (leave * (1 - 1e-9)))
                local[axis] = min(max(np.int64(position), origin[axis]), origin[axis] + dims[axis] - 1) - origin[axis]
            out[count] = (local[0] * dims[1] + local[1]) * dims[2] + local[2]
            count += 1
        return out[:count]

    def _free_space_numba(sensor, occupied, weights, through, offsets, tap_weights, origin, dims, alpha, mask,
                          counts):
        volume, shared_plane = counts
        _count_rays(sensor, occupied, weights, through, dims, volume, shared_plane)
        sensor_x = int(np.floor(sensor[0])) % int(dims[0])
        parts = max(1, min(numba.get_num_threads(), int(dims[0])))
        return _apply_counts(sensor_x, offsets, tap_weights, origin, dims, alpha, mask, volume, shared_plane, parts)
