"""The grid read in place from the dense torus window (``window_pass``): equal to the grid of its
voxels gathered, after the window moved and wrapped; a region of it equal to the crop of the
whole grid, reading only its own columns and their margin; a hidden column's ground from its
patch equal to the spread over the whole grid."""

import numpy as np
import pytest
from costmap_helpers import CAR, RESOLUTION, with_sigma

from convbki_core.config import MapperConfig
from convbki_core.costmap.columns import column_costs
from convbki_core.costmap.grid import rasterise
from convbki_core.io.labels import load_label_map


@pytest.mark.parametrize("update_path", ["fast", "torch"])
def test_the_grid_read_from_the_dense_window_equals_the_grid_of_its_voxels_gathered(update_path):
    """The node computes its rolling grid from the window's dense torus arrays in place; the same
    voxels gathered (what a saved map holds) give the same grid, cell for cell, also after the
    window moved and wrapped around its torus, with hidden ground and empty space in it."""
    from convbki_core.costmap.window_pass import grid_of_window
    from convbki_core.mapper import ConvBKIMapper
    from convbki_core.paths import kernel_path

    label_map = load_label_map("semantic_kitti")
    config = MapperConfig.paper(local_bounds=((-8, -6, -3), (8, 6, 3)), prior=0.001, device="cpu",
                                ignore_classes=label_map.ignore_classes, free_space=True, update_path=update_path)
    mapper = ConvBKIMapper(config, kernel_path("semantic_kitti_compound"))
    rng = np.random.default_rng(3)
    raw_classes = np.array([40, 48, 70, 72, 10, 50, 51, 80])  # road, sidewalk, vegetation, terrain, car, ...
    compared = 0
    for step in range(6):
        ground = np.column_stack([rng.uniform(-7, 7, (4000, 2)), rng.normal(-1.6, 0.03, 4000)])
        things = rng.uniform([-6, -5, -1.5], [6, 5, 1.5], (1500, 3))
        points = np.concatenate([ground, things]).astype(np.float32)
        raw = np.concatenate([rng.choice(raw_classes[:4], len(ground)), rng.choice(raw_classes, len(things))])
        pose = np.eye(4)
        pose[:3, 3] = [2.3 * step, -1.1 * step, 0.0]
        mapper.integrate(points, label_map.to_learning(raw.astype(np.uint32)), pose)
        window = mapper.window
        for profile in (CAR, with_sigma(CAR, 0.0)):
            dense = grid_of_window(window, RESOLUTION, profile, 0.001)
            gathered = rasterise(column_costs(*window.items(), RESOLUTION, profile, 0.001), RESOLUTION,
                                 window.origin[:2], tuple(window.dims[:2].tolist()))
            assert np.array_equal(dense.origin, gathered.origin)
            assert np.array_equal(dense.values, gathered.values), int((dense.values != gathered.values).sum())
            compared += int((dense.values >= 0).sum())
    assert (mapper.window.origin % mapper.window.dims != 0).any()  # the torus wrapped
    assert compared > 10_000


