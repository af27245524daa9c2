"""The traffic's planner: the ego vehicle's drive at every conflict-check step, the classic
behaviours' candidates (``oncoming``, ``lead``, ``crossing``, ``cross-traffic``; ``traffic``
says what each does) and the check that keeps a candidate clear of the ego vehicle and of the
movers planned before it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from convbki_core.synth.movers import Mover, Template
from convbki_core.synth.primitives import SIDEWALK, TERRAIN
from convbki_core.synth.route import Trajectory, drive
from convbki_core.synth.streets import CURB_HEIGHT, RasterSpec, Street, StreetLayout
from convbki_core.synth.traffic_geometry import EGO_CENTRE, EGO_HALF, heading, lane_offset, overlap, street_point

FINE = 5  # conflict-check steps per scan (0.1 s / 5 = 0.02 s)
ACTIVE_RANGE = 105.0  # m from the ego vehicle
EGO_MARGIN = 1.0  # m kept between a mover's box and the ego vehicle's
MOVER_MARGIN = 0.4  # m between two movers' boxes
BEHAVIOURS = {"oncoming": 0.35, "crossing": 0.3, "cross-traffic": 0.25, "lead": 0.1}
VEHICLES = {  # kind: (weight in oncoming, in cross-traffic, speed range m/s)
    "car": (0.5, 0.45, (7.0, 13.0)),
    "truck": (0.15, 0.1, (6.0, 10.0)),
    "bus": (0.1, 0.05, (6.0, 10.0)),
    "motorcyclist": (0.1, 0.15, (8.0, 14.0)),
    "bicyclist": (0.15, 0.25, (3.5, 6.5)),
}
WALK_SPEED = (1.0, 1.7)  # m/s


@dataclass
class Candidate:
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


class Planner:
    """Movers planned one after another around the ego vehicle's drive (``traffic.plan``)."""

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
        self.ego_box = self.ego_xy + np.stack([c, s], -1) * EGO_CENTRE[0]
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


    # ---- candidates -------------------------------------------------------------------------------------
    def _straight(self, kind: str, street: Street, sense: int, along_m: float, j_m: int, offset: float,
                  behaviour: str) -> Candidate:
        speed = self.rng.uniform(*VEHICLES[kind][2])
        along = along_m + sense * speed * (self.t - self.t[j_m])
        xy = street_point(street, along, offset)
        return Candidate(kind, behaviour, xy, np.full(len(xy), heading(street, sense)), np.zeros(len(xy)), j_m)

    def oncoming(self) -> Candidate | None:
        j = int(self.rng.integers(len(self.t)))
        here = self._ego_street(j)
        if here is None:
            return None
        street, sense, along = here
        kind = self._kind(0)
        lane = int(self.rng.integers(street.lanes))
        offset = lane_offset(street, -sense, lane)
        if kind == "bicyclist":
            offset = math.copysign(street.road_half - 0.9, offset)
        return self._straight(kind, street, -sense, along + sense * self.rng.uniform(10, 60), j, offset, "oncoming")

    def cross_traffic(self) -> Candidate | None:
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
        offset = lane_offset(cs, c_sense, int(self.rng.integers(cs.lanes)))
        if kind == "bicyclist":
            offset = math.copysign(cs.road_half - 0.9, offset)
        # At the meeting step the mover is 0-40 m before the ego street's centre line.
        along_m = street.pos - c_sense * self.rng.uniform(0, 40)
        return self._straight(kind, cs, c_sense, along_m, j, offset, "cross-traffic")

    def crossing(self) -> Candidate | None:
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
        corners = street_point(street, np.array([a_c - d0 * 80.0, a_c, a_far, a_far + d1 * 80.0]),
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
        return Candidate("person", "crossing", xy, yaw, self._ground(xy), j, (s > 0.0) & (s < s_corner[-1]))

    def lead(self) -> Candidate:
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
        return Candidate(kind, "lead", xy, yaw, np.zeros(len(xy)), 0)

    def _walkway(self, street: Street, side: int) -> float:
        """Offset from the centre line of a pedestrian's line along the sidewalk on ``side``: on
        the paved part, clear of the lawn strip and the curb."""
        k = (side + 1) // 2
        inner = street.curb(side) + street.lawn[k] + 0.15
        return side * (inner + self.rng.uniform(0.3, 0.7) * max(street.curb(side) + street.sidewalk[k] - inner, 0.0))

    def _ground(self, xy: np.ndarray) -> np.ndarray:
        """Height of the surface under each (x, y): the sidewalk top on sidewalks and lawn strips."""
        raster: RasterSpec = self.layout.raster
        ix = np.clip(((xy[:, 0] - raster.x0) / raster.res).astype(np.int64), 0, raster.nx - 1)
        iy = np.clip(((xy[:, 1] - raster.y0) / raster.res).astype(np.int64), 0, raster.ny - 1)
        return np.where(np.isin(self.layout.ground[iy, ix], (SIDEWALK, TERRAIN)), CURB_HEIGHT, 0.0)

    # ---- checking and keeping a candidate ------------------------------------------------------------
    def try_add(self, candidate: Candidate | None) -> bool:
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
        if overlap(xy[on], yaw[on], half + EGO_MARGIN / 2, self.ego_box[on], self.ego_yaw[on],
                    np.array(EGO_HALF) + EGO_MARGIN / 2).any():
            return False
        for other, oxy, oyaw, oactive in self.accepted:
            both = np.flatnonzero(active & oactive)
            if len(both) and overlap(xy[both], yaw[both], half + MOVER_MARGIN / 2, oxy[both], oyaw[both],
                                      other.template.size[:2] / 2 + MOVER_MARGIN / 2).any():
                return False
        pose = np.column_stack([xy, candidate.z0, yaw])[::FINE]
        mover = Mover(candidate.kind, candidate.behaviour, template, pose, frame_active)
        self.accepted.append((mover, xy, yaw, active))
        return True


