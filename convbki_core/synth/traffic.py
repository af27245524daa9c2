"""Where the movers go: traffic planned around the ego vehicle's drive.

Each mover is planned relative to the ego vehicle at a random *meeting time* of the drive, so
that the LiDAR sees it over many scans:

- ``oncoming``: a car, truck, bus, motorcyclist or cyclist in the opposite lane of the street
  the ego vehicle is on, passing it;
- ``lead``: a car, truck or bus ahead of the ego vehicle in its lane at the start, following
  the loop route faster than the ego vehicle (it pulls away, never blocks);
- ``crossing``: a pedestrian walking along a sidewalk, across the ego vehicle's street in front
  of it, and on along the far sidewalk;
- ``cross-traffic``: a vehicle or cyclist on a cross street, through the intersection ahead.

Vehicles keep to the centre of their lane (cyclists near its right edge) and drive straight
along the street grid at a constant speed, through intersections; pedestrians step up on the
sidewalk (``CURB_HEIGHT``). A mover is present while it is within ``ACTIVE_RANGE`` of the ego
vehicle around its meeting time (beyond the LiDAR's range, so it appears and leaves unseen),
and inside the scene. A candidate whose box would come close to the ego vehicle's or to a
mover already planned (checked every 0.02 s) is dropped and another one drawn, up to
``TRIES`` times, so fewer movers than asked may result on a short or crowded drive.
``swept_height`` rasterises the space the movers sweep; ``scene`` removes static objects from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from convbki_core.synth.lidar import EGO_BOXES
from convbki_core.synth.movers import Mover, Template
from convbki_core.synth.primitives import SIDEWALK, TERRAIN
from convbki_core.synth.route import Trajectory, drive
from convbki_core.synth.streets import CURB_HEIGHT, RasterSpec, Street, StreetLayout

FINE = 5  # conflict-check steps per scan (0.1 s / 5 = 0.02 s)
ACTIVE_RANGE = 105.0  # m from the ego vehicle
EGO_MARGIN = 1.0  # m kept between a mover's box and the ego vehicle's
MOVER_MARGIN = 0.4  # m between two movers' boxes
SWEEP_STEP = 0.25  # m between the poses painted into the swept raster
TRIES = 30  # candidates drawn for each mover before it is given up
BEHAVIOURS = {"oncoming": 0.35, "crossing": 0.3, "cross-traffic": 0.25, "lead": 0.1}
VEHICLES = {  # kind: (weight in oncoming, in cross-traffic, speed range m/s)
    "car": (0.5, 0.45, (7.0, 13.0)),
    "truck": (0.15, 0.1, (6.0, 10.0)),
    "bus": (0.1, 0.05, (6.0, 10.0)),
    "motorcyclist": (0.1, 0.15, (8.0, 14.0)),
    "bicyclist": (0.15, 0.25, (3.5, 6.5)),
}
WALK_SPEED = (1.0, 1.7)  # m/s
# The ego vehicle's body in its sensor frame (x forward): centre and half extents.
_EGO_CENTRE = ((EGO_BOXES[0][0] + EGO_BOXES[0][1]) / 2, 0.0)
_EGO_HALF = ((EGO_BOXES[0][1] - EGO_BOXES[0][0]) / 2, (EGO_BOXES[0][3] - EGO_BOXES[0][2]) / 2)


def _lane_offset(street: Street, sense: int, lane: int) -> float:
    """Signed offset (m, along +x or +y from the centre line) of a lane driven in direction
    ``sense`` (+1: towards +y on a street along y, +x on one along x), right-hand traffic."""
    right = sense if street.axis == 0 else -sense
    return right * (street.median / 2 + street.lane * (lane + 0.5))


def _point(street: Street, along: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Scene (x, y) of street coordinates: ``along`` the street, ``offset`` from its centre line."""
    along, offset = np.broadcast_arrays(along, offset)
    if street.axis == 0:
        return np.stack([street.pos + offset, along], -1)
    return np.stack([along, street.pos + offset], -1)


def _heading(street: Street, sense: int) -> float:
    return (math.pi / 2 if sense > 0 else -math.pi / 2) if street.axis == 0 else (0.0 if sense > 0 else math.pi)


