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

* A voxel that holds the ground's surface takes none either: its most likely occupied class
  (the arg-max over classes 1..C-1) is a ground class of the label map (road, parking,
  sidewalk, ...: ``ground_classes``), and its ground evidence (those classes' concentrations
  above the prior) is not below that of the voxel under it nor of the one over it. A ray that
  reaches the ground some way off runs just above it for its last metres, through the voxels
  that hold the surface between the rings of returns: those crossings say that the top of
  the voxel is empty, not that the ground has gone, and the map would otherwise lose the far
  ground it has seen. Only the surface: the kernel spreads the ground's evidence a voxel or
  two up into the air, and rays still empty those voxels (under a car that has gone they are
  the empty space the movers' support rule looks for). A mover's voxels are not ground.

Where the rays first find a voxel empty, its concentrations are clamped to a bounded sum
(``clamping``), so that a mover that stood long can be emptied by a bounded number of rays.

Which voxels hold the surface is kept as a bit of the window's mask (``GROUND``), derived
again, a column at a time, where a voxel's classes changed (``RECLASSED``: this scan's class
evidence reached it, it came back from the store, it was clamped, or the window moved along z
past its neighbour); a pass reads only the runs the window's per-column class bits say are
held (``classes_by_column``).

Rays: returns that fall into the same voxel share one ray, from the sensor to that voxel's
centre, weighted by their number (the evidence sum of the voxel: one per labelled point);
octomap's discretised insertion does the same. Each ray is walked voxel by voxel (the
Amanatides-Woo traversal). Returns beyond the window (far, or above or below it) still say
that the window's part of their ray is empty: they share rays by the boundary voxel where
they leave the window, which those rays cross too.

