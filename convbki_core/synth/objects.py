"""Street objects built from primitives: vehicles, people, trees, poles, signs, buildings.

Every function takes the builder, a random generator and the object's pose on the ground:
(x, y) in the scene frame (m), ``yaw`` (rad, the object's forward direction) and ``z0`` (m,
the height of the surface it stands on: 0 on the road, 0.15 on a sidewalk). Dimensions are
real-world ones (KITTI-like cars of 4-5 m, poles of 0.1-0.15 m radius, ...), drawn per object.
"""

from __future__ import annotations

import math

import numpy as np

from convbki_core.synth.primitives import (
    BICYCLE,
    BICYCLIST,
    BUILDING,
    CAR,
    FENCE,
    MOTORCYCLE,
    MOTORCYCLIST,
    OTHER_VEHICLE,
    PERSON,
    POLE,
    TRAFFIC_SIGN,
    TRUCK,
    TRUNK,
    VEGETATION,
    SceneBuilder,
    SceneObject,
)


def _at(x: float, y: float, yaw: float, lx: float, ly: float) -> tuple[float, float]:
    """Object-local (lx forward, ly left) -> scene (x, y)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return x + c * lx - s * ly, y + s * lx + c * ly


def _wheels(obj: SceneObject, x: float, y: float, yaw: float, z0: float, axles: list[float], track: float,
            radius: float, width: float, raw: int) -> None:
    for lx in axles:
        for side in (-1, 1):
            wx, wy = _at(x, y, yaw, lx, side * track / 2)
            obj.ellipsoid(wx, wy, z0 + radius, radius, width / 2, radius, yaw, raw, base=z0)


def car(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float, z0: float = 0.0) -> SceneObject:
    """Passenger car: body box, cabin box set back on top, four wheels."""
    obj = b.new()
    length, width = rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.95)
    tall = rng.random() < 0.25  # SUVs and vans
    height = rng.uniform(1.65, 1.9) if tall else rng.uniform(1.4, 1.55)
    body_top = z0 + rng.uniform(0.9, 1.05)
    obj.new_part()
    obj.box(x, y, z0 + 0.28, body_top, length, width, yaw, CAR, base=z0)
    _wheels(obj, x, y, yaw, z0, [length / 2 - 0.8, -(length / 2 - 0.85)], width - 0.25, rng.uniform(0.3, 0.35),
            0.22, CAR)
    obj.new_part()
    cabin_len = length * (rng.uniform(0.62, 0.75) if tall else rng.uniform(0.45, 0.56))
    cx, cy = _at(x, y, yaw, -length * rng.uniform(0.02, 0.12), 0)
    obj.box(cx, cy, body_top, z0 + height, cabin_len, width - 0.12, yaw, CAR, base=z0)
    return obj


def truck(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float, z0: float = 0.0) -> SceneObject:
    """Box truck, (x, y) at its middle: cab in front, cargo box behind, chassis, wheels."""
    obj = b.new()
    cargo_len, width = rng.uniform(4.5, 7.5), 2.5
    total = cargo_len + 2.4
    top = z0 + rng.uniform(3.2, 3.9)
    obj.new_part()
    cx, cy = _at(x, y, yaw, total / 2 - 1.1, 0)
    obj.box(cx, cy, z0 + 0.55, z0 + 2.9, 2.2, 2.4, yaw, TRUCK, base=z0)
    obj.new_part()
    cx, cy = _at(x, y, yaw, total / 2 - 2.3 - cargo_len / 2, 0)
    obj.box(cx, cy, z0 + 1.1, top, cargo_len, width, yaw, TRUCK, base=z0)
    cx, cy = _at(x, y, yaw, -0.2, 0)
    obj.box(cx, cy, z0 + 0.45, z0 + 1.1, total - 1.0, 1.0, yaw, TRUCK, base=z0)
    _wheels(obj, x, y, yaw, z0, [total / 2 - 1.2, -total / 2 + 1.6, -total / 2 + 2.7], 2.0, 0.5, 0.35, TRUCK)
    return obj


def other_vehicle(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float,
                  z0: float = 0.0) -> SceneObject:
    """Bus (70 %) or a caravan trailer: SemanticKITTI's other-vehicle."""
    obj = b.new()
    obj.new_part()
    if rng.random() < 0.7:
        _bus_body(obj, rng, x, y, yaw, z0)
    else:
        length = rng.uniform(4.5, 6.5)
        obj.box(x, y, z0 + 0.5, z0 + rng.uniform(2.4, 2.8), length, 2.3, yaw, OTHER_VEHICLE, base=z0)
        hx, hy = _at(x, y, yaw, length / 2 + 0.6, 0)
        obj.box(hx, hy, z0 + 0.45, z0 + 0.55, 1.2, 0.1, yaw, OTHER_VEHICLE, base=z0)
        _wheels(obj, x, y, yaw, z0, [0.0], 2.1, 0.33, 0.2, OTHER_VEHICLE)
    return obj


