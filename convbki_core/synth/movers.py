"""Moving road users ("movers"): their geometry, their pose in each scan, the ray casting
against them and the ``movers.json`` sidecar.

A mover is one object (car, truck, bus, cyclist, motorcyclist, pedestrian) built from the
same primitives as the static scene (``objects``), in its own frame: x forward, y left, z up,
the origin at the centre of its footprint on the surface it stands on. Every primitive of a
mover carries the mover's *moving* raw id (252 moving-car, 253 moving-bicyclist, 254
moving-person, 255 moving-motorcyclist, 257 moving-bus, 258 moving-truck), which the label
map sends to the same learning class as the static one: the ground truth says "moving-car",
the segmentation noise (which works on learning classes) predicts "car", as a single-scan
network does. With ``synth --moving-labels`` the predictions are those of a multi-scan network
instead (``with_moving_ids``): a mover's point predicted as the mover's class gets the moving
raw id ("moving-car"), every other prediction stays as it was.
``traffic`` plans where the movers go; each has one pose per scan (x, y, ground height, yaw,
scene frame) over a contiguous run of scans, and is absent outside it. A scan sees a mover
where it is at that scan's time (no rolling-shutter smear), in front of whatever static
scene it hides.

Sidecar ``movers.json`` (in the sequence folder, written only when a drive has movers; real
SemanticKITTI has no such file, so readers must treat it as optional)::

    {"format": "convbki-synth-movers", "version": 1,
     "frame": "map",            # the frame of the LiDAR poses inv(Tr) @ P @ Tr of poses.txt
     "frames": F,               # scans in the drive
     "movers": [
       {"instance": 2467,       # instance id in labels/ (label >> 16), unique in the drive
        "raw": 252,             # moving raw id in labels/ (label & 0xFFFF)
        "class": "moving-car",
        "behaviour": "oncoming", # oncoming | lead | crossing | cross-traffic, and with
                                 # --traffic varied also stop-and-go | kerb-cyclist |
                                 # close-pass | sidewalk-pause (see traffic)
        "size": [4.52, 1.83, 1.49],   # box length (along yaw), width, height, m
        "first_frame": 12, "last_frame": 97,
        "poses": [[x, y, z, yaw], ...]}]}  # box centre (m) and heading (rad, about z),
                                           # one per scan first_frame..last_frame

The box is oriented by yaw and encloses every primitive of the mover, so a point labelled with
the mover's instance in scan k lies in the box of ``poses[k - first_frame]`` (up to the range
noise). The space a mover swept is the union of its boxes; the scene has no static object in
it (``scene`` drops those, and keeps parked vehicles, people and bicycles ``MOVABLE_CLEARANCE``
away from it), so in a good map no movable-class voxel remains there, except where a mover
still is at the end of the drive (its last pose).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from convbki_core.synth import objects as obj
from convbki_core.synth.lidar import _intersect, _sdf, hash_uniform, njit, prange
from convbki_core.synth.primitives import CYLINDER, SceneBuilder, footprint_extent

# kind -> (builder, moving raw id, name of that id)
KINDS = {
    "car": (obj.car, 252, "moving-car"),
    "bicyclist": (obj.bicyclist, 253, "moving-bicyclist"),
    "person": (obj.person, 254, "moving-person"),
    "motorcyclist": (obj.motorcyclist, 255, "moving-motorcyclist"),
    "bus": (obj.bus, 257, "moving-bus"),
    "truck": (obj.truck, 258, "moving-truck"),
}
MOVING_RAW = range(252, 260)  # every moving raw id of SemanticKITTI


@dataclass
class Template:
    """A mover's primitives in its own frame (see the module docstring)."""

    kind: np.ndarray  # (P,) int8
    param: np.ndarray  # (P, 9) float64
    part: np.ndarray  # (P,) int32: 0.. within the mover
    size: np.ndarray  # (3,) length, width, height of the enclosing box, m

    @classmethod
    def build(cls, kind: str, rng: np.random.Generator) -> Template:
        builder = SceneBuilder()
        KINDS[kind][0](builder, rng, 0.0, 0.0, 0.0)
        arr = builder.arrays()
        param = arr["param"].copy()
        ext = np.array([footprint_extent(k, row) for k, row in zip(arr["kind"], param)])
        lo = np.min(param[:, :2] - ext, axis=0)
        hi = np.max(param[:, :2] + ext, axis=0)
        param[:, :2] -= (lo + hi) / 2  # the origin at the footprint's centre
        top = float(np.max(param[:, 2] + param[:, 5]))
        return cls(arr["kind"], param, arr["part"], np.array([hi[0] - lo[0], hi[1] - lo[1], top]))

    def posed(self, x: float, y: float, z0: float, yaw: float) -> np.ndarray:
        """(P, 9) primitive rows in the scene frame at pose (x, y, z0, yaw)."""
        c, s = math.cos(yaw), math.sin(yaw)
        p = self.param.copy()
        p[:, 0] = x + c * self.param[:, 0] - s * self.param[:, 1]
        p[:, 1] = y + s * self.param[:, 0] + c * self.param[:, 1]
        p[:, 2] += z0
        turn = self.kind != CYLINDER  # cylinders are vertical: their rows keep cos 1, sin 0
        p[turn, 6] = self.param[turn, 6] * c - self.param[turn, 7] * s
        p[turn, 7] = self.param[turn, 7] * c + self.param[turn, 6] * s
        return p


