"""The ego vehicle's route and the LiDAR poses along it.

The route is a closed loop of lane-centre corners (scene frame, metres) driven counter-
clockwise, so every turn is a left turn. Corners are rounded with circular arcs, the speed
drops in the arcs (lateral acceleration limit) and changes smoothly (longitudinal limit), and
the pose at time t follows from integrating that speed profile: heading is continuous, as a
real car's is. Pitch and roll get small suspension-like motions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SENSOR_HEIGHT = 1.73  # m above the ground, as the KITTI Velodyne
SAMPLE_STEP = 0.1  # m between route samples
LATERAL_ACCEL = 2.0  # m/s^2: comfortable city cornering
LONGITUDINAL_ACCEL = 1.2  # m/s^2


@dataclass
class Route:
    """A sampled closed path: arc length s (m), position, heading (rad), curvature (1/m)."""

    s: np.ndarray  # (M,) 0 .. length - step
    xy: np.ndarray  # (M, 2)
    heading: np.ndarray  # (M,) unwrapped
    curvature: np.ndarray  # (M,)
    length: float
    corner_s: np.ndarray  # (K,) arc length where each rounded corner starts

    @classmethod
    def from_corners(cls, corners: np.ndarray, radius: float) -> Route:
        """Round the corners of a closed polygon (K, 2) with arcs of ``radius`` (m)."""
        corners = np.asarray(corners, np.float64)
        k = len(corners)
        pieces: list[np.ndarray] = []
        curv: list[np.ndarray] = []
        arc_starts: list[int] = []
        # Arc endpoints for every corner: the straight parts join the end of one arc to the
        # start of the next.
        arcs = []
        for i in range(k):
            prev, here, nxt = corners[i - 1], corners[i], corners[(i + 1) % k]
            d_in = (here - prev) / np.linalg.norm(here - prev)
            d_out = (nxt - here) / np.linalg.norm(nxt - here)
            turn = math.atan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], float(d_in @ d_out))
            tangent = radius * math.tan(abs(turn) / 2)
            start, end = here - d_in * tangent, here + d_out * tangent
            left = np.array([-d_in[1], d_in[0]])
            centre = start + left * radius * math.copysign(1.0, turn)
            arcs.append((start, end, centre, turn))
        for i in range(k):
            start, end, centre, turn = arcs[i]
            prev_end = arcs[i - 1][1]
            seg = start - prev_end
            n = max(int(np.linalg.norm(seg) / SAMPLE_STEP), 1)
            t = np.arange(n) / n
            pieces.append(prev_end + t[:, None] * seg)
            curv.append(np.zeros(n))
            arc_starts.append(sum(len(p) for p in pieces))
            phi0 = math.atan2(start[1] - centre[1], start[0] - centre[0])
            n = max(int(abs(turn) * radius / SAMPLE_STEP), 1)
            phi = phi0 + turn * np.arange(n) / n
            pieces.append(centre + radius * np.stack([np.cos(phi), np.sin(phi)], 1))
            curv.append(np.full(n, math.copysign(1.0 / radius, turn)))
        xy = np.concatenate(pieces)
        step = np.linalg.norm(np.diff(np.vstack([xy, xy[:1]]), axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(step)[:-1]])
        forward = np.roll(xy, -1, axis=0) - xy
        heading = np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))
        return cls(s, xy, heading, np.concatenate(curv), float(step.sum()), s[np.asarray(arc_starts)])

    def speed_profile(self, cruise: float) -> np.ndarray:
        """Speed (m/s) at each sample: cruise on straights, slower in arcs, smooth in between."""
        limit = np.minimum(cruise, np.sqrt(LATERAL_ACCEL / np.maximum(np.abs(self.curvature), 1e-9)))
        v = limit.copy()
        step = np.diff(np.append(self.s, self.length))
        # Forward and backward passes around the loop (twice, so the wrap is consistent).
        for _ in range(2):
            for i in range(len(v)):
                v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * LONGITUDINAL_ACCEL * step[i - 1]))
            for i in range(len(v) - 1, -1, -1):
                j = (i + 1) % len(v)
                v[i] = min(v[i], math.sqrt(v[j] ** 2 + 2 * LONGITUDINAL_ACCEL * step[i]))
        return v


@dataclass
class Trajectory:
    """Scene-frame LiDAR poses of a drive, one per frame."""

    poses: np.ndarray  # (F, 4, 4) scene <- lidar
    times: np.ndarray  # (F,) s
    speed: np.ndarray  # (F,) m/s


def _rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll): x forward, y left, z up."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def drive(route: Route, frames: int, cruise: float, start_s: float, rng: np.random.Generator,
          period: float = 0.1) -> Trajectory:
    """Poses of ``frames`` scans ``period`` s apart, starting at arc length ``start_s``."""
    v = route.speed_profile(cruise)
    step = np.diff(np.append(route.s, route.length))
    # Time to reach each sample, lap after lap, so long drives go round the loop again.
    lap_time = float(np.sum(step / v))
    t_sample = np.concatenate([[0.0], np.cumsum(step / v)[:-1]])
    t_start = float(np.interp(start_s, route.s, t_sample))
    times = np.arange(frames) * period
    t_abs = t_start + times
    laps, t_in = np.divmod(t_abs, lap_time)
    s_now = np.interp(t_in, t_sample, route.s)
    idx = np.minimum(np.searchsorted(route.s, s_now, side="right") - 1, len(route.s) - 1)
    frac = (s_now - route.s[idx]) / step[idx]
    nxt = (idx + 1) % len(route.s)
    xy = route.xy[idx] + frac[:, None] * (route.xy[nxt] - route.xy[idx])
    # Heading gained over one lap: 2 pi for a counter-clockwise loop.
    turn = 2 * np.pi * round(float(route.heading[-1] - route.heading[0]) / (2 * np.pi))
    h_next = np.where(nxt == 0, route.heading[0] + turn, route.heading[nxt])
    heading = route.heading[idx] + frac * (h_next - route.heading[idx]) + laps * turn
    speed = np.interp(s_now, route.s, v)
    curvature = route.curvature[idx]
    accel = np.gradient(speed, period) if frames > 1 else np.zeros(1)
    # Small lateral weave in the lane and suspension motion: braking pitches the nose down,
    # cornering rolls the body outward; plus slow road-surface undulation.
    phase = rng.uniform(0, 2 * np.pi, 4)
    dist = s_now + laps * route.length
    weave = 0.12 * np.sin(2 * np.pi * dist / 53.0 + phase[0])
    normal = np.stack([-np.sin(heading), np.cos(heading)], 1)
    xy = xy + weave[:, None] * normal
    pitch = -0.004 * accel + 0.003 * np.sin(2 * np.pi * dist / 17.0 + phase[1])
    roll = 0.006 * speed ** 2 * curvature + 0.002 * np.sin(2 * np.pi * dist / 11.0 + phase[2])
    z = SENSOR_HEIGHT + 0.01 * np.sin(2 * np.pi * dist / 7.0 + phase[3])
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for i in range(frames):
        poses[i, :3, :3] = _rotation(float(heading[i]), float(pitch[i]), float(roll[i]))
        poses[i, :3, 3] = (xy[i, 0], xy[i, 1], z[i])
    return Trajectory(poses, times, speed)
