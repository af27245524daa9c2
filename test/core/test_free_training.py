"""Learning the free-space length: the free-space questions of a training sample
(``training.free_samples``) on scenes written by the test, where freeing is clearly right (a car
that left) or clearly wrong (a pole the past scans missed while their rays passed beside it)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from kitti_fixture import pose_about_z, write_sequence

from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import WindowGeometry
from convbki_core.inference.kernels import ConvBKIKernel
from convbki_core.training import objective, samples, trainer

CAR, POLE, BUILDING = 10, 80, 50  # raw ids


def grid(x, y, z, step=0.1):
    """Points filling the box [x0, x1) x [y0, y1) x [z0, z1) every ``step`` metres."""
    axes = [np.arange(lo + step / 2, hi, step) for lo, hi in (x, y, z)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def wall(y_ranges):
    return np.concatenate([grid((8.0, 8.2), y, (-1.0, 1.0)) for y in y_ranges])


def write(root, scans):
    """``scans``: per frame a list of (points, raw id); a still sensor at the origin."""
    frames, poses = [], []
    for parts in scans:
        points = np.concatenate([p for p, _ in parts]).astype(np.float32)
        labels = np.concatenate([np.full(len(p), raw, np.uint32) for p, raw in parts])
        frames.append((points, labels, labels))
        poses.append(pose_about_z(0.0, [0.0, 0.0, 0.0]))
    write_sequence(root, "00", frames, poses)
    return SemanticKittiSequence(root, "00")


def car_that_left(root):
    """A car in front of a wall in scans 0-2, gone in scans 3-6: the rays of scans 3-5 cross the
    voxels it held, and scan 6 (the sample) sees empty space there."""
    building = (wall([(-3.0, 3.0)]), BUILDING)
    car = (grid((4.0, 4.8), (-0.6, 0.6), (-0.6, 0.6)), CAR)
    return write(root, [[building, car]] * 3 + [[building]] * 4)


def pole_missed(root):
    """A pole seen in scans 0-2 and 6; scans 3-5 miss it, and their rays to a wall behind pass
    beside it (never through it): spreading their free evidence empties a real surface."""
    pole = (grid((5.0, 5.2), (0.0, 0.2), (-1.0, 1.0), step=0.05), POLE)
    beside = (wall([(-0.3, -0.02), (0.34, 0.6)]), BUILDING)
    return write(root, [[pole]] * 3 + [[beside]] * 3 + [[pole]])


IDENTITY = 0.1  # class lengths below a voxel: class evidence stays in its voxel, so the scenes are exact


def start_kernel(free_ell):
    return ConvBKIKernel("single", 20, 5, 0.2, ell=IDENTITY, free_ell=free_ell).to_config()


def built_sample(dataset, frames=7):
    support = ConvBKIKernel("single", 20, 5, 0.2, ell=IDENTITY).filters().detach().numpy()[:, 0]
    builder = samples.SampleBuilder(WindowGeometry(0.2), 20, frames, 5, (0,), free_support=support)
    return builder.build(0, dataset, frames - 1)


def test_the_free_term_has_a_finite_non_zero_gradient_in_free_ell(tmp_path):
    built = built_sample(car_that_left(tmp_path / "data"))
    free = built[3]
    assert free is not None and free.at_free.num_queries > 20  # free points where the car was
    kernel = ConvBKIKernel.from_config(start_kernel(0.3))
    loss = objective.sample_loss(built, kernel, torch.ones(20), 1e-3, torch.device("cpu"))
    loss.backward()
    gradient = kernel.free_ell.grad
    assert gradient is not None and torch.isfinite(gradient) and float(gradient) < -1e-3
    assert torch.isfinite(loss)


def test_without_free_questions_the_trainer_is_exactly_the_paper_trainer(tmp_path):
    """One scan a sample has no past scans, so no free-space question: learning free_ell then
    changes nothing, step for step, and free_ell stays where it started."""
    dataset = car_that_left(tmp_path / "data")
    runs = {}
    for learn in (False, True):
        runs[learn] = trainer.train_kernel([dataset], [list(range(7))], "single", frames_per_sample=1, epochs=2,
                                           start=ConvBKIKernel("single", 20, 5, 0.2, ell=0.45).to_config(),
                                           learn_free_ell=learn)
    assert runs[False].losses == runs[True].losses and len(runs[False].losses) == 14
    assert runs[False].config.ell == runs[True].config.ell
    assert runs[True].free_ells[-1] == pytest.approx(trainer.FREE_ELL_START_VOXELS * 0.2)
    built = built_sample(dataset, frames=1)
    assert built[3] is None


@pytest.mark.parametrize(("scene", "start", "direction"), [(car_that_left, 0.22, "up"), (pole_missed, 0.5, "down")])
def test_free_ell_grows_where_freeing_is_right_and_shrinks_where_it_is_wrong(tmp_path, scene, start, direction):
    dataset = scene(tmp_path / "data")
    result = trainer.train_kernel([dataset], [[6]], "single", frames_per_sample=7, epochs=12, lr=0.02,
                                  start=start_kernel(start), learn_free_ell=True)
    first, last = result.free_ells[0], result.free_ells[-1]
    assert len(result.free_ells) == 12
    if direction == "up":
        assert last > max(start, trainer.FREE_ELL_START_VOXELS * 0.2) + 0.05
    else:
        assert last < start - 0.05
    assert (last > first) == (direction == "up")
    assert result.config.free_ell == pytest.approx(last, abs=1e-6)


def test_the_ray_counts_a_sample_reads_are_those_of_a_walk_of_every_ray():
    """H[q, tap] is the weighted number of the later scan's rays that cross q + tap - h, at the
    voxels the earlier scan gave class evidence and the later one did not (checked against
    ``free_space.crossed_voxels``, ray by ray)."""
    from helpers import crossed_voxels

    from convbki_core.geometry.volume import voxelize
    from convbki_core.training.free_samples import free_evidence, past_rays, reached, support_offsets

    rng = np.random.default_rng(2)
    geometry = WindowGeometry(0.2, (-2.0, -2.0, -1.0), (6.0, 2.0, 1.0))
    origin, dims = geometry.origin_for(np.zeros(3)), geometry.dims
    block = grid((2.0, 3.0), (-0.6, 0.6), (-0.4, 0.4), step=0.2)  # scan 0: class evidence the rays cross
    returns = np.column_stack([rng.uniform(4.5, 5.8, 40), rng.uniform(-0.5, 0.5, 40), rng.uniform(-0.3, 0.3, 40)])
    volumes = [voxelize(points, np.full(len(points), 13), origin, dims, 0.2, 20) for points in (block, returns)]
    support = support_offsets(ConvBKIKernel("single", 20, 3, 0.2, ell=IDENTITY).filters().detach().numpy()[:, 0])
    reach = [reached(volume, *support) for volume in volumes]
    rays = [past_rays(points, np.eye(4), volume, 0.2) for points, volume in zip((block, returns), volumes)]
    queries = np.unique(np.floor(block / 0.2).astype(np.int64), axis=0)
    evidence, held = free_evidence(queries, rays, reach, origin, dims, 3)
    assert held.all()
    got = np.zeros((len(queries), 27))
    np.add.at(got, (evidence.row.numpy(), evidence.tap.numpy()), evidence.value.numpy())
    sensor, ends, weights, through = rays[1]
    crossed = {}
    for end, weight, beyond in zip(ends, weights, through):
        for voxel in crossed_voxels(sensor, end, bool(beyond)):
            crossed[voxel] = crossed.get(voxel, 0.0) + float(weight)
    steps = np.arange(3) - 1
    taps = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
    expected = np.array([[crossed.get(tuple(int(v) for v in q + tap), 0.0) for tap in taps] for q in queries])
    assert expected.sum() > 100  # the rays do cross the block
    np.testing.assert_allclose(got, expected, rtol=1e-6)