def _bus_body(obj: SceneObject, rng: np.random.Generator, x: float, y: float, yaw: float, z0: float) -> None:
    length = rng.uniform(10.0, 12.5)
    obj.box(x, y, z0 + 0.35, z0 + rng.uniform(3.0, 3.3), length, 2.55, yaw, OTHER_VEHICLE, base=z0)
    _wheels(obj, x, y, yaw, z0, [length / 2 - 2.5, -length / 2 + 3.0], 2.1, 0.5, 0.3, OTHER_VEHICLE)


def bus(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float, z0: float = 0.0) -> SceneObject:
    """City bus, 10-12.5 m (SemanticKITTI's other-vehicle; a moving one is moving-bus)."""
    obj = b.new()
    obj.new_part()
    _bus_body(obj, rng, x, y, yaw, z0)
    return obj


def _bicycle_frame(obj: SceneObject, x: float, y: float, yaw: float, z0: float, raw: int) -> None:
    for lx in (-0.53, 0.53):
        wx, wy = _at(x, y, yaw, lx, 0)
        obj.ellipsoid(wx, wy, z0 + 0.34, 0.34, 0.025, 0.34, yaw, raw, base=z0)
    obj.box(x, y, z0 + 0.76, z0 + 0.81, 0.62, 0.04, yaw, raw, base=z0)  # top tube
    tx, ty = _at(x, y, yaw, 0.05, 0)
    obj.box(tx, ty, z0 + 0.42, z0 + 0.5, 0.62, 0.04, yaw, raw, base=z0)  # down and chain stays
    sx, sy = _at(x, y, yaw, -0.22, 0)
    obj.cylinder(sx, sy, z0 + 0.42, z0 + 0.93, 0.02, raw, base=z0)  # seat tube
    obj.box(sx, sy, z0 + 0.93, z0 + 0.98, 0.25, 0.12, yaw, raw, base=z0)  # saddle
    hx, hy = _at(x, y, yaw, 0.45, 0)
    obj.cylinder(hx, hy, z0 + 0.5, z0 + 1.0, 0.025, raw, base=z0)  # head tube and fork
    obj.box(hx, hy, z0 + 0.98, z0 + 1.02, 0.05, 0.6, yaw, raw, base=z0)  # handlebar


def bicycle(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float, z0: float = 0.0,
            raw: int = BICYCLE) -> SceneObject:
    """Bicycle: two thin wheel discs, tubes, saddle, handlebar."""
    obj = b.new()
    obj.new_part()
    _bicycle_frame(obj, x, y, yaw, z0, raw)
    return obj


def _motorcycle_frame(obj: SceneObject, rng: np.random.Generator, x: float, y: float, yaw: float, z0: float,
                      raw: int) -> None:
    for lx in (-0.72, 0.72):
        wx, wy = _at(x, y, yaw, lx, 0)
        obj.ellipsoid(wx, wy, z0 + 0.32, 0.32, 0.07, 0.32, yaw, raw, base=z0)
    obj.box(x, y, z0 + 0.35, z0 + rng.uniform(0.85, 0.95), 1.3, 0.4, yaw, raw, base=z0)
    sx, sy = _at(x, y, yaw, -0.15, 0)
    obj.box(sx, sy, z0 + 0.85, z0 + 1.05, 0.95, 0.32, yaw, raw, base=z0)
    hx, hy = _at(x, y, yaw, 0.5, 0)
    obj.box(hx, hy, z0 + 1.02, z0 + 1.08, 0.06, 0.75, yaw, raw, base=z0)


