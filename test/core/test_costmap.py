"""The traversability cost of hand-built columns, against expectations written out by hand; the
profiles that give the classes their costs; a car's cells once it drove off, through mapping."""

import numpy as np
import pytest
from costmap_helpers import CAR, CLASS, NAMES, RESOLUTION, with_sigma

from convbki_core.config import MapperConfig
from convbki_core.costmap.columns import column_costs
from convbki_core.costmap.grid import rasterise
from convbki_core.costmap.profile import LETHAL_MIN, ProfileError, load_profile
from convbki_core.io.labels import load_label_map
from convbki_core.paths import config_dir


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
