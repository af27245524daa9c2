"""Simulated Velodyne HDL-64E and the compiled geometric kernels (numba).

Beam model: 64 lasers, an upper block of 32 from +2.0 to -8.33 deg (about 1/3 deg apart) and
a lower block of 32 from -8.83 to -24.9 deg (about 1/2 deg apart), as on the real sensor,
each with a small fixed calibration offset; ``azimuth_steps`` columns per revolution. Rays are
cast exactly against the ground plane (z = 0) and the scene's primitives, walking the 2D grid
of cells outward from the sensor (Amanatides-Woo), so a ray only tests primitives near its
path. Porous primitives (foliage, mesh fences) are hit at a random depth or passed through.

All kernels are cached (``convbki_core.compiled``: the first run in a fresh environment compiles
them, which takes a while; later runs load them from numba's cache). Frames: ray directions are
given in the scene frame; the sensor frame only matters to ``Beams`` and the ego-body mask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from convbki_core.compiled import HAVE_NUMBA

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange
else:  # pragma: no cover - exercised only without numba

    def njit(**options):  # stand-in decorator: the kernels are never called without numba
        return lambda function: function

    prange = range


class MissingDependency(RuntimeError):
    """numba is not installed."""


def require_numba() -> None:
    """Raise a one-line, actionable error when numba is missing."""
    if not HAVE_NUMBA:
        raise MissingDependency(
            "the synthetic LiDAR needs numba, which is not installed; install the pinned version with "
            "`.venv/bin/pip install -r requirements.txt` (numba==0.68.1)")


UPPER_BLOCK = (2.0, -8.33)  # deg, first and last of the upper 32 lasers
LOWER_BLOCK = (-8.83, -24.9)  # deg
EGO_BOXES = (  # the ego car in the sensor frame (x forward, z up; sensor 1.73 m over the ground), m
    (-2.75, 1.95, -0.9, 0.9, -1.75, -0.72),  # body, 1.0 m high, bonnet and boot
    (-1.3, 0.2, -0.6, 0.6, -0.73, -0.33),  # roof (narrow, so the lowest beams clear it sideways), 1.4 m up
)


@dataclass
class Beams:
    """Ray directions of one revolution in the sensor frame, beam-major (row = laser)."""

    elevation: np.ndarray  # (B,) rad, top laser first
    azimuth: np.ndarray  # (A,) rad
    dirs: np.ndarray  # (B*A, 3) unit vectors
    ego: np.ndarray  # (B*A,) bool: the ray hits the ego car's own body (never returned)

    @classmethod
    def hdl64(cls, beams: int = 64, azimuth_steps: int = 2048, seed: int = 0) -> Beams:
        """``beams`` lasers chosen evenly from the 64 (all when 64), ``azimuth_steps`` columns."""
        table = np.deg2rad(np.concatenate([np.linspace(*UPPER_BLOCK, 32), np.linspace(*LOWER_BLOCK, 32)]))
        rng = np.random.default_rng([seed, 0xBEA5])
        # Per-laser calibration residuals: elevation and azimuth offsets of a few hundredths of a degree.
        table = table + np.deg2rad(rng.normal(0, 0.02, 64))
        az_offset = np.deg2rad(rng.normal(0, 0.05, 64))
        pick = np.unique(np.round(np.linspace(0, 63, beams)).astype(int))
        elevation = table[pick]
        azimuth = np.arange(azimuth_steps) * (2 * np.pi / azimuth_steps)
        az = azimuth[None, :] + az_offset[pick][:, None]
        el = np.broadcast_to(elevation[:, None], az.shape)
        dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
        return cls(elevation, azimuth, dirs, _ego_mask(dirs))


def _ego_mask(dirs: np.ndarray) -> np.ndarray:
    """Rays from the sensor origin that hit one of EGO_BOXES (slab test)."""
    hit = np.zeros(len(dirs), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for box in EGO_BOXES:
            lo, hi = np.array(box[0::2]), np.array(box[1::2])
            t1, t2 = lo / dirs, hi / dirs
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            hit |= (far >= np.maximum(near, 0)) & (far > 0)
    return hit


# ---- hashing: deterministic uniforms tied to integers (world cells, parts, rays) ----------------
@njit(inline="always")
def _mix(h):
    """splitmix64 finaliser."""
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


@njit(inline="always")
def _hash4(a, b, c, d):
    h = _mix(np.uint64(a) + np.uint64(0x9E3779B97F4A7C15))
    h = _mix(h ^ np.uint64(b))
    h = _mix(h ^ np.uint64(c))
    return _mix(h ^ np.uint64(d))


@njit(inline="always")
def _unit(h):
    """uint64 -> float in (0, 1)."""
    return ((h >> np.uint64(11)) + np.uint64(1)) * (1.0 / 9007199254740994.0)


@njit(parallel=True)
def hash_uniform(salt, a, b, c):
    """Uniforms in (0, 1) from integer triples (int64 arrays of one length) and a salt."""
    out = np.empty(a.shape[0], np.float64)
    for i in prange(a.shape[0]):
        out[i] = _unit(_hash4(salt, a[i], b[i], c[i]))
    return out


# ---- ray-primitive intersection ------------------------------------------------------------------
@njit(inline="always")
def _intersect(kind, p, ox, oy, oz, dx, dy, dz):
    """(t_enter, t_exit, nx, ny, nz) of a ray and a primitive; t_enter = inf when missed.

    The normal is the outward normal where the ray enters.
    """
    inf = np.inf
    px, py, pz = ox - p[0], oy - p[1], oz - p[2]
    if kind == 1:  # vertical cylinder
        r, hz = p[3], p[5]
        a = dx * dx + dy * dy
        bq = px * dx + py * dy
        cq = px * px + py * py - r * r
        disc = bq * bq - a * cq
        if disc < 0.0 or a < 1e-12:
            return inf, inf, 0.0, 0.0, 0.0
        sq = math.sqrt(disc)
        t0, t1 = (-bq - sq) / a, (-bq + sq) / a
        z0 = pz + t0 * dz
        if abs(z0) <= hz:
            hx, hy = px + t0 * dx, py + t0 * dy
            return t0, t1, hx / r, hy / r, 0.0
        # Through a cap: only when the ray crosses the cap plane inside the side interval.
        if abs(dz) > 1e-12:
            cap = hz if z0 > hz else -hz
            tc = (cap - pz) / dz
            if t0 <= tc <= t1:
                return tc, t1, 0.0, 0.0, 1.0 if cap > 0 else -1.0
        return inf, inf, 0.0, 0.0, 0.0
    c, s = p[6], p[7]
    lx, ly, lz = c * px + s * py, -s * px + c * py, pz
    ex, ey, ez = c * dx + s * dy, -s * dx + c * dy, dz
    if kind == 0:  # box, slab test in its own frame
        t0, t1 = -inf, inf
        axis, sign = -1, 0.0
        for k in range(3):
            lo = lx if k == 0 else (ly if k == 1 else lz)
            de = ex if k == 0 else (ey if k == 1 else ez)
            h = p[3 + k]
            if abs(de) < 1e-12:
                if abs(lo) > h:
                    return inf, inf, 0.0, 0.0, 0.0
                continue
            ta, tb = (-h - lo) / de, (h - lo) / de
            sg = -1.0
            if ta > tb:
                ta, tb = tb, ta
                sg = 1.0
            if ta > t0:
                t0, axis, sign = ta, k, sg
            if tb < t1:
                t1 = tb
        if t0 > t1 or axis < 0:
            return inf, inf, 0.0, 0.0, 0.0
        if axis == 0:
            return t0, t1, sign * c, sign * s, 0.0
        if axis == 1:
            return t0, t1, -sign * s, sign * c, 0.0
        return t0, t1, 0.0, 0.0, sign
    # ellipsoid: unit sphere after scaling by the radii
    rx, ry, rz = p[3], p[4], p[5]
    qx, qy, qz = lx / rx, ly / ry, lz / rz
    fx, fy, fz = ex / rx, ey / ry, ez / rz
    a = fx * fx + fy * fy + fz * fz
    bq = qx * fx + qy * fy + qz * fz
    cq = qx * qx + qy * qy + qz * qz - 1.0
    disc = bq * bq - a * cq
    if disc < 0.0:
        return inf, inf, 0.0, 0.0, 0.0
    sq = math.sqrt(disc)
    t0, t1 = (-bq - sq) / a, (-bq + sq) / a
    gx, gy, gz = (lx + t0 * ex) / (rx * rx), (ly + t0 * ey) / (ry * ry), (lz + t0 * ez) / (rz * rz)
    norm = math.sqrt(gx * gx + gy * gy + gz * gz) + 1e-12
    gx, gy, gz = gx / norm, gy / norm, gz / norm
    return t0, t1, c * gx - s * gy, s * gx + c * gy, gz


@njit(parallel=True)
def cast_rays(origin, dirs, max_range, salt, kinds, params, cell_start, cell_items, gx0, gy0, cell, gnx, gny):
    """Nearest hit of each ray from ``origin`` (3,) along ``dirs`` (R, 3) (scene frame).

    Returns range t (R,) float64 (inf: no hit within ``max_range``), primitive index (R,) int32
    (-1: the ground plane, -2: nothing) and cos of the incidence angle (R,) float32.
    """
    n = dirs.shape[0]
    out_t = np.full(n, np.inf)
    out_p = np.full(n, -2, np.int32)
    out_c = np.zeros(n, np.float32)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in prange(n):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        best, bp, bc = max_range, -2, 0.0
        if dz < -1e-9:
            tg = -oz / dz
            if tg < best:
                best, bp, bc = tg, -1, -dz
        # Grid walk over the ray's 2D shadow.
        fx, fy = (ox - gx0) / cell, (oy - gy0) / cell
        ix, iy = math.floor(fx), math.floor(fy)
        hxy = math.sqrt(dx * dx + dy * dy)
        if hxy < 1e-9:
            continue
        if dx > 0:
            step_x, t_x, dt_x = 1, (ix + 1 - fx) * cell / dx, cell / dx
        elif dx < 0:
            step_x, t_x, dt_x = -1, (fx - ix) * cell / -dx, cell / -dx
        else:
            step_x, t_x, dt_x = 0, np.inf, np.inf
        if dy > 0:
            step_y, t_y, dt_y = 1, (iy + 1 - fy) * cell / dy, cell / dy
        elif dy < 0:
            step_y, t_y, dt_y = -1, (fy - iy) * cell / -dy, cell / -dy
        else:
            step_y, t_y, dt_y = 0, np.inf, np.inf
        while True:
            if 0 <= ix < gnx and 0 <= iy < gny:
                c = iy * gnx + ix
                for k in range(cell_start[c], cell_start[c + 1]):
                    q = cell_items[k]
                    t0, t1, nx, ny, nz = _intersect(kinds[q], params[q], ox, oy, oz, dx, dy, dz)
                    if t0 >= best or t1 <= 0.0:
                        continue
                    t0 = max(t0, 0.0)
                    mfp = params[q, 8]
                    if mfp > 0.0:
                        depth = -mfp * math.log(_unit(_hash4(salt, i, q, 7)))
                        if t0 + depth > t1:
                            continue  # the beam found a gap in the foliage / mesh
                        t0 += depth
                        if t0 >= best:
                            continue
                    best, bp = t0, q
                    bc = abs(nx * dx + ny * dy + nz * dz)
            t_exit = min(t_x, t_y)
            if best <= t_exit or t_exit >= max_range:
                break
            if t_x < t_y:
                t_x += dt_x
                ix += step_x
            else:
                t_y += dt_y
                iy += step_y
            if (ix < 0 and step_x <= 0) or (ix >= gnx and step_x >= 0) or (iy < 0 and step_y <= 0) or (
                    iy >= gny and step_y >= 0):
                break
        if bp != -2:
            out_t[i], out_p[i], out_c[i] = best, bp, bc
    return out_t, out_p, out_c


# ---- neighbour queries for the boundary-blur part of the noise model --------------------------------
@njit(parallel=True)
def raster_neighbours_kernel(top, offsets_y, offsets_x, offsets_d):
    """For each cell: the nearest different class among ``offsets`` (sorted by distance)."""
    ny, nx = top.shape
    nb_class = np.full((ny, nx), -1, np.int8)
    nb_dist = np.full((ny, nx), np.inf, np.float32)
    for iy in prange(ny):
        for ix in range(nx):
            own = top[iy, ix]
            for k in range(offsets_d.shape[0]):
                jy, jx = iy + offsets_y[k], ix + offsets_x[k]
                if 0 <= jy < ny and 0 <= jx < nx and top[jy, jx] != own:
                    nb_class[iy, ix] = top[jy, jx]
                    nb_dist[iy, ix] = offsets_d[k]
                    break
    return nb_class, nb_dist


def raster_neighbours(top: np.ndarray, res: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest other class (int8, -1 none) and its distance (float32, m) within ``radius``."""
    require_numba()
    r = math.ceil(radius / res)
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
    d = np.hypot(oy, ox) * res
    keep = (d > 0) & (d <= radius + 1e-9)
    order = np.argsort(d[keep], kind="stable")
    return raster_neighbours_kernel(top, oy[keep][order].astype(np.int64), ox[keep][order].astype(np.int64),
                                    d[keep][order].astype(np.float32))


