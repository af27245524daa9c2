"""The rays' walk: each ray from the sensor to its end voxel, voxel by voxel (Amanatides-Woo),
counting how many rays cross each voxel before their end (G of the free-space update).

``_walk_ray`` is the numpy reference and the compiled walk (``_count_ray``,
``_count_ray_inside``) takes the same steps, as the device's walk (``device_rays``) does bit
for bit: on equal boundary times x before y before z, each crossing's time computed on its own.
``_count_rays`` counts a scan's rays on two cores in the layout the free-space update reads
(``update``'s docstring); ``count_rays`` is that count alone, for a window kept elsewhere.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange


def count_rays(sensor: np.ndarray, ends: np.ndarray, weights: np.ndarray, through: np.ndarray, dims: np.ndarray,
               counts: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Only the counting half of ``free_space_update``: the rays' counts G (X, Y, Z), torus
    order, in ``counts`` (whose caller zeroes it again); for a window kept elsewhere (on a GPU)."""
    volume, shared_plane = counts
    sensor = np.ascontiguousarray(sensor, np.float64)
    dims = np.ascontiguousarray(dims, np.int64)
    if HAVE_NUMBA:
        with parallel_region():
            _count_rays(sensor, np.ascontiguousarray(ends, np.int64), np.ascontiguousarray(weights, np.float32),
                        np.ascontiguousarray(through, np.bool_), np.zeros(3, np.int64), dims, volume, shared_plane)
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
    volume and one (Y, Z) plane. Written now (np.zeros alone maps the pages lazily), so the
    first scan does not pay for the page faults."""
    shape = tuple(int(d) for d in dims)
    return np.full(shape, 0.0, np.float32), np.full(shape[1:], 0.0, np.float32)


def _walk_ray(start, end_voxel, visit, through=False) -> None:
    """Amanatides-Woo: step into the neighbour whose boundary the ray meets first (on equal
    times, x before y before z). The k-th boundary along an axis is met at t0 + k * delta, one
    product and one sum in float64 (not a running sum), so that every crossing's time can be
    computed on its own, as the device's walk (``device_rays``) does, with the same bits."""
    end = end_voxel + 0.5
    direction = end - start
    voxel = np.floor(start).astype(np.int64)
    steps = int(np.abs(end_voxel - voxel).sum()) + int(through)
    step = np.where(direction > 0, 1, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(direction != 0, np.abs(1.0 / direction), np.inf)
        boundary = np.where(direction > 0, voxel + 1.0, voxel.astype(np.float64))
        t_first = np.where(direction != 0, (boundary - start) / direction, np.inf)
    t_max, crossed = t_first.copy(), np.zeros(3, np.int64)
    for _ in range(steps):
        visit((int(voxel[0]), int(voxel[1]), int(voxel[2])))
        axis = int(np.argmin(t_max))
        voxel[axis] += step[axis]
        crossed[axis] += 1
        t_max[axis] = t_first[axis] + np.float64(crossed[axis]) * delta[axis]


if HAVE_NUMBA:

    @njit(nogil=True, inline="always")
    def _ray_start(sensor, end_voxel, through):  # pragma: no cover - compiled
        """The walk of ``_walk_ray`` at the sensor's voxel: (voxel x, y, z, steps, step x, y, z,
        the times of the first boundary crossings x, y, z and their increments x, y, z)."""
        vx = np.int64(np.floor(sensor[0]))
        vy = np.int64(np.floor(sensor[1]))
        vz = np.int64(np.floor(sensor[2]))
        dx = end_voxel[0] + 0.5 - sensor[0]
        dy = end_voxel[1] + 0.5 - sensor[1]
        dz = end_voxel[2] + 0.5 - sensor[2]
        steps = abs(end_voxel[0] - vx) + abs(end_voxel[1] - vy) + abs(end_voxel[2] - vz) + (1 if through else 0)
        inf = np.inf
        tx = ((vx + 1.0 if dx > 0 else vx * 1.0) - sensor[0]) / dx if dx != 0 else inf
        ty = ((vy + 1.0 if dy > 0 else vy * 1.0) - sensor[1]) / dy if dy != 0 else inf
        tz = ((vz + 1.0 if dz > 0 else vz * 1.0) - sensor[2]) / dz if dz != 0 else inf
        return (vx, vy, vz, steps, 1 if dx > 0 else -1, 1 if dy > 0 else -1, 1 if dz > 0 else -1, tx, ty, tz,
                abs(1.0 / dx) if dx != 0 else inf, abs(1.0 / dy) if dy != 0 else inf,
                abs(1.0 / dz) if dz != 0 else inf)

    @njit(nogil=True, inline="always")
    def _count_ray(sensor, end_voxel, weight, through, corner, dims, counts, shared_x,
                   shared_plane):  # pragma: no cover - compiled
        """Add ``weight`` to the count of every voxel the ray crosses before its end voxel (and
        the end voxel too when ``through``); voxel v counts at ``counts[(v - corner) % dims]``,
        except those of the x plane ``shared_x`` (in that layout), which go to ``shared_plane``
        (Y, Z) (-1: none)."""
        vx, vy, vz, steps, sx, sy, sz, tx0, ty0, tz0, tdx, tdy, tdz = _ray_start(sensor, end_voxel, through)
        tx, ty, tz = tx0, ty0, tz0
        kx = ky = kz = 0  # boundaries crossed along each axis: the next is met at t0 + k * delta
        # Positions in the counts, advanced with the voxel: no modulo inside the loop.
        px = (vx - corner[0]) % dims[0]
        py = (vy - corner[1]) % dims[1]
        pz = (vz - corner[2]) % dims[2]
        for _ in range(steps):
            if px == shared_x:
                shared_plane[py, pz] += weight
            else:
                counts[px, py, pz] += weight
            # The same choice as numpy's argmin over (tx, ty, tz): the first smallest.
            if tx <= ty and tx <= tz:
                kx += 1
                tx = tx0 + kx * tdx
                px += sx
                if px == dims[0]:
                    px = 0
                elif px < 0:
                    px = dims[0] - 1
            elif ty <= tz:
                ky += 1
                ty = ty0 + ky * tdy
                py += sy
                if py == dims[1]:
                    py = 0
                elif py < 0:
                    py = dims[1] - 1
            else:
                kz += 1
                tz = tz0 + kz * tdz
                pz += sz
                if pz == dims[2]:
                    pz = 0
                elif pz < 0:
                    pz = dims[2] - 1

    @njit(nogil=True, inline="always")
    def _step_inside(t, k, t0, td, index, pz, sz, stride_x, stride_y, size_z):  # pragma: no cover
        """One step of ``_count_ray_inside``'s walk (the first smallest of the times ``t`` (x, y, z),
        as ``_walk_ray``; ``k`` the boundaries crossed, ``t0`` the first times, ``td`` their
        increments): the new (t, k, flat index, z on the torus, whether it stepped along x)."""
        tx, ty, tz = t
        kx, ky, kz = k
        if tx <= ty and tx <= tz:
            return (t0[0] + (kx + 1) * td[0], ty, tz), (kx + 1, ky, kz), index + stride_x, pz, True
        if ty <= tz:
            return (tx, t0[1] + (ky + 1) * td[1], tz), (kx, ky + 1, kz), index + stride_y, pz, False
        pz += sz
        index += sz
        if pz == size_z:
            pz = 0
            index -= size_z
        elif pz < 0:
            pz = size_z - 1
            index += size_z
        return (tx, ty, t0[2] + (kz + 1) * td[2]), (kx, ky, kz + 1), index, pz, False

    @njit(nogil=True, inline="always")
    def _count_ray_inside(sensor, end_voxel, weight, through, corner, dims, counts, shared_plane,
                          shared):  # pragma: no cover - compiled
        """``_count_ray`` for a ray whose voxels lie within ``corner`` + ``dims`` in x and y,
        with ``corner[2]`` 0 (z on the torus), into ``counts`` and ``shared_plane`` flattened:
        the index moves by a fixed stride per step, and only a step along z can wrap.
        ``shared``: the ray ends below the sensor's x plane, so its visits of that plane, which
        go to ``shared_plane``, are its first ones."""
        vx, vy, vz, steps, sx, sy, sz, tx0, ty0, tz0, tdx, tdy, tdz = _ray_start(sensor, end_voxel, through)
        t0, td = (tx0, ty0, tz0), (tdx, tdy, tdz)
        t, k = t0, (0, 0, 0)
        size_y, size_z = dims[1], dims[2]
        plane = size_y * size_z
        pz = vz % size_z
        base = (vx - corner[0]) * plane
        index = base + (vy - corner[1]) * size_z + pz
        stride_x, stride_y = sx * plane, sy * size_z
        if shared:
            while steps > 0:
                shared_plane[index - base] += weight
                steps -= 1
                t, k, index, pz, along_x = _step_inside(t, k, t0, td, index, pz, sz, stride_x, stride_y, size_z)
                if along_x:
                    break  # x only decreases along this ray: it has left the plane
        for _ in range(steps):
            counts[index] += weight
            t, k, index, pz, _along_x = _step_inside(t, k, t0, td, index, pz, sz, stride_x, stride_y, size_z)

    @njit(parallel=True, nogil=True)
    def _count_rays(sensor, occupied, weights, through, corner, dims, counts, shared_plane):  # pragma: no cover
        """Two threads, no shared voxel: rays that end at or beyond the sensor's x plane only
        visit planes on that side, the others only planes below it; the sensor's own plane,
        which both visit, is counted separately for the second group. Voxel v counts at
        ``counts[(v - corner) % dims]``; a ray whose voxels all lie within ``corner`` +
        ``dims`` in x and y (those of a window around the sensor, with ``corner`` its origin)
        walks with ``_count_ray_inside``, which the torus would slow down."""
        sensor_x = np.int64(np.floor(sensor[0]))
        sensor_y = np.int64(np.floor(sensor[1]))
        shared_x = (sensor_x - corner[0]) % dims[0]
        # A ray's voxels lie between its first (the sensor's) and its last (the end voxel).
        sensor_inside = (corner[0] <= sensor_x < corner[0] + dims[0] and corner[1] <= sensor_y < corner[1] + dims[1]
                         and corner[2] == 0)
        flat_counts = counts.reshape(counts.size)
        flat_plane = shared_plane.reshape(shared_plane.size)
        for group in prange(2):
            for m in range(occupied.shape[0]):
                if (occupied[m, 0] >= sensor_x) == (group == 0):
                    if (sensor_inside and corner[0] <= occupied[m, 0] < corner[0] + dims[0]
                            and corner[1] <= occupied[m, 1] < corner[1] + dims[1]):
                        _count_ray_inside(sensor, occupied[m], weights[m], through[m], corner, dims, flat_counts,
                                          flat_plane, group == 1)
                    else:
                        _count_ray(sensor, occupied[m], weights[m], through[m], corner, dims, counts,
                                   -1 if group == 0 else shared_x, shared_plane)
