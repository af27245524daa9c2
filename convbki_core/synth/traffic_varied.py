"""The varied traffic's behaviours, beside the classic ones: movers that stop and go, crawl by
the kerb, pass the ego vehicle close or pause on the sidewalk (``traffic`` says what each
does), as candidates of the planner.
"""

from __future__ import annotations

import math

import numpy as np

from convbki_core.synth.movers import Template
from convbki_core.synth.traffic_geometry import (
    EGO_HALF,
    along_and_offset,
    heading,
    lane_offset,
    pulled_out,
    stop_and_go_progress,
    stop_line,
    street_point,
)
from convbki_core.synth.traffic_planner import VEHICLES, WALK_SPEED, Candidate, Planner

# The varied traffic: every classic behaviour, and those that stop, crawl or come close.
VARIED_BEHAVIOURS = {"oncoming": 0.2, "crossing": 0.16, "cross-traffic": 0.14, "lead": 0.06, "stop-and-go": 0.16,
                     "kerb-cyclist": 0.1, "close-pass": 0.1, "sidewalk-pause": 0.08}
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


class VariedPlanner(Planner):
    """The planner with the varied traffic's candidates too (the classic ones are its base's)."""

    def _stop_shown(self, t_stop: float, t_go: float) -> tuple[int, int] | None:
        """The steps a stop from ``t_stop`` to ``t_go`` needs in view (``SHOWN_MOTION`` of motion on
        either side), or None when they do not fit in the drive."""
        first, last = self._step(t_stop - SHOWN_MOTION), self._step(t_go + SHOWN_MOTION)
        return (first, last) if first >= 0 and last < len(self.t) else None

    # ---- candidates of the varied traffic ------------------------------------------------------------
    def stop_and_go(self) -> Candidate | None:
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
            offset = lane_offset(road, m_sense, int(rng.integers(road.lanes)))
            stop_at = stop_line(street, m_sense, half, gap)
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
            offset = lane_offset(street, m_sense, lane)
            stop_at = stop_line(junction, m_sense, half, gap)
            # Ahead in the ego vehicle's lane it sets off at step j, with the ego vehicle still
            # far enough behind; in the opposite lane it is waiting at step j.
            t_stop = self.t[j] - (1.0 if where == "ahead" else rng.uniform(0.2, 0.8)) * wait
        t_go = t_stop + wait
        shown = self._stop_shown(t_stop, t_go)
        if shown is None:
            return None
        progress = stop_and_go_progress(self.t, t_stop, t_go, speed, BRAKE, ACCEL)
        xy = street_point(road, stop_at + m_sense * progress, offset)
        meet = min(max(self._step((t_stop + t_go) / 2), 0), len(self.t) - 1)
        return Candidate(kind, "stop-and-go", xy, np.full(len(xy), heading(road, m_sense)), np.zeros(len(xy)),
                          meet, None, template, shown)

    def kerb_cyclist(self) -> Candidate | None:
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
        right = math.copysign(1.0, lane_offset(street, m_sense, 0))
        offset = right * (street.road_half - template.size[1] / 2 - rng.uniform(*KERB_GAP))
        start = along - sense * rng.uniform(8.0, 40.0) if way == "behind" else along + sense * rng.uniform(10.0, 60.0)
        xy = street_point(street, start + m_sense * speed * (self.t - self.t[j]), offset)
        return Candidate("bicyclist", "kerb-cyclist", xy, np.full(len(xy), heading(street, m_sense)),
                          np.zeros(len(xy)), j, None, template)

    def close_pass(self) -> Candidate | None:
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
        if abs(math.remainder(self.ego_yaw[j] - heading(street, sense), 2 * math.pi)) > STRAIGHT_TOLERANCE:
            return None
        along, ego_offset = along_and_offset(street, self.ego_box[j])
        left = -math.copysign(1.0, lane_offset(street, sense, 0))
        passing = ego_offset + left * (EGO_HALF[1] + gap + template.size[1] / 2)
        if not overtaking:
            speed = rng.uniform(*VEHICLES[kind][2])
            xy = street_point(street, along - sense * speed * (self.t - self.t[j]), passing)
            return Candidate(kind, "close-pass", xy, np.full(len(xy), heading(street, -sense)), np.zeros(len(xy)),
                              j, None, template)
        ego_speed = self._ego_speed(j)
        faster = rng.uniform(*OVERTAKE_SPEEDUP)
        clearance = (2 * EGO_HALF[0] + template.size[0]) / 2 + rng.uniform(*OVERTAKE_CLEARANCE)
        lane = lane_offset(street, sense, street.lanes - 1)
        share = pulled_out(self.t - self.t[j], clearance / faster, LANE_CHANGE_TIME)
        offset = lane + (passing - lane) * share
        xy = street_point(street, along + sense * (ego_speed + faster) * (self.t - self.t[j]), offset)
        velocity = np.gradient(xy, self.t, axis=0) if len(xy) > 1 else np.zeros_like(xy)
        yaw = np.where(np.hypot(*velocity.T) > 0, np.arctan2(velocity[:, 1], velocity[:, 0]), heading(street, sense))
        return Candidate(kind, "close-pass", xy, yaw, np.zeros(len(xy)), j, None, template)

    def sidewalk_pause(self) -> Candidate | None:
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
        xy = street_point(street, stop_at + m_sense * stop_and_go_progress(self.t, t_stop, t_stop + wait, speed,
                                                                      WALK_ACCEL, WALK_ACCEL), offset)
        return Candidate("person", "sidewalk-pause", xy, np.full(len(xy), heading(street, m_sense)),
                          self._ground(xy), j, None, template, shown)

