"""The traversability cost of hand-built columns, against expectations written out by hand."""

import numpy as np
import pytest

from convbki_core.config import MapperConfig
from convbki_core.costmap.columns import LETHAL_MIN, ProfileError, column_costs, load_profile, rasterise
from convbki_core.io.labels import load_label_map
from convbki_core.paths import config_dir

NAMES = load_label_map("semantic_kitti").class_names
CLASS = {name: number for number, name in enumerate(NAMES)}
RESOLUTION = 0.2
CAR = load_profile(config_dir() / "traversability" / "car.yaml", NAMES)


def voxel(**concentrations: float) -> np.ndarray:
    alpha = np.zeros(len(NAMES))
    for name, value in concentrations.items():
        alpha[CLASS[name.replace("_", "-")]] = value
    return alpha


def costs_of(voxels: dict, profile=CAR) -> dict:
    """{(x, y): cost} of voxels given as {(x, y, z): alpha}."""
    indices = np.array(list(voxels), np.int64)
    alpha = np.stack(list(voxels.values()))
    columns = column_costs(indices, alpha, RESOLUTION, profile)
    return {tuple(cell): int(cost) for cell, cost in zip(columns.cells.tolist(), columns.cost)}


def with_sigma(profile, sigma: float):
    from dataclasses import replace

    return replace(profile, risk_sigma=sigma)


def test_a_sure_road_is_free_and_a_sure_sidewalk_past_a_kerb_costs_its_class():
    # road at z 0; a kerb: the next column's sidewalk one voxel (0.2 m, under the 0.25 m
    # obstacle height) higher, and in the kerb's own column both.
    voxels = {(0, 0, 0): voxel(road=10), (1, 0, 0): voxel(road=10), (1, 0, 1): voxel(sidewalk=10),
              (2, 0, 1): voxel(sidewalk=10)}
    assert costs_of(voxels) == {(0, 0): 0, (1, 0): 70, (2, 0): 70}


def test_a_canopy_above_the_band_does_not_block_the_road_under_it():
    voxels = {(0, 0, 0): voxel(road=10), (0, 0, 11): voxel(vegetation=20), (0, 0, 15): voxel(vegetation=20)}
    assert costs_of(voxels) == {(0, 0): 0}  # 2.2 m and 3.0 m above the road: over the 2.0 m band
    voxels[(0, 0, 9)] = voxel(vegetation=20)  # a branch at 1.8 m: in the band
    assert costs_of(voxels) == {(0, 0): 100}


def test_a_car_on_hidden_ground_is_lethal_at_its_neighbours_ground_height():
    voxels = {(x, 0, 0): voxel(road=10) for x in (0, 2)}
    voxels |= {(1, 0, z): voxel(car=10) for z in range(3, 8)}  # 0.6 .. 1.4 m, the road under it unseen
    assert costs_of(voxels) == {(0, 0): 0, (1, 0): 100, (2, 0): 0}


def test_a_road_whatever_its_ground_class_noise_is_free_and_an_unsure_surface_costs_its_kind():
    # Road 8, sidewalk 1, terrain 1: p_free = 0.8 > 1/2, no lethal evidence: 0, with or without a
    # margin. (The expected cost plus a standard deviation called it 22: E = 14, Var = (980 - 196)
    # / 11 = 71.3, sigma 8.4.)
    noisy_road = {(0, 0, 0): voxel(road=8, sidewalk=1, terrain=1)}
    for sigma in (0.0, 1.0, 2.0):
        assert costs_of(noisy_road, with_sigma(CAR, sigma)) == {(0, 0): 0}
    # Terrain 3, road 2: p_free = 0.4 is not over one half, and nothing lethal: the costly
    # classes' cost, 70, however sure (30, 20 the same); road 3, terrain 2 is free.
    assert costs_of({(0, 0, 0): voxel(terrain=3, road=2)}) == {(0, 0): 70}
    assert costs_of({(0, 0, 0): voxel(terrain=30, road=20)}) == {(0, 0): 70}
    assert costs_of({(0, 0, 0): voxel(terrain=2, road=3)}) == {(0, 0): 0}
    # Sidewalk 3 and other-ground 1: the costly classes' mean, (3 * 70 + 50) / 4 = 65.
    assert costs_of({(0, 0, 0): voxel(sidewalk=3, other_ground=1)}) == {(0, 0): 65}


