"""An input segmentation for labelled real scans: a documented *noise model*, not a network.

Real SemanticKITTI scans come with ground truth but without any network's predictions. This
module makes an input segmentation from the labels by corrupting them the way a LiDAR
segmentation network is wrong: in places and on whole objects, not at random points. Nothing
is learnt and no network is run; every error is drawn from the rules below, deterministically
from (seed, sequence, scan, world position, instance id). All classes are learning classes
(``config/semantic_kitti.yaml``); the confusion table ``CONFUSIONS``, the per-class
``DIFFICULTY``, ``range_factor`` and the hash and blob kernels are the synthetic drives'
(``convbki_core.synth.noise``, ``convbki_core.synth.lidar``), imported.

The mechanisms, from the lowest priority to the highest (a later one overwrites an earlier
one on the points it hits). ``s`` is the one knob, ``strength``; ``f = range_factor(range) ** 2``
(0.30 near the car, 0.46 at 15 m, 1.1 at 30 m, 3.8 at 50 m, 9 from 66 m on: errors grow with range)
and ``x = s * DIFFICULTY[class] * f`` (DIFFICULTY: road 0.25, car and building 0.45, ...,
bicycle and other-ground 2.2). Rate constants: K_POINT 0.03, K_VIEW 0.12, K_BOUNDARY 1.5,
K_WORLD 0.4, K_OBJECT 1.0.

1. **Range-dependent confusions, per scan** (imitates a network's view-dependent mistakes,
   most of them on sparse, far returns). Salt and pepper: each point flips with rate
   ``1 - exp(-K_POINT * x)`` to a confused class drawn from ``CONFUSIONS`` (road <-> parking
   <-> sidewalk <-> other-ground <-> terrain, vegetation <-> terrain <-> trunk, pole <-> trunk
   <-> traffic-sign, building <-> fence <-> vegetation, car <-> truck <-> other-vehicle, ...).
   View blobs: spheres of 0.3-0.7 m radius on 0.8 m world cells, re-drawn in every scan; a
   blob is active with rate ``1 - exp(-K_VIEW * x)`` and its points show one confused class.
2. **Boundary blur** (imitates the bleeding of classes across their borders: the curb, a car's
   bottom over the road, trunk into crown). A point whose nearest point of another class in
   the same scan lies ``d < BLUR_WIDTH`` (0.4 m) away takes that neighbour's class with
   probability ``(1 - exp(-K_BOUNDARY * s * f)) * (1 - d / BLUR_WIDTH) ** 0.7``, falling with
   the distance; three quarters of it persistent (one uniform per 0.25 m world voxel, so the
   same border is wrong in every scan), one quarter re-drawn per scan. Points 0.4 m or more
   from any other class are never blurred. The neighbour search is a voxel hash in numba
   (``nearest_other``).
3. **Range-dependent confusions, persistent** (imitates a network's systematic mistakes: the
   same bush is terrain in every scan). World blobs: spheres of 0.4-1 m radius on 1.2 m cells
   of the world frame (the sequence's poses), active with rate ``1 - exp(-K_WORLD * x)``, each
   showing one confused class (``CONFUSIONS``) in every scan that sees it; as the range of
   the points falls the rate does too, so a blob seen far away may vanish up close.
4. **Per-object persistent confusions inside confusion groups** (imitates a network that
   takes a parked van for a car, a motorcycle for a bicycle, a cyclist for a pedestrian). The
   groups: vehicles (car, truck, other-vehicle; bus and on-rails map to other-vehicle),
   two-wheelers (bicycle, motorcycle) and people (person, bicyclist, motorcyclist). An object
   is one real instance id (the high 16 bits of the label words) of one class; things without
   an instance id are grouped by 3 m world cells. A hash of (seed, sequence, instance id, true
   class) decides whether the object is confused, with rate ``1 - exp(-K_OBJECT * s *
   OBJECT_DIFFICULTY[class])`` (car 0.4, person 1, bicyclist 1.5, two-wheelers and
   motorcyclist 2, truck and other-vehicle 2.5: big and rare vehicles often, cars rarely), and
   into which class of its group (weights of ``CONFUSIONS`` inside the group); the rate does
   not depend on range. In each scan a draw decides how the confused object shows it: on all
   its points (50 % of the scans), on most (60-95 %, 25 % of the scans), on a part (15-45 %,
   10 %) or not at all (15 %); the points shown are those on one side of a random vertical
   plane through the object, so a part is one piece. In 15 % of the scans a vehicle or a
   person shows the third class of its group instead. So a parked van reads "car" in one
   scan and "other-vehicle" in the next: label flicker that is not motion. An object just
   past its confusion threshold shows it on a share of its points that grows from 0 to the
   scan's share as its confusion probability passes the object's draw by ``OBJECT_RAMP``
   (0.03), so the input's mIoU is continuous in the strength (blobs likewise fill over
   ``BLOB_RAMP``, 15 % of their rate) and the bisection can meet a target closely.

Points the ground truth leaves unlabelled (class 0, not scored) first take the class (and the
object) of the nearest labelled point within 1 m, as a network labels every point; those with
none keep 0. Moving objects keep their static class: the input marks no moving ids, like a
single-scan network's. Instance bits are written as 0. At mIoU 0.55 on the first 10 scans of
real sequences 00, 01 and 05 (``label_noise.json``'s ``wrong_points_by_mechanism``), of the
wrong points 52-69 % come from persistent world blobs, 11-25 % from boundary blur, 17-22 % from the
per-scan mechanisms and 0-6 % from object confusions (few points, but whole objects: the
flicker a map must fuse).

One knob, ``strength``, scales every rate; ``calibrate`` finds by bisection the strength whose
input mIoU over all the written scans (as ``convbki_core.measures.metrics`` computes it: class 0
ignored, mean over the classes in the ground truth) is the target, within ``TOLERANCE``
(0.002; a target the model cannot meet within 0.01 is reported as out of reach):
``label_noise_calibration``. The neighbour search is ``label_noise_neighbours``.
"""

