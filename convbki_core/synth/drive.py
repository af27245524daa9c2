"""The synthetic-drive generator: scene + route + LiDAR + noise model -> SemanticKITTI files.

Frames: the *scene* frame is the one the scene is built in (streets along its axes, ground at
z = 0); the *map/world* frame of the written poses is the scene frame turned by a random yaw
and shifted by a random offset (``world_from_scene``), so the first pose is an arbitrary one,
never the identity; the *sensor* frame is the Velodyne's (x forward, y left, z up), in which
the scans are written.

With ``movers`` > 0 the drive also has moving road users (``traffic`` plans them, ``movers``
poses and casts them, and writes ``movers.json``); with 0, the default, none of that runs:
the scene, the scans and every file are those of the static drive, byte for byte. The options
added later keep to the same rule: ``traffic`` other than ``classic`` (movers that stop, crawl
or pass close) and ``moving_labels`` (predictions with the moving raw ids, as a multi-scan
segmentation network gives them) change the drive only when set, and only then appear in
synth.yaml.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from convbki_core.io.labels import load_label_map
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.synth import drift, lidar, movers, traffic, writer
from convbki_core.synth.noise import BLUR_WIDTH, CalibrationSample, NoiseModel, PointNoise, calibrate
from convbki_core.synth.primitives import OUTLIER
from convbki_core.synth.route import Trajectory, drive
from convbki_core.synth.scene import Scene, build_scene
from convbki_core.synth.streets import StreetLayout

VERSION = 1
OUTLIER_RATE = 0.002  # spurious returns (dust, multi-path), labelled "outlier" (learning class 0)
CALIBRATION_POINTS = 1_000_000  # points kept over the whole drive to calibrate the noise strength

# Remission by learning class (Velodyne-like reflectivity in [0, 1]): dark asphalt, brighter
# concrete and vegetation, retro-reflective sign plates.
REMISSION = {
    "car": 0.3, "bicycle": 0.25, "motorcycle": 0.3, "truck": 0.3, "other-vehicle": 0.3, "person": 0.3,
    "bicyclist": 0.3, "motorcyclist": 0.3, "road": 0.2, "parking": 0.22, "sidewalk": 0.3,
    "other-ground": 0.26, "building": 0.32, "fence": 0.3, "vegetation": 0.45, "trunk": 0.35, "terrain": 0.38,
    "pole": 0.4, "traffic-sign": 0.9,
}
MARKING_REMISSION = 0.7


class SynthError(Exception):
    """A drive that cannot be written as asked (the message says why)."""


@dataclass
class DriveConfig:
    """Settings of one synthetic drive (units: m, m/s, s)."""

    out: Path
    sequence: str = "00"
    frames: int = 100
    seed: int = 0
    input_miou: float = 0.55
    noise_strength: float | None = None  # set: skip calibration and use this strength
    probabilities: bool = False
    beams: int = 64
    azimuth_steps: int = 2083
    speed: float = 8.0  # cruise speed, m/s
    max_range: float = 90.0
    range_noise: float = 0.02  # sigma, m
    force: bool = False
    movers: int = 0  # moving road users planned over the drive
    traffic: str = "classic"  # the movers' behaviour mix, a key of traffic.TRAFFIC
    moving_labels: bool = False  # predictions of correctly classified mover points carry moving raw ids
    drift_heading: float = 0.0  # odometry's heading bias, degrees per 100 m (0 with drift_scale 0: no odometry.txt)
    drift_scale: float = 0.0  # odometry's scale error, a fraction
    loop_closure: int | None = None  # frame at which the SLAM closes the loop (None: after the first lap, or the last)
    keyframe_every: int = 5  # scans between the keyframes a SLAM re-publishes at the closure


@dataclass
class Scan:
    """One simulated scan (N returned points)."""

    points: np.ndarray  # (N, 3) float32 sensor frame, m (measured)
    remission: np.ndarray  # (N,) float32
    label_words: np.ndarray  # (N,) uint32 ground truth: raw id | instance << 16
    truth: np.ndarray  # (N,) int64 learning class of the ground truth (0 for outliers)
    noise: PointNoise


@dataclass
class DriveResult:
    """What was written, for the summary and synth.yaml."""

    sequence_dir: Path
    frames: int
    points: list[int]
    seconds_per_frame: float  # whole run (scene, calibration pre-pass, writing) / frames
    strength: float
    calibrated: bool
    sample_miou: float | None
    confusion: ConfusionMatrix
    class_points: np.ndarray
    info: dict = field(default_factory=dict)
    placed_movers: list[movers.Mover] = field(default_factory=list)  # may be fewer than asked
    moving_points: list[int] = field(default_factory=list)  # points with a moving raw id, per frame


def world_from_scene(seed: int) -> np.ndarray:
    """4x4 map <- scene transform: random heading and offset (the map frame of the drive)."""
    rng = np.random.default_rng([seed, 0x3091D])
    yaw = rng.uniform(-math.pi, math.pi)
    t = np.eye(4)
    t[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    t[:3, 3] = (rng.uniform(-400, 400), rng.uniform(-400, 400), rng.uniform(-3, 3))
    return t


def _trajectory(scene: Scene, config: DriveConfig) -> Trajectory:
    return drive(scene.route, config.frames, config.speed, scene.start_s, np.random.default_rng([config.seed, 0xD21]))


def _traffic(config: DriveConfig) -> Callable[[StreetLayout], list[movers.Mover]]:
    """The mover planner of ``config``: around the very trajectory ``_trajectory`` gives."""
    def plan(layout: StreetLayout) -> list[movers.Mover]:
        ego = drive(layout.route_, config.frames, config.speed, layout.start_s,
                    np.random.default_rng([config.seed, 0xD21]))
        return traffic.plan(layout, ego, config.movers, config.seed, config.speed, config.traffic)
    return plan


def lidar_poses(config: DriveConfig, scene: Scene | None = None) -> np.ndarray:
    """(F, 4, 4) LiDAR poses in the map frame (map <- sensor) that ``config`` produces."""
    scene = scene or build_scene(config.seed)
    return world_from_scene(config.seed) @ _trajectory(scene, config).poses


class Simulator:
    """Casts scans in a scene and attaches everything the noise model needs."""

    def __init__(self, scene: Scene, config: DriveConfig, model: NoiseModel):
        self.scene, self.config, self.model = scene, config, model
        self.labels = model.labels
        names = self.labels.class_names
        self.remission_base = np.array([REMISSION.get(n, 0.3) for n in names])
        self.prim_tint = lidar.hash_uniform(config.seed * 16 + 9, np.arange(len(scene.kind), dtype=np.int64),
                                            np.zeros(len(scene.kind), np.int64), np.zeros(len(scene.kind), np.int64))
        self.part = np.where(scene.instance > 0, scene.part, -1).astype(np.int64)
        self.mover_tints = movers.tints(scene.movers, config.seed * 16 + 10)

    def scan(self, pose: np.ndarray, frame: int, beams: lidar.Beams) -> Scan:
        """Scan from scene-frame ``pose`` (4x4, scene <- sensor) for scan number ``frame``."""
        sc, cfg, grid = self.scene, self.config, self.scene.grid
        rot, origin = pose[:3, :3], np.ascontiguousarray(pose[:3, 3])
        dirs = np.ascontiguousarray(beams.dirs @ rot.T)
        salt = (cfg.seed * 1_000_003 + frame) * 16 + 8
        t, prim, cos = lidar.cast_rays(origin, dirs, cfg.max_range, salt, sc.kind, sc.param, grid.start, grid.items,
                                       grid.x0, grid.y0, grid.cell, grid.nx, grid.ny)
        frame_movers = movers.frame_of(sc.movers, frame, self.mover_tints) if sc.movers else None
        if frame_movers is not None:
            # Movers hide what is behind them; prim -3 marks a mover hit, ``which`` says whose.
            mt, which, mcos = movers.cast(origin, dirs, np.minimum(t, cfg.max_range), frame_movers)
            nearer = which >= 0
            t, cos = np.where(nearer, mt, t), np.where(nearer, mcos, cos)
            prim = np.where(nearer, -3, prim).astype(np.int32)
        keep = np.flatnonzero(np.isfinite(t) & ~beams.ego)
        t, prim, cos = t[keep], prim[keep], cos[keep]
        which = which[keep] if frame_movers is not None else None
        n = len(keep)
        rng = np.random.default_rng([cfg.seed, frame, 0x5CA7])
        measured = t + rng.normal(0.0, cfg.range_noise, n) if cfg.range_noise > 0 else t.copy()
        outlier = rng.random(n) < OUTLIER_RATE
        measured[outlier] = t[outlier] * rng.uniform(0.3, 0.95, int(outlier.sum()))
        measured = np.maximum(measured, 0.5)
        hit = origin + dirs[keep] * t[:, None]  # true surface point, scene frame
        seen = origin + dirs[keep] * measured[:, None]  # what the sensor reports, scene frame
        # Ground truth: primitive class, or the ground raster under the hit.
        raster = sc.raster
        ix = np.clip(((hit[:, 0] - raster.x0) / raster.res).astype(np.int64), 0, raster.nx - 1)
        iy = np.clip(((hit[:, 1] - raster.y0) / raster.res).astype(np.int64), 0, raster.ny - 1)
        moving = prim == -3
        ground = (prim < 0) & ~moving
        obj = np.where(prim < 0, 0, prim)
        raw = np.where(ground, sc.ground_raw[iy, ix], sc.raw[obj]).astype(np.uint32)
        instance = np.where(ground, 0, sc.instance[obj]).astype(np.uint32)
        part = np.where(ground, -1, self.part[obj])
        tint = np.where(ground, 0.5, self.prim_tint[obj])
        if which is not None:
            q = which[moving]
            raw[moving], instance[moving] = frame_movers.raw[q], frame_movers.instance[q]
            part[moving], tint[moving] = frame_movers.part[q], frame_movers.tint[q]
        surface = self.labels.learning_map[raw].astype(np.int64)
        gt_raw = np.where(outlier, OUTLIER, raw).astype(np.uint32)
        instance[outlier] = 0
        # Remission: class reflectivity, per-object tint, lane paint, incidence angle, range, noise.
        base = np.where(ground & sc.marking[iy, ix], MARKING_REMISSION, self.remission_base[surface])
        angle = np.where(surface == self.labels.class_names.index("traffic-sign"), 0.85 + 0.15 * cos, 0.4 + 0.6 * cos)
        remission = base * (0.75 + 0.5 * tint) * angle * (1.0 - 0.2 * np.minimum(t / 80.0, 1.0))
        remission = np.clip(remission + rng.normal(0, 0.025, n), 0.0, 1.0).astype(np.float32)
        nb_class, nb_dist = lidar.neighbour_query(seen, surface, sc.kind, sc.param, sc.learning, grid.start,
                                                  grid.items, grid.x0, grid.y0, grid.cell, grid.nx, grid.ny, sc.top,
                                                  sc.nb_class, sc.nb_dist, raster.x0, raster.y0, raster.res,
                                                  BLUR_WIDTH)
        if frame_movers is not None:
            nb_class, nb_dist = movers.neighbours(seen, surface, frame_movers, self.labels.learning_map, BLUR_WIDTH,
                                                  nb_class, nb_dist)
        noise = self.model.features(seen, surface, measured, part, nb_class, nb_dist, frame)
        points = (beams.dirs[keep] * measured[:, None]).astype(np.float32)
        truth = self.labels.learning_map[gt_raw].astype(np.int64)
        return Scan(points, remission, gt_raw | (instance << np.uint32(16)), truth, noise)


def check_destination(config: DriveConfig) -> None:
    """Raise SynthError when the drive may not be written where ``config`` says (nothing is created)."""
    if config.loop_closure is not None and not (config.drift_heading or config.drift_scale):
        raise SynthError("--loop-closure needs --drift or --drift-scale: without drift there is nothing to close")
    if config.loop_closure is not None and not 1 <= config.loop_closure < config.frames:
        raise SynthError(f"--loop-closure {config.loop_closure} must be a frame of the drive, 1..{config.frames - 1}")
    try:
        writer.check_sequence(Path(config.out), config.sequence, config.force)
    except (FileExistsError, PermissionError, NotADirectoryError) as error:
        raise SynthError(str(error)) from None


def generate_drive(config: DriveConfig, progress: Callable[[int], None] | None = None,
                   status: Callable[[str], None] | None = None) -> DriveResult:
    """Write the drive ``config`` describes.

    ``progress(k)`` is called after each simulated scan: k runs to ``frames`` in the calibration
    pre-pass, then on to 2 * ``frames`` in the writing pass (only the latter without calibration).
    """
    lidar.require_numba()
    if config.traffic not in traffic.TRAFFIC:
        raise SynthError(f"unknown traffic {config.traffic!r} (one of: {', '.join(traffic.TRAFFIC)})")
    say = status or (lambda _text: None)
    try:
        seq = writer.prepare_sequence(Path(config.out), config.sequence, config.force, config.probabilities)
    except (FileExistsError, PermissionError, NotADirectoryError) as error:
        raise SynthError(str(error)) from None
    except OSError as error:
        raise SynthError(f"cannot create the sequence folder: {error}") from None
    started = time.perf_counter()
    labels = load_label_map()
    say("building the scene")
    if config.movers:
        say("planning the movers")
    scene = build_scene(config.seed, _traffic(config) if config.movers else None)
    trajectory = _trajectory(scene, config)
    model = NoiseModel(labels, config.seed)
    sim = Simulator(scene, config, model)
    beams = lidar.Beams.hdl64(config.beams, config.azimuth_steps, config.seed)

    sample_miou = None
    if config.noise_strength is None:
        # Calibration pre-pass: simulate every scan once and keep a weighted sample of its
        # points' noise draws (the write pass re-creates exactly the same scans and draws).
        say("calibrating the segmentation noise")
        per_class = max(100, CALIBRATION_POINTS // (config.frames * labels.num_classes))
        rng = np.random.default_rng([config.seed, 0xCA1])
        samples = []
        for k in range(config.frames):
            scan = sim.scan(trajectory.poses[k], k, beams)
            samples.append(CalibrationSample.of(scan.noise, scan.truth, per_class, rng))
            if progress:
                progress(k + 1)
        sample = CalibrationSample.join(samples)
        del samples
        strength, sample_miou = calibrate(model, sample, config.input_miou)
        del sample
    else:
        strength = float(config.noise_strength)

    tr = writer.velodyne_to_camera()
    poses = world_from_scene(config.seed) @ trajectory.poses
    matrix = ConfusionMatrix(labels.num_classes, labels.ignore_classes)
    class_points = np.zeros(labels.num_classes, np.int64)
    counts: list[int] = []
    moving_counts: list[int] = []
    say("writing scans")
    for k in range(config.frames):
        scan = sim.scan(trajectory.poses[k], k, beams)
        pred = model.predict(scan.noise, strength)
        probs = model.probabilities(scan.noise, pred, k) if config.probabilities else None
        predicted_raw = labels.to_raw(pred)
        if config.moving_labels:
            predicted_raw = movers.with_moving_ids(predicted_raw, pred, scan.label_words, labels.learning_map)
        writer.write_scan(seq, k, scan.points, scan.remission, scan.label_words, predicted_raw, probs)
        matrix.add(scan.truth, pred)
        class_points += np.bincount(scan.truth, minlength=labels.num_classes)
        counts.append(len(scan.points))
        if config.movers:
            moving_counts.append(int(np.count_nonzero((scan.label_words & 0xFFFF) >= movers.MOVING_RAW.start)))
        if progress:
            progress(k + 1 + (config.frames if config.noise_strength is None else 0))
    elapsed = time.perf_counter() - started
    writer.write_text(seq / "calib.txt", writer.calib_text(tr))
    writer.write_text(seq / "poses.txt", writer.poses_text(poses, tr))
    writer.write_text(seq / "times.txt", writer.times_text(trajectory.times))
    if config.movers:
        writer.write_text(seq / "movers.json", movers.sidecar(scene.movers, world_from_scene(config.seed),
                                                              config.frames))
    if config.drift_heading or config.drift_scale:
        odometry = drift.drifted_odometry(poses, config.drift_heading, config.drift_scale)
        closure = config.loop_closure or drift.first_lap_frame(poses, scene.route.length) or config.frames - 1
        writer.write_text(seq / "odometry.txt", writer.poses_text(odometry, tr))
        writer.write_yaml(seq / "loop_closure.yaml", drift.record(closure, config.keyframe_every,
                                                                  config.drift_heading, config.drift_scale))
    result = DriveResult(seq, config.frames, counts, elapsed / config.frames, strength,
                         config.noise_strength is None, sample_miou, matrix, class_points, dict(scene.info),
                         scene.movers, moving_counts)
    writer.write_yaml(seq / "synth.yaml", _record(config, result, labels.class_names, trajectory))
    return result


def _record(config: DriveConfig, result: DriveResult, names: tuple[str, ...], trajectory: Trajectory) -> dict:
    """Contents of synth.yaml: the settings and what was measured on the written files."""
    summary = result.confusion.summary(names)
    record = {
        "generator": "convbki_core.tools.synth (synth)",
        "version": VERSION,
        "seed": config.seed,
        "sequence": config.sequence,
        "frames": config.frames,
        "lidar": {"beams": config.beams, "azimuth_steps": config.azimuth_steps, "max_range_m": config.max_range,
                  "range_noise_m": config.range_noise, "sensor_height_m": 1.73, "rate_hz": 10},
        "speed_mps": {"cruise": config.speed, "mean": round(float(np.mean(trajectory.speed)), 3)},
        "probabilities": config.probabilities,
        **({"moving_labels": True} if config.moving_labels else {}),  # absent when not set, as before it existed
        "scene": result.info,
        "world_from_scene": [[round(float(v), 9) for v in row] for row in world_from_scene(config.seed)],
        "noise": {
            "input_miou_target": config.input_miou,
            "strength": round(result.strength, 6),
            "calibrated": result.calibrated,
            "calibration_sample_miou": None if result.sample_miou is None else round(result.sample_miou, 4),
            "input_miou_measured": round(summary["miou"], 4),
            "input_accuracy": round(summary["accuracy"], 4),
            "input_iou": {k: round(v, 4) for k, v in summary["iou"].items()},
        },
        "points_per_frame_mean": round(float(np.mean(result.points)), 1),
        "class_points": {names[c]: int(n) for c, n in enumerate(result.class_points) if n},
    }
    if config.movers:  # absent without movers: such a drive's synth.yaml stays as it always was
        kinds = [movers.KINDS[m.kind][2] for m in result.placed_movers]
        record["movers"] = {
            "requested": config.movers,
            "planned": len(result.placed_movers),
            "classes": {name: kinds.count(name) for name in sorted(set(kinds))},
            "behaviours": {b: sum(m.behaviour == b for m in result.placed_movers)
                           for b in traffic.TRAFFIC[config.traffic]},
            "moving_points_per_frame_mean": round(float(np.mean(result.moving_points)), 1),
            "sidecar": "movers.json",
        }
        if config.traffic != "classic":  # a classic drive's record stays as it always was
            record["movers"]["traffic"] = config.traffic
    return record