def test_a_region_of_the_window_reads_its_columns_only_and_equals_the_crop_of_the_whole_grid():
    """A rolling costmap smaller than the window reads only its own columns and the few around
    them that a hidden ground's estimate depends on; its cells are those of the whole window's
    grid cropped, at the window's edges and corners too, for a region partly or wholly outside
    it, and where columns with hidden ground (a car on the road) lie at the region's edge."""
    from convbki_core.costmap.columns import NEIGHBOUR_PASSES
    from convbki_core.costmap.grid import crop
    from convbki_core.costmap.window_pass import grid_of_window, window_grid
    from convbki_core.mapper import ConvBKIMapper
    from convbki_core.paths import kernel_path

    label_map = load_label_map("semantic_kitti")
    config = MapperConfig.paper(local_bounds=((-8, -6, -3), (8, 6, 3)), prior=0.001, device="cpu",
                                ignore_classes=label_map.ignore_classes, free_space=True)
    mapper = ConvBKIMapper(config, kernel_path("semantic_kitti_compound"))
    rng = np.random.default_rng(5)
    compared = hidden_compared = poisoned_compared = 0
    # Cars parked in the map's frame: no ground return under their bodies, so their columns'
    # ground is hidden and comes from their neighbours'.
    bodies = [(-4.0, -3.0), (1.0, 2.0), (5.0, -4.5), (9.0, -2.0)]
    # Signs over the road, above the band, with no ground return under them either: their
    # columns take the ground from their neighbours, which puts the sign above the band.
    signs = [(-1.0, 3.4), (6.0, 2.9), (3.0, -1.5)]
    hidden_cells = set()
    for step in range(4):
        pose = np.eye(4)
        pose[:3, 3] = [2.3 * step, -1.1 * step, 0.0]
        ground = np.column_stack([rng.uniform(-7, 7, (6000, 2)), rng.normal(-1.6, 0.03, 6000)])
        world = ground[:, :2] + pose[:2, 3]
        under = np.zeros(len(ground), bool)
        cars = []
        for x, y in bodies:
            under |= (np.abs(world[:, 0] - x) < 1.5) & (np.abs(world[:, 1] - y) < 1.0)
            body = np.column_stack([rng.uniform(x - 1.5, x + 1.5, 600), rng.uniform(y - 1.0, y + 1.0, 600),
                                    rng.uniform(-1.2, -0.2, 600)])
            cars.append(body - [*pose[:2, 3], 0.0])
        boards = []
        for x, y in signs:
            under |= (np.abs(world[:, 0] - x) < 0.5) & (np.abs(world[:, 1] - y) < 0.3)
            board = np.column_stack([rng.uniform(x - 0.5, x + 0.5, 200), rng.uniform(y - 0.3, y + 0.3, 200),
                                     rng.uniform(1.25, 1.4, 200)])
            boards.append(board - [*pose[:2, 3], 0.0])
        ground, cars, boards = ground[~under], np.concatenate(cars), np.concatenate(boards)
        points = np.concatenate([ground, cars, boards]).astype(np.float32)
        raw = np.concatenate([rng.choice([40, 48, 72], len(ground)), np.full(len(cars), 10), np.full(len(boards), 81)])
        mapper.integrate(points, label_map.to_learning(raw.astype(np.uint32)), pose)
        window = mapper.window
        whole = grid_of_window(window, RESOLUTION, CAR, 0.001)
        for x, y in bodies:  # the centre of a body: its ground hidden, its cell lethal
            cell = np.floor(np.array([x, y]) / RESOLUTION).astype(np.int64) - whole.origin
            if 0 <= cell[0] < whole.values.shape[1] and 0 <= cell[1] < whole.values.shape[0]:
                assert whole.values[cell[1], cell[0]] >= 90
                hidden_cells.add((x, y))
        corner, (width, height) = window.origin[:2], window.dims[:2]
        regions = [(corner + [10, 7], (20, 20)), (corner - [5, 9], (30, 25)),
                   (corner + [width - 8, height - 4], (16, 12)), (corner + [33, 21], (1, 1)),
                   (corner + [width + 5, 0], (10, 10)), (corner, (width, height))]
        for origin, size in regions:
            part = grid_of_window(window, RESOLUTION, CAR, 0.001, (origin, size))
            expected = crop(whole, origin, size)
            assert np.array_equal(part.origin, expected.origin)
            assert np.array_equal(part.values, expected.values), (origin - corner, size)
            compared += int((part.values >= 0).sum())
        # What lies beyond a region and its margin is not read: poisoned, the region's cells stay.
        # A region of one cell on a car's hidden ground depends on its margin's columns.
        reach = NEIGHBOUR_PASSES
        for x, y in bodies + signs:
            cell = np.floor(np.array([x, y]) / RESOLUTION).astype(np.int64)
            start = cell - corner
            if not (0 <= start[0] < width and 0 <= start[1] < height):
                continue
            outside = np.ones((width, height), bool)  # global order
            low = np.maximum(start - reach, 0)
            outside[low[0]:start[0] + 1 + reach, low[1]:start[1] + 1 + reach] = False
            alpha = window.alpha.copy()
            alpha[:, np.roll(outside, tuple(corner % [width, height]), (0, 1))] = np.nan
            poisoned = window_grid(alpha, window.mask, window.origin, window.dims, RESOLUTION, CAR, 0.001,
                                   window.classes_by_column(), (cell, (1, 1)))
            assert poisoned.values[0, 0] == whole.values[start[1], start[0]], (x, y)
            poisoned_compared += 1
        # Each lethal cell on its own, a region of one cell: the cars' hidden ground at its edge.
        for row, column in np.argwhere(whole.values >= 90)[::10]:
            origin = whole.origin + [column, row]
            part = grid_of_window(window, RESOLUTION, CAR, 0.001, (origin, (1, 1)))
            assert part.values[0, 0] == whole.values[row, column]
            hidden_compared += 1
    assert compared > 2_000 and hidden_compared > 20 and len(hidden_cells) >= 3 and poisoned_compared >= 6, (
        compared, hidden_compared, poisoned_compared)


def test_a_hidden_columns_ground_from_its_patch_equals_the_spread_over_the_whole_grid():
    """The window's second pass estimates a hidden column's ground from the patch of neighbours
    the estimate depends on; the gathered path spreads the known heights over the whole grid
    (with a margin beyond it) pass by pass. Both give the same height at every cell, the edges
    and corners of the grid included, where heights spread into the margin and back."""
    from convbki_core.costmap.columns import _NO_GROUND, NEIGHBOUR_PASSES, _ground_near, _spread_ground

    rng = np.random.default_rng(4)
    margin = NEIGHBOUR_PASSES
    side = 2 * margin + 1
    compared = 0
    for density in (0.05, 0.2, 0.5):
        top = np.where(rng.random((23, 17)) < density, rng.integers(-5, 6, (23, 17)), _NO_GROUND).astype(np.int64)
        grid = np.full((23 + 2 * margin, 17 + 2 * margin), np.nan)
        grid[margin:-margin, margin:-margin] = np.where(top > _NO_GROUND, top.astype(np.float64), np.nan)
        spread = _spread_ground(grid)[margin:-margin, margin:-margin]
        patch, fresh = np.empty((side, side)), np.empty((side, side))
        for x, y in np.argwhere(top == _NO_GROUND):
            near = _ground_near(top, x, y, patch, fresh)
            assert (np.isnan(near) and np.isnan(spread[x, y])) or near == spread[x, y], (density, x, y)
            compared += int(not np.isnan(near))
    assert compared > 300
