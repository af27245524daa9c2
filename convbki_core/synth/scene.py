"""Procedural street scene: a grid of streets and blocks around a loop route.

Scene frame: metres, z up, the ground plane at z = 0, streets along the x and y axes (the
world/map frame of the written drive is this frame turned and shifted, see ``drive``).

Cross-section of a street, from its centre line outwards: optional flat median (other-ground),
one or two lanes per direction (road, with painted markings), an optional parking lane
(parking), a 0.15 m raised sidewalk with a curb (box primitives, sidewalk), then the block.
Block sides get a frontage: buildings with yards, paths, hedges and fences; a park with trees
and bushes; a parking lot with rows of cars; or a paved plaza. Sidewalks carry street trees,
street lights, traffic signs, pedestrians and parked bicycles; parking lanes parked cars,
trucks, buses and motorcycles; the roads a few stopped vehicles and cyclists.

Ground classes live in a 0.2 m raster (road, parking, sidewalk, other-ground, terrain); every
solid is a primitive (see ``primitives``) indexed by a 2D grid of cells for ray casting.
Everything is drawn from ``numpy.random.default_rng(seed)``: the same seed gives the same
scene, a different seed a different layout.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from convbki_core.datasets.labels import load_label_map
from convbki_core.synth import objects as obj
from convbki_core.synth.primitives import (
    BOX,
    CORRIDOR_MAX_BOTTOM,
    CYLINDER,
    FOOTPRINT_MAX_BOTTOM,
    OTHER_GROUND,
    PARKING,
    ROAD,
    SIDEWALK,
    TERRAIN,
    SceneBuilder,
    footprint_extent,
    obb_distance,
)
from convbki_core.synth.route import Route

RASTER_RESOLUTION = 0.2  # m per ground-raster cell
GRID_CELL = 4.0  # m per ray-casting grid cell
QUERY_MARGIN = 0.5  # m: primitives are also listed in cells this close, for neighbour queries
CURB_HEIGHT = 0.15  # m, sidewalk top above the road
EXTENT_MARGIN = 115.0  # m of scene around the route (the LiDAR sees 90 m at most)
EGO_CLEARANCE = 1.3  # m from the route centre line kept free of objects (half car width + margin)


@dataclass
class Street:
    """One straight street on a grid line."""

    axis: int  # 0: runs along y at x = pos; 1: runs along x at y = pos
    pos: float
    lane: float  # lane width, m
    lanes: int  # per direction
    median: float  # flat median width, m (0 = none)
    parking: tuple[float, float]  # parking-lane width on the side towards -pos / +pos (0 = none)
    sidewalk: tuple[float, float]  # curb to block, lawn strip included
    trees: tuple[bool, bool]
    lawn: tuple[float, float]  # grass strip between curb and walkway (0 = none)

    @property
    def road_half(self) -> float:
        return self.median / 2 + self.lanes * self.lane

    def curb(self, side: int) -> float:
        """Distance (m) from the centre line to the curb on ``side`` (-1 or +1)."""
        return self.road_half + self.parking[(side + 1) // 2]

    @property
    def ego_offset(self) -> float:
        """Distance (m) from the centre line to the centre of the outer (right-hand) lane."""
        return self.road_half - self.lane / 2


@dataclass
class RasterSpec:
    """A 2D raster over the scene: cell (iy, ix) covers x0 + ix*res .. x0 + (ix+1)*res."""

    x0: float
    y0: float
    res: float
    nx: int
    ny: int

    def window(self, xmin: float, xmax: float, ymin: float, ymax: float) -> tuple[slice, slice]:
        """Cells whose centres lie in [xmin, xmax) x [ymin, ymax), clipped to the raster."""
        ix0 = max(math.ceil((xmin - self.x0) / self.res - 0.5), 0)
        ix1 = min(math.ceil((xmax - self.x0) / self.res - 0.5), self.nx)
        iy0 = max(math.ceil((ymin - self.y0) / self.res - 0.5), 0)
        iy1 = min(math.ceil((ymax - self.y0) / self.res - 0.5), self.ny)
        return slice(iy0, max(iy1, iy0)), slice(ix0, max(ix1, ix0))

    def centres(self, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray]:
        """Scene x (1, W) and y (H, 1) of the cell centres of a window."""
        xs = self.x0 + (np.arange(cols.start, cols.stop) + 0.5) * self.res
        ys = self.y0 + (np.arange(rows.start, rows.stop) + 0.5) * self.res
        return xs[None, :], ys[:, None]


@dataclass
class Grid:
    """Primitives listed per square cell (CSR): cell (iy, ix) -> items[start[c]:start[c+1]]."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    start: np.ndarray  # (nx*ny + 1,) int64
    items: np.ndarray  # int32 primitive indices