@dataclass
class Mover:
    """One planned mover. ``pose`` rows are (x, y, z0, yaw), scene frame, valid where ``active``."""

    kind: str
    behaviour: str
    template: Template
    pose: np.ndarray  # (F, 4) float64
    active: np.ndarray  # (F,) bool, one contiguous run
    instance: int = 0  # set when the static scene is numbered
    part0: int = 0  # first part id (noise model), after the static scene's

    @property
    def raw(self) -> int:
        return KINDS[self.kind][1]

    @property
    def frames(self) -> tuple[int, int]:
        """First and last scan the mover is in."""
        on = np.flatnonzero(self.active)
        return int(on[0]), int(on[-1])


@dataclass
class MoverFrame:
    """The movers present in one scan, as primitive tables (CSR by mover)."""

    kind: np.ndarray  # (Q,) int8
    param: np.ndarray  # (Q, 9)
    raw: np.ndarray  # (Q,) uint32 moving raw id
    instance: np.ndarray  # (Q,) uint32
    part: np.ndarray  # (Q,) int64 part id (unique in the drive)
    tint: np.ndarray  # (Q,) float64 per-primitive remission tint
    start: np.ndarray  # (M + 1,) int64
    bounds: np.ndarray  # (M, 4) bounding sphere: centre x, y, z, radius


def frame_of(movers: list[Mover], frame: int, tints: list[np.ndarray]) -> MoverFrame | None:
    """The movers present in scan ``frame`` (None when there are none)."""
    here = [k for k, m in enumerate(movers) if m.active[frame]]
    if not here:
        return None
    params, bounds = [], []
    for k in here:
        m = movers[k]
        x, y, z0, yaw = m.pose[frame]
        params.append(m.template.posed(x, y, z0, yaw))
        bounds.append((x, y, z0 + m.template.size[2] / 2, 0.5 * float(np.linalg.norm(m.template.size)) + 0.05))
    sizes = [len(movers[k].template.kind) for k in here]
    return MoverFrame(
        np.concatenate([movers[k].template.kind for k in here]),
        np.concatenate(params),
        np.concatenate([np.full(n, movers[k].raw, np.uint32) for k, n in zip(here, sizes)]),
        np.concatenate([np.full(n, movers[k].instance, np.uint32) for k, n in zip(here, sizes)]),
        np.concatenate([movers[k].part0 + movers[k].template.part.astype(np.int64) for k in here]),
        np.concatenate([tints[k] for k in here]),
        np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        np.asarray(bounds, np.float64),
    )


def with_moving_ids(predicted_raw: np.ndarray, predicted_class: np.ndarray, truth_words: np.ndarray,
                    learning_map: np.ndarray) -> np.ndarray:
    """Predicted raw ids as a multi-scan network gives them: where the ground truth is a mover
    (a moving raw id) and the prediction is the mover's learning class, the mover's moving raw
    id; elsewhere ``predicted_raw`` unchanged. A wrong class stays wrong and static: the network
    tells motion only of what it recognises."""
    truth_raw = np.asarray(truth_words).astype(np.int64) & 0xFFFF
    moving = (truth_raw >= MOVING_RAW.start) & (truth_raw < MOVING_RAW.stop)
    agree = moving & (learning_map[truth_raw].astype(np.int64) == np.asarray(predicted_class, np.int64))
    out = np.array(predicted_raw, np.uint32, copy=True)
    out[agree] = truth_raw[agree]
    return out


def tints(movers: list[Mover], salt: int) -> list[np.ndarray]:
    """Per-primitive remission tint of each mover (fixed over the drive, like a static object's)."""
    out = []
    for m in movers:
        n = len(m.template.kind)
        out.append(hash_uniform(salt, np.full(n, m.instance, np.int64), np.arange(n, dtype=np.int64),
                                np.zeros(n, np.int64)))
    return out