The compiled pass counts the rays on two cores without sharing a voxel (rays ending on either
side of the sensor's x plane), then each core adds the counts of its own x planes into the map.
The counts are kept in window order along x and y and on the torus along z: every ray of a
window around its sensor lies inside the window, so its walk moves one flat index by a fixed
stride per step and wraps only along z, and each x plane of the window meets its counts in two
long runs, which the pass adds branch-free.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.free_space.clamping import FIRST_CONTRADICTION, clamp_numpy
from convbki_core.geometry.volume import SparseVolume, unravel_linear
from convbki_core.memory.window import CHANGED, EVIDENCE, GROUND, RECLASSED, TOUCHED, class_bits

FREE_CLASS = 0
_KEEP_UNTOUCHED = 0xFF & ~TOUCHED  # the mask bits left after a scan
# A voxel takes free evidence when, of these bits, it has EVIDENCE alone.
_TAKES_TEST = EVIDENCE | TOUCHED | GROUND
# A mask bit that lives only inside one free-space pass: the voxel is to be checked for clamping.
_CHECK = 8

if HAVE_NUMBA:
    import numba

    from convbki_core.compiled import njit, prange
    from convbki_core.free_space.clamping import clamp_voxel, evidence_scale

    # Bytes, so that the mask's update stays in bytes and vectorises.
    _CHANGED_BYTE = np.uint8(CHANGED)
    _CHECK_BYTES = np.uint8(CHANGED | _CHECK)
    _NO_BYTE = np.uint8(0)
    _GROUND_BYTE = np.uint8(GROUND)
    _RECLASSED_BYTE = np.uint8(RECLASSED)


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
    weights = ray_weights(volume.features)
    beyond = beyond_window(points, pose, volume, resolution)
    origin = np.ascontiguousarray(volume.origin, np.int64)
    dims = np.ascontiguousarray(volume.dims, np.int64)
    exit_linear, rays = _unique_exits(pose[:3, 3] / resolution, beyond, origin, dims)
    linear = np.concatenate([volume.linear, exit_linear])
    through = np.zeros(len(linear), np.bool_)
    through[len(volume.linear):] = True
    ends = _unravel_numba(linear, origin, dims) if HAVE_NUMBA else unravel_linear(linear, dims) + origin
    return ends, np.concatenate([weights, rays]), through


def beyond_window(points: np.ndarray, pose: np.ndarray, volume: SparseVolume, resolution: float) -> np.ndarray:
    """The scan's returns the volume dropped (beyond the window, or not finite), in voxel units
    of the map frame: ``window_exits`` finds where their rays leave the window."""
    dropped = points[volume.point_linear < 0]
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite points are skipped by the exits
        return (dropped @ pose[:3, :3].T + pose[:3, 3]) / resolution


def ray_weights(features: np.ndarray) -> np.ndarray:
    """Rays per occupied voxel: its evidence sum (the number of labelled points in it)."""
    return np.ascontiguousarray(features.sum(axis=1, dtype=np.float32))


def free_space_update(sensor: np.ndarray, occupied: np.ndarray, weights: np.ndarray, offsets: np.ndarray,
                      tap_weights: np.ndarray, origin: np.ndarray, dims: np.ndarray, alpha: np.ndarray,
                      mask: np.ndarray, counts: np.ndarray, through: np.ndarray | None = None,
                      max_concentration: float = 0.0, prior: float = 0.0, ground_classes=(),
                      classes: np.ndarray | None = None) -> int:
    """Add one scan's free-space evidence into the torus window, in place; returns the number
    of voxels whose free concentration grew.

    ``sensor`` (3,) the sensor position in voxel units (global grid, metres / resolution);
    ``occupied`` (M, 3) int64 global indices of the voxels holding the scan's returns, with
    ``weights`` (M,) float32 rays each; ``offsets``/``tap_weights`` from ``free_taps``; the
    window as in ``update.scatter_update``: voxels with ``TOUCHED`` in ``mask`` received
    this scan's class evidence and take no free evidence; the bit is cleared here.
    ``counts``: the scratch of ``scratch_counts``. ``through`` (M,) bool: rays whose return
    lies beyond the window; they end in the window's boundary voxel ``occupied[m]``, which
    they cross too (``window_exits``). ``max_concentration``: the clamping limit of the
    voxels that take free evidence (``clamping``; 0: none), which keeps the ``prior``.
    ``ground_classes``: the classes whose voxels take none (the module's docstring; the
    ``GROUND`` bits of ``mask`` are derived here where ``RECLASSED`` is set, which is cleared);
    ``classes``: the window's ``classes_by_column``, so that only held class runs are read
    (None: every run).
    """
    occupied = np.ascontiguousarray(occupied, np.int64)
    ground_bits = class_bits(ground_classes)
    through = np.zeros(len(occupied), np.bool_) if through is None else np.ascontiguousarray(through, np.bool_)
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    sensor = np.ascontiguousarray(sensor, np.float64)
    if HAVE_NUMBA:
        with parallel_region():
            if ground_bits:
                read_all = classes is None
                _derive_ground(alpha, mask, np.zeros((1, 1), np.uint64) if read_all else classes, read_all,
                               ground_bits, np.float32(prior), int(origin[2]))
            return int(_free_space_numba(sensor, occupied, np.ascontiguousarray(weights, np.float32), through,
                                         offsets, tap_weights, origin, dims, alpha, mask, counts,
                                         float(max_concentration), float(prior), ground_bits))
    return _free_space_numpy(sensor, occupied, weights, through, offsets, tap_weights, origin, dims, alpha, mask,
                             float(max_concentration), float(prior), ground_bits)


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


def window_exits(sensor: np.ndarray, points: np.ndarray, origin: np.ndarray,
                 dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For returns beyond the window (``points`` (N, 3) in voxel units; those inside and
    those not finite are skipped): the window voxels where their rays leave it, unique, with
    the number of rays each."""
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    linear, rays = _unique_exits(sensor, points, origin, dims)
    local = np.stack(np.unravel_index(linear, tuple(int(d) for d in dims)), axis=1)
    return local + origin, rays


def _unique_exits(sensor, points, origin, dims) -> tuple[np.ndarray, np.ndarray]:
    """``window_exits`` as window-linear indices (sorted) and rays (float32)."""
    sensor = np.ascontiguousarray(sensor, np.float64)
    if HAVE_NUMBA:
        linear = _exit_linear_numba(np.ascontiguousarray(points, np.float64), sensor, origin, dims)
    else:
        linear = _exit_linear_numpy(np.asarray(points, np.float64), sensor, origin, dims)
    linear, rays = np.unique(linear, return_counts=True)
    return linear, rays.astype(np.float32)


def _exit_linear_numpy(points, sensor, origin, dims) -> np.ndarray:
    points = points[np.isfinite(points).all(axis=1)]
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


def _free_space_numpy(sensor, occupied, weights, through, offsets, tap_weights, origin, dims, alpha, mask,
                      max_concentration=0.0, prior=0.0, ground_bits=0) -> int:
    """The same pass in Python loops and numpy (the fallback without numba, and a reference):
    the ground bits derived for every voxel (the compiled pass keeps them, with the same values)."""
    if ground_bits:
        _set_ground(mask, (mask & EVIDENCE != 0) & ground_marks(alpha, ground_bits, origin[2], prior))
        mask &= np.uint8(0xFF & ~RECLASSED)
    counts = np.zeros(tuple(int(d) for d in dims), np.float64)

    def count(voxel, weight):
        counts[tuple(np.mod(voxel, dims))] += weight

    for m in range(occupied.shape[0]):
        _walk_ray(sensor, occupied[m], lambda voxel, w=float(weights[m]): count(np.array(voxel), w), bool(through[m]))
    counts = counts.astype(np.float32)
    takes = mask & _TAKES_TEST == EVIDENCE
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
    before = alpha[FREE_CLASS, x, y, z].copy()
    alpha[FREE_CLASS, x, y, z] += evidence[grew]
    scaled = clamp_numpy(alpha, (x, y, z), before, max_concentration, prior)
    mask[x, y, z] |= np.uint8(CHANGED)
    mask &= np.uint8(_KEEP_UNTOUCHED)
    if ground_bits:  # scaling changed their ground evidence: derived again in the next pass
        mask[scaled] |= np.uint8(RECLASSED)
    return int(grew.sum())


def _set_ground(mask: np.ndarray, ground: np.ndarray) -> None:
    mask[...] = np.where(ground, mask | np.uint8(GROUND), mask & np.uint8(0xFF & ~GROUND))


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

    @njit(nogil=True, inline="always")
    def _join_shared_plane(counts, sensor_x, shared_plane):  # pragma: no cover - compiled
        """The sensor plane's second counts join the rest first, and are cleared. In loops, not
        ``counts[sensor_x] += shared_plane``: numba's array expression brings a shape check
        whose error message alone takes seconds to compile."""
        for y in range(shared_plane.shape[0]):
            for z in range(shared_plane.shape[1]):
                counts[sensor_x, y, z] += shared_plane[y, z]
                shared_plane[y, z] = 0.0

    @njit(nogil=True, inline="always")
    def _apply_run(free, marks, counted, weight, clamping):  # pragma: no cover - compiled
        """``_apply_centre`` over a run of the window (``free``, ``marks``: flat runs of the
        free concentrations and the mask) and its counts; branch-free over indices from 0,
        so that it vectorises. With ``clamping``, the voxels first contradicted get the
        ``_CHECK`` bit for ``_clamp_run``. Returns (voxels grown, the last index to check + 1,
        the first index to check), so that the clamping pass reads only that stretch."""
        size = marks.shape[0]
        found = 0
        last = 0
        first = size
        for j in range(size):
            m = marks[j]
            evidence = counted[j] * weight
            grows = (m & _TAKES_TEST) == EVIDENCE and evidence > 0
            check = grows and clamping and free[j] < FIRST_CONTRADICTION
            if grows:
                free[j] += evidence
            marks[j] = (m & _KEEP_UNTOUCHED) | (_CHECK_BYTES if check else (_CHANGED_BYTE if grows else _NO_BYTE))
            counted[j] = 0.0
            found += grows
            last = max(last, j + 1 if check else 0)
            first = min(first, j if check else size)
        return found, last, first

    @njit(nogil=True)
    def _clamp_run(alpha, start, marks, limit, prior, ground_bits):  # pragma: no cover - compiled
        """Clamp the voxels of a run that ``_apply_run`` marked ``_CHECK`` (``alpha`` (C, V)
        flat planes, the run starting at flat index ``start``) and clear their bit."""
        for j in range(marks.shape[0]):
            m = marks[j]
            if m & _CHECK == 0:
                continue
            marks[j] = m & ~_CHECK
            voxel = start + j
            total = np.float32(0.0)
            for c in range(alpha.shape[0]):
                total += alpha[c, voxel]
            if total > limit:  # clamping's rule (``clamping.clamp_voxel``), on flat planes
                floor, scale = evidence_scale(total, limit, prior, alpha.shape[0])
                for c in range(alpha.shape[0]):
                    alpha[c, voxel] = floor + (alpha[c, voxel] - floor) * scale
                if ground_bits:  # its ground evidence changed: derived again in the next pass
                    marks[j] |= _RECLASSED_BYTE

    @njit(parallel=True, nogil=True)
    def _apply_centre(sensor_x, weight, origin, alpha, mask, counts, shared_plane, parts,
                      limit, prior, ground_bits):  # pragma: no cover
        """Add the counted rays as free evidence through a centre-only free kernel, each thread
        over its own x planes; clear the counts and the ``TOUCHED`` bits. ``counts`` as
        ``_count_rays`` left them with ``corner`` (origin x, origin y, 0), ``sensor_x`` the
        sensor's plane there: a plane of the window is its counts' plane in two runs, split
        where the torus wraps in y."""
        size_x, size_y, size_z = mask.shape
        _join_shared_plane(counts, sensor_x, shared_plane)
        plane = size_y * size_z
        seam = (origin[1] % size_y) * size_z  # the window's flat offset of the counts' first row
        free = alpha[FREE_CLASS].reshape(plane * size_x)
        planes = alpha.reshape(alpha.shape[0], plane * size_x)
        marks = mask.reshape(plane * size_x)
        counted = counts.reshape(plane * size_x)
        clamping = limit > 0
        grew = np.zeros(parts, np.int64)
        for part in prange(parts):
            found = 0
            for x in range(size_x * part // parts, size_x * (part + 1) // parts):
                window = x * plane
                local = ((x - origin[0]) % size_x) * plane
                runs = ((window + seam, window + plane, local), (window, window + seam, local + plane - seam))
                for begin, end, source in runs:
                    grown, last, first = _apply_run(free[begin:end], marks[begin:end],
                                                    counted[source:source + end - begin], weight, clamping)
                    if last:
                        _clamp_run(planes, begin + first, marks[begin + first:begin + last], limit, prior,
                                   ground_bits)
                    found += grown
            grew[part] = found
        return grew.sum()

    @njit(parallel=True, nogil=True)
    def _apply_counts(sensor_x, offsets, tap_weights, origin, dims, alpha, mask, counts,
                      shared_plane, parts, limit, prior, ground_bits):  # pragma: no cover - compiled
        """Add the counted rays as free evidence through a free kernel of any taps, each thread
        over its own x planes; clear the counts and the ``TOUCHED`` bits. ``counts`` and
        ``sensor_x`` as in ``_apply_centre``."""
        taps = offsets.shape[0]
        _join_shared_plane(counts, sensor_x, shared_plane)
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
                        if marks & _TAKES_TEST == EVIDENCE:
                            global_z = origin[2] + (z - origin[2]) % dims[2]
                            evidence = np.float32(0.0)
                            for t in range(taps):
                                sx = global_x - offsets[t, 0]
                                sy = global_y - offsets[t, 1]
                                sz = global_z - offsets[t, 2]
                                if (origin[0] <= sx < origin[0] + dims[0] and origin[1] <= sy < origin[1] + dims[1]
                                        and origin[2] <= sz < origin[2] + dims[2]):
                                    evidence += tap_weights[t] * counts[sx - origin[0], sy - origin[1], sz % dims[2]]
                            if evidence > 0:
                                before = alpha[FREE_CLASS, x, y, z]
                                alpha[FREE_CLASS, x, y, z] += evidence
                                marks |= CHANGED
                                if clamp_voxel(alpha, x, y, z, before, limit, prior) and ground_bits:
                                    marks |= _RECLASSED_BYTE  # derived again in the next pass
                                mask[x, y, z] = marks
                                found += 1
                        elif marks & TOUCHED != 0:
                            mask[x, y, z] = marks & _KEEP_UNTOUCHED
            grew[part] = found
        counts[:] = 0.0  # a tap reads other threads' planes: clear only after every thread has read
        return grew.sum()

    @njit(nogil=True)
    def _exit_linear_numba(points, sensor, origin, dims):  # pragma: no cover - compiled; tested against numpy
        """Window-local linear index of the voxel where each finite outside point's ray leaves
        the window."""
        out = np.empty(points.shape[0], np.int64)
        count = 0
        for i in range(points.shape[0]):
            if not (np.isfinite(points[i, 0]) and np.isfinite(points[i, 1]) and np.isfinite(points[i, 2])):
                continue
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
            linear = 0
            for axis in range(3):
                position = np.floor(sensor[axis] + (points[i, axis] - sensor[axis]) * (leave * (1 - 1e-9)))
                local = min(max(np.int64(position), origin[axis]), origin[axis] + dims[axis] - 1) - origin[axis]
                linear = linear * dims[axis] + local
            out[count] = linear
            count += 1
        return out[:count]

    @njit(nogil=True)
    def _unravel_numba(linear, origin, dims):  # pragma: no cover - compiled; the twin of unravel_linear
        """Global indices (N, 3) of window-linear indices."""
        out = np.empty((linear.shape[0], 3), np.int64)
        for i in range(linear.shape[0]):
            rest = linear[i]
            out[i, 2] = rest % dims[2] + origin[2]
            rest //= dims[2]
            out[i, 1] = rest % dims[1] + origin[1]
            out[i, 0] = rest // dims[1] + origin[0]
        return out

    def _free_space_numba(sensor, occupied, weights, through, offsets, tap_weights, origin, dims, alpha, mask,
                          counts, limit, prior, ground_bits):
        volume, shared_plane = counts
        # Counted in window order along x and y, where a window around the sensor holds every
        # ray whole, and on the torus along z, where the window's planes keep their runs long.
        corner = np.array([origin[0], origin[1], 0], np.int64)
        _count_rays(sensor, occupied, weights, through, corner, dims, volume, shared_plane)
        sensor_x = (int(np.floor(sensor[0])) - int(origin[0])) % int(dims[0])
        parts = max(1, min(numba.get_num_threads(), int(dims[0])))
        if len(offsets) == 1 and not offsets[0].any():
            return _apply_centre(sensor_x, tap_weights[0], origin, alpha, mask, volume, shared_plane, parts, limit,
                                 prior, ground_bits)
        return _apply_counts(sensor_x, offsets, tap_weights, origin, dims, alpha, mask, volume, shared_plane, parts,
                             limit, prior, ground_bits)

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