def test_the_margin_goes_where_the_posterior_gives_a_lethal_class_weight():
    # Road 6, car 4 (A = 10): free by its kind (p_free 0.6), but p_lethal = 0.4 with the Beta
    # standard deviation sqrt(0.4 * 0.6 / 11) = 0.1477: 100 * (0.4 + s * 0.1477) = 40, 54.8, 69.5.
    near_car = {(0, 0, 0): voxel(road=6, car=4)}
    assert costs_of(near_car, with_sigma(CAR, 0.0)) == {(0, 0): 40}
    assert costs_of(near_car) == {(0, 0): 55}
    assert costs_of(near_car, with_sigma(CAR, 2.0)) == {(0, 0): 70}
    # The same shares seen ten times as often: a surer posterior, a smaller margin:
    # sqrt(0.24 / 101) = 0.0487: 44.9 -> 45.
    assert costs_of({(0, 0, 0): voxel(road=60, car=40)}) == {(0, 0): 45}
    # Car 6, road 4 in the band over a road: lethal by its kind (p_lethal 0.6 is at least one half).
    assert costs_of({(0, 0, 0): voxel(road=10), (0, 0, 3): voxel(road=4, car=6)}, with_sigma(CAR, 0.0)) == {(0, 0): 100}
    # A fence's posterior with a whiff of road: 100 * (0.9 + sqrt(0.09 / 11)) > 100: lethal.
    assert costs_of({(0, 0, 0): voxel(road=10), (0, 0, 3): voxel(fence=9, road=1)}) == {(0, 0): 100}


def test_unobserved_and_only_empty_columns_are_unknown_and_a_departed_car_leaves_no_obstacle():
    # A column that rays only found empty has no ground and nothing in the band: unknown.
    empty = {(0, 0, z): voxel(unlabeled=20) for z in range(0, 5)}
    assert costs_of(empty) == {(0, 0): -1}
    # A car drove through and left: free space put 50 rays of evidence into class 0 over its 2.
    # Empty space holds 50/52 of the voxel: it is empty, and costs nothing.
    left = {(0, 0, 0): voxel(road=10), (0, 0, 4): voxel(car=2, unlabeled=50)}
    assert costs_of(left) == {(0, 0): 0}
    grid = rasterise(column_costs(np.array([[0, 0, 0], [2, 1, 0]]), np.stack([voxel(road=10), voxel(road=10)]),
                                  RESOLUTION, CAR), RESOLUTION)
    assert grid.values.tolist() == [[0, -1, -1], [-1, -1, 0]]  # rows are y, the cells between unknown
    assert grid.origin.tolist() == [0, 0]


def test_empty_space_evidence_in_an_occupied_voxel_does_not_dilute_its_cost():
    # Rays grazing a fence leave class-0 evidence in its voxels: fence 7, empty 3. Given that the
    # voxel is occupied (3/10 is not over 3/4 empty) it is fence for sure: E = 100, Var = 0:
    # lethal, where the plain expectation (0.7 * 100 = 70, +1 sigma 14.5) would have called it 84.
    fence = {(0, 0, 0): voxel(road=10), (0, 0, 3): voxel(fence=7, unlabeled=3)}
    assert costs_of(fence) == {(0, 0): 100}
    # Rays that grazed it more often (fence 3, empty 7: more likely empty than not, not clearly)
    # leave it an obstacle as well.
    assert costs_of({(0, 0, 0): voxel(road=10), (0, 0, 3): voxel(fence=3, unlabeled=7)}) == {(0, 0): 100}
    # Road 6 and car 4 (the test above) with three times as much empty-space evidence as class
    # evidence (not more: still occupied) costs what it did: 40 without the margin, 55 with it.
    grass = {(0, 0, 0): voxel(road=6, car=4, unlabeled=30)}
    assert costs_of(grass, with_sigma(CAR, 0.0)) == {(0, 0): 40}
    assert costs_of(grass) == {(0, 0): 55}
    # A little more empty space and it is empty space: a column with nothing else is unknown.
    assert costs_of({(0, 0, 0): voxel(road=6, car=4, unlabeled=30.01)}) == {(0, 0): -1}


