"""Input-segmentation noise that behaves like a real network's errors.

A segmentation network is wrong in *places*, not at random points: the same bush is called
terrain in every scan, a truck is called a car, class borders bleed into each other, and far
away, where points are sparse, everything gets worse. Some errors do change from view to view.
The model combines, per point (all in learning-class ids):

1. object-part confusion (persistent): a whole part (car cabin, truck cargo box, tree crown,
   sign plate) shows one confused class, decided by a hash of the part id; it holds in about
   85 % of the scans that see the part (a per-scan draw), so views rarely disagree;
2. world blobs (persistent): spheres of 0.4-1 m radius hashed on 1.2 m world cells (scene
   frame); a point inside an active blob takes that blob's confused class, in every scan;
3. boundary blur: a point within ``BLUR_WIDTH`` (0.45 m) of a surface of another class (road
   at the curb, trunk into the crown, car bottom over the road) takes that neighbour's class
   with a probability rising towards the border; mostly persistent (hash of a 0.25 m world
   voxel), partly per scan;
4. view blobs (per scan): like 2, on 0.8 m cells re-drawn for every scan;
5. salt-and-pepper (per scan): independent flips of single points.

Rates of 1, 2, 4, 5 scale with a per-class difficulty (bicycles and other-ground are hard, roads
and cars easy) and, except 1, grow with range (2 more weakly than 4 and 5: a network's
systematic mistakes do not all go away up close, which also means a map fusing near and far
views fixes some but not all of them). Confused classes come from a table of plausible
confusions (car <-> truck <-> other-vehicle, road <-> parking <-> sidewalk, trunk <-> pole, ...).
At mIoU 0.55 roughly 70 % of the wrong points come from the persistent mechanisms (1-3).
One knob, ``strength``, scales every rate; ``calibrate`` finds the strength that gives a target
input mIoU (as ConfusionMatrix computes it: class 0 ignored, mean over classes present in the
ground truth) by bisection on a weighted sample of the very points that will be written
(``CalibrationSample``: every scan of the drive is simulated once beforehand, up to ~500
points per class and scan on a 100-scan drive, rare classes whole), so the written drive meets the target
to about +-0.01.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from convbki_core.io.labels import LabelMap
from convbki_core.synth import lidar

BLUR_WIDTH = 0.45  # m
WORLD_BLOB_CELL = 1.2  # m
VIEW_BLOB_CELL = 0.8  # m
BOUNDARY_VOXEL = 0.25  # m
PART_SHOWN = 0.85  # fraction of scans in which a confused part shows its confusion
MAX_STRENGTH = 12.0

# Plausible confusions: true class -> {predicted class: relative weight}.
CONFUSIONS: dict[str, dict[str, float]] = {
    "car": {"truck": 3, "other-vehicle": 2, "building": 0.5, "fence": 0.4, "vegetation": 0.4},
    "bicycle": {"motorcycle": 3, "bicyclist": 2, "person": 1, "vegetation": 0.7, "pole": 0.5, "fence": 0.5},
    "motorcycle": {"bicycle": 3, "car": 1.5, "motorcyclist": 1, "bicyclist": 0.5},
    "truck": {"car": 3, "other-vehicle": 3, "building": 1},
    "other-vehicle": {"truck": 3, "car": 2, "building": 1},
    "person": {"bicyclist": 2, "pole": 1, "trunk": 1, "vegetation": 0.7, "motorcyclist": 0.3},
    "bicyclist": {"person": 2.5, "bicycle": 2, "motorcyclist": 1},
    "motorcyclist": {"bicyclist": 2, "motorcycle": 2, "person": 1},
    "road": {"parking": 3, "sidewalk": 2, "other-ground": 1, "terrain": 0.5},
    "parking": {"road": 3, "sidewalk": 2, "other-ground": 1.5, "terrain": 0.3},
    "sidewalk": {"road": 2, "parking": 1.5, "other-ground": 1.5, "terrain": 1},
    "other-ground": {"sidewalk": 3, "road": 1.5, "terrain": 2, "parking": 1},
    "building": {"fence": 1, "vegetation": 1.5, "pole": 0.3, "other-vehicle": 0.3, "truck": 0.2},
    "fence": {"building": 2, "vegetation": 2, "pole": 0.5, "terrain": 0.3},
    "vegetation": {"terrain": 2, "trunk": 1.5, "building": 1, "fence": 0.4, "pole": 0.3},
    "trunk": {"vegetation": 3, "pole": 2, "building": 0.3},
    "terrain": {"vegetation": 3, "sidewalk": 1, "other-ground": 1, "road": 0.3},
    "pole": {"trunk": 2, "traffic-sign": 1.5, "vegetation": 1, "building": 0.5},
    "traffic-sign": {"pole": 3, "building": 1, "vegetation": 0.5},
}
# How hard a class is, pointwise (scales rates 2, 4, 5) and as whole parts (rate 1).
DIFFICULTY = {
    "car": 0.45, "bicycle": 2.2, "motorcycle": 2.0, "truck": 1.5, "other-vehicle": 1.5, "person": 1.3,
    "bicyclist": 1.5, "motorcyclist": 2.0, "road": 0.25, "parking": 1.6, "sidewalk": 0.7, "other-ground": 2.2,
    "building": 0.45, "fence": 1.4, "vegetation": 0.55, "trunk": 1.1, "terrain": 0.9, "pole": 1.0,
    "traffic-sign": 1.1,
}
PART_DIFFICULTY = {
    "car": 0.25, "bicycle": 1.2, "motorcycle": 1.2, "truck": 2.5, "other-vehicle": 2.5, "person": 0.8,
    "bicyclist": 1.2, "motorcyclist": 1.2, "building": 0.02, "fence": 0.5, "vegetation": 0.25, "trunk": 0.6,
    "pole": 0.6, "traffic-sign": 1.0,
}
# Rate constants per mechanism: rate = 1 - exp(-K * strength * difficulty * range_factor).
K_PART, K_WORLD, K_BOUNDARY, K_VIEW, K_POINT = 0.15, 0.45, 0.5, 0.1, 0.04


def range_factor(distance: np.ndarray) -> np.ndarray:
    """Error-rate multiplier over range (m): 0.55 near the car, 1 at 30 m, 2.5 at 67 m, capped at 3."""
    return np.clip(0.55 + 0.5 * (distance / 30.0) ** 2, 0.55, 3.0)


@dataclass
class PointNoise:
    """What the noise model needs to know about each point of one scan (N points)."""

    truth: np.ndarray  # (N,) int64 learning class of the surface hit (0 for outliers' own surface too)
    distance: np.ndarray  # (N,) float32 range, m
    part: np.ndarray  # (N,) int64 part id, -1 for the ground and stuff
    neighbour: np.ndarray  # (N,) int64 nearest other class within BLUR_WIDTH, -1 none
    neighbour_dist: np.ndarray  # (N,) float32, m
    world_m: np.ndarray  # (N,) activation of the world blob holding the point (1: none)
    world_v: np.ndarray  # (N,) its class draw
    view_m: np.ndarray
    view_v: np.ndarray
    boundary_persistent: np.ndarray  # (N,) uniform of the point's 0.25 m world voxel
    boundary_view: np.ndarray  # (N,) per-scan uniform
    point_u: np.ndarray
    point_v: np.ndarray
    part_u: np.ndarray  # uniform of the part (persistent)
    part_v: np.ndarray
    part_shown: np.ndarray  # (N,) bool: this scan shows the part's confusion


class NoiseModel:
    """The segmentation-noise model of one drive (seeded); see the module docstring."""

    def __init__(self, label_map: LabelMap, seed: int):
        self.labels = label_map
        self.seed = int(seed)
        c = label_map.num_classes
        names = {n: i for i, n in enumerate(label_map.class_names)}
        weights = np.zeros((c, c))
        for true, row in CONFUSIONS.items():
            for pred, w in row.items():
                weights[names[true], names[pred]] = w
        weights[0, 0] = 1.0
        self.confusion = weights / weights.sum(1, keepdims=True).clip(1e-12)
        self.cumulative = np.cumsum(self.confusion, 1)
        self.difficulty = np.zeros(c)
        self.part_difficulty = np.zeros(c)
        for name, value in DIFFICULTY.items():
            self.difficulty[names[name]] = value
        for name, value in PART_DIFFICULTY.items():
            self.part_difficulty[names[name]] = value

    # ---- per-scan features --------------------------------------------------------------------
    def features(self, points: np.ndarray, truth: np.ndarray, distance: np.ndarray, part: np.ndarray,
                 neighbour: np.ndarray, neighbour_dist: np.ndarray, frame: int) -> PointNoise:
        """Draws for one scan. ``points``: (N, 3) measured points in the scene frame (m)."""
        n = len(truth)
        pts = np.ascontiguousarray(points, np.float64)
        world_m, world_v = lidar.blob_field(pts, WORLD_BLOB_CELL, self.seed * 16 + 1)
        view_m, view_v = lidar.blob_field(pts, VIEW_BLOB_CELL, (self.seed * 1_000_003 + frame) * 16 + 2)
        vox = np.floor(pts / BOUNDARY_VOXEL).astype(np.int64)
        boundary = lidar.hash_uniform(self.seed * 16 + 3, vox[:, 0], vox[:, 1], vox[:, 2])
        part64 = part.astype(np.int64)
        zeros = np.zeros(n, np.int64)
        part_u = lidar.hash_uniform(self.seed * 16 + 4, part64, zeros, zeros)
        part_v = lidar.hash_uniform(self.seed * 16 + 5, part64, zeros, zeros)
        part_shown = lidar.hash_uniform(self.seed * 16 + 6, part64, np.full(n, frame, np.int64), zeros) < PART_SHOWN
        rng = np.random.default_rng([self.seed, frame, 0x0015E])
        u = rng.random((3, n))
        return PointNoise(truth.astype(np.int64), distance.astype(np.float32), part64, neighbour.astype(np.int64),
                          neighbour_dist.astype(np.float32), world_m, world_v, view_m, view_v, boundary, u[0],
                          u[1], u[2], part_u, part_v, part_shown)

    # ---- prediction -------------------------------------------------------------------------------
    def _pick(self, truth: np.ndarray, v: np.ndarray) -> np.ndarray:
        """A confused class for each point from its true class's confusion row, by uniform ``v``."""
        # Column by column: no (N, C) temporary for the millions of points of a calibration.
        pick = np.zeros(len(truth), np.int64)
        for column in range(self.labels.num_classes - 1):
            pick += v > self.cumulative[truth, column]
        return pick

    def predict(self, f: PointNoise, strength: float) -> np.ndarray:
        """Predicted learning class of each point at noise ``strength`` (0 = ground truth)."""
        c = f.truth.astype(np.int64)
        pred = c.copy()
        if strength <= 0:
            return pred
        x = strength * self.difficulty[c] * range_factor(f.distance)
        # Lowest priority first; later mechanisms overwrite earlier ones.
        flip = f.point_u < 1 - np.exp(-K_POINT * x)
        pred[flip] = self._pick(c[flip], f.point_v[flip])
        flip = f.view_m < 1 - np.exp(-K_VIEW * x)
        pred[flip] = self._pick(c[flip], f.view_v[flip])
        has = f.neighbour >= 0
        neighbour = f.neighbour.astype(np.int64)
        p_b = np.zeros(len(c))
        p_b[has] = (1 - np.exp(-K_BOUNDARY * strength)) * np.clip(1 - f.neighbour_dist[has] / BLUR_WIDTH, 0, 1) ** 0.7
        flip = has & ((f.boundary_persistent < 0.75 * p_b) | (f.boundary_view < 0.25 * p_b))
        pred[flip] = neighbour[flip]
        # Persistent blobs depend on range more weakly than per-scan errors: a network's
        # systematic mistakes do not all go away when it comes closer.
        x_world = strength * self.difficulty[c] * np.sqrt(range_factor(f.distance))
        flip = f.world_m < 1 - np.exp(-K_WORLD * x_world)
        pred[flip] = self._pick(c[flip], f.world_v[flip])
        p_part = 1 - np.exp(-K_PART * strength * self.part_difficulty[c])
        flip = (f.part >= 0) & (f.part_u < p_part) & f.part_shown
        pred[flip] = self._pick(c[flip], f.part_v[flip])
        return pred

    # ---- class probabilities ---------------------------------------------------------------------
    def probabilities(self, f: PointNoise, pred: np.ndarray, frame: int) -> np.ndarray:
        """(N, C) float16 class probabilities whose arg-max is ``pred``.

        Like a real network's softmax: confident when right (0.5-0.97, less far away), less so
        when wrong (0.3-0.7) with the true class usually second; the rest spread over the
        predicted class's usual confusions. Class 0 gets (almost) nothing.
        """
        n, c = len(pred), self.labels.num_classes
        rng = np.random.default_rng([self.seed, frame, 0x9B0B])
        wrong = pred != f.truth
        far = np.clip(f.distance / 80.0, 0, 1)
        top = np.where(wrong, rng.uniform(0.3, 0.7, n), rng.uniform(0.5, 0.97, n) - 0.15 * far)
        rest = 1.0 - top
        probs = np.full((n, c), 0.002)
        probs[:, 0] = 1e-4
        spread = self.confusion[pred] * (rest * rng.uniform(0.3, 0.9, n))[:, None]
        probs += spread
        second = np.where(wrong, f.truth, pred)
        probs[np.arange(n), second] += np.where(wrong, rest * rng.uniform(0.3, 0.8, n), 0.0)
        probs[np.arange(n), pred] = 0.0
        # The top class must stay clearly first, also after rounding to float16.
        others = probs.max(1)
        probs[np.arange(n), pred] = np.maximum(top, others + 0.03)
        probs /= probs.sum(1, keepdims=True)
        out = probs.astype(np.float16)
        bad = np.argmax(out, 1) != pred
        if bad.any():  # cannot happen with the margin above; kept as a guard
            out[bad, pred[bad]] = np.float16(1.0)
        return out