@njit(inline="always")
def _sdf(kind, p, x, y, z):
    """Distance (m) from a point to a primitive's surface when outside, 0 inside (ellipsoids approximate)."""
    px, py, pz = x - p[0], y - p[1], z - p[2]
    if kind == 1:
        dr = max(math.sqrt(px * px + py * py) - p[3], 0.0)
        dh = max(abs(pz) - p[5], 0.0)
        return math.sqrt(dr * dr + dh * dh)
    c, s = p[6], p[7]
    lx, ly = c * px + s * py, -s * px + c * py
    if kind == 0:
        qx, qy, qz = max(abs(lx) - p[3], 0.0), max(abs(ly) - p[4], 0.0), max(abs(pz) - p[5], 0.0)
        return math.sqrt(qx * qx + qy * qy + qz * qz)
    k0 = math.sqrt((lx / p[3]) ** 2 + (ly / p[4]) ** 2 + (pz / p[5]) ** 2)
    if k0 <= 1.0:
        return 0.0
    k1 = math.sqrt((lx / p[3] ** 2) ** 2 + (ly / p[4] ** 2) ** 2 + (pz / p[5] ** 2) ** 2)
    return k0 * (k0 - 1.0) / k1


@njit(parallel=True)
def neighbour_query(points, point_class, kinds, params, prim_class, cell_start, cell_items, gx0, gy0, cell, gnx,
                    gny, top, nb_class, nb_dist, rx0, ry0, res, width):
    """Nearest surface of another class within ``width`` of each point (scene frame).

    Looks at primitives listed in the point's grid cell (they are listed with a margin >= width)
    and at the ground raster: the class seen from above at the point's (x, y) with the point's
    height as distance, or that raster's nearest other class. Returns (class int8, -1 none;
    distance float32, m).
    """
    n = points.shape[0]
    out_c = np.full(n, -1, np.int8)
    out_d = np.full(n, np.inf, np.float32)
    ny, nx = top.shape
    for i in prange(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        own = point_class[i]
        best, bc = width, -1
        jx, jy = int((x - rx0) / res), int((y - ry0) / res)
        if 0 <= jx < nx and 0 <= jy < ny:
            below = top[jy, jx]
            hz = max(z, 0.0)
            if below != own:
                if hz < best:
                    best, bc = hz, below
            elif nb_class[jy, jx] >= 0:
                d = math.sqrt(hz * hz + nb_dist[jy, jx] ** 2)
                if d < best:
                    best, bc = d, nb_class[jy, jx]
        ix, iy = math.floor((x - gx0) / cell), math.floor((y - gy0) / cell)
        if 0 <= ix < gnx and 0 <= iy < gny:
            c = iy * gnx + ix
            for k in range(cell_start[c], cell_start[c + 1]):
                q = cell_items[k]
                if prim_class[q] == own:
                    continue
                d = _sdf(kinds[q], params[q], x, y, z)
                if d < best:
                    best, bc = d, prim_class[q]
        if bc >= 0:
            out_c[i], out_d[i] = bc, best
    return out_c, out_d


@njit(parallel=True)
def blob_field(points, scale, salt):
    """Persistent error blobs: spheres of radius 0.35-0.85 * ``scale`` (m), one per cubic cell of
    edge ``scale``, centred at a random place in the cell, each with an activation draw.

    Returns, per point, the smallest activation of the blobs that contain it (1.0: none) and a
    second uniform of that blob (which wrong class it shows). Thresholding the activation at a
    rate p marks whole blobs, the same for every scan that sees them.
    """
    n = points.shape[0]
    m = np.ones(n, np.float32)
    v = np.zeros(n, np.float32)
    for i in prange(n):
        x, y, z = points[i, 0] / scale, points[i, 1] / scale, points[i, 2] / scale
        cx, cy, cz = math.floor(x), math.floor(y), math.floor(z)
        for ax in range(cx - 1, cx + 2):
            for ay in range(cy - 1, cy + 2):
                for az in range(cz - 1, cz + 2):
                    h = _hash4(salt, ax, ay, az)
                    u0 = _unit(h)
                    if u0 >= m[i]:
                        continue
                    h1 = _mix(h ^ np.uint64(1))
                    h2 = _mix(h ^ np.uint64(2))
                    h3 = _mix(h ^ np.uint64(3))
                    h4 = _mix(h ^ np.uint64(4))
                    bx, by, bz = ax + _unit(h1), ay + _unit(h2), az + _unit(h3)
                    r = 0.35 + 0.5 * _unit(h4)
                    if (x - bx) ** 2 + (y - by) ** 2 + (z - bz) ** 2 < r * r:
                        m[i] = u0
                        v[i] = _unit(_mix(h ^ np.uint64(5)))
    return m, v