@dataclass
class Scene:
    """Everything the LiDAR simulation and the noise model need (scene frame)."""

    seed: int
    kind: np.ndarray  # (P,) int8 BOX / CYLINDER / ELLIPSOID
    param: np.ndarray  # (P, 9) float64, see primitives
    raw: np.ndarray  # (P,) uint16 raw SemanticKITTI id
    learning: np.ndarray  # (P,) int64 learning class
    part: np.ndarray  # (P,) int32 part id (noise model)
    instance: np.ndarray  # (P,) uint32 instance id (0: stuff)
    raster: RasterSpec
    ground_raw: np.ndarray  # (ny, nx) uint16 raw id of the ground surface
    marking: np.ndarray  # (ny, nx) bool: painted lane markings (bright remission)
    top: np.ndarray  # (ny, nx) uint8 learning class seen from above at ground level (ground or footprint)
    nb_class: np.ndarray  # (ny, nx) int8 nearest other class of ``top`` within QUERY_MARGIN (-1: none)
    nb_dist: np.ndarray  # (ny, nx) float32 its distance, m
    grid: Grid
    route: Route
    start_s: float  # arc length where the drive starts, m
    info: dict = field(default_factory=dict)


class _Rng:
    """numpy Generator whose ``uniform(lo, hi)`` gives ``lo`` when a small block or lot makes
    the interval empty (numpy raises), so no layout is ever impossible."""

    def __init__(self, generator: np.random.Generator):
        self._generator = generator

    def __getattr__(self, name: str):
        return getattr(self._generator, name)

    def uniform(self, low=0.0, high=1.0, size=None):
        return self._generator.uniform(low, np.maximum(low, high), size)


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


@dataclass
class _Side:
    """A block side in local coordinates: a along the street, b into the block (b = 0 at the
    sidewalk's inner edge, b < 0 over the sidewalk towards the curb)."""

    ox: float
    oy: float
    ux: float
    uy: float
    length: float
    sidewalk: float
    parking: float
    street: Street
    trees: bool
    lawn: float

    @property
    def yaw(self) -> float:
        return math.atan2(self.uy, self.ux)

    def at(self, a: float, b: float) -> tuple[float, float]:
        # The inward normal is u turned left by 90 degrees (blocks are walked counter-clockwise).
        return self.ox + a * self.ux - b * self.uy, self.oy + a * self.uy + b * self.ux

    def rect(self, a0: float, a1: float, b0: float, b1: float) -> tuple[float, float, float, float]:
        """Axis-aligned scene rectangle (xmin, xmax, ymin, ymax) of a local rectangle."""
        (xa, ya), (xb, yb) = self.at(a0, b0), self.at(a1, b1)
        return min(xa, xb), max(xa, xb), min(ya, yb), max(ya, yb)