def test_leaves_read_as_terrain_on_top_of_a_tree_do_not_lift_the_ground_into_the_canopy():
    # Terrain at z 0, the tree's foliage from 0.4 m to 1.6 m, and at 1.8 m leaves the segmentation
    # called terrain. The ground is the terrain under the first obstacle, so the foliage is in
    # the band: lethal. (The highest ground voxel would put the band above the tree: 70.)
    tree = {(0, 0, 0): voxel(terrain=10)} | {(0, 0, z): voxel(vegetation=10) for z in range(2, 9)}
    tree[(0, 0, 9)] = voxel(terrain=6, vegetation=2)
    assert costs_of(tree) == {(0, 0): 100}
    # With nothing under it, a raised ground is still ground: a sidewalk past a kerb.
    assert costs_of({(0, 0, 1): voxel(sidewalk=10), (0, 0, 6): voxel(vegetation=10)}) == {(0, 0): 100}
    assert costs_of({(0, 0, 1): voxel(sidewalk=10), (0, 0, 13): voxel(vegetation=10)}) == {(0, 0): 70}


@pytest.mark.parametrize("update_path", ["fast", "torch"])
def test_the_grid_read_from_the_dense_window_equals_the_grid_of_its_voxels_gathered(update_path):
    """The node computes its rolling grid from the window's dense torus arrays in place; the same
    voxels gathered (what a saved map holds) give the same grid, cell for cell, also after the
    window moved and wrapped around its torus, with hidden ground and empty space in it."""
    from convbki_core.costmap.columns import grid_of_window
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
    from convbki_core.costmap.columns import NEIGHBOUR_PASSES, crop, grid_of_window, window_grid
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


@pytest.mark.parametrize("text, problem", [
    ("costs: {car: 100}\nground: [road]\n", "no cost for bicycle"),
    ("costs: {cars: 100}\nground: [road]\n", "unknown class 'cars' in costs"),
    ("costs: {car: 101}\nground: [road]\n", "cost of 'car' must be a number from 0 to 100, got 101"),
    ("costs: {car: -1}\nground: [road]\n", "cost of 'car' must be a number from 0 to 100, got -1"),
    ("costs: [1, 2]\n", "needs a `costs` mapping"),
    (": : :\n", "not YAML"),
])
def test_a_bad_profile_is_one_line_naming_the_problem(tmp_path, text, problem):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ProfileError) as error:
        load_profile(path, NAMES)
    assert problem in str(error.value) and str(error.value).startswith(str(path)) and "\n" not in str(error.value)


def test_both_shipped_profiles_load():
    small = load_profile(config_dir() / "traversability" / "small_robot.yaml", NAMES)
    assert small.class_costs[CLASS["sidewalk"]] == 0 and CAR.class_costs[CLASS["sidewalk"]] == 70
    assert small.robot_height < CAR.robot_height


