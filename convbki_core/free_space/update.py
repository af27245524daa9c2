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
  Which voxels hold the surface is kept in the window's mask (``ground``).

Where the rays first find a voxel empty, its concentrations are clamped to a bounded sum
(``clamping``), so that a mover that stood long can be emptied by a bounded number of rays.

Rays (``scan_rays``): returns that fall into the same voxel share one ray, from the sensor to
that voxel's centre, weighted by their number (the evidence sum of the voxel: one per labelled
point); octomap's discretised insertion does the same. Each ray is walked voxel by voxel (the
Amanatides-Woo traversal, ``ray_walk``). Returns beyond the window (far, or above or below it)
still say that the window's part of their ray is empty: they share rays by the boundary voxel
where they leave the window, which those rays cross too.

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
from convbki_core.free_space.ground import _set_ground, ground_marks
from convbki_core.free_space.ray_walk import _walk_ray
from convbki_core.memory.column_classes import class_bits
from convbki_core.memory.window import CHANGED, EVIDENCE, GROUND, RECLASSED, TOUCHED

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
    from convbki_core.free_space.ground import _derive_ground
    from convbki_core.free_space.ray_walk import _count_rays

    # Bytes, so that the mask's update stays in bytes and vectorises.
    _CHANGED_BYTE = np.uint8(CHANGED)
    _CHECK_BYTES = np.uint8(CHANGED | _CHECK)
    _NO_BYTE = np.uint8(0)
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
    window as in ``inference.update.scatter_update``: voxels with ``TOUCHED`` in ``mask`` received
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


if HAVE_NUMBA:

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
