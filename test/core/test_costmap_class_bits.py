"""The classes a window keeps by column (``column_classes``), which the costmap reads to skip
the class runs at the prior: they cover every class the window holds through every way a map
changes, and the compiled bookkeeping equals its numpy twin."""

import numpy as np
import pytest
from costmap_helpers import CAR, RESOLUTION, with_sigma

from convbki_core.config import MapperConfig
from convbki_core.io.labels import load_label_map


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
    from convbki_core.costmap.window_pass import grid_of_window, window_grid
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
    import convbki_core.memory.column_classes as column_classes_module
    from convbki_core.memory.column_classes import _note_scan_classes, classes_held

    rng = np.random.default_rng(2)
    dims = np.array([15, 13, 5])
    alpha = np.full((20, *dims), np.float32(0.001), np.float32)
    alpha[rng.integers(0, 20, 40), rng.integers(0, 15, 40), rng.integers(0, 13, 40), rng.integers(0, 5, 40)] += 2.0
    linear = np.unique(rng.integers(0, int(np.prod(dims)), 6))
    features = np.where(rng.random((len(linear), 20)) < 0.1, rng.random((len(linear), 20)), 0).astype(np.float32)
    origin = np.array([-13, 24, 3])
    results = []
    for compiled in (True, False):
        monkeypatch.setattr(column_classes_module, "HAVE_NUMBA", compiled)
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
