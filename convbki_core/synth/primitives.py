"""Scene primitives and the object builder.

Every solid in the synthetic world is one of three ray-castable primitives, stored as one row
of a float64 parameter table (scene frame: metres, z up, the ground plane at z = 0):

    [cx, cy, cz, hx, hy, hz, cos(yaw), sin(yaw), mean_free_path]

- BOX: centre, half extents along the box's own x, y, z; yaw turns it about z.
- CYLINDER: vertical; centre, radius in hx (= hy), half height hz.
- ELLIPSOID: centre, radii hx, hy, hz along its own axes; yaw turns it about z.

``mean_free_path`` > 0 makes a primitive porous (tree crowns, hedges, mesh fences): a ray
entering it hits at an exponentially distributed depth (mean = the path, metres) or passes
through when that depth exceeds its chord, as a LiDAR beam does in foliage.

An object (a car, a tree, a building) is a group of primitives with one instance id; its
primitives are grouped further into *parts* (car body, cabin, tree crown), the unit the
segmentation-noise model confuses as a whole.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

BOX, CYLINDER, ELLIPSOID = 0, 1, 2
PARAMS = 9

# Raw SemanticKITTI ids used by the generator (shared/reference/semantic_kitti.md).
OUTLIER = 1
CAR, BICYCLE, MOTORCYCLE, TRUCK, OTHER_VEHICLE = 10, 11, 15, 18, 20
PERSON, BICYCLIST, MOTORCYCLIST = 30, 31, 32
ROAD, PARKING, SIDEWALK, OTHER_GROUND = 40, 44, 48, 49
BUILDING, FENCE, VEGETATION, TRUNK, TERRAIN, POLE, TRAFFIC_SIGN = 50, 51, 70, 71, 72, 80, 81

# Primitives whose bottom is below this height (m above their base) leave a footprint on the
# ground: the boundary-blur part of the noise model uses footprints (road next to a car's
# wheels, grass at a trunk's foot); the ego-corridor check also only looks at these.
FOOTPRINT_MAX_BOTTOM = 0.6
CORRIDOR_MAX_BOTTOM = 2.2  # anything higher (tree crowns, lamp arms) passes over the ego vehicle


@dataclass
class SceneObject:
    """One object under construction: its primitives (scene frame) and metadata."""

    instance: int
    stuff: bool = False  # sidewalk slabs: no footprint painting, never removed
    kinds: list[int] = field(default_factory=list)
    params: list[list[float]] = field(default_factory=list)
    raws: list[int] = field(default_factory=list)
    parts: list[int] = field(default_factory=list)
    bottoms: list[float] = field(default_factory=list)  # height of each primitive's bottom over its base, m
    _builder: SceneBuilder | None = None
    _part: int = -1

    def new_part(self) -> SceneObject:
        """Start a new part: the primitives added next are confused together by the noise model."""
        assert self._builder is not None
        self._part = self._builder.next_part()
        return self

    def _add(self, kind: int, row: list[float], raw: int, base: float) -> None:
        if self._part < 0:
            self.new_part()
        self.kinds.append(kind)
        self.params.append(row)
        self.raws.append(raw)
        self.parts.append(self._part)
        self.bottoms.append(row[2] - row[5] - base)

    def box(self, cx: float, cy: float, z0: float, z1: float, length: float, width: float, yaw: float,
            raw: int, porous: float = 0.0, base: float = 0.0) -> None:
        """Box of ``length`` x ``width`` (along its yaw / across), from z0 to z1 (m)."""
        self._add(BOX, [cx, cy, 0.5 * (z0 + z1), 0.5 * length, 0.5 * width, 0.5 * (z1 - z0),
                        math.cos(yaw), math.sin(yaw), porous], raw, base)

    def cylinder(self, cx: float, cy: float, z0: float, z1: float, radius: float, raw: int,
                 base: float = 0.0) -> None:
        """Vertical cylinder from z0 to z1 (m)."""
        self._add(CYLINDER, [cx, cy, 0.5 * (z0 + z1), radius, radius, 0.5 * (z1 - z0), 1.0, 0.0, 0.0], raw, base)

    def ellipsoid(self, cx: float, cy: float, cz: float, rx: float, ry: float, rz: float, yaw: float,
                  raw: int, porous: float = 0.0, base: float = 0.0) -> None:
        """Ellipsoid with radii rx (along yaw), ry (across), rz (up), m."""
        self._add(ELLIPSOID, [cx, cy, cz, rx, ry, rz, math.cos(yaw), math.sin(yaw), porous], raw, base)


class SceneBuilder:
    """Collects objects; ``arrays`` packs the kept ones into the primitive table."""

    def __init__(self) -> None:
        self.objects: list[SceneObject] = []
        self._parts = 0

    def next_part(self) -> int:
        self._parts += 1
        return self._parts - 1

    def new(self, stuff: bool = False) -> SceneObject:
        """A new object with the next instance id (1, 2, ...; 0 is the ground)."""
        obj = SceneObject(instance=len(self.objects) + 1, stuff=stuff, _builder=self)
        self.objects.append(obj)
        return obj

    def arrays(self, keep: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Primitive table of the kept objects (all when ``keep`` is None).

        Instance ids are renumbered 1..K over the kept objects so they stay dense and below 2**16.
        """
        kinds, params, raws, parts, instances, bottoms = [], [], [], [], [], []
        instance = 0
        for index, obj in enumerate(self.objects):
            if (keep is not None and not keep[index]) or not obj.kinds:
                continue
            instance += 1
            kinds += obj.kinds
            params += obj.params
            raws += obj.raws
            parts += obj.parts
            bottoms += obj.bottoms
            instances += [0 if obj.stuff else instance] * len(obj.kinds)
        if instance >= 2 ** 16:
            raise ValueError(f"{instance} objects do not fit the 16-bit instance field")
        return {
            "kind": np.asarray(kinds, np.int8),
            "param": np.asarray(params, np.float64).reshape(-1, PARAMS),
            "raw": np.asarray(raws, np.uint16),
            "part": np.asarray(parts, np.int32),
            "instance": np.asarray(instances, np.uint32),
            "bottom": np.asarray(bottoms, np.float64),
        }


def footprint_extent(kind: int, row: np.ndarray) -> tuple[float, float]:
    """Half extents (along x, along y of the scene frame) of a primitive's 2D bounding box."""
    hx, hy, c, s = row[3], row[4], abs(row[6]), abs(row[7])
    if kind == CYLINDER:
        return hx, hx
    return c * hx + s * hy, s * hx + c * hy


def obb_distance(points: np.ndarray, row: np.ndarray, kind: int) -> np.ndarray:
    """2D distance (m) from ``points`` (M, 2) to a primitive's footprint (0 inside)."""
    dx, dy = points[:, 0] - row[0], points[:, 1] - row[1]
    if kind == CYLINDER:
        return np.maximum(np.hypot(dx, dy) - row[3], 0.0)
    c, s = row[6], row[7]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    return np.hypot(np.maximum(np.abs(lx) - row[3], 0.0), np.maximum(np.abs(ly) - row[4], 0.0))