class _SceneMaker:
    def __init__(self, seed: int):
        self.rng = _Rng(np.random.default_rng([seed, 0x5CE4E]))
        self.builder = SceneBuilder()
        self.labels = load_label_map()

    # ---- layout ---------------------------------------------------------------------------
    def _street(self, axis: int, pos: float) -> Street:
        rng = self.rng
        lanes = 2 if rng.random() < 0.1 else 1
        median = rng.uniform(0.8, 2.0) if rng.random() < 0.3 else 0.0
        parking = tuple(float(rng.uniform(2.1, 2.5)) if rng.random() < 0.6 else 0.0 for _ in range(2))
        lawn = tuple(float(rng.uniform(1.0, 2.2)) if rng.random() < 0.4 else 0.0 for _ in range(2))
        sidewalk = tuple(float(rng.uniform(1.8, 3.5)) + w for w in lawn)
        trees = tuple(bool(rng.random() < 0.75) or w > 0 for w in lawn)
        return Street(axis, pos, float(rng.uniform(3.0, 3.6)), lanes, median, parking, sidewalk, trees, lawn)

    def layout(self) -> None:
        rng = self.rng
        # Route: the loop around 1x1, 2x1 or 1x2 blocks, 300-600 m long.
        while True:
            nbx, nby = [(1, 1), (2, 1), (1, 2)][rng.choice(3, p=[0.5, 0.25, 0.25])]
            gx, gy = rng.uniform(65, 135, nbx), rng.uniform(65, 135, nby)
            if 300 <= 2 * (gx.sum() + gy.sum()) <= 600:
                break
        loop_x = np.concatenate([[0.0], np.cumsum(gx)])
        loop_y = np.concatenate([[0.0], np.cumsum(gy)])
        self.extent = (loop_x[0] - EXTENT_MARGIN, loop_x[-1] + EXTENT_MARGIN,
                       loop_y[0] - EXTENT_MARGIN, loop_y[-1] + EXTENT_MARGIN)

        def grow(lines: np.ndarray, lo: float, hi: float) -> tuple[list[float], int]:
            lines = list(lines)
            added = 0
            while lines[0] > lo - 40:
                lines.insert(0, lines[0] - rng.uniform(65, 135))
                added += 1
            while lines[-1] < hi + 40:
                lines.append(lines[-1] + rng.uniform(65, 135))
            return lines, added

        xs, i0 = grow(loop_x, self.extent[0], self.extent[1])
        ys, j0 = grow(loop_y, self.extent[2], self.extent[3])
        self.vstreets = [self._street(0, x) for x in xs]
        self.hstreets = [self._street(1, y) for y in ys]
        self.loop = (i0, i0 + nbx, j0, j0 + nby)
        x0, x1, y0, y1 = self.extent
        nx, ny = math.ceil((x1 - x0) / RASTER_RESOLUTION), math.ceil((y1 - y0) / RASTER_RESOLUTION)
        self.raster = RasterSpec(x0, y0, RASTER_RESOLUTION, nx, ny)
        self.ground = np.full((ny, nx), TERRAIN, np.uint16)
        self.marking = np.zeros((ny, nx), bool)

    def route(self) -> None:
        i0, i1, j0, j1 = self.loop
        w, e, s, n = self.vstreets[i0], self.vstreets[i1], self.hstreets[j0], self.hstreets[j1]
        # Counter-clockwise around the loop's blocks, in the right-hand lane: every turn is a left turn.
        corners = np.array([
            [w.pos - w.ego_offset, s.pos - s.ego_offset],
            [e.pos + e.ego_offset, s.pos - s.ego_offset],
            [e.pos + e.ego_offset, n.pos + n.ego_offset],
            [w.pos - w.ego_offset, n.pos + n.ego_offset],
        ])
        self.route_ = Route.from_corners(corners, float(self.rng.uniform(8.0, 12.0)))
        corner = self.rng.integers(len(self.route_.corner_s))
        # Start 15-45 m before a corner, so that even a short drive has a turn in it.
        self.start_s = float((self.route_.corner_s[corner] - self.rng.uniform(15, 45)) % self.route_.length)

    # ---- ground painting ------------------------------------------------------------------
    def paint(self, rect: tuple[float, float, float, float], value: int, target: np.ndarray | None = None) -> None:
        rows, cols = self.raster.window(*rect)
        (self.ground if target is None else target)[rows, cols] = value

    def streets(self) -> None:
        x0, x1, y0, y1 = self.extent
        for st in self.vstreets + self.hstreets:
            cross = self.hstreets if st.axis == 0 else self.vstreets
            lo, hi = st.pos - st.curb(-1), st.pos + st.curb(1)
            self.paint((lo, hi, y0, y1) if st.axis == 0 else (x0, x1, lo, hi), ROAD)
            # Between two cross streets: median, centre and edge markings (not in intersections).
            for c0, c1 in itertools.pairwise(cross):
                a0, a1 = c0.pos + c0.curb(1) + 3.0, c1.pos - c1.curb(-1) - 3.0
                if a1 <= a0:
                    continue

                def strip(d0: float, d1: float, value: int | None, dash: bool = False,
                          st=st, a0=a0, a1=a1) -> None:
                    pieces = [(a0, a1)]
                    if dash:  # 3 m dashes, 6 m gaps
                        pieces = [(a, min(a + 3.0, a1)) for a in np.arange(a0, a1, 9.0)]
                    for p0, p1 in pieces:
                        lo, hi = st.pos + d0, st.pos + d1
                        rect = (lo, hi, p0, p1) if st.axis == 0 else (p0, p1, lo, hi)
                        if value is None:
                            self.paint(rect, True, self.marking)
                        else:
                            self.paint(rect, value)

                if st.median > 0:
                    strip(-st.median / 2, st.median / 2, OTHER_GROUND)
                else:
                    strip(-0.08, 0.08, None, dash=st.lanes == 1)
                for side in (-1, 1):
                    edge = side * st.road_half
                    strip(min(edge, edge - side * 0.15), max(edge, edge - side * 0.15), None)

    # ---- blocks ---------------------------------------------------------------------------
    def blocks(self) -> None:
        x0, x1, y0, y1 = self.extent
        for i in range(len(self.vstreets) - 1):
            for j in range(len(self.hstreets) - 1):
                w, e = self.vstreets[i], self.vstreets[i + 1]
                s, n = self.hstreets[j], self.hstreets[j + 1]
                cx0, cx1 = w.pos + w.curb(1), e.pos - e.curb(-1)  # curb lines
                cy0, cy1 = s.pos + s.curb(1), n.pos - n.curb(-1)
                if cx1 < x0 or cx0 > x1 or cy1 < y0 or cy0 > y1:
                    continue
                ix0, ix1 = cx0 + w.sidewalk[1], cx1 - e.sidewalk[0]  # sidewalk inner edges
                iy0, iy1 = cy0 + s.sidewalk[1], cy1 - n.sidewalk[0]
                self._sidewalk_ring(cx0, cx1, cy0, cy1, ix0, ix1, iy0, iy1)
                depth = min(28.0, 0.5 * min(ix1 - ix0, iy1 - iy0) - 1.0)
                sides = [
                    (_Side(ix0, iy0, 1, 0, ix1 - ix0, s.sidewalk[1], s.parking[1], s, s.trees[1], s.lawn[1]), 0.0),
                    (_Side(ix1, iy0, 0, 1, iy1 - iy0, e.sidewalk[0], e.parking[0], e, e.trees[0], e.lawn[0]), depth),
                    (_Side(ix1, iy1, -1, 0, ix1 - ix0, n.sidewalk[0], n.parking[0], n, n.trees[0], n.lawn[0]), 0.0),
                    (_Side(ix0, iy1, 0, -1, iy1 - iy0, w.sidewalk[1], w.parking[1], w, w.trees[1], w.lawn[1]), depth),
                ]
                for side, trim in sides:
                    if self._near_extent(side):
                        self._side(side, trim, depth)

    def _near_extent(self, side: _Side) -> bool:
        x0, x1, y0, y1 = self.extent
        xa, xb, ya, yb = side.rect(0, side.length, -side.sidewalk - side.parking - 4, 30)
        return xb > x0 and xa < x1 and yb > y0 and ya < y1

    def _sidewalk_ring(self, cx0: float, cx1: float, cy0: float, cy1: float,
                       ix0: float, ix1: float, iy0: float, iy1: float) -> None:
        """Raised sidewalk around a block: four slabs from below ground to the curb height."""
        slab = self.builder.new(stuff=True)
        for xa, xb, ya, yb in ((cx0, cx1, cy0, iy0), (cx0, cx1, iy1, cy1), (cx0, ix0, iy0, iy1), (ix1, cx1, iy0, iy1)):
            slab.box((xa + xb) / 2, (ya + yb) / 2, -0.3, CURB_HEIGHT, xb - xa, yb - ya, 0.0, SIDEWALK)
            self.paint((xa, xb, ya, yb), SIDEWALK)

    def _side(self, side: _Side, trim: float, depth: float) -> None:
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
    def _sidewalk_furniture(self, side: _Side, occ: _Occupancy) -> None:
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

    def _parked_vehicles(self, side: _Side) -> None:
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

    def _road_users(self, side: _Side) -> None:
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
    def _yard_edge(self, side: _Side, a0: float, a1: float, b: float, gaps: list[tuple[float, float]]) -> None:
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

    def _frontage_buildings(self, side: _Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
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

    def _frontage_park(self, side: _Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
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

    def _frontage_lot(self, side: _Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
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

    def _frontage_plaza(self, side: _Side, a0: float, a1: float, depth: float, occ: _Occupancy) -> None:
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

    # ---- finishing ---------------------------------------------------------------------------
    def keep_mask(self) -> np.ndarray:
        """Objects to keep: drop those whose low parts come within EGO_CLEARANCE of the route."""
        path = self.route_.xy[::5]  # every 0.5 m
        keep = np.ones(len(self.builder.objects), bool)
        for index, ob in enumerate(self.builder.objects):
            if ob.stuff or not ob.kinds:
                continue
            low = [k for k in range(len(ob.kinds)) if ob.bottoms[k] < CORRIDOR_MAX_BOTTOM]
            if not low:
                continue
            rows = np.asarray([ob.params[k] for k in low])
            # Cheap screen on the bounding circle before the exact footprint distances.
            reach = float(np.max(np.abs(rows[:, 3:5]).sum(1))) + EGO_CLEARANCE
            near = np.abs(path - rows[0, :2]).max(1) < reach + 20
            if not near.any():
                continue
            pts = path[near]
            for k, row in zip(low, rows):
                if obb_distance(pts, row, ob.kinds[k]).min() < EGO_CLEARANCE:
                    keep[index] = False
                    break
        return keep

    def finish(self, seed: int) -> Scene:
        keep = self.keep_mask()
        arr = self.builder.arrays(keep)
        learning_map = self.labels.learning_map
        learning = learning_map[arr["raw"]].astype(np.int64)
        top = learning_map[self.ground].astype(np.uint8)
        # Footprints of everything standing on the ground, for the boundary part of the noise.
        for k in range(len(arr["kind"])):
            if arr["instance"][k] == 0 or arr["bottom"][k] > FOOTPRINT_MAX_BOTTOM:
                continue
            self._paint_footprint(top, arr["kind"][k], arr["param"][k], learning[k])
        from convbki_core.synth.lidar import raster_neighbours

        nb_class, nb_dist = raster_neighbours(top, RASTER_RESOLUTION, QUERY_MARGIN)
        grid = build_grid(arr["kind"], arr["param"], self.extent)
        i0, i1, j0, j1 = self.loop
        info = {
            "route_length_m": round(self.route_.length, 1),
            "loop_blocks": [i1 - i0, j1 - j0],
            "primitives": len(arr["kind"]),
            "objects": int(arr["instance"].max(initial=0)),
        }
        return Scene(seed, arr["kind"], arr["param"], arr["raw"], learning, arr["part"], arr["instance"],
                     self.raster, self.ground, self.marking, top, nb_class, nb_dist, grid, self.route_,
                     self.start_s, info)

    def _paint_footprint(self, top: np.ndarray, kind: int, row: np.ndarray, value: int) -> None:
        ex, ey = footprint_extent(kind, row)
        rows, cols = self.raster.window(row[0] - ex, row[0] + ex, row[1] - ey, row[1] + ey)
        if rows.stop <= rows.start or cols.stop <= cols.start:
            return
        xs, ys = self.raster.centres(rows, cols)
        dx, dy = xs - row[0], ys - row[1]
        if kind == CYLINDER:
            inside = dx ** 2 + dy ** 2 <= row[3] ** 2
        else:
            lx, ly = row[6] * dx + row[7] * dy, -row[7] * dx + row[6] * dy
            if kind == BOX:
                inside = (np.abs(lx) <= row[3]) & (np.abs(ly) <= row[4])
            else:
                inside = (lx / row[3]) ** 2 + (ly / row[4]) ** 2 <= 1.0
        window = top[rows, cols]
        window[inside] = value
        # Thin things (poles, posts) cover less than a cell: mark the cell under the centre.
        if not inside.any():
            iy = int((row[1] - self.raster.y0) / self.raster.res)
            ix = int((row[0] - self.raster.x0) / self.raster.res)
            if 0 <= iy < top.shape[0] and 0 <= ix < top.shape[1]:
                top[iy, ix] = value


def build_grid(kind: np.ndarray, param: np.ndarray, extent: tuple[float, float, float, float],
               cell: float = GRID_CELL, margin: float = QUERY_MARGIN) -> Grid:
    """List every primitive in each grid cell its 2D bounding box (grown by ``margin``) touches."""
    x0, x1, y0, y1 = extent
    nx, ny = math.ceil((x1 - x0) / cell), math.ceil((y1 - y0) / cell)
    c, s = np.abs(param[:, 6]), np.abs(param[:, 7])
    ex = np.where(kind == CYLINDER, param[:, 3], c * param[:, 3] + s * param[:, 4]) + margin
    ey = np.where(kind == CYLINDER, param[:, 3], s * param[:, 3] + c * param[:, 4]) + margin
    ix0 = np.floor((param[:, 0] - ex - x0) / cell).astype(np.int64)
    ix1 = np.floor((param[:, 0] + ex - x0) / cell).astype(np.int64)
    iy0 = np.floor((param[:, 1] - ey - y0) / cell).astype(np.int64)
    iy1 = np.floor((param[:, 1] + ey - y0) / cell).astype(np.int64)
    inside = (ix1 >= 0) & (ix0 < nx) & (iy1 >= 0) & (iy0 < ny)
    ix0, ix1 = np.clip(ix0, 0, nx - 1), np.clip(ix1, 0, nx - 1)
    iy0, iy1 = np.clip(iy0, 0, ny - 1), np.clip(iy1, 0, ny - 1)
    wx, wy = ix1 - ix0 + 1, iy1 - iy0 + 1
    count = np.where(inside, wx * wy, 0)
    prim = np.repeat(np.arange(len(kind)), count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    cells = (iy0[prim] + offset // wx[prim]) * nx + ix0[prim] + offset % wx[prim]
    order = np.argsort(cells, kind="stable")
    start = np.zeros(nx * ny + 1, np.int64)
    np.cumsum(np.bincount(cells, minlength=nx * ny), out=start[1:])
    return Grid(x0, y0, cell, nx, ny, start, prim[order].astype(np.int32))


def build_scene(seed: int) -> Scene:
    """The street scene of ``seed`` (deterministic)."""
    maker = _SceneMaker(seed)
    maker.layout()
    maker.route()
    maker.streets()
    maker.blocks()
    return maker.finish(seed)
