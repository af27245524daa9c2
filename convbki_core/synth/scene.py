"""Procedural street scene: a grid of streets and blocks around a loop route.

Scene frame: metres, z up, the ground plane at z = 0, streets along the x and y axes (the
world/map frame of the written drive is this frame turned and shifted, see ``drive``).

``streets`` lays out the street grid, the loop route, the ground raster and the raised
sidewalks; ``furnish`` fills the block sides (buildings, parks, parking lots, plazas, street
furniture, parked and stopped vehicles, people); this module drops what stands in the ego
vehicle's way (and in the way of the movers, when a drive has them), paints the footprints
the noise model needs and indexes every primitive (see ``primitives``) in a 2D grid of
cells for ray casting. Everything is drawn from ``numpy.random.default_rng(seed)``: the same
seed gives the same scene, a different seed a different layout.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from convbki_core.synth.furnish import Furnishing
from convbki_core.synth.movers import Mover
from convbki_core.synth.primitives import (
    BICYCLE,
    BICYCLIST,
    BOX,
    CAR,
    CORRIDOR_MAX_BOTTOM,
    CYLINDER,
    FOOTPRINT_MAX_BOTTOM,
    MOTORCYCLE,
    MOTORCYCLIST,
    OTHER_VEHICLE,
    PERSON,
    TRUCK,
    footprint_extent,
    obb_distance,
)
from convbki_core.synth.route import Route
from convbki_core.synth.streets import RASTER_RESOLUTION, RasterSpec, StreetLayout
from convbki_core.synth.traffic import swept_height

GRID_CELL = 4.0  # m per ray-casting grid cell
QUERY_MARGIN = 0.5  # m: primitives are also listed in cells this close, for neighbour queries
EGO_CLEARANCE = 1.3  # m from the route centre line kept free of objects (half car width + margin)
MOVER_CLEARANCE = 0.3  # m kept free around the space the movers sweep
# Parked cars, people, bicycles: a map's movable-class voxels this close to where a mover went
# would read as its trail at the usual 0.2 m voxels (a swept voxel, its neighbour, the
# kernel's spread), so these keep further away.
MOVABLE_CLEARANCE = 0.8  # m
MOVABLE_RAW = frozenset((CAR, BICYCLE, MOTORCYCLE, TRUCK, OTHER_VEHICLE, PERSON, BICYCLIST, MOTORCYCLIST))


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
    movers: list[Mover] = field(default_factory=list)  # instance and part ids after the static ones


class _SceneMaker(StreetLayout, Furnishing):
    """The whole scene: street layout, furnishing, then ``finish``."""

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

    def clear_movers_way(self, keep: np.ndarray, movers: list[Mover]) -> None:
        """Drop (in ``keep``) objects reaching into the space the movers sweep, grown by
        MOVER_CLEARANCE (MOVABLE_CLEARANCE for vehicles, people and bicycles), lower than the
        top of the mover that swept it."""
        swept = swept_height(movers, self.raster)
        # Summed-area table of the swept cells: a cheap screen before the exact footprint test.
        table = np.zeros((swept.shape[0] + 1, swept.shape[1] + 1), np.int64)
        table[1:, 1:] = (swept > 0).cumsum(0).cumsum(1)
        for index, ob in enumerate(self.builder.objects):
            if ob.stuff or not keep[index]:
                continue
            for kind, row, raw in zip(ob.kinds, ob.params, ob.raws):
                grow = MOVABLE_CLEARANCE if raw in MOVABLE_RAW else MOVER_CLEARANCE
                cells = self._footprint_cells(kind, np.asarray(row), grow)
                if cells is None:
                    continue
                rows, cols, inside = cells
                hit = table[rows.stop, cols.stop] - table[rows.start, cols.stop] - table[rows.stop, cols.start] + table[
                    rows.start, cols.start]
                if hit and np.any(swept[rows, cols][inside] > row[2] - row[5]):
                    keep[index] = False
                    break

    def finish(self, seed: int, movers: list[Mover] | None = None) -> Scene:
        keep = self.keep_mask()
        if movers:
            self.clear_movers_way(keep, movers)
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
        movers = list(movers or [])
        instance, part = int(arr["instance"].max(initial=0)), self.builder.next_part()
        for mover in movers:
            instance += 1
            mover.instance, mover.part0 = instance, part
            part += int(mover.template.part.max()) + 1
        if instance >= 2 ** 16:
            raise ValueError(f"{instance} objects and movers do not fit the 16-bit instance field")
        return Scene(seed, arr["kind"], arr["param"], arr["raw"], learning, arr["part"], arr["instance"],
                     self.raster, self.ground, self.marking, top, nb_class, nb_dist, grid, self.route_,
                     self.start_s, info, movers)

    def _footprint_cells(self, kind: int, row: np.ndarray, grow: float = 0.0
                         ) -> tuple[slice, slice, np.ndarray] | None:
        """Raster window around a primitive's footprint grown by ``grow`` (m), and the cells of
        the window inside it; None when the footprint is off the raster."""
        ex, ey = footprint_extent(kind, row)
        ex, ey = ex + grow, ey + grow
        rows, cols = self.raster.window(row[0] - ex, row[0] + ex, row[1] - ey, row[1] + ey)
        if rows.stop <= rows.start or cols.stop <= cols.start:
            return None
        xs, ys = self.raster.centres(rows, cols)
        dx, dy = xs - row[0], ys - row[1]
        if kind == CYLINDER:
            inside = dx ** 2 + dy ** 2 <= (row[3] + grow) ** 2
        else:
            lx, ly = row[6] * dx + row[7] * dy, -row[7] * dx + row[6] * dy
            if kind == BOX:
                inside = (np.abs(lx) <= row[3] + grow) & (np.abs(ly) <= row[4] + grow)
            else:
                inside = (lx / (row[3] + grow)) ** 2 + (ly / (row[4] + grow)) ** 2 <= 1.0
        return rows, cols, inside

    def _paint_footprint(self, top: np.ndarray, kind: int, row: np.ndarray, value: int) -> None:
        cells = self._footprint_cells(kind, row)
        if cells is None:
            return
        rows, cols, inside = cells
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


def build_scene(seed: int, traffic: Callable[[StreetLayout], list[Mover]] | None = None) -> Scene:
    """The street scene of ``seed`` (deterministic).

    ``traffic`` plans the movers once the streets and the route are laid out (it gets the
    layout; see ``traffic.plan``); the static objects in their way are left out of the scene.
    """
    maker = _SceneMaker(seed)
    maker.layout()
    maker.route()
    maker.streets()
    maker.blocks()
    return maker.finish(seed, traffic(maker) if traffic is not None else None)
