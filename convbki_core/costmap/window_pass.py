"""The costmap read in place from the dense torus window: one compiled pass over its columns.

``window_grid`` computes, from a ``RollingWindow``'s arrays and without gathering its voxels,
the grid that ``rasterise(column_costs(...))`` gives of the same voxels (``columns``' rules,
in the same float64 arithmetic): each column's voxel costs, ground and cell in a first pass,
then the few columns whose ground is hidden from their neighbours'. It reads only the class
runs that the window's ``classes_by_column`` says may hold more than the prior, and only the
columns a region asks for. ``grid_of_window`` picks the pass for a mapper's window: this one
where its arrays are in host memory, ``device``'s where they are on a GPU.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.costmap.columns import (
    _COSTLY,
    _COSTLY_COST,
    _COSTLY_GROUND,
    _EMPTY_ONLY,
    _EMPTY_SUM,
    _FREE,
    _FREE_GROUND,
    _GROUND_SUM,
    _NO_GROUND,
    _ONLY_TOTAL,
    _TOTAL,
    EMPTY_SHARE,
    GROUND_SHARE,
    MOMENTS,
    NEIGHBOUR_PASSES,
    UNKNOWN,
    _class_codes,
    _ground_near,
    _lethal_prior,
    _moment_weights,
    _prior_moments,
    column_costs,
)
from convbki_core.costmap.grid import CostGrid, _cropped, columns_to_read, rasterise
from convbki_core.costmap.profile import LETHAL, TraversabilityProfile
from convbki_core.memory.window import EVIDENCE, gather_window

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange


def _gathered_grid(indices: np.ndarray, alpha: np.ndarray, origin: np.ndarray, dims: np.ndarray, resolution: float,
                   profile: TraversabilityProfile, prior: float) -> CostGrid:
    """The grid of a window's gathered voxels over its footprint (``window_grid``'s rules the slow way)."""
    return rasterise(column_costs(indices, alpha, resolution, profile, prior), resolution,
                     np.asarray(origin[:2], np.int64), (int(dims[0]), int(dims[1])))


def grid_of_window(window, resolution: float, profile: TraversabilityProfile, prior: float,
                   region: tuple | None = None) -> CostGrid:
    """``window_grid`` of a mapper's window (``RollingWindow`` or ``TorchWindow``) over its
    footprint, or over ``region`` (origin cell (2,), (width, height) cells) only: read in place
    where its arrays are in host memory (numpy, or torch on the CPU), skipping the class runs
    its ``classes_by_column`` says hold the prior; computed on the device where they are on a
    GPU (``device``: the same cells, only the grid comes back)."""
    alpha, mask = window.alpha, window.mask
    if not isinstance(alpha, np.ndarray):
        if alpha.device.type != "cpu":
            from convbki_core.costmap.device import device_window_grid  # imports torch: only for a GPU window

            return device_window_grid(alpha, mask, window.origin, resolution, profile, prior, region)
        alpha, mask = alpha.numpy(), mask.numpy()
    return window_grid(alpha, mask, window.origin, window.dims, resolution, profile, prior,
                       window.classes_by_column(), region)


def window_grid(alpha: np.ndarray, mask: np.ndarray, origin: np.ndarray, dims: np.ndarray, resolution: float,
                profile: TraversabilityProfile, prior: float, classes: np.ndarray | None = None,
                region: tuple | None = None) -> CostGrid:
    """The costs of the dense torus window's columns (``RollingWindow``'s ``alpha`` (C, X, Y, Z),
    ``mask``, ``origin``, ``dims``) over its footprint: equal to ``rasterise(column_costs(
    *window.items(), ...))`` on that footprint, without gathering the voxels. ``classes``
    (X, Y) uint64, the window's ``classes_by_column``: the class runs of a column whose bit is
    clear hold the prior and are not read; None: every run is read. ``region`` (origin cell
    (2,), (width, height) cells): only that part, equal to ``crop`` of the footprint's grid,
    reading only its columns and the NEIGHBOUR_PASSES around them that a hidden ground's
    estimate depends on (a rolling costmap smaller than the window costs its share of it).

    One compiled pass over the columns computes each column's voxel costs and ground, and the
    cell of every column whose ground it saw, and keeps the voxel costs of the columns whose
    ground is hidden (a few of them); a second pass gives those their neighbours' ground and
    their cells, without reading the window again."""
    origin = np.asarray(origin, np.int64)
    if not HAVE_NUMBA:  # the same rules, through the voxels gathered
        return _cropped(_gathered_grid(*gather_window(alpha, mask.copy(), origin, dims), origin, dims, resolution,
                                       profile, prior), region)
    size_x, size_y = mask.shape[:2]
    partial = region is not None
    inner_low, inner_high, low, high = columns_to_read(origin, (size_x, size_y), region)
    dims = np.asarray(dims, np.int64)
    read_all = classes is None
    if read_all:
        classes = np.zeros((size_x, size_y), np.uint64)
    weights = _moment_weights(profile)
    codes = _class_codes(weights)
    rules = np.array([float(resolution), profile.min_obstacle_height, profile.robot_height, profile.min_evidence,
                      profile.risk_sigma, float(prior) * alpha.shape[0], _lethal_prior(profile, prior)])
    base = _prior_moments(weights, prior)
    # In global order: row y of the grid is the column at origin + y (the torus unrolled).
    # Every cell is written when every column is read; a region leaves the rest unknown.
    values = np.full((size_y, size_x), UNKNOWN, np.int8) if partial else np.empty((size_y, size_x), np.int8)
    top = np.empty((size_x, size_y), np.int64)
    # Where the voxel costs of a hidden column are kept, or -1.
    hidden = np.full((size_x, size_y), -1, np.int64) if partial else np.empty((size_x, size_y), np.int64)
    ground_z = np.empty((size_x, size_y), np.int64)  # filled where ``hidden``
    # Room for every column of a row, but a row fills only as many slots as it has hidden
    # columns, and only the pages written are ever mapped.
    kept_risk = np.empty((size_x * size_y, mask.shape[2]))
    kept_kind = np.empty((size_x * size_y, mask.shape[2]), np.uint8)
    with parallel_region():
        _grounded_columns(alpha, mask, origin, dims, codes, weights, np.float32(prior), base, rules, classes,
                          read_all, low, high, values, top, hidden, ground_z, kept_risk, kept_kind)
    # The inner columns' hidden grounds only: the margin's would need neighbours not read.
    inner = hidden[inner_low[0]:inner_high[0], inner_low[1]:inner_high[1]]
    # C order whatever the count (argwhere's is F for two cells or more): one compiled signature.
    cells = np.ascontiguousarray(np.argwhere(inner >= 0) + inner_low, np.int64)
    if len(cells):
        with parallel_region():
            _hidden_columns(origin, rules, cells, top, ground_z, hidden, kept_risk, kept_kind, values)
    return _cropped(CostGrid(origin[:2].copy(), values, float(resolution)), region)


_NO_VOXEL = np.iinfo(np.int64).max
_EVIDENT, _GROUND, _EMPTY = 1, 2, 4
_TINY = np.finfo(np.float64).tiny
# The profile's numbers as the compiled passes take them (one float64 array).
_RESOLUTION, _MIN_HEIGHT, _ROBOT_HEIGHT, _MIN_EVIDENCE, _RISK_SIGMA, _PRIOR_TOTAL, _LETHAL_PRIOR = range(7)

if HAVE_NUMBA:

    @njit(nogil=True, inline="always")
    def _column_evident(mask, x, y, kind):  # pragma: no cover - compiled
        """Whether the column holds a voxel with evidence; clears ``kind``."""
        evident = False
        for z in range(mask.shape[2]):
            kind[z] = 0
            evident |= (mask[x, y, z] & EVIDENCE) != 0
        return evident

    @njit(nogil=True, inline="always")
    def _add_run(alpha, c, x, y, read_all, codes, weights, prior, sums):  # pragma: no cover - compiled
        """Class c's run of the column into its moment ``sums`` (MOMENTS, Z), as ``_row_moments``
        adds it (nothing where it holds the prior), to the moments it has a weight in only
        (``_class_codes``: one loop per common set of them, each vectorised)."""
        size_z = alpha.shape[3]
        if read_all:
            held = False
            for z in range(size_z):
                held |= alpha[c, x, y, z] != prior
            if not held:
                return
        prior64 = np.float64(prior)
        code = codes[c]
        if code == _ONLY_TOTAL:
            for z in range(size_z):
                sums[_TOTAL, z] += np.float64(alpha[c, x, y, z]) - prior64
        elif code == _FREE_GROUND:
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[_TOTAL, z] += value
                sums[_FREE, z] += value
                sums[_GROUND_SUM, z] += value
        elif code == _COSTLY_GROUND:
            cost = weights[_COSTLY_COST, c]
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[_TOTAL, z] += value
                sums[_COSTLY, z] += value
                sums[_COSTLY_COST, z] += value * cost
                sums[_GROUND_SUM, z] += value
        elif code == _EMPTY_ONLY:
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[_TOTAL, z] += value
                sums[_EMPTY_SUM, z] += value
        else:
            w0, w1, w2 = weights[0, c], weights[1, c], weights[2, c]
            w3, w4, w5 = weights[3, c], weights[4, c], weights[5, c]
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[0, z] += value * w0
                sums[1, z] += value * w1
                sums[2, z] += value * w2
                sums[3, z] += value * w3
                sums[4, z] += value * w4
                sums[5, z] += value * w5

    @njit(nogil=True, inline="always")
    def _reads_class(c, runs, read_all):  # pragma: no cover - compiled
        """Whether class c's run of a column with the class bits ``runs`` is read: class 0
        (empty space) always, as free space adds it without a bit."""
        return read_all or c == 0 or ((runs >> np.uint64(c)) & np.uint64(1)) != 0

    @njit(nogil=True, inline="always")
    def _voxel_cost(free, costly, costly_cost, occupied, rules):  # pragma: no cover - compiled
        """``_voxel_risks``' cost of one occupied voxel from its moments."""
        lethal = max(occupied - free - costly, 0.0)
        lethal_share = min(lethal / occupied, 1.0)
        if free / occupied > 0.5:
            kind_cost = 0.0
        elif lethal_share < 0.5:
            kind_cost = costly_cost / max(costly, _TINY)
        else:
            kind_cost = np.float64(LETHAL)
        evidence = min(max((lethal - rules[_LETHAL_PRIOR]) / occupied, 0.0), 1.0)
        margin = LETHAL * (evidence + rules[_RISK_SIGMA] * np.sqrt(evidence * (1.0 - evidence) / (occupied + 1.0)))
        return min(max(max(kind_cost, margin), 0.0), 100.0)

    @njit(nogil=True, inline="always")
    def _column_kinds(sums, mask, x, y, origin, dims, rules, risk, kind):  # pragma: no cover - compiled
        """One column's voxels (physical x, y) from their moment ``sums`` (MOMENTS, Z by physical z):
        per step up the window (global z = origin z + step) its risk and kind bits
        (``_voxel_risks``' rules) into ``risk``, ``kind``; returns (its ground voxel's global z
        by ``column_costs``' rule, its lowest voxel's, whether it holds an occupied voxel that
        is not ground)."""
        size_z = mask.shape[2]
        ground_below = _NO_GROUND  # the highest ground voxel under the first obstacle
        ground_any = _NO_GROUND
        obstacle_seen = False
        low = _NO_VOXEL
        z = origin[2] % dims[2] - 1  # the physical z of each step, without a division per voxel
        for step in range(size_z):
            global_z = origin[2] + step
            z = z + 1 if z + 1 < size_z else 0
            if (mask[x, y, z] & EVIDENCE) == 0:
                continue
            total, empty = sums[_TOTAL, z], sums[_EMPTY_SUM, z]
            if not total - rules[_PRIOR_TOTAL] >= rules[_MIN_EVIDENCE]:
                continue
            low = min(low, global_z)
            if empty / total > EMPTY_SHARE:
                risk[step] = 0.0
                kind[step] = _EVIDENT | _EMPTY
                continue
            occupied = max(total - empty, _TINY)
            risk[step] = _voxel_cost(sums[_FREE, z], sums[_COSTLY, z], sums[_COSTLY_COST, z], occupied, rules)
            if sums[_GROUND_SUM, z] / occupied > GROUND_SHARE:
                kind[step] = _EVIDENT | _GROUND
                ground_any = global_z
                if not obstacle_seen:
                    ground_below = global_z
            else:
                kind[step] = _EVIDENT
                obstacle_seen = True
        return (ground_below if ground_below != _NO_GROUND else ground_any), low, obstacle_seen

    @njit(nogil=True, inline="always")
    def _column_voxels(alpha, mask, x, y, origin, dims, codes, weights, prior, base, rules, runs, read_all, sums,
                       risk,
                       kind):  # pragma: no cover - compiled
        """``_column_kinds`` of one column read on its own (``runs``: its class bits)."""
        if not _column_evident(mask, x, y, kind):
            return _NO_GROUND, _NO_VOXEL, False
        # Class by class along z: a class's run of the column is contiguous in memory, where the
        # classes of one voxel lie a whole class plane apart. A run at the prior adds nothing and
        # is skipped: most classes of a column hold no evidence.
        for k in range(MOMENTS):
            sums[k, :] = base[k]
        for c in range(alpha.shape[0]):
            if _reads_class(c, runs, read_all):
                _add_run(alpha, c, x, y, read_all, codes, weights, prior, sums)
        return _column_kinds(sums, mask, x, y, origin, dims, rules, risk, kind)

    @njit(nogil=True, inline="always")
    def _column_value(risk, kind, origin_z, ground, rules):  # pragma: no cover - compiled
        """The cell of a column whose ground is at global z ``ground``: the most costly of its
        ground voxel and its band voxels, -1 unless something non-empty is in the band or its
        ground was seen."""
        cost = -np.inf
        observed = False
        for step in range(kind.shape[0]):
            bits = kind[step]
            if bits == 0:
                continue
            global_z = origin_z + step
            above = (global_z - ground) * rules[_RESOLUTION]
            in_band = above >= rules[_MIN_HEIGHT] - 1e-9 and above <= rules[_ROBOT_HEIGHT] + 1e-9
            surface = (bits & _GROUND) != 0 and global_z == ground
            if in_band or surface:
                cost = max(cost, risk[step])
                if surface or (bits & _EMPTY) == 0:
                    observed = True
        return np.int8(np.rint(min(max(cost, 0.0), 100.0))) if observed else np.int8(-1)

    @njit(parallel=True, nogil=True)
    def _grounded_columns(alpha, mask, origin, dims, codes, weights, prior, base, rules, classes, read_all, low,
                          high, values, top, hidden, ground_z, kept_risk,
                          kept_kind):  # pragma: no cover - compiled
        """Every column from ``low`` to ``high`` (x, y in global order, ``high`` excluded): its
        ground voxel into ``top``, its cell into ``values`` where it saw its own ground or holds
        no obstacle (then its ground does not matter); a hidden-ground column with an obstacle
        keeps its voxel costs (``_column_kinds``' ``risk`` and ``kind``) in a row of
        ``kept_risk``, ``kept_kind`` (the first free one of its x's ``size_y`` rows), whose
        number goes into ``hidden`` (-1 for the others), and the height under its lowest voxel
        into ``ground_z`` (for when no neighbour has ground); all in global order."""
        size_x, size_y, size_z = mask.shape
        for column_x in prange(low[0], high[0]):
            sums = np.empty((MOMENTS, size_z))  # the column's moments per physical z
            risk = np.empty(size_z)
            kind = np.empty(size_z, np.uint8)
            kept = column_x * size_y  # the next free row of this x's share of the kept costs
            x = (column_x + origin[0]) % size_x
            y = (low[1] + origin[1]) % size_y - 1
            for column_y in range(low[1], high[1]):
                y = y + 1 if y + 1 < size_y else 0
                ground, lowest, obstacle = _column_voxels(alpha, mask, x, y, origin, dims, codes, weights, prior,
                                                          base, rules, classes[x, y], read_all, sums, risk, kind)
                top[column_x, column_y] = ground
                hidden[column_x, column_y] = -1
                if ground != _NO_GROUND:
                    values[column_y, column_x] = _column_value(risk, kind, origin[2], ground, rules)
                else:  # nothing seen or only empty space, or hidden: its cell comes in the second pass
                    values[column_y, column_x] = -1
                    ground_z[column_x, column_y] = lowest - 1
                    if obstacle:
                        kept_risk[kept, :] = risk
                        kept_kind[kept, :] = kind
                        hidden[column_x, column_y] = kept
                        kept += 1

    @njit(parallel=True, nogil=True)
    def _hidden_columns(origin, rules, cells, top, ground_z, hidden, kept_risk, kept_kind,
                        values):  # pragma: no cover - compiled
        """The columns at global-order ``cells`` (n, 2), whose ground is hidden: the ground from
        their neighbours' (``top``, global order), or ``ground_z`` (under their lowest voxel)
        where none is near; their cells, from the voxel costs the first pass kept (row
        ``hidden`` of ``kept_risk``, ``kept_kind``), into ``values``."""
        count = cells.shape[0]
        chunk = 256
        side = 2 * NEIGHBOUR_PASSES + 1
        for first in prange((count + chunk - 1) // chunk):
            patch = np.empty((side, side))
            fresh = np.empty((side, side))
            for i in range(first * chunk, min(count, (first + 1) * chunk)):
                column_x, column_y = cells[i, 0], cells[i, 1]
                estimate = _ground_near(top, column_x, column_y, patch, fresh)
                ground = ground_z[column_x, column_y] if np.isnan(estimate) else np.int64(np.rint(estimate))
                kept = hidden[column_x, column_y]
                values[column_y, column_x] = _column_value(kept_risk[kept], kept_kind[kept], origin[2], ground, rules)