from __future__ import annotations

import hashlib
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np

from convbki_core.datasets import Frame
from convbki_core.datasets.label_noise_neighbours import nearest_other
from convbki_core.io.labels import LabelMap
from convbki_core.synth import lidar
from convbki_core.synth.noise import CONFUSIONS, DIFFICULTY, range_factor

MODEL_VERSION = 1

BLUR_WIDTH = 0.4  # m: how far from another class a point can be blurred
BOUNDARY_VOXEL = 0.25  # m: world voxel of the persistent blur draw
FILL_RADIUS = 1.0  # m: an unlabelled point takes the class of the nearest labelled point this close
WORLD_BLOB_CELL = 1.2  # m: persistent blobs
VIEW_BLOB_CELL = 0.8  # m: per-scan blobs
OBJECT_CELL = 3.0  # m: world cell grouping a thing class's points that carry no instance id
BLUR_PERSISTENT = 0.75  # share of the blur probability drawn per world voxel (the rest per scan)
# Rate constants: rate = 1 - exp(-K * strength * ...).
K_POINT, K_VIEW, K_BOUNDARY, K_WORLD, K_OBJECT = 0.03, 0.12, 1.5, 0.4, 1.0
# How readily a whole object of a class is taken for another class of its group.
OBJECT_DIFFICULTY = {"car": 0.4, "truck": 2.5, "other-vehicle": 2.5, "bicycle": 2.0, "motorcycle": 2.0,
                     "person": 1.0, "bicyclist": 1.5, "motorcyclist": 2.0}
GROUPS = (("car", "truck", "other-vehicle"), ("bicycle", "motorcycle"), ("person", "bicyclist", "motorcyclist"))
# How a confused object shows its confusion in one scan: (probability, smallest, largest share of its points).
SCAN_MODES = ((0.50, 1.0, 1.0), (0.25, 0.6, 0.95), (0.10, 0.15, 0.45), (0.15, 0.0, 0.0))
THIRD_CLASS = 0.15  # share of the scans in which a confused object of a 3-class group shows the third class
OBJECT_RAMP = 0.03  # confusion-probability range over which a newly confused object grows to its full share
BLOB_RAMP = 0.15  # relative rate range over which a newly active blob fills
RANGE_POWER = 2.0  # rates grow with range_factor(range) ** RANGE_POWER
# Mechanism codes of ``predict``'s second result (which rule set each point's label).
NONE, POINT, VIEW_BLOB, BOUNDARY, WORLD_BLOB, OBJECT = range(6)
MECHANISMS = ("none", "point", "view_blob", "boundary", "world_blob", "object")


def _salt(seed: int, sequence: str, stream: str) -> int:
    """A 56-bit hash salt of (seed, sequence, stream), the same on every machine."""
    text = f"label_noise/{seed}/{sequence}/{stream}".encode()
    return int.from_bytes(hashlib.blake2b(text, digest_size=7).digest(), "little")