def motorcycle(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float,
               z0: float = 0.0) -> SceneObject:
    """Motorcycle: two wheels, engine/body block, seat, handlebar."""
    obj = b.new()
    obj.new_part()
    _motorcycle_frame(obj, rng, x, y, yaw, z0, MOTORCYCLE)
    return obj


def _body(obj: SceneObject, x: float, y: float, yaw: float, z0: float, height: float, raw: int,
          seated: bool) -> None:
    """A human figure: legs, torso, arms, head (standing, or seated on a bike/motorbike)."""
    k = height / 1.75
    if seated:
        for side in (-1, 1):
            lx, ly = _at(x, y, yaw, -0.02, side * 0.13)
            obj.cylinder(lx, ly, z0 + 0.4, z0 + 0.95, 0.07 * k, raw, base=z0)
        tx, ty = _at(x, y, yaw, -0.08, 0)
        obj.ellipsoid(tx, ty, z0 + 1.28 * k, 0.22 * k, 0.2 * k, 0.3 * k, yaw, raw, base=z0)
        hx, hy = _at(x, y, yaw, 0.1, 0)
        obj.ellipsoid(hx, hy, z0 + 1.68 * k, 0.12, 0.1, 0.12, yaw, raw, base=z0)
        for side in (-1, 1):
            ax, ay = _at(x, y, yaw, 0.22, side * 0.24)
            obj.box(ax, ay, z0 + 1.05 * k, z0 + 1.15 * k, 0.45, 0.08, yaw, raw, base=z0)
        return
    for side in (-1, 1):
        lx, ly = _at(x, y, yaw, 0, side * 0.1 * k)
        obj.cylinder(lx, ly, z0, z0 + 0.48 * height, 0.075 * k, raw, base=z0)
        ax, ay = _at(x, y, yaw, 0, side * 0.27 * k)
        obj.cylinder(ax, ay, z0 + 0.45 * height, z0 + 0.8 * height, 0.045 * k, raw, base=z0)
    obj.ellipsoid(x, y, z0 + 0.65 * height, 0.13 * k, 0.21 * k, 0.18 * height, yaw, raw, base=z0)
    obj.ellipsoid(x, y, z0 + 0.93 * height, 0.1 * k, 0.09 * k, 0.07 * height, yaw, raw, base=z0)


def person(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float, z0: float = 0.0) -> SceneObject:
    """Standing pedestrian, 1.55-1.95 m tall."""
    obj = b.new()
    obj.new_part()
    _body(obj, x, y, yaw, z0, rng.uniform(1.55, 1.95), PERSON, seated=False)
    return obj


def bicyclist(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float,
              z0: float = 0.0) -> SceneObject:
    """Rider on a bicycle; SemanticKITTI labels rider and bicycle both bicyclist."""
    obj = b.new()
    obj.new_part()
    _bicycle_frame(obj, x, y, yaw, z0, BICYCLIST)
    obj.new_part()
    _body(obj, x, y, yaw, z0, rng.uniform(1.6, 1.9), BICYCLIST, seated=True)
    return obj


def motorcyclist(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float,
                 z0: float = 0.0) -> SceneObject:
    """Rider on a motorcycle (both labelled motorcyclist)."""
    obj = b.new()
    obj.new_part()
    _motorcycle_frame(obj, rng, x, y, yaw, z0, MOTORCYCLIST)
    obj.new_part()
    _body(obj, x - 0.1 * math.cos(yaw), y - 0.1 * math.sin(yaw), yaw, z0 + 0.05, rng.uniform(1.65, 1.9),
          MOTORCYCLIST, seated=True)
    return obj