def _overlap(ca: np.ndarray, yaw_a: np.ndarray, half_a, cb: np.ndarray, yaw_b: np.ndarray, half_b) -> np.ndarray:
    """Whether oriented 2D boxes (centres (n, 2), yaws (n,), half extents) overlap (separating axes)."""
    ua = np.stack([np.cos(yaw_a), np.sin(yaw_a)], -1)
    va = np.stack([-ua[:, 1], ua[:, 0]], -1)
    ub = np.stack([np.cos(yaw_b), np.sin(yaw_b)], -1)
    vb = np.stack([-ub[:, 1], ub[:, 0]], -1)
    d = cb - ca
    apart = np.zeros(len(d), bool)
    for axis in (ua, va, ub, vb):
        def proj(u, v, half, axis=axis):
            return half[0] * np.abs((u * axis).sum(1)) + half[1] * np.abs((v * axis).sum(1))
        apart |= np.abs((d * axis).sum(1)) > proj(ua, va, half_a) + proj(ub, vb, half_b)
    return ~apart


@dataclass
class _Candidate:
    """A mover's motion at every conflict-check step of the drive (scene frame)."""

    kind: str
    behaviour: str
    xy: np.ndarray  # (n, 2) footprint centre, m
    yaw: np.ndarray  # (n,) rad
    z0: np.ndarray  # (n,) height of the surface under it, m
    meet: int  # the step at which it is near the ego vehicle by construction
    valid: np.ndarray | None = None  # (n,) bool: steps where its path exists (None: all)


