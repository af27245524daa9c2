"""Where the movers go: traffic planned around the ego vehicle's drive.

Each mover is planned relative to the ego vehicle at a random *meeting time* of the drive, so
that the LiDAR sees it over many scans. The ``classic`` traffic (``BEHAVIOURS``, the default)
has four behaviours, all at constant speeds:

- ``oncoming``: a car, truck, bus, motorcyclist or cyclist in the opposite lane of the street
  the ego vehicle is on, passing it;
- ``lead``: a car, truck or bus ahead of the ego vehicle in its lane at the start, following
  the loop route faster than the ego vehicle (it pulls away, never blocks);
- ``crossing``: a pedestrian walking along a sidewalk, across the ego vehicle's street in front
  of it, and on along the far sidewalk;
- ``cross-traffic``: a vehicle or cyclist on a cross street, through the intersection ahead.

The ``varied`` traffic (``VARIED_BEHAVIOURS``) keeps those and adds movers that change speed or
come close:

- ``stop-and-go``: a car, truck or bus that drives, brakes to a standstill at the stop line of
  an intersection (a red traffic light) for ``STOP_SCANS`` scans, then speeds up and drives on:
  on a cross street ahead while the ego vehicle passes, ahead of it in its own lane, or in the
  opposite lane;
- ``kerb-cyclist``: a slow bicyclist (``KERB_CYCLIST_SPEED``) along the right edge of the outer
  lane, by the kerb, in the ego vehicle's direction (ahead of it, or behind it at the start) or
  in the opposite one;
- ``close-pass``: a vehicle passing the ego vehicle with a lateral gap of ``CLOSE_PASS_GAP``
  between the two boxes: oncoming, or overtaking it on the left (pulling out of the ego
  vehicle's lane behind it and back in ahead of it);
- ``sidewalk-pause``: a pedestrian walking along a sidewalk who stands still for
  ``PAUSE_SCANS`` scans, then walks on.

A stop is planned only where the drive shows it whole: the mover is in view for
``SHOWN_MOTION`` of driving (walking) before it stops and after it goes on.

Vehicles keep to the centre of their lane (cyclists near its right edge) and drive straight
along the street grid, through intersections; pedestrians step up on the sidewalk
(``CURB_HEIGHT``). A mover is present while it is within ``ACTIVE_RANGE`` of the ego vehicle
around its meeting time (beyond the LiDAR's range, so it appears and leaves unseen), and inside
the scene. A candidate whose box would come close to the ego vehicle's or to a mover already
planned (checked every 0.02 s, stopped or not) is dropped and another one drawn, up to
``TRIES`` times, so fewer movers than asked may result on a short or crowded drive: in
particular the ego vehicle, which never brakes for anyone, does not run into a stopped or slow
mover ahead of it, because such a mover is not planned. ``swept_height`` rasterises the space
the movers sweep, including where they stand still; ``scene`` removes static objects from it.
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
# The varied traffic: every classic behaviour, and those that stop, crawl or come close.
VARIED_BEHAVIOURS = {"oncoming": 0.2, "crossing": 0.16, "cross-traffic": 0.14, "lead": 0.06, "stop-and-go": 0.16,
                     "kerb-cyclist": 0.1, "close-pass": 0.1, "sidewalk-pause": 0.08}
TRAFFIC = {"classic": BEHAVIOURS, "varied": VARIED_BEHAVIOURS}  # --traffic: behaviour weights
STOP_SCANS = (15, 40)  # how long a stop-and-go vehicle stands still, scans
PAUSE_SCANS = (15, 60)  # how long a pedestrian stands on the sidewalk, scans
SHOWN_MOTION = 1.0  # s of motion in view before a stop and after it
STOP_LINE_GAP = (1.5, 4.0)  # m between a waiting vehicle's front and the crossed street's kerb line
BRAKE, ACCEL = 2.5, 2.0  # m/s^2 of a stop-and-go vehicle
WALK_ACCEL = 1.0  # m/s^2 of a pedestrian stopping and setting off
KERB_CYCLIST_SPEED = (1.5, 3.5)  # m/s
KERB_GAP = (0.2, 0.5)  # m between a kerb cyclist's box and the right edge of the road
CLOSE_PASS_GAP = (1.0, 2.0)  # m between a close-passing vehicle's box and the ego vehicle's
OVERTAKE_SPEEDUP = (3.0, 6.0)  # m/s an overtaking vehicle is faster than the ego vehicle
OVERTAKE_CLEARANCE = (4.0, 8.0)  # m between the two boxes, lengthwise, when it pulls out and back in
LANE_CHANGE_TIME = 3.0  # s
STRAIGHT_TOLERANCE = 0.02  # rad: how far the ego vehicle's heading may be off its street's for a close pass
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


def _along_and_offset(street: Street, xy: np.ndarray) -> tuple[float, float]:
    """Street coordinates of a scene point: the inverse of ``_point``."""
    if street.axis == 0:
        return float(xy[1]), float(xy[0] - street.pos)
    return float(xy[0]), float(xy[1] - street.pos)


def _stop_line(crossed: Street, sense: int, half_length: float, gap: float) -> float:
    """Where (along its own street) the centre of a mover driving in direction ``sense`` stands
    when it waits in front of ``crossed``: its front ``gap`` short of that street's kerb line."""
    return crossed.pos - sense * (crossed.curb(-sense) + gap + half_length)