def test_a_car_that_drove_off_leaves_no_lethal_cells_behind_it():
    """One scan sees a car on the road; then the road is seen with the car gone, the rays to it
    and to a wall behind crossing where the car was. Free space empties its voxels: its cells,
    all lethal at first, are lethal no more (not yet free: the voxel just above the road keeps
    the car's own points' evidence beside the road's spread, which the margin charges)."""
    from convbki_core.mapper import ConvBKIMapper
    from convbki_core.paths import kernel_path

    label_map = load_label_map("semantic_kitti")
    config = MapperConfig.paper(local_bounds=((-20, -12, -3), (20, 12, 4)), prior=0.001, device="cpu",
                                ignore_classes=label_map.ignore_classes, free_space=True)
    mapper = ConvBKIMapper(config, kernel_path("semantic_kitti_compound"))
    grid = np.stack(np.meshgrid(np.arange(-2, 16, 0.15), np.arange(-4, 4, 0.15)), -1).reshape(-1, 2)
    ground = np.column_stack([grid, np.full(len(grid), -1.6)])
    car = np.random.default_rng(1).uniform([4, -1, -1.5], [6, 1, -0.3], (1500, 3))
    hidden = (ground[:, 0] > 3.8) & (ground[:, 0] < 6.2) & (np.abs(ground[:, 1]) < 1.2)
    wall_grid = np.stack(np.meshgrid(np.arange(-4, 4, 0.15), np.arange(-1.6, 2.0, 0.15)), -1).reshape(-1, 2)
    wall = np.column_stack([np.full(len(wall_grid), 19.0), wall_grid])

    def car_cells() -> np.ndarray:
        columns = column_costs(*mapper.items(), RESOLUTION, CAR, 0.001)
        centres = (columns.cells + 0.5) * RESOLUTION
        return columns.cost[(centres[:, 0] > 4.1) & (centres[:, 0] < 5.9) & (np.abs(centres[:, 1]) < 0.9)]

    raw = np.concatenate([np.full((~hidden).sum(), 40), np.full(len(car), 10)]).astype(np.uint32)
    mapper.integrate(np.concatenate([ground[~hidden], car]).astype(np.float32), label_map.to_learning(raw),
                     np.eye(4))
    seen = len(car_cells())
    assert seen > 50 and (car_cells() == 100).all()
    later = np.concatenate([ground, wall]).astype(np.float32)
    raw = np.concatenate([np.full(len(ground), 40), np.full(len(wall), 50)]).astype(np.uint32)
    # What a planner needs: the spot passable. A cell of LETHAL_MIN (90) or more is an obstacle
    # to it (the planning check blocks it), so every cell the car stood on must read less, in
    # every scan once the road has been seen clear a few times, and stay observed.
    for scan in range(20):
        mapper.integrate(later, label_map.to_learning(raw), np.eye(4))
        cells = car_cells()
        assert len(cells) == seen and (cells >= 0).all(), (scan, cells)
        if scan >= 4:
            assert (cells < LETHAL_MIN).all(), (scan, cells)


def held_classes(window) -> np.ndarray:
    """(C, X, Y) bool: the classes that hold anything but the prior in each column of a window."""
    alpha = window.alpha if isinstance(window.alpha, np.ndarray) else window.alpha.numpy()
    return (alpha != window.prior).any(axis=3)


def column_bits(bits: np.ndarray, classes: int) -> np.ndarray:
    return np.stack([((bits >> np.uint64(c)) & np.uint64(1)) != 0 for c in range(classes)])