# ---- ray casting and neighbour queries against the movers of one scan ----------------------------
@njit(parallel=True)
def _cast_kernel(origin, dirs, best_t, kinds, params, start, bounds):
    n = dirs.shape[0]
    out_t = best_t.copy()
    out_q = np.full(n, -1, np.int32)
    out_c = np.zeros(n, np.float32)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in prange(n):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        best = best_t[i]
        for m in range(bounds.shape[0]):
            px, py, pz = bounds[m, 0] - ox, bounds[m, 1] - oy, bounds[m, 2] - oz
            r = bounds[m, 3]
            tc = px * dx + py * dy + pz * dz
            if tc + r < 0.0 or tc - r >= best or px * px + py * py + pz * pz - tc * tc > r * r:
                continue  # the ray misses the mover's bounding sphere, or something nearer hides it
            for q in range(start[m], start[m + 1]):
                t0, t1, nx, ny, nz = _intersect(kinds[q], params[q], ox, oy, oz, dx, dy, dz)
                if t0 >= best or t1 <= 0.0:
                    continue
                best = max(t0, 0.0)
                out_q[i] = q
                out_c[i] = abs(nx * dx + ny * dy + nz * dz)
        out_t[i] = best
    return out_t, out_q, out_c


def cast(origin: np.ndarray, dirs: np.ndarray, best_t: np.ndarray, frame: MoverFrame
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ranges, mover primitive (-1: none nearer than ``best_t``) and incidence cosines of rays
    (unit ``dirs``, scene frame) against the movers of one scan."""
    return _cast_kernel(origin, dirs, best_t, frame.kind, frame.param, frame.start, frame.bounds)


@njit(parallel=True)
def _neighbour_kernel(points, point_class, kinds, params, prim_class, start, bounds, width, nb_class, nb_dist):
    n = points.shape[0]
    out_c = nb_class.copy()
    out_d = nb_dist.copy()
    for i in prange(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        best = min(width, out_d[i])
        for m in range(bounds.shape[0]):
            reach = bounds[m, 3] + best
            if (x - bounds[m, 0]) ** 2 + (y - bounds[m, 1]) ** 2 + (z - bounds[m, 2]) ** 2 > reach * reach:
                continue
            for q in range(start[m], start[m + 1]):
                if prim_class[q] == point_class[i]:
                    continue
                d = _sdf(kinds[q], params[q], x, y, z)
                if d < best:
                    best = d
                    out_c[i], out_d[i] = prim_class[q], d
    return out_c, out_d


def neighbours(points: np.ndarray, point_class: np.ndarray, frame: MoverFrame, learning: np.ndarray,
               width: float, nb_class: np.ndarray, nb_dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``nb_class``/``nb_dist`` (from the static scene) updated with the movers' surfaces: the
    road next to a moving car's wheels blurs into car as it does next to a parked one."""
    prim_class = learning[frame.raw].astype(np.int64)
    return _neighbour_kernel(np.ascontiguousarray(points, np.float64), point_class.astype(np.int64), frame.kind,
                             frame.param, prim_class, frame.start, frame.bounds, float(width), nb_class, nb_dist)


# ---- sidecar -----------------------------------------------------------------------------------------
def sidecar(movers: list[Mover], world_from_scene: np.ndarray, frames: int) -> str:
    """``movers.json`` text (see the module docstring), poses in the map frame."""
    world_yaw = math.atan2(world_from_scene[1, 0], world_from_scene[0, 0])
    entries = []
    for m in movers:
        first, last = m.frames
        pose = m.pose[first:last + 1]
        centre = np.column_stack([pose[:, 0], pose[:, 1], pose[:, 2] + m.template.size[2] / 2, np.ones(len(pose))])
        centre = centre @ world_from_scene.T
        yaw = np.angle(np.exp(1j * (pose[:, 3] + world_yaw)))
        rows = [[round(float(a), 4), round(float(b), 4), round(float(c), 4), round(float(d), 6)]
                for a, b, c, d in zip(centre[:, 0], centre[:, 1], centre[:, 2], yaw)]
        entries.append({
            "instance": int(m.instance), "raw": int(m.raw), "class": KINDS[m.kind][2], "behaviour": m.behaviour,
            "size": [round(float(v), 4) for v in m.template.size], "first_frame": first, "last_frame": last,
            "poses": rows,
        })
    record = {"format": "convbki-synth-movers", "version": 1, "frame": "map", "frames": int(frames),
              "movers": entries}
    return json.dumps(record, separators=(",", ":")) + "\n"


def load_sidecar(path: str | Path) -> dict | None:
    """The parsed ``movers.json`` of a sequence folder or file path, or None when there is none."""
    path = Path(path)
    if path.is_dir():
        path = path / "movers.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
