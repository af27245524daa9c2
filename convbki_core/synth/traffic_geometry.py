"""The traffic's geometry: street coordinates (lanes, stop lines, headings), the motion
profiles of a mover that stops and goes or pulls out to overtake, the ego vehicle's body, and
the overlap test of two oriented boxes that keeps movers apart.
"""

from __future__ import annotations

import math

import numpy as np

from convbki_core.synth.lidar import EGO_BOXES
from convbki_core.synth.streets import Street

# The ego vehicle's body in its sensor frame (x forward): centre and half extents.
EGO_CENTRE = ((EGO_BOXES[0][0] + EGO_BOXES[0][1]) / 2, 0.0)
EGO_HALF = ((EGO_BOXES[0][1] - EGO_BOXES[0][0]) / 2, (EGO_BOXES[0][3] - EGO_BOXES[0][2]) / 2)


def lane_offset(street: Street, sense: int, lane: int) -> float:
    """Signed offset (m, along +x or +y from the centre line) of a lane driven in direction
    ``sense`` (+1: towards +y on a street along y, +x on one along x), right-hand traffic."""
    right = sense if street.axis == 0 else -sense
    return right * (street.median / 2 + street.lane * (lane + 0.5))


def street_point(street: Street, along: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Scene (x, y) of street coordinates: ``along`` the street, ``offset`` from its centre line."""
    along, offset = np.broadcast_arrays(along, offset)
    if street.axis == 0:
        return np.stack([street.pos + offset, along], -1)
    return np.stack([along, street.pos + offset], -1)


def heading(street: Street, sense: int) -> float:
    return (math.pi / 2 if sense > 0 else -math.pi / 2) if street.axis == 0 else (0.0 if sense > 0 else math.pi)


def along_and_offset(street: Street, xy: np.ndarray) -> tuple[float, float]:
    """Street coordinates of a scene point: the inverse of ``street_point``."""
    if street.axis == 0:
        return float(xy[1]), float(xy[0] - street.pos)
    return float(xy[0]), float(xy[1] - street.pos)


def stop_line(crossed: Street, sense: int, half_length: float, gap: float) -> float:
    """Where (along its own street) the centre of a mover driving in direction ``sense`` stands
    when it waits in front of ``crossed``: its front ``gap`` short of that street's kerb line."""
    return crossed.pos - sense * (crossed.curb(-sense) + gap + half_length)


def stop_and_go_progress(t: np.ndarray, t_stop: float, t_go: float, speed: float, brake: float,
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


def pulled_out(time_from_level: np.ndarray, alongside: float, change: float) -> np.ndarray:
    """Share (0..1) of an overtaking vehicle's way from its lane out to its passing line: all of
    it while it is within ``alongside`` seconds of being level with the vehicle it overtakes,
    none before it pulls out or after it is back, a smooth lane change of ``change`` s between."""
    beyond = np.clip((np.abs(time_from_level) - alongside) / change, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * beyond))


def overlap(ca: np.ndarray, yaw_a: np.ndarray, half_a, cb: np.ndarray, yaw_b: np.ndarray, half_b) -> np.ndarray:
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