def _stop_and_go_progress(t: np.ndarray, t_stop: float, t_go: float, speed: float, brake: float,
                          accel: float) -> np.ndarray:
    """Signed distance (m) a mover has come past the place where it stops, at times ``t``: it
    cruises at ``speed``, brakes evenly (``brake``, m/s^2) to stand still from ``t_stop`` to
    ``t_go`` and speeds up evenly (``accel``) to ``speed`` again. Exactly zero while it stands,
    so that its poses repeat bit for bit."""
    t_brake, t_accel = speed / brake, speed / accel
    before, after = t_stop - t, t - t_go
    approach = np.where(before > t_brake, -speed * (t_brake / 2 + before - t_brake), -0.5 * brake * before ** 2)
    leave = np.where(after > t_accel, speed * (t_accel / 2 + after - t_accel), 0.5 * accel * after ** 2)
    return np.where(before > 0, approach, np.where(after > 0, leave, 0.0))


def _pulled_out(time_from_level: np.ndarray, alongside: float, change: float) -> np.ndarray:
    """Share (0..1) of an overtaking vehicle's way from its lane out to its passing line: all of
    it while it is within ``alongside`` seconds of being level with the vehicle it overtakes,
    none before it pulls out or after it is back, a smooth lane change of ``change`` s between."""
    beyond = np.clip((np.abs(time_from_level) - alongside) / change, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * beyond))


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
    # Drawn with the candidate when its path depends on its size (None: drawn when it is checked).
    template: Template | None = None
    # First and last step that must lie in the mover's run: a stop with the motion around it.
    shown: tuple[int, int] | None = None


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

    def _kind(self, column: int, exclude: tuple[str, ...] = ()) -> str:
        names = [n for n in VEHICLES if n not in exclude]
        weights = np.array([VEHICLES[n][column] for n in names])
        return names[self.rng.choice(len(names), p=weights / weights.sum())]

    def _ego_speed(self, j: int) -> float:
        """The ego vehicle's speed (m/s) around step j."""
        if len(self.t) < 2:
            return self.cruise
        a, b = max(j - 1, 0), min(j + 1, len(self.t) - 1)
        return float(np.linalg.norm(self.ego_xy[b] - self.ego_xy[a]) / (self.t[b] - self.t[a]))

    def _step(self, time: float) -> int:
        """The conflict-check step nearest to ``time`` (s; may lie outside the drive)."""
        return round(time / (0.1 / FINE))

    def _stop_shown(self, t_stop: float, t_go: float) -> tuple[int, int] | None:
        """The steps a stop from ``t_stop`` to ``t_go`` needs in view (``SHOWN_MOTION`` of motion on
        either side), or None when they do not fit in the drive."""
        first, last = self._step(t_stop - SHOWN_MOTION), self._step(t_go + SHOWN_MOTION)
        return (first, last) if first >= 0 and last < len(self.t) else None

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
        o0, o1 = self._walkway(street, start), self._walkway(street, -start)
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

    def _walkway(self, street: Street, side: int) -> float:
        """Offset from the centre line of a pedestrian's line along the sidewalk on ``side``: on
        the paved part, clear of the lawn strip and the curb."""
        k = (side + 1) // 2
        inner = street.curb(side) + street.lawn[k] + 0.15
        return side * (inner + self.rng.uniform(0.3, 0.7) * max(street.curb(side) + street.sidewalk[k] - inner, 0.0))

    # ---- candidates of the varied traffic ------------------------------------------------------------
    def stop_and_go(self) -> _Candidate | None:
        """A car, truck or bus that waits at an intersection's stop line, then drives on: on a cross
        street ahead while the ego vehicle goes through, ahead of it in its lane (gone again before
        the ego vehicle comes up: else the conflict check drops it), or in the opposite lane."""
        rng = self.rng
        kind = ["car", "truck", "bus"][rng.choice(3, p=[0.7, 0.15, 0.15])]
        where = ["cross", "ahead", "opposite"][rng.choice(3, p=[0.5, 0.3, 0.2])]
        template = Template.build(kind, rng)
        speed = rng.uniform(*VEHICLES[kind][2])
        wait = int(rng.integers(STOP_SCANS[0], STOP_SCANS[1] + 1)) * 0.1
        gap = rng.uniform(*STOP_LINE_GAP)
        j = int(rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, along = here
        cross = self.layout.hstreets if street.axis == 0 else self.layout.vstreets
        half = template.size[0] / 2
        if where == "cross":
            ahead = [c for c in cross if 8.0 <= sense * (c.pos - along) <= 70.0]
            if not ahead:
                return None
            road = ahead[int(rng.integers(len(ahead)))]
            m_sense = 1 if rng.random() < 0.5 else -1
            offset = _lane_offset(road, m_sense, int(rng.integers(road.lanes)))
            stop_at = _stop_line(street, m_sense, half, gap)
            # Red for it while the ego vehicle reaches the intersection.
            arrive = self.t[j] + sense * (road.pos - along) / max(self._ego_speed(j), 1.0)
            t_stop = arrive - rng.uniform(0.2, 0.8) * wait
        else:
            m_sense = sense if where == "ahead" else -sense
            lo, hi = (30.0, 90.0) if where == "ahead" else (15.0, 80.0)
            ahead = [c for c in cross if lo <= sense * (c.pos - along) <= hi]
            if not ahead:
                return None
            junction = ahead[int(rng.integers(len(ahead)))]
            road = street
            lane = street.lanes - 1 if where == "ahead" else int(rng.integers(street.lanes))
            offset = _lane_offset(street, m_sense, lane)
            stop_at = _stop_line(junction, m_sense, half, gap)
            # Ahead in the ego vehicle's lane it sets off at step j, with the ego vehicle still
            # far enough behind; in the opposite lane it is waiting at step j.
            t_stop = self.t[j] - (1.0 if where == "ahead" else rng.uniform(0.2, 0.8)) * wait
        t_go = t_stop + wait
        shown = self._stop_shown(t_stop, t_go)
        if shown is None:
            return None
        progress = _stop_and_go_progress(self.t, t_stop, t_go, speed, BRAKE, ACCEL)
        xy = _point(road, stop_at + m_sense * progress, offset)
        meet = min(max(self._step((t_stop + t_go) / 2), 0), len(self.t) - 1)
        return _Candidate(kind, "stop-and-go", xy, np.full(len(xy), _heading(road, m_sense)), np.zeros(len(xy)),
                          meet, None, template, shown)

    def kerb_cyclist(self) -> _Candidate | None:
        """A slow bicyclist by the kerb of the ego vehicle's street: ahead of it in its direction,
        behind it at the start of the drive, or towards it on the far side. The ego vehicle cannot
        pass one in its own lane with a safe gap, so one it would catch up with is not planned."""
        rng = self.rng
        template = Template.build("bicyclist", rng)
        speed = rng.uniform(*KERB_CYCLIST_SPEED)
        way = ["ahead", "behind", "opposite"][rng.choice(3, p=[0.35, 0.25, 0.4])]
        j = 0 if way == "behind" else int(rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, along = here
        m_sense = -sense if way == "opposite" else sense
        right = math.copysign(1.0, _lane_offset(street, m_sense, 0))
        offset = right * (street.road_half - template.size[1] / 2 - rng.uniform(*KERB_GAP))
        start = along - sense * rng.uniform(8.0, 40.0) if way == "behind" else along + sense * rng.uniform(10.0, 60.0)
        xy = _point(street, start + m_sense * speed * (self.t - self.t[j]), offset)
        return _Candidate("bicyclist", "kerb-cyclist", xy, np.full(len(xy), _heading(street, m_sense)),
                          np.zeros(len(xy)), j, None, template)

    def close_pass(self) -> _Candidate | None:
        """A vehicle that passes the ego vehicle with a gap of ``CLOSE_PASS_GAP`` between the two
        boxes while they are level: oncoming, or overtaking it on the left."""
        rng = self.rng
        kind = self._kind(0, exclude=("bicyclist",))
        template = Template.build(kind, rng)
        overtaking = rng.random() < 0.4
        gap = rng.uniform(*CLOSE_PASS_GAP)
        j = int(rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, _ = here
        # Level with the ego vehicle on a straight stretch: the gap is measured square to the street.
        if abs(math.remainder(self.ego_yaw[j] - _heading(street, sense), 2 * math.pi)) > STRAIGHT_TOLERANCE:
            return None
        along, ego_offset = _along_and_offset(street, self.ego_box[j])
        left = -math.copysign(1.0, _lane_offset(street, sense, 0))
        passing = ego_offset + left * (_EGO_HALF[1] + gap + template.size[1] / 2)
        if not overtaking:
            speed = rng.uniform(*VEHICLES[kind][2])
            xy = _point(street, along - sense * speed * (self.t - self.t[j]), passing)
            return _Candidate(kind, "close-pass", xy, np.full(len(xy), _heading(street, -sense)), np.zeros(len(xy)),
                              j, None, template)
        ego_speed = self._ego_speed(j)
        faster = rng.uniform(*OVERTAKE_SPEEDUP)
        clearance = (2 * _EGO_HALF[0] + template.size[0]) / 2 + rng.uniform(*OVERTAKE_CLEARANCE)
        lane = _lane_offset(street, sense, street.lanes - 1)
        share = _pulled_out(self.t - self.t[j], clearance / faster, LANE_CHANGE_TIME)
        offset = lane + (passing - lane) * share
        xy = _point(street, along + sense * (ego_speed + faster) * (self.t - self.t[j]), offset)
        velocity = np.gradient(xy, self.t, axis=0) if len(xy) > 1 else np.zeros_like(xy)
        yaw = np.where(np.hypot(*velocity.T) > 0, np.arctan2(velocity[:, 1], velocity[:, 0]), _heading(street, sense))
        return _Candidate(kind, "close-pass", xy, yaw, np.zeros(len(xy)), j, None, template)

    def sidewalk_pause(self) -> _Candidate | None:
        """A pedestrian walking along a sidewalk of the ego vehicle's street who stands still for
        ``PAUSE_SCANS`` scans (around step j), then walks on."""
        rng = self.rng
        template = Template.build("person", rng)
        j = int(rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, along = here
        offset = self._walkway(street, 1 if rng.random() < 0.5 else -1)
        m_sense = 1 if rng.random() < 0.5 else -1
        speed = rng.uniform(*WALK_SPEED)
        wait = int(rng.integers(PAUSE_SCANS[0], PAUSE_SCANS[1] + 1)) * 0.1
        stop_at = along + sense * rng.uniform(5.0, 50.0)
        t_stop = self.t[j] - rng.uniform(0.1, 0.9) * wait
        shown = self._stop_shown(t_stop, t_stop + wait)
        if shown is None:
            return None
        xy = _point(street, stop_at + m_sense * _stop_and_go_progress(self.t, t_stop, t_stop + wait, speed,
                                                                      WALK_ACCEL, WALK_ACCEL), offset)
        return _Candidate("person", "sidewalk-pause", xy, np.full(len(xy), _heading(street, m_sense)),
                          self._ground(xy), j, None, template, shown)

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
        template = candidate.template if candidate.template is not None else Template.build(candidate.kind, self.rng)
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
        if candidate.shown is not None and not (lo <= candidate.shown[0] and candidate.shown[1] < hi):
            return False
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


def plan(layout: StreetLayout, ego: Trajectory, count: int, seed: int, cruise: float,
         traffic: str = "classic") -> list[Mover]:
    """Up to ``count`` movers around the ego trajectory ``ego`` (scene frame), deterministic in ``seed``,
    with the behaviours of ``traffic`` (a key of ``TRAFFIC``). The classic traffic draws exactly
    what it always has, so the drives of existing seeds stay as they were."""
    planner = _Planner(layout, ego, seed, cruise)
    behaviours = TRAFFIC[traffic]
    names = list(behaviours)
    weights = np.array(list(behaviours.values()))
    wanted = [names[k] for k in planner.rng.choice(len(names), size=count, p=weights / weights.sum())]
    # One lead vehicle at most (a second one would mostly sit behind the first), planned first:
    # it is tied to the start of the drive, the others can go around it.
    if "lead" in wanted:
        wanted = ["lead"] + ["oncoming" if b == "lead" else b for b in wanted[1:]]
    # Pedestrians fit in more easily than vehicles: each mover gets its drawn behaviour if any
    # of a number of tries fits, so the mix follows the weights rather than what fits first.
    for behaviour in wanted:
        for _ in range(TRIES):
            if planner.try_add(getattr(planner, behaviour.replace("-", "_"))()):
                break
    return [entry[0] for entry in planner.accepted]


def swept_height(movers: list[Mover], raster: RasterSpec) -> np.ndarray:
    """(ny, nx) float32 raster: the highest top (m above z = 0) of a mover box that swept each
    cell (0: none), from the movers' poses in every scan (those where a mover stands still too)
    plus poses interpolated between them every ``SWEEP_STEP`` m."""
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