def tree(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, z0: float = 0.0,
         scale: float = 1.0, street: bool = True) -> SceneObject:
    """Trunk cylinder up into a porous crown of one to three overlapping ellipsoids.

    Street trees are pruned to clear traffic (crown from 2.3-3.6 m); garden and park trees
    may branch from 1.2 m.
    """
    obj = b.new()
    radius = rng.uniform(0.1, 0.25) * scale
    clear = rng.uniform(2.5, 3.8) if street else rng.uniform(1.2, 2.8)  # crown base height
    crown_r = rng.uniform(1.6, 3.2) * scale
    crown_h = crown_r * rng.uniform(0.9, 1.4)
    obj.new_part()
    obj.cylinder(x, y, z0, z0 + clear + crown_h, radius, TRUNK, base=z0)
    obj.new_part()
    centre = z0 + clear + crown_h
    obj.ellipsoid(x, y, centre, crown_r, crown_r * rng.uniform(0.85, 1.0), crown_h, rng.uniform(0, np.pi),
                  VEGETATION, porous=rng.uniform(0.25, 0.45), base=z0)
    for _ in range(rng.integers(0, 3)):
        ang = rng.uniform(0, 2 * np.pi)
        r = crown_r * rng.uniform(0.5, 0.75)
        ox, oy = x + 0.55 * crown_r * math.cos(ang), y + 0.55 * crown_r * math.sin(ang)
        rz = r * rng.uniform(0.8, 1.2)
        # Side lobes never hang below the main crown (street trees must clear traffic).
        cz = max(centre + rng.uniform(-0.3, 0.5) * crown_h, z0 + clear + rz)
        obj.ellipsoid(ox, oy, cz, r, r, rz, 0.0, VEGETATION, porous=rng.uniform(0.25, 0.45), base=z0)
    return obj


def bush(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, z0: float = 0.0) -> SceneObject:
    """Porous half-buried ellipsoid."""
    obj = b.new()
    obj.new_part()
    rx, ry, rz = rng.uniform(0.5, 1.4), rng.uniform(0.5, 1.4), rng.uniform(0.5, 1.1)
    obj.ellipsoid(x, y, z0 + rz * rng.uniform(0.3, 0.6), rx, ry, rz, rng.uniform(0, np.pi), VEGETATION,
                  porous=0.2, base=z0)
    return obj


def hedge(b: SceneBuilder, rng: np.random.Generator, x0: float, y0: float, x1: float, y1: float,
          z0: float = 0.0) -> SceneObject:
    """Trimmed hedge from (x0, y0) to (x1, y1), 0.8-1.8 m tall."""
    obj = b.new()
    obj.new_part()
    length = math.hypot(x1 - x0, y1 - y0)
    obj.box((x0 + x1) / 2, (y0 + y1) / 2, z0, z0 + rng.uniform(0.8, 1.8), length, rng.uniform(0.6, 1.1),
            math.atan2(y1 - y0, x1 - x0), VEGETATION, porous=0.12, base=z0)
    return obj