def sequence_number(sequence: str) -> int:
    """The sequence as an integer for the hashes (``"05"`` -> 5; a non-numeric name by its CRC)."""
    return int(sequence) if sequence.isdigit() else zlib.crc32(sequence.encode())


# ---- the draws of one scan ----------------------------------------------------------------------
@dataclass
class ScanDraws:
    """Everything ``predict`` needs about each point (N points of one or several scans); all
    independent of the strength, so a calibration draws once and predicts many times."""

    truth: np.ndarray  # (N,) int8 ground-truth learning class (0: unlabelled, not scored)
    base: np.ndarray  # (N,) int8 the class the noise starts from (truth; unlabelled: nearest labelled)
    distance: np.ndarray  # (N,) float32 range from the sensor, m
    neighbour: np.ndarray  # (N,) int8 class of the nearest point of another class within BLUR_WIDTH, -1 none
    neighbour_dist: np.ndarray  # (N,) float32, m (inf: none)
    point_u: np.ndarray  # (N,) float32 per-scan uniforms of the salt and pepper
    point_v: np.ndarray
    view_m: np.ndarray  # (N,) float32 activation of the per-scan blob holding the point (1: none)
    view_v: np.ndarray  # its confused-class draw
    view_r: np.ndarray  # per-point fill draw of the blob ramp
    world_m: np.ndarray  # (N,) float32 the same for the persistent world blobs
    world_v: np.ndarray
    world_r: np.ndarray
    blur_persistent: np.ndarray  # (N,) float32 uniform of the point's 0.25 m world voxel
    blur_scan: np.ndarray  # (N,) float32 per-scan uniform
    object_u: np.ndarray  # (N,) float32 the object's confusion draw (2: the point is on no object)
    object_share: np.ndarray  # (N,) float32 share of the object's points that show the confusion this scan
    object_q: np.ndarray  # (N,) float32 the point's place along the scan's cut through the object, in (0, 1)
    object_class: np.ndarray  # (N,) int8 the class the object shows this scan when confused
    object_key: np.ndarray  # (N,) int64 the object's id (instance << 5 | class; -1: no object)

    def __len__(self) -> int:
        return len(self.truth)

    def subset(self, keep: np.ndarray) -> ScanDraws:
        return ScanDraws(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    @staticmethod
    def join(parts: Sequence[ScanDraws]) -> ScanDraws:
        return ScanDraws(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(ScanDraws)})


