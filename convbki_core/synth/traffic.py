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

This module draws the behaviours (``plan``) and rasterises the sweep; ``traffic_planner`` holds
the planner, the classic candidates and the conflict check, ``traffic_varied`` the varied
traffic's candidates and ``traffic_geometry`` the street coordinates and box overlaps.
"""

from __future__ import annotations

import math

import numpy as np

from convbki_core.synth.movers import Mover
from convbki_core.synth.route import Trajectory
from convbki_core.synth.streets import RasterSpec, StreetLayout
from convbki_core.synth.traffic_planner import BEHAVIOURS
from convbki_core.synth.traffic_varied import VARIED_BEHAVIOURS, VariedPlanner

SWEEP_STEP = 0.25  # m between the poses painted into the swept raster
TRIES = 30  # candidates drawn for each mover before it is given up
TRAFFIC = {"classic": BEHAVIOURS, "varied": VARIED_BEHAVIOURS}  # --traffic: behaviour weights


def plan(layout: StreetLayout, ego: Trajectory, count: int, seed: int, cruise: float,
         traffic: str = "classic") -> list[Mover]:
    """Up to ``count`` movers around the ego trajectory ``ego`` (scene frame), deterministic in ``seed``,
    with the behaviours of ``traffic`` (a key of ``TRAFFIC``). The classic traffic draws exactly
    what it always has, so the drives of existing seeds stay as they were."""
    planner = VariedPlanner(layout, ego, seed, cruise)  # every behaviour's candidates
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