def fence(b: SceneBuilder, rng: np.random.Generator, x0: float, y0: float, x1: float, y1: float,
          z0: float = 0.0, style: str | None = None) -> SceneObject:
    """Fence from (x0, y0) to (x1, y1): a solid low wall, wooden boards, or a mesh with posts."""
    obj = b.new()
    obj.new_part()
    style = style or str(rng.choice(["wall", "boards", "mesh"], p=[0.25, 0.35, 0.4]))
    length = math.hypot(x1 - x0, y1 - y0)
    yaw = math.atan2(y1 - y0, x1 - x0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    if style == "wall":
        obj.box(cx, cy, z0, z0 + rng.uniform(0.8, 1.8), length, 0.25, yaw, FENCE, base=z0)
    elif style == "boards":
        obj.box(cx, cy, z0, z0 + rng.uniform(1.0, 2.0), length, 0.04, yaw, FENCE, base=z0)
    else:
        height = rng.uniform(1.2, 2.2)
        # A chain-link mesh lets about half the beams through.
        obj.box(cx, cy, z0 + 0.05, z0 + height, length, 0.05, yaw, FENCE, porous=0.07, base=z0)
        n = max(int(length / 2.5), 1)
        for i in range(n + 1):
            px, py = x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n
            obj.cylinder(px, py, z0, z0 + height + 0.05, 0.03, FENCE, base=z0)
    return obj


def street_light(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, arm_yaw: float,
                 z0: float = 0.0) -> SceneObject:
    """Pole of 0.08-0.15 m radius, 5-8.5 m tall, with an arm and lamp head over the road."""
    obj = b.new()
    obj.new_part()
    height = rng.uniform(5.0, 8.5)
    obj.cylinder(x, y, z0, z0 + height, rng.uniform(0.08, 0.15), POLE, base=z0)
    if rng.random() < 0.75:
        arm = rng.uniform(1.0, 2.2)
        ax, ay = _at(x, y, arm_yaw, arm / 2, 0)
        obj.box(ax, ay, z0 + height - 0.12, z0 + height - 0.02, arm, 0.08, arm_yaw, POLE, base=z0)
        lx, ly = _at(x, y, arm_yaw, arm, 0)
        obj.box(lx, ly, z0 + height - 0.3, z0 + height - 0.05, 0.6, 0.3, arm_yaw, POLE, base=z0)
    return obj


def utility_pole(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, z0: float = 0.0) -> SceneObject:
    """Plain pole (bollard-like to mast-like), 0.05-0.12 m radius."""
    obj = b.new()
    obj.new_part()
    obj.cylinder(x, y, z0, z0 + rng.uniform(1.0, 4.0), rng.uniform(0.05, 0.12), POLE, base=z0)
    return obj


def traffic_sign(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, facing: float,
                 z0: float = 0.0) -> SceneObject:
    """Plate(s) on a thin post; ``facing`` is the direction the plate's face looks (rad)."""
    obj = b.new()
    obj.new_part()
    top = z0 + rng.uniform(2.2, 3.0)
    obj.cylinder(x, y, z0, top, rng.uniform(0.035, 0.06), POLE, base=z0)
    obj.new_part()
    plates = 1 if rng.random() < 0.7 else 2
    z = top
    px, py = _at(x, y, facing, 0.05, 0)
    for _ in range(plates):
        size = rng.uniform(0.55, 0.85)
        if rng.random() < 0.5:  # round plate: a flat ellipsoid facing ``facing``
            obj.ellipsoid(px, py, z - size / 2, 0.02, size / 2, size / 2, facing, TRAFFIC_SIGN, base=z0)
        else:
            obj.box(px, py, z - size, z, 0.03, size, facing, TRAFFIC_SIGN, base=z0)
        z -= size + 0.08
    return obj


def building(b: SceneBuilder, rng: np.random.Generator, x: float, y: float, yaw: float, length: float,
             depth: float, height: float, front_sign: float, front_room: float = 0.0) -> SceneObject:
    """Building block of ``length`` along ``yaw`` and ``depth`` across, with optional low front
    annex (a shop front or porch, when ``front_room`` m of yard allow it), set-back top storey
    and balconies. ``front_sign`` (+-1) says which local-y side faces the street.
    """
    obj = b.new()
    obj.new_part()
    obj.box(x, y, 0.0, height, length, depth, yaw, BUILDING)
    if height > 9 and rng.random() < 0.3:  # set-back top storey
        inset = rng.uniform(1.5, 3.0)
        cx, cy = _at(x, y, yaw, 0, -front_sign * inset / 2)
        obj.box(cx, cy, height, height + rng.uniform(2.8, 3.5), length - 2 * inset, depth - inset, yaw, BUILDING)
    if front_room > 2.0 and rng.random() < 0.35:  # low annex in front, within the yard
        obj.new_part()
        width = length * rng.uniform(0.3, 0.8)
        reach = rng.uniform(1.5, min(front_room - 0.5, 5.0))
        cx, cy = _at(x, y, yaw, rng.uniform(-0.5, 0.5) * (length - width), front_sign * (depth / 2 + reach / 2))
        obj.box(cx, cy, 0.0, rng.uniform(2.6, min(4.5, height)), width, reach, yaw, BUILDING)
    if height > 7 and rng.random() < 0.3:  # balconies on the street facade, one row per storey
        obj.new_part()
        n = max(int(length / rng.uniform(3.5, 6.0)), 1)
        span = length / n
        for storey in range(1, int(height / 3.0)):
            for i in range(n):
                if rng.random() < 0.3:
                    continue
                bx, by = _at(x, y, yaw, -length / 2 + span * (i + 0.5), front_sign * (depth / 2 + 0.6))
                z = storey * 3.0
                obj.box(bx, by, z, z + rng.uniform(0.9, 1.1), span * 0.7, 1.2, yaw, BUILDING)
    return obj
