"""Street layout of the synthetic scene: the street grid, the loop route, the ground raster.

Scene frame: metres, z up, the ground plane at z = 0, streets along the x and y axes (the
world/map frame of the written drive is this frame turned and shifted, see ``drive``).

Cross-section of a street, from its centre line outwards: optional flat median (other-ground),
one or two lanes per direction (road, with painted markings), an optional parking lane
(parking), a 0.15 m raised sidewalk with a curb (box primitives, sidewalk), then the block.
Ground classes live in a 0.2 m raster (road, parking, sidewalk, other-ground, terrain).
``StreetLayout`` lays out streets, blocks and the route; what stands on the block sides comes
from ``furnish``; ``scene`` puts the two together.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from convbki_core.io.labels import load_label_map
from convbki_core.synth.primitives import OTHER_GROUND, ROAD, SIDEWALK, TERRAIN, SceneBuilder
from convbki_core.synth.route import Route

RASTER_RESOLUTION = 0.2  # m per ground-raster cell
CURB_HEIGHT = 0.15  # m, sidewalk top above the road
EXTENT_MARGIN = 115.0  # m of scene around the route (the LiDAR sees 90 m at most)


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


class _Rng:
    """numpy Generator whose ``uniform(lo, hi)`` gives ``lo`` when a small block or lot makes
    the interval empty (numpy raises), so no layout is ever impossible."""

    def __init__(self, generator: np.random.Generator):
        self._generator = generator

    def __getattr__(self, name: str):
        return getattr(self._generator, name)

    def uniform(self, low=0.0, high=1.0, size=None):
        return self._generator.uniform(low, np.maximum(low, high), size)


@dataclass
class Side:
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


class StreetLayout:
    """Lays out the streets, the route and the blocks; the block sides are furnished by the
    ``furnish`` mix-in (``_side``) of the scene maker that derives from this class."""

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
                    (Side(ix0, iy0, 1, 0, ix1 - ix0, s.sidewalk[1], s.parking[1], s, s.trees[1], s.lawn[1]), 0.0),
                    (Side(ix1, iy0, 0, 1, iy1 - iy0, e.sidewalk[0], e.parking[0], e, e.trees[0], e.lawn[0]), depth),
                    (Side(ix1, iy1, -1, 0, ix1 - ix0, n.sidewalk[0], n.parking[0], n, n.trees[0], n.lawn[0]), 0.0),
                    (Side(ix0, iy1, 0, -1, iy1 - iy0, w.sidewalk[1], w.parking[1], w, w.trees[1], w.lawn[1]), depth),
                ]
                for side, trim in sides:
                    if self._near_extent(side):
                        self._side(side, trim, depth)

    def _near_extent(self, side: Side) -> bool:
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