class _Planner:
    def __init__(self, layout: StreetLayout, ego: Trajectory, seed: int, cruise: float):
        self.layout, self.cruise = layout, cruise
        self.rng = np.random.default_rng([seed, 0x30BE5])
        self.frames = len(ego.times)
        self.t = np.arange((self.frames - 1) * FINE + 1) * (0.1 / FINE)
        frame_t = np.arange(self.frames) * 0.1
        yaw = np.unwrap(np.arctan2(ego.poses[:, 1, 0], ego.poses[:, 0, 0]))
        self.ego_xy = np.stack([np.interp(self.t, frame_t, ego.poses[:, i, 3]) for i in (0, 1)], -1)
        self.ego_yaw = np.interp(self.t, frame_t, yaw)
        c, s = np.cos(self.ego_yaw), np.sin(self.ego_yaw)
        self.ego_box = self.ego_xy + np.stack([c, s], -1) * _EGO_CENTRE[0]
        self.accepted: list[tuple[Mover, np.ndarray, np.ndarray, np.ndarray]] = []  # mover, xy, yaw, active

    # ---- where the ego vehicle is ---------------------------------------------------------------
    def _ego_street(self, j: int) -> tuple[Street, int, float] | None:
        """The street the ego vehicle drives along at step j: (street, sense, along), or None in a turn."""
        (x, y), yaw = self.ego_xy[j], self.ego_yaw[j]
        c, s = math.cos(yaw), math.sin(yaw)
        if abs(s) > 0.985:
            street = min(self.layout.vstreets, key=lambda st: abs(st.pos - x))
            return street, (1 if s > 0 else -1), y
        if abs(c) > 0.985:
            street = min(self.layout.hstreets, key=lambda st: abs(st.pos - y))
            return street, (1 if c > 0 else -1), x
        return None

    def _kind(self, column: int) -> str:
        names = list(VEHICLES)
        weights = np.array([VEHICLES[n][column] for n in names])
        return names[self.rng.choice(len(names), p=weights / weights.sum())]

    # ---- candidates -------------------------------------------------------------------------------------
    def _straight(self, kind: str, street: Street, sense: int, along_m: float, j_m: int, offset: float,
                  behaviour: str) -> _Candidate:
        speed = self.rng.uniform(*VEHICLES[kind][2])
        along = along_m + sense * speed * (self.t - self.t[j_m])
        xy = _point(street, along, offset)
        return _Candidate(kind, behaviour, xy, np.full(len(xy), _heading(street, sense)), np.zeros(len(xy)), j_m)

    def oncoming(self) -> _Candidate | None:
        j = int(self.rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, along = here
        kind = self._kind(0)
        lane = int(self.rng.integers(street.lanes))
        offset = _lane_offset(street, -sense, lane)
        if kind == "bicyclist":
            offset = math.copysign(street.road_half - 0.9, offset)
        return self._straight(kind, street, -sense, along + sense * self.rng.uniform(10, 60), j, offset, "oncoming")

    def cross_traffic(self) -> _Candidate | None:
        j = int(self.rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, along = here
        cross = self.layout.hstreets if street.axis == 0 else self.layout.vstreets
        ahead = [c for c in cross if 8.0 <= sense * (c.pos - along) <= 70.0]
        if not ahead:
            return None
        cs = ahead[int(self.rng.integers(len(ahead)))]
        kind = self._kind(1)
        c_sense = 1 if self.rng.random() < 0.5 else -1
        offset = _lane_offset(cs, c_sense, int(self.rng.integers(cs.lanes)))
        if kind == "bicyclist":
            offset = math.copysign(cs.road_half - 0.9, offset)
        # At the meeting step the mover is 0-40 m before the ego street's centre line.
        along_m = street.pos - c_sense * self.rng.uniform(0, 40)
        return self._straight(kind, cs, c_sense, along_m, j, offset, "cross-traffic")

    def crossing(self) -> _Candidate | None:
        j = int(self.rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, along = here
        rng = self.rng
        a_c = along + sense * rng.uniform(12, 45)
        start = 1 if rng.random() < 0.5 else -1

        def walkway(side: int) -> float:
            k = (side + 1) // 2
            inner = street.curb(side) + street.lawn[k] + 0.15
            return side * (inner + rng.uniform(0.3, 0.7) * max(street.curb(side) + street.sidewalk[k] - inner, 0.0))

        o0, o1 = walkway(start), walkway(-start)
        d0, d1 = (1 if rng.random() < 0.5 else -1), (1 if rng.random() < 0.5 else -1)
        a_far = a_c + rng.uniform(-1.5, 1.5)
        corners = _point(street, np.array([a_c - d0 * 80.0, a_c, a_far, a_far + d1 * 80.0]),
                         np.array([o0, o0, o1, o1]))
        speed = rng.uniform(*WALK_SPEED)
        seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
        s_corner = np.concatenate([[0.0], np.cumsum(seg)])
        # At the meeting step the pedestrian is somewhere on the crossing, 0-90 % of the way over.
        s_m = s_corner[1] + rng.uniform(0.0, 0.9) * seg[1]
        s = np.clip(s_m + speed * (self.t - self.t[j]), 0.0, s_corner[-1])
        xy = np.stack([np.interp(s, s_corner, corners[:, i]) for i in (0, 1)], -1)
        ahead = np.stack([np.interp(s + 0.4, s_corner, corners[:, i]) for i in (0, 1)], -1)
        behind = np.stack([np.interp(s - 0.4, s_corner, corners[:, i]) for i in (0, 1)], -1)
        yaw = np.arctan2(ahead[:, 1] - behind[:, 1], ahead[:, 0] - behind[:, 0])
        # Walking off either end of the path counts as leaving: outside the window.
        return _Candidate("person", "crossing", xy, yaw, self._ground(xy), j, (s > 0.0) & (s < s_corner[-1]))

    def lead(self) -> _Candidate:
        kind = ["car", "truck", "bus"][self.rng.choice(3, p=[0.75, 0.1, 0.15])]
        layout = self.layout
        start = (layout.start_s + self.rng.uniform(14, 30)) % layout.route_.length
        # The same speed profile with a higher cruise speed: never slower than the ego vehicle
        # at any place of the route, so starting ahead it stays ahead.
        cruise = self.cruise + self.rng.uniform(1.5, 4.0)
        path = drive(layout.route_, len(self.t), cruise, start, np.random.default_rng(self.rng.integers(2**32)),
                     period=0.1 / FINE)
        xy = path.poses[:, :2, 3]
        yaw = np.arctan2(path.poses[:, 1, 0], path.poses[:, 0, 0])
        return _Candidate(kind, "lead", xy, yaw, np.zeros(len(xy)), 0)

    def _ground(self, xy: np.ndarray) -> np.ndarray:
        """Height of the surface under each (x, y): the sidewalk top on sidewalks and lawn strips."""
        raster: RasterSpec = self.layout.raster
        ix = np.clip(((xy[:, 0] - raster.x0) / raster.res).astype(np.int64), 0, raster.nx - 1)
        iy = np.clip(((xy[:, 1] - raster.y0) / raster.res).astype(np.int64), 0, raster.ny - 1)
        return np.where(np.isin(self.layout.ground[iy, ix], (SIDEWALK, TERRAIN)), CURB_HEIGHT, 0.0)

    # ---- checking and keeping a candidate ------------------------------------------------------------
    def try_add(self, candidate: _Candidate | None) -> bool:
        """Plan ``candidate`` when it keeps clear of the ego vehicle and the movers planned so far."""
        if candidate is None:
            return False
        xy, yaw, j_m = candidate.xy, candidate.yaw, candidate.meet
        template = Template.build(candidate.kind, self.rng)
        x0, x1, y0, y1 = self.layout.extent
        near = (np.linalg.norm(xy - self.ego_xy, axis=1) < ACTIVE_RANGE) & (xy[:, 0] > x0 + 5) & (
            xy[:, 0] < x1 - 5) & (xy[:, 1] > y0 + 5) & (xy[:, 1] < y1 - 5)
        if candidate.valid is not None:
            near &= candidate.valid
        if not near[j_m]:
            return False
        # The contiguous run of steps around the meeting step.
        off = np.flatnonzero(~near)
        lo = off[off < j_m].max(initial=-1) + 1
        hi = off[off > j_m].min(initial=len(near))
        active = np.zeros(len(near), bool)
        active[lo:hi] = True
        frame_active = active[::FINE]
        if frame_active.sum() < min(5, self.frames):
            return False
        half = template.size[:2] / 2
        on = np.flatnonzero(active)
        if _overlap(xy[on], yaw[on], half + EGO_MARGIN / 2, self.ego_box[on], self.ego_yaw[on],
                    np.array(_EGO_HALF) + EGO_MARGIN / 2).any():
            return False
        for other, oxy, oyaw, oactive in self.accepted:
            both = np.flatnonzero(active & oactive)
            if len(both) and _overlap(xy[both], yaw[both], half + MOVER_MARGIN / 2, oxy[both], oyaw[both],
                                      other.template.size[:2] / 2 + MOVER_MARGIN / 2).any():
                return False
        pose = np.column_stack([xy, candidate.z0, yaw])[::FINE]
        mover = Mover(candidate.kind, candidate.behaviour, template, pose, frame_active)
        self.accepted.append((mover, xy, yaw, active))
        return True


def plan(layout: StreetLayout, ego: Trajectory, count: int, seed: int, cruise: float) -> list[Mover]:
    """Up to ``count`` movers around the ego trajectory ``ego`` (scene frame), deterministic in ``seed``."""
    planner = _Planner(layout, ego, seed, cruise)
    names = list(BEHAVIOURS)
    weights = np.array(list(BEHAVIOURS.values()))
    wanted = [names[k] for k in planner.rng.choice(len(names), size=count, p=weights / weights.sum())]
    # One lead vehicle at most (a second one would mostly sit behind the first), planned first:
    # it is tied to the start of the drive, the others can go around it.
    if "lead" in wanted:
        wanted = ["lead"] + ["oncoming" if b == "lead" else b for b in wanted[1:]]
    # Pedestrians fit in more easily than vehicles: each mover gets its drawn behaviour if any
    # of a number of tries fits, so the mix follows BEHAVIOURS rather than what fits first.
    for behaviour in wanted:
        for _ in range(TRIES):
            if planner.try_add(getattr(planner, behaviour.replace("-", "_"))()):
                break
    return [entry[0] for entry in planner.accepted]


def swept_height(movers: list[Mover], raster: RasterSpec) -> np.ndarray:
    """(ny, nx) float32 raster: the highest top (m above z = 0) of a mover box that swept each
    cell (0: none), from the movers' poses in every scan plus poses interpolated between them
    every ``SWEEP_STEP`` m."""
    out = np.zeros((raster.ny, raster.nx), np.float32)
    for m in movers:
        first, last = m.frames
        pose = m.pose[first:last + 1]
        step = np.linalg.norm(np.diff(pose[:, :2], axis=0), axis=1)
        sub = np.maximum(np.ceil(step / SWEEP_STEP), 1).astype(int)
        idx = np.concatenate([np.repeat(np.arange(len(step)), sub), [len(pose) - 1]])
        frac = np.concatenate([np.concatenate([np.arange(n) / n for n in sub]) if len(sub) else [], [0.0]])
        nxt = np.minimum(idx + 1, len(pose) - 1)
        yaw = pose[:, 3] + 0.0
        turn = np.angle(np.exp(1j * (yaw[nxt] - yaw[idx])))
        samples = np.column_stack([pose[idx, :3] + frac[:, None] * (pose[nxt, :3] - pose[idx, :3]),
                                   yaw[idx] + frac * turn])
        hx, hy = m.template.size[0] / 2, m.template.size[1] / 2
        for x, y, z0, yaw_k in samples:
            c, s = math.cos(yaw_k), math.sin(yaw_k)
            ex, ey = abs(c) * hx + abs(s) * hy, abs(s) * hx + abs(c) * hy
            rows, cols = raster.window(x - ex, x + ex, y - ey, y + ey)
            if rows.stop <= rows.start or cols.stop <= cols.start:
                continue
            xs, ys = raster.centres(rows, cols)
            dx, dy = xs - x, ys - y
            inside = (np.abs(c * dx + s * dy) <= hx) & (np.abs(-s * dx + c * dy) <= hy)
            window = out[rows, cols]
            window[inside] = np.maximum(window[inside], z0 + m.template.size[2])
    return out
