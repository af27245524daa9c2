"""Furnishing of the block sides: sidewalk furniture, parked cars, road users and frontages.

Block sides get a frontage: buildings with yards, paths, hedges and fences; a park with trees
and bushes; a parking lot with rows of cars; or a paved plaza. Sidewalks carry street trees,
street lights, traffic signs, pedestrians and parked bicycles; parking lanes parked cars,
trucks, buses and motorcycles; the roads a few stopped vehicles and cyclists. All of it is
static; moving road users come from ``traffic``.
"""

from __future__ import annotations

import math

import numpy as np

from convbki_core.synth import objects as obj
from convbki_core.synth.primitives import OTHER_GROUND, PARKING, TERRAIN
from convbki_core.synth.streets import CURB_HEIGHT, Side


class _Occupancy:
    """Discs already taken on one block side, so objects do not interpenetrate."""

    def __init__(self) -> None:
        self.discs: list[tuple[float, float, float]] = []

    def take(self, x: float, y: float, r: float) -> bool:
        for px, py, pr in self.discs:
            if (px - x) ** 2 + (py - y) ** 2 < (pr + r) ** 2:
                return False
        self.discs.append((x, y, r))
        return True


class Furnishing:
    """Mix-in of the scene maker: fills one block side (``rng``, ``builder`` and ``paint`` come
    from ``StreetLayout``)."""

    def _side(self, side: Side, trim: float, depth: float) -> None:
        rng = self.rng
        occ = _Occupancy()
        if side.lawn > 0:  # grass strip behind the curb stone, 2 cm above the walkway
            a0, a1, b0, b1 = 1.5, side.length - 1.5, -side.sidewalk + 0.15, -side.sidewalk + 0.15 + side.lawn
            (xa, ya), (xb, yb) = side.at(a0, b0), side.at(a1, b1)
            lawn = self.builder.new(stuff=True)
            lawn.box((xa + xb) / 2, (ya + yb) / 2, -0.3, CURB_HEIGHT + 0.02, a1 - a0, b1 - b0, side.yaw, TERRAIN)
            self.paint(side.rect(a0, a1, b0, b1), TERRAIN)
        self._sidewalk_furniture(side, occ)
        if side.parking > 0:
            self.paint(side.rect(4.0, side.length - 4.0, -side.sidewalk - side.parking, -side.sidewalk), PARKING)
            self._parked_vehicles(side)
        self._road_users(side)
        kind = rng.choice(["buildings", "park", "lot", "plaza"], p=[0.55, 0.25, 0.12, 0.08])
        a0, a1 = trim, side.length - trim
        if a1 - a0 < 12:
            return
        getattr(self, f"_frontage_{kind}")(side, a0, a1, depth, occ)

    # ---- sidewalk, parking lane, road --------------------------------------------------------
    def _sidewalk_furniture(self, side: Side, occ: _Occupancy) -> None:
        rng, b, z = self.rng, self.builder, CURB_HEIGHT
        line = -side.sidewalk + 0.6  # furniture line, 0.6 m from the curb
        street_dir = side.yaw
        if side.trees:
            a = rng.uniform(2, 8)
            while a < side.length - 2:
                x, y = side.at(a, line)
                if occ.take(x, y, 0.5):
                    obj.tree(b, rng, x, y, z, scale=rng.uniform(0.8, 1.15))
                a += rng.uniform(6, 12)
        a = rng.uniform(4, 20)
        while a < side.length - 3:
            x, y = side.at(a, line + 0.05)
            if occ.take(x, y, 0.4):
                obj.street_light(b, rng, x, y, street_dir - math.pi / 2, z)  # arm over the road
            a += rng.uniform(22, 40)
        # Signs near both corners and now and then between; plates face oncoming traffic.
        spots = [rng.uniform(2, 9) if rng.random() < 0.75 else None,
                 side.length - rng.uniform(2, 9) if rng.random() < 0.75 else None]
        spots += list(rng.uniform(10, max(side.length - 10, 11), rng.poisson(side.length / 70)))
        for a in spots:
            if a is None:
                continue
            x, y = side.at(a, line + rng.uniform(-0.2, 0.3))
            if occ.take(x, y, 0.45):
                obj.traffic_sign(b, rng, x, y, street_dir + (math.pi if rng.random() < 0.5 else 0.0), z)
        for _ in range(rng.poisson(side.length / 70)):  # bollards and short poles
            x, y = side.at(rng.uniform(1, side.length - 1), line - 0.2)
            if occ.take(x, y, 0.3):
                obj.utility_pole(b, rng, x, y, z)
        for _ in range(rng.poisson(side.length / 22)):
            x, y = side.at(rng.uniform(1, side.length - 1), rng.uniform(-side.sidewalk + 1.1, -0.4))
            if occ.take(x, y, 0.45):
                obj.person(b, rng, x, y, rng.uniform(0, 2 * np.pi), z)
        for _ in range(rng.poisson(side.length / 45)):
            a = rng.uniform(1, side.length - 3)
            count = rng.integers(1, 4)
            for k in range(count):
                x, y = side.at(a + 0.7 * k, -0.55)
                if occ.take(x, y, 0.35):
                    obj.bicycle(b, rng, x, y, side.yaw + math.pi / 2 + rng.uniform(-0.2, 0.2), z)

    def _vehicle(self, x: float, y: float, yaw: float, choice: str) -> None:
        rng, b = self.rng, self.builder
        {"car": obj.car, "truck": obj.truck, "other": obj.other_vehicle, "motorcycle": obj.motorcycle,
         "bicycle": obj.bicycle}[choice](b, rng, x, y, yaw)

    def _parked_vehicles(self, side: Side) -> None:
        rng = self.rng
        b_mid = -side.sidewalk - side.parking / 2
        a = rng.uniform(6, 12)
        while a < side.length - 8:
            if rng.random() < 0.2:  # an empty stretch
                a += rng.uniform(5, 15)
                continue
            kind = rng.choice(["car", "truck", "other", "motorcycle"], p=[0.76, 0.1, 0.07, 0.07])
            length = {"car": 4.9, "truck": 10.0, "other": 12.5, "motorcycle": 2.0}[kind]
            if a + length > side.length - 6:
                break
            x, y = side.at(a + length / 2, b_mid + rng.uniform(-0.15, 0.15))
            yaw = side.yaw + (math.pi if rng.random() < 0.5 else 0.0) + rng.uniform(-0.04, 0.04)
            self._vehicle(x, y, yaw, str(kind))
            a += length + rng.uniform(0.6, 4.0)

    def _road_users(self, side: Side) -> None:
        """Stopped vehicles and cyclists in the lane next to this side (dropped later where
        they would stand in the ego vehicle's way)."""
        rng, b = self.rng, self.builder
        edge = -side.sidewalk - side.parking
        lane_mid = edge - side.street.lane / 2
        lo, hi = 18.0, side.length - 18.0
        if hi <= lo:
            return
        flip = math.pi if rng.random() < 0.5 else 0.0
        for _ in range(rng.poisson(side.length / 90)):
            x, y = side.at(rng.uniform(lo, hi), edge - rng.uniform(0.7, 1.1))
            obj.bicyclist(b, rng, x, y, side.yaw + flip + rng.uniform(-0.1, 0.1))
        for _ in range(rng.poisson(side.length / 260)):
            x, y = side.at(rng.uniform(lo, hi), edge - rng.uniform(0.8, 1.2))
            obj.motorcyclist(b, rng, x, y, side.yaw + flip + rng.uniform(-0.1, 0.1))
        for _ in range(rng.poisson(side.length / 200)):
            x, y = side.at(rng.uniform(lo, hi), lane_mid)
            kind = rng.choice(["car", "truck", "other"], p=[0.6, 0.25, 0.15])
            self._vehicle(x, y, side.yaw + flip, str(kind))

    # ---- frontages ---------------------------------------------------------------------------
    def _yard_edge(self, side: Side, a0: float, a1: float, b: float, gaps: list[tuple[float, float]]) -> None:
        """Hedge or fence along a line at depth b, leaving ``gaps`` (a-intervals) open."""
        rng = self.rng
        kind = rng.choice(["hedge", "fence", "none"], p=[0.45, 0.35, 0.2])
        if kind == "none":
            return
        cuts = sorted(gaps)
        start = a0
        for g0, g1 in cuts + [(a1, a1)]:
            if g0 - start > 1.0:
                (xa, ya), (xb, yb) = side.at(start, b), side.at(min(g0, a1), b)
                if kind == "hedge":
                    obj.hedge(self.builder, rng, xa, ya, xb, yb)
                else:
                    obj.fence(self.builder, rng, xa, ya, xb, yb)
            start = max(start, g1)

    def _frontage_buildings(self, side: Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
        rng, b = self.rng, self.builder
        a = a0 + rng.uniform(0, 4)
        while a < a1 - 6:
            width = min(rng.uniform(8, 32), a1 - a)
            if width < 6:
                break
            setback = rng.uniform(0.3, 2.0) if rng.random() < 0.35 else rng.uniform(2.0, 8.0)
            bdepth = min(rng.uniform(10, 20), depth - setback)
            if bdepth < 6:
                break
            height = float(np.clip(rng.gamma(4.0, 2.8), 4.0, 24.0))
            x, y = side.at(a + width / 2, setback + bdepth / 2)
            obj.building(b, rng, x, y, side.yaw, width, bdepth, height, front_sign=-1, front_room=setback - 1.0)
            if setback > 1.5:
                if rng.random() < 0.35:
                    self.paint(side.rect(a, a + width, 0, setback), OTHER_GROUND)
                door = rng.uniform(a + 1, a + max(width - 3, 1.5))
                door_w = rng.uniform(1.5, 3.0)
                self.paint(side.rect(door, door + door_w, 0, setback), OTHER_GROUND)
                self._yard_edge(side, a, a + width, 0.5, [(door - 0.5, door + door_w + 0.5)])
                for _ in range(rng.poisson(width * setback / 25) if setback > 2.4 else 0):
                    x, y = side.at(rng.uniform(a + 1, a + width - 1), rng.uniform(1.2, setback - 0.6))
                    if occ.take(x, y, 1.0):
                        obj.bush(b, rng, x, y)
                if setback > 3.5 and rng.random() < 0.5:
                    x, y = side.at(rng.uniform(a + 2, a + width - 2), setback / 2)
                    if occ.take(x, y, 1.0):
                        obj.tree(b, rng, x, y, scale=rng.uniform(0.6, 0.9), street=False)
                if setback > 2.0 and rng.random() < 0.4:  # shrubs along the facade
                    for bx in np.arange(a + 1.0, a + width - 1.0, rng.uniform(1.5, 3.0)):
                        x, y = side.at(bx, setback - 0.7)
                        if occ.take(x, y, 0.6):
                            obj.bush(b, rng, x, y)
            a += width
            gap = rng.uniform(0, 9)
            if gap > 3.5 and a + gap < a1:
                if rng.random() < 0.3:  # driveway with a car in it
                    self.paint(side.rect(a + 0.3, a + gap - 0.3, 0, min(depth, 14)), OTHER_GROUND)
                    if rng.random() < 0.6:
                        x, y = side.at(a + gap / 2, rng.uniform(3.0, 5.0))
                        obj.car(b, rng, x, y, side.yaw + math.pi / 2 + rng.uniform(-0.1, 0.1))
                elif rng.random() < 0.6:  # fence between the two lots
                    (xa, ya), (xb, yb) = side.at(a + gap / 2, 1.0), side.at(a + gap / 2, depth - 2)
                    obj.fence(b, rng, xa, ya, xb, yb)
            a += gap

    def _frontage_park(self, side: Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
        rng, b = self.rng, self.builder
        path = rng.uniform(3.0, min(9.0, depth - 4))
        self.paint(side.rect(a0, a1, path, path + 2.5), OTHER_GROUND)
        self._yard_edge(side, a0, a1, 0.4, [(a0 + (a1 - a0) * f - 1.5, a0 + (a1 - a0) * f + 1.5) for f in (0.3, 0.7)])
        area = (a1 - a0) * depth
        for _ in range(rng.poisson(area / 70)):
            bb = rng.uniform(1.5, depth - 1)
            if path - 1.0 < bb < path + 3.5:
                continue
            x, y = side.at(rng.uniform(a0 + 1, a1 - 1), bb)
            if occ.take(x, y, 1.5):
                obj.tree(b, rng, x, y, scale=rng.uniform(0.8, 1.3), street=False)
        for _ in range(rng.poisson(area / 50)):
            bb = rng.uniform(1.5, depth - 1)
            if path - 1.5 < bb < path + 4.0:
                continue
            x, y = side.at(rng.uniform(a0 + 1, a1 - 1), bb)
            if occ.take(x, y, 1.2):
                obj.bush(b, rng, x, y)
        for _ in range(rng.poisson((a1 - a0) / 18)):
            x, y = side.at(rng.uniform(a0 + 1, a1 - 1), path + rng.uniform(0.4, 2.1))
            if occ.take(x, y, 0.45):
                obj.person(b, rng, x, y, rng.uniform(0, 2 * np.pi))
        for _ in range(rng.poisson((a1 - a0) / 45)):
            x, y = side.at(rng.uniform(a0 + 1, a1 - 1), path + 1.25)
            if occ.take(x, y, 0.8):
                obj.bicyclist(b, rng, x, y, side.yaw + (math.pi if rng.random() < 0.5 else 0.0))
        a = a0 + rng.uniform(5, 15)
        while a < a1 - 2:
            x, y = side.at(a, path - 0.3)
            if occ.take(x, y, 0.3):
                obj.utility_pole(b, rng, x, y)
            a += rng.uniform(15, 30)

    def _frontage_lot(self, side: Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
        rng, b = self.rng, self.builder
        back = min(depth, 30.0)
        self.paint(side.rect(a0 + 1, a1 - 1, 1.5, back), PARKING)
        entry = rng.uniform(a0 + 4, a1 - 10)
        self._yard_edge(side, a0 + 1, a1 - 1, 0.8, [(entry, entry + 6.0)])
        rows = [1.5 + 2.5] + ([1.5 + 4.9 + 6.0 + 2.5] if back > 1.5 + 4.9 + 6.0 + 5.0 else [])
        for row, bb in enumerate(rows):
            a = a0 + 2.5
            while a < a1 - 2.5:
                if rng.random() < 0.68:
                    x, y = side.at(a, bb)
                    yaw = side.yaw + math.pi / 2 * (1 if row == 0 else -1) + rng.uniform(-0.06, 0.06)
                    kind = rng.choice(["car", "truck", "other", "motorcycle"], p=[0.84, 0.04, 0.05, 0.07])
                    if kind in ("truck", "other") and rng.random() < 0.5:
                        kind = "car"  # only half the stalls have room for the long ones
                    self._vehicle(x, y, yaw, str(kind))
                a += 2.6
        a = a0 + rng.uniform(5, 12)
        while a < a1 - 3:
            x, y = side.at(a, 1.5 + 4.9 + 3.0)
            if occ.take(x, y, 0.4):
                obj.street_light(b, rng, x, y, side.yaw + math.pi / 2)
            a += rng.uniform(22, 35)

    def _frontage_plaza(self, side: Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
        rng, b = self.rng, self.builder
        back = min(depth, rng.uniform(12, 20))
        self.paint(side.rect(a0, a1, 0, back), OTHER_GROUND)
        for a in np.arange(a0 + rng.uniform(3, 8), a1 - 3, rng.uniform(8, 14)):
            x, y = side.at(a, rng.uniform(2, back - 2))
            if occ.take(x, y, 1.5):
                obj.tree(b, rng, x, y, scale=rng.uniform(0.7, 1.0), street=False)
                for _ in range(rng.integers(0, 3)):
                    bx, by = x + rng.uniform(-1.2, 1.2), y + rng.uniform(-1.2, 1.2)
                    obj.bush(b, rng, bx, by)
        for _ in range(rng.poisson((a1 - a0) / 8)):
            x, y = side.at(rng.uniform(a0 + 1, a1 - 1), rng.uniform(0.5, back - 0.5))
            if occ.take(x, y, 0.45):
                obj.person(b, rng, x, y, rng.uniform(0, 2 * np.pi))
        a = rng.uniform(a0 + 2, max(a1 - 8, a0 + 3))
        for k in range(rng.integers(3, 9)):  # a bicycle rack
            x, y = side.at(a + 0.75 * k, back - 1.2)
            if occ.take(x, y, 0.3):
                obj.bicycle(b, rng, x, y, side.yaw + math.pi / 2)
        for _ in range(rng.integers(1, 3)):
            x, y = side.at(rng.uniform(a0 + 1, a1 - 1), rng.uniform(0.5, back - 0.5))
            if occ.take(x, y, 0.5):
                obj.traffic_sign(b, rng, x, y, side.yaw - math.pi / 2)
        if depth - back > 8:
            x, y = side.at((a0 + a1) / 2, back + 1 + (depth - back - 1) / 2)
            obj.building(b, rng, x, y, side.yaw, a1 - a0 - 4, depth - back - 1, rng.uniform(6, 20), front_sign=-1)