@pytest.mark.parametrize("update_path", ["fast", "dense", "torch"])
def test_the_classes_a_window_keeps_by_column_cover_every_class_it_holds(update_path):
    """The costmap skips the class runs that the window's ``classes_by_column`` says hold the
    prior. Through scans of labels and of probabilities, free space with clamping and the movers'
    rules, the window driving off (slabs to the store) and back (slabs loaded), a box forgotten,
    a map loaded and a reset: every class above the prior in a column has its bit, the bits
    are not all set, and the grid read with them equals the grid read from every run."""
    from convbki_core.costmap.columns import grid_of_window, window_grid
    from convbki_core.mapper import ConvBKIMapper
    from convbki_core.paths import kernel_path

    label_map = load_label_map("semantic_kitti")
    config = MapperConfig.paper(local_bounds=((-8, -6, -3), (8, 6, 3)), prior=0.001, device="cpu",
                                ignore_classes=label_map.ignore_classes, movable_classes=label_map.movable_classes,
                                free_space=True, max_concentration=30.0, update_path=update_path)
    mapper = ConvBKIMapper(config, kernel_path("semantic_kitti_compound"))
    window = mapper.window
    rng = np.random.default_rng(5)
    raw_classes = np.array([40, 48, 70, 72, 10, 50, 51, 80, 30])
    route = [0, 1, 2, 5, 9, 5, 2, 1, 0, 0]  # x in metres / 2: away beyond the window and back
    sparse_columns = []
    for step, place in enumerate(route):
        ground = np.column_stack([rng.uniform(-7, 7, (3000, 2)), rng.normal(-1.6, 0.03, 3000)])
        things = rng.uniform([-6, -5, -1.5], [6, 5, 1.5], (800, 3))
        points = np.concatenate([ground, things]).astype(np.float32)
        if step == 4:  # probabilities: every class gets some evidence
            values = rng.dirichlet(np.full(20, 0.3), len(points)).astype(np.float32)
        else:
            raw = np.concatenate([rng.choice(raw_classes[:4], len(ground)), rng.choice(raw_classes, len(things))])
            values = label_map.to_learning(raw.astype(np.uint32))
        pose = np.eye(4)
        pose[:3, 3] = [2.0 * place, 0.3 * step, 0.0]
        mapper.integrate(points, values, pose)
        if step == 1:
            bits = window.classes_by_column()  # kept from here on
        if step == 6:
            mapper.forget_box((-1.0, -1.0, -3.0), (1.0, 1.0, 3.0))
        bits = window.classes_by_column()
        held = held_classes(window)
        covered = column_bits(bits, 20)
        assert not (held[1:] & ~covered[1:]).any(), f"step {step}: {int((held[1:] & ~covered[1:]).sum())} missed"
        sparse_columns.append(float(covered.sum(axis=0)[held.any(axis=0)].mean()))
        for profile in (CAR, with_sigma(CAR, 0.0)):
            kept = grid_of_window(window, RESOLUTION, profile, 0.001)
            alpha = window.alpha if isinstance(window.alpha, np.ndarray) else window.alpha.numpy()
            mask = window.mask if isinstance(window.mask, np.ndarray) else window.mask.numpy()
            every = window_grid(alpha, mask, window.origin, window.dims, RESOLUTION, profile, 0.001)
            assert np.array_equal(kept.values, every.values)
    assert min(sparse_columns) < 8  # a column holds a few classes: the bits skip most runs
    # A map loaded into the window, then a reset: the bits follow both.
    snapshot = mapper.snapshot()
    mapper.reset()
    assert not window.classes_by_column().any()
    mapper.replace_with(snapshot.metadata, snapshot.indices, snapshot.alpha)
    held = held_classes(window)
    assert held[1:].any() and not (held[1:] & ~column_bits(window.classes_by_column(), 20)[1:]).any()


def test_the_compiled_class_bookkeeping_equals_its_numpy_twin(monkeypatch):
    """Per column, the classes held and the classes a scan reaches (its voxels' classes spread by
    the filter's half-width, clipped to the window, placed on the torus): compiled and numpy."""
    import convbki_core.memory.window as window_module
    from convbki_core.memory.window import _note_scan_classes, classes_held

    rng = np.random.default_rng(2)
    dims = np.array([15, 13, 5])
    alpha = np.full((20, *dims), np.float32(0.001), np.float32)
    alpha[rng.integers(0, 20, 40), rng.integers(0, 15, 40), rng.integers(0, 13, 40), rng.integers(0, 5, 40)] += 2.0
    linear = np.unique(rng.integers(0, int(np.prod(dims)), 6))
    features = np.where(rng.random((len(linear), 20)) < 0.1, rng.random((len(linear), 20)), 0).astype(np.float32)
    origin = np.array([-13, 24, 3])
    results = []
    for compiled in (True, False):
        monkeypatch.setattr(window_module, "HAVE_NUMBA", compiled)
        held = np.zeros(tuple(dims[:2]), np.uint64)
        _note_scan_classes(linear, features, origin, dims, 2, held, np.zeros((2, *dims[:2]), np.uint64))
        results.append((classes_held(alpha, 0.001), held))
    assert np.array_equal(results[0][0], results[1][0]) and np.array_equal(results[0][1], results[1][1])
    assert results[0][1].any() and (results[0][1] == 0).any()
    # By hand: one voxel of class 3 at local (0, 12): columns local x 0..2, y 10..12, on the torus.
    held = np.zeros(tuple(dims[:2]), np.uint64)
    one = np.zeros((1, 20), np.float32)
    one[0, 3] = 1.0
    _note_scan_classes(np.array([(0 * 13 + 12) * 5 + 1]), one, origin, dims, 2, held,
                       np.zeros((2, 15, 13), np.uint64))
    expected = np.zeros((15, 13), np.uint64)
    for x in range(0, 3):
        for y in range(10, 13):
            expected[(origin[0] + x) % 15, (origin[1] + y) % 13] = np.uint64(1) << np.uint64(3)
    assert np.array_equal(held, expected)


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