class LabelNoiseModel:
    """The noise model of one sequence and seed (module docstring)."""

    def __init__(self, label_map: LabelMap, seed: int, sequence: str):
        self.label_map = label_map
        self.seed = int(seed)
        self.sequence = str(sequence)
        self.sequence_id = sequence_number(self.sequence)
        c = label_map.num_classes
        names = {name: i for i, name in enumerate(label_map.class_names)}
        weights = np.zeros((c, c))
        for true, row in CONFUSIONS.items():
            for predicted, weight in row.items():
                weights[names[true], names[predicted]] = weight
        weights[0, 0] = 1.0  # class 0 (nothing near to take from) stays 0
        self.cumulative = np.cumsum(weights / weights.sum(1, keepdims=True).clip(1e-12), 1)
        self.difficulty = np.zeros(c)
        for name, value in DIFFICULTY.items():
            self.difficulty[names[name]] = value
        self.object_difficulty = np.zeros(c)
        for name, value in OBJECT_DIFFICULTY.items():
            self.object_difficulty[names[name]] = value
        # Per class of a group: its group's other classes and their weights (from CONFUSIONS).
        self.group_of = np.full(c, -1, np.int64)
        self.group_classes: list[tuple[int, ...]] = []
        self.in_group: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for number, group in enumerate(GROUPS):
            members = tuple(names[name] for name in group)
            self.group_classes.append(members)
            for name in group:
                others = [other for other in group if other != name]
                w = np.array([CONFUSIONS[name].get(other, 0.0) for other in others]) + 1e-3
                self.group_of[names[name]] = number
                self.in_group[names[name]] = (np.array([names[o] for o in others]), np.cumsum(w / w.sum()))

    def salt(self, stream: str) -> int:
        return _salt(self.seed, self.sequence, stream)

    # ---- draws --------------------------------------------------------------------------------
    def draws(self, frame: Frame, instances: np.ndarray) -> ScanDraws:
        """The draws of one scan. ``frame`` needs points, pose, index and ground truth;
        ``instances``: (N,) the instance ids of its label words (``words >> 16``)."""
        truth = np.asarray(frame.ground_truth, np.int64)
        n = len(truth)
        points = np.ascontiguousarray(frame.points, np.float64)
        world = points @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        distance = np.linalg.norm(points, axis=1).astype(np.float32)
        scan = int(frame.index)
        instances = np.asarray(instances, np.int64)

        # Unlabelled points take the class and object of the nearest labelled point within FILL_RADIUS.
        base = truth.copy()
        instance = instances.copy()
        unlabelled = np.flatnonzero(truth == 0)
        if len(unlabelled):
            nearest, _ = nearest_other(points, truth, FILL_RADIUS, points[unlabelled], truth[unlabelled])
            found = nearest >= 0
            base[unlabelled[found]] = truth[nearest[found]]
            instance[unlabelled[found]] = instances[nearest[found]]

        # Boundary blur: the nearest point of another class within BLUR_WIDTH.
        nearest, neighbour_dist = nearest_other(points, base, BLUR_WIDTH)
        neighbour = np.where(nearest >= 0, base[np.maximum(nearest, 0)], -1)
        voxel = np.floor(world / BOUNDARY_VOXEL).astype(np.int64)
        blur_persistent = lidar.hash_uniform(self.salt("boundary"), voxel[:, 0], voxel[:, 1], voxel[:, 2])
        world_r = lidar.hash_uniform(self.salt("world-fill"), voxel[:, 0], voxel[:, 1], voxel[:, 2])

        world_m, world_v = lidar.blob_field(world, WORLD_BLOB_CELL, self.salt("world-blobs"))
        view_salt = _salt(self.seed, self.sequence, f"view-blobs/{scan}")
        view_m, view_v = lidar.blob_field(world, VIEW_BLOB_CELL, view_salt)
        rng = np.random.default_rng([self.salt("scan"), scan])
        point_u, point_v, view_r, blur_scan = rng.random((4, n), dtype=np.float32)

        objects = self._object_draws(world, base, instance, scan)
        return ScanDraws(truth.astype(np.int8), base.astype(np.int8), distance, neighbour.astype(np.int8),
                         neighbour_dist.astype(np.float32), point_u, point_v, view_m, view_v.astype(np.float32),
                         view_r, world_m, world_v.astype(np.float32), world_r.astype(np.float32),
                         blur_persistent.astype(np.float32), blur_scan, *objects)

    def _object_draws(self, world: np.ndarray, base: np.ndarray, instance: np.ndarray, scan: int):
        n = len(base)
        on_object = self.group_of[base] >= 0
        # The object id: the instance id, or a 3 m world cell for things without one.
        cell = np.floor(world / OBJECT_CELL).astype(np.int64)
        cell_id = 0x10000 + (lidar.hash_uniform(self.salt("object-cell"), cell[:, 0], cell[:, 1], cell[:, 2])
                             * float(1 << 40)).astype(np.int64)
        key = np.where(on_object, (np.where(instance > 0, instance, cell_id) << 5) | base, -1)
        object_u = np.full(n, 2.0, np.float32)
        object_share = np.zeros(n, np.float32)
        object_q = np.ones(n, np.float32)
        object_class = base.astype(np.int8)
        where = np.flatnonzero(on_object)
        if not len(where):
            return object_u, object_share, object_q, object_class, key
        keys, inverse = np.unique(key[where], return_inverse=True)
        classes = keys & 0x1F
        ids = keys >> 5
        sequence = np.full(len(keys), self.sequence_id, np.int64)
        scans = np.full(len(keys), scan, np.int64)
        # Persistent: whether the object is confused, and into which class of its group.
        confused_u = lidar.hash_uniform(self.salt("object-confused"), ids, classes, sequence)
        class_v = lidar.hash_uniform(self.salt("object-class"), ids, classes, sequence)
        # Per scan: how it shows (mode, share), where the cut runs, whether the third class shows.
        mode_u = lidar.hash_uniform(self.salt("object-mode"), ids, classes, scans)
        share_u = lidar.hash_uniform(self.salt("object-share"), ids, classes, scans)
        angle_u = lidar.hash_uniform(self.salt("object-cut"), ids, classes, scans)
        third_u = lidar.hash_uniform(self.salt("object-third"), ids, classes, scans)
        shown = np.empty(len(keys), np.int64)
        share = np.zeros(len(keys))
        bounds = np.cumsum([mode[0] for mode in SCAN_MODES])
        for k, c in enumerate(classes):
            others, cumulative = self.in_group[int(c)]
            primary = int(np.searchsorted(cumulative, class_v[k], side="right").clip(0, len(others) - 1))
            shown[k] = others[primary]
            if len(others) > 1 and third_u[k] < THIRD_CLASS:
                shown[k] = others[1 - primary]
            _, low, high = SCAN_MODES[min(int(np.searchsorted(bounds, mode_u[k], side="right")), len(bounds) - 1)]
            share[k] = low + (high - low) * share_u[k]
        # The point's place along a random horizontal direction through its object: the points
        # with the smallest places show the confusion, so a part is one piece of the object.
        angle = 2 * np.pi * angle_u[inverse]
        along = world[where, 0] * np.cos(angle) + world[where, 1] * np.sin(angle)
        order = np.lexsort((along, inverse))
        counts = np.bincount(inverse, minlength=len(keys))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.arange(len(where)) - starts[inverse[order]]
        place = np.empty(len(where))
        place[order] = (rank + 0.5) / counts[inverse[order]]
        object_u[where] = confused_u[inverse]
        object_share[where] = share[inverse]
        object_q[where] = place
        object_class[where] = shown[inverse]
        return object_u, object_share, object_q, object_class, key

    # ---- prediction ---------------------------------------------------------------------------
    def _pick(self, true_class: np.ndarray, v: np.ndarray) -> np.ndarray:
        """A confused class for each point from its true class's row of CONFUSIONS, by uniform ``v``."""
        pick = np.zeros(len(true_class), np.int64)
        rows = self.cumulative[true_class]
        for column in range(self.label_map.num_classes - 1):
            pick += v > rows[:, column]
        return pick

    def _blob(self, m: np.ndarray, r: np.ndarray, rate: np.ndarray) -> np.ndarray:
        """Points of active blobs: a blob fills as the rate passes its activation (BLOB_RAMP)."""
        fill = np.clip((rate - m) / np.maximum(BLOB_RAMP * rate, 1e-9), 0.0, 1.0)
        return (m < rate) & (r < fill)

    def object_rate(self, classes: np.ndarray, strength: float) -> np.ndarray:
        """Probability that an object of each class is confused, at ``strength``."""
        return 1.0 - np.exp(-K_OBJECT * strength * self.object_difficulty[classes])

    def predict(self, d: ScanDraws, strength: float) -> tuple[np.ndarray, np.ndarray]:
        """(predicted learning class (N,) int64, mechanism that set it (N,) int8: ``MECHANISMS``)."""
        c = d.base.astype(np.int64)
        predicted = c.copy()
        mechanism = np.zeros(len(c), np.int8)
        if strength <= 0:
            return predicted, mechanism
        factor = range_factor(d.distance) ** RANGE_POWER
        x = strength * self.difficulty[c] * factor

        def apply(flip: np.ndarray, labels: np.ndarray | Callable[[np.ndarray], np.ndarray], code: int) -> None:
            predicted[flip] = labels(flip) if callable(labels) else labels[flip]
            mechanism[flip] = code

        apply(d.point_u < 1 - np.exp(-K_POINT * x), lambda f: self._pick(c[f], d.point_v[f]), POINT)
        apply(self._blob(d.view_m, d.view_r, 1 - np.exp(-K_VIEW * x)), lambda f: self._pick(c[f], d.view_v[f]),
              VIEW_BLOB)
        has = d.neighbour >= 0
        p_blur = np.zeros(len(c))
        p_blur[has] = (1 - np.exp(-K_BOUNDARY * strength * factor[has])) \
            * (1 - d.neighbour_dist[has] / BLUR_WIDTH).clip(0, 1) ** 0.7
        blur = has & ((d.blur_persistent < BLUR_PERSISTENT * p_blur) | (d.blur_scan < (1 - BLUR_PERSISTENT) * p_blur))
        apply(blur, d.neighbour.astype(np.int64), BOUNDARY)
        apply(self._blob(d.world_m, d.world_r, 1 - np.exp(-K_WORLD * x)),
              lambda f: self._pick(c[f], d.world_v[f]), WORLD_BLOB)
        on_object = d.object_u < 1.5
        ramp = np.zeros(len(c))
        ramp[on_object] = np.clip((self.object_rate(c[on_object], strength) - d.object_u[on_object]) / OBJECT_RAMP,
                                  0, 1)
        apply(on_object & (d.object_q < d.object_share * ramp), d.object_class.astype(np.int64), OBJECT)
        return predicted, mechanism