def weighted_miou(truth: np.ndarray, pred: np.ndarray, weight: np.ndarray, num_classes: int,
                  ignore: tuple[int, ...] = (0,)) -> float:
    """mIoU as ConfusionMatrix computes it, from a weighted sample of points (weight = 1 / keep rate)."""
    valid = ~np.isin(truth, ignore)
    counts = np.bincount(truth[valid] * num_classes + pred[valid], weights=weight[valid],
                         minlength=num_classes ** 2).reshape(num_classes, num_classes)
    tp = np.diag(counts)
    union = counts.sum(0) + counts.sum(1) - tp
    present = counts.sum(1) > 0
    present[list(ignore)] = False
    return float(np.mean(tp[present] / union[present])) if present.any() else float("nan")


@dataclass
class CalibrationSample:
    """Noise draws of a weighted sample of a drive's points (truth class 0 left out)."""

    noise: PointNoise
    weight: np.ndarray  # (N,) float64: how many written points each sampled point stands for

    @classmethod
    def of(cls, noise: PointNoise, truth: np.ndarray, per_class: int, rng: np.random.Generator) -> CalibrationSample:
        """Keep at most about ``per_class`` points of each true class (all of a rare one), weighted."""
        counts = np.bincount(truth, minlength=int(truth.max(initial=0)) + 1)
        rate = np.minimum(1.0, per_class / np.maximum(counts, 1))[truth]
        keep = (rng.random(len(truth)) < rate) & (truth > 0)
        fields = {}
        for name in noise.__dataclass_fields__:
            values = getattr(noise, name)[keep]
            # Compact copies: a long drive keeps up to CALIBRATION_POINTS of these.
            if values.dtype == np.float64:
                values = values.astype(np.float32)
            elif name in ("truth", "neighbour"):
                values = values.astype(np.int8)
            elif name == "part":
                values = values.astype(np.int32)
            fields[name] = values
        return cls(PointNoise(**fields), (1.0 / rate[keep]).astype(np.float32))

    @staticmethod
    def join(samples: list[CalibrationSample]) -> CalibrationSample:
        names = PointNoise.__dataclass_fields__
        noise = PointNoise(**{n: np.concatenate([getattr(s.noise, n) for s in samples]) for n in names})
        return CalibrationSample(noise, np.concatenate([s.weight for s in samples]))


def calibrate(model: NoiseModel, sample: CalibrationSample, target: float, iterations: int = 22) -> tuple[float, float]:
    """Strength whose input mIoU over ``sample`` is ``target`` (bisection; mIoU falls with strength).

    Returns (strength, mIoU reached on the sample). Targets out of reach are clamped to
    strength 0 (perfect input) or MAX_STRENGTH.
    """
    c = model.labels.num_classes

    def miou(strength: float) -> float:
        truth = sample.noise.truth.astype(np.int64)
        return weighted_miou(truth, model.predict(sample.noise, strength), sample.weight, c,
                             model.labels.ignore_classes)

    lo, hi = 0.0, MAX_STRENGTH
    if miou(hi) >= target:
        return hi, miou(hi)
    if miou(lo) <= target:
        return lo, miou(lo)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if miou(mid) > target:
            lo = mid
        else:
            hi = mid
    strength = 0.5 * (lo + hi)
    return strength, miou(strength)
