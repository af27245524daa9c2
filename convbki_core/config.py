"""``MapperConfig``: every setting of a ``ConvBKIMapper``, grouped, with one set of defaults.

The defaults are the product's (what the node and ``evaluate`` map with): the paper's
SemanticKITTI window and its compound kernel, free space with clamping, and the movers'
rules for the label map's movable classes. ``MapperConfig.paper()`` is the paper's own
ConvBKI (no free space). The node's parameters, the programs' flags and the mapper all read
these defaults from here; ``from_params_file`` reads the node's YAML.

Groups:

* ``window``: the grid and the local window (bounds around the sensor, resolution and
  filter size, which default to the kernel's, and the Dirichlet prior);
* ``kernel_file``: the kernel (``""``: the shipped compound kernel);
* ``free_space``: rays, clamping and the movers' rules;
* ``compute``: torch device and update path;
* ``store``: whether the map remembers its changes for outputs that send only changes, and the
  map's memory budget;
* ``scan_log``: the log of integrated scans that a SLAM's correction moves, and its bounds;
* ``classes``: the label map whose ignored and movable classes apply, or explicit lists.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import yaml

# The paper's SemanticKITTI set-up: the local window around the sensor (m) and the kernel.
PAPER_BOUNDS = ((-40.0, -40.0, -2.6), (40.0, 40.0, 2.6))
PAPER_KERNEL = "semantic_kitti_compound"
UPDATE_PATHS = ("auto", "fast", "dense", "torch")


@dataclass(frozen=True)
class WindowConfig:
    """The grid: the window around the sensor (m), voxel edge (m) and filter edge (voxels),
    ``None`` meaning the kernel file's (a kernel is trained for its grid), and the prior."""

    local_bounds: tuple[tuple[float, float, float], tuple[float, float, float]] = PAPER_BOUNDS
    resolution: float | None = None
    filter_size: int | None = None
    prior: float = 1e-3


@dataclass(frozen=True)
class FreeSpaceConfig:
    """Free space (class 0 holds the rays' evidence), clamping (0: off) and the movers' rules."""

    enabled: bool = True
    max_concentration: float = 300.0
    forget_movers: bool = True
    # A return contradicts a movable voxel (the movers' first rule) only where this scan has no
    # return of a movable class within this many metres (horizontally): where the object is in
    # view, a return of another class on it is the input's label noise, not a change (0: no
    # such condition, every contradicting return resets).
    contradiction_radius: float = 2.0


@dataclass(frozen=True)
class ScanLogConfig:
    """The scan log (``scan_log``): every integrated scan kept bit for bit with its pose, so a
    SLAM's correction can move it (``correction``). In memory only, the oldest fall out past
    ``max_scans`` scans or ``max_megabytes`` (0: no such bound), frozen into the map. With a
    folder (``use_log_folder``: the node's) memory keeps ``max_megabytes`` of the newest, the
    folder the rest, and the oldest fall out past ``max_scans`` or ``disk_gigabytes`` there."""

    enabled: bool = True
    max_scans: int = 0
    max_megabytes: float = 256.0
    disk_gigabytes: float = 16.0


@dataclass(frozen=True)
class ComputeConfig:
    """``device``: auto (CUDA when present), cpu, cuda[:N]. ``update_path``: auto (fast on the
    CPU, torch on CUDA), fast, dense (the paper's conv3d, the reference) or torch."""

    device: str = "auto"
    update_path: str = "auto"


@dataclass(frozen=True)
class StoreConfig:
    """``track_changes``: remember what changed for ``take_changes``. ``max_megabytes``: the
    map's memory budget in MB (10^6 bytes) of the global store (0: no bound): at it the map is
    full and stops growing, mapping goes on in the window (``memory.budget``, ``ConvBKIMapper``)."""

    track_changes: bool = False
    max_megabytes: float = 4000.0  # the node's default too: a robot's map stops growing before its memory ends


@dataclass(frozen=True)
class ClassesConfig:
    """The classes the map ignores (never mapped), those that move and those of the ground
    (which free space leaves), from ``label_map`` unless given as lists."""

    label_map: str = "semantic_kitti"
    ignore_classes: tuple[int, ...] | None = None
    movable_classes: tuple[int, ...] | None = None
    ground_classes: tuple[int, ...] | None = None


# The settings that decide what a scan does to the map (a map file keeps them with its scan log).
MAPPING_SETTINGS = ("local_bounds", "resolution", "filter_size", "prior", "free_space", "max_concentration",
                    "forget_movers", "contradiction_radius", "label_map", "ignore_classes", "movable_classes",
                    "ground_classes", "frame_id")
# Each flat name (the node's parameter names where it has one) and the group that holds it.
_FLAT = {
    "local_bounds": ("window", "local_bounds"), "resolution": ("window", "resolution"),
    "filter_size": ("window", "filter_size"), "prior": ("window", "prior"),
    "free_space": ("free_space", "enabled"), "max_concentration": ("free_space", "max_concentration"),
    "forget_movers": ("free_space", "forget_movers"),
    "contradiction_radius": ("free_space", "contradiction_radius"),
    "device": ("compute", "device"), "update_path": ("compute", "update_path"),
    "track_changes": ("store", "track_changes"), "max_map_megabytes": ("store", "max_megabytes"),
    "scan_log": ("scan_log", "enabled"), "scan_log_scans": ("scan_log", "max_scans"),
    "scan_log_megabytes": ("scan_log", "max_megabytes"),
    "scan_log_disk_gigabytes": ("scan_log", "disk_gigabytes"),
    "label_map": ("classes", "label_map"), "ignore_classes": ("classes", "ignore_classes"),
    "movable_classes": ("classes", "movable_classes"), "ground_classes": ("classes", "ground_classes"),
    "kernel_file": (None, "kernel_file"), "frame_id": (None, "frame_id"),
}


@dataclass(frozen=True)
class MapperConfig:
    window: WindowConfig = field(default_factory=WindowConfig)
    kernel_file: str = ""
    free_space: FreeSpaceConfig = field(default_factory=FreeSpaceConfig)
    compute: ComputeConfig = field(default_factory=ComputeConfig)
    store: StoreConfig = field(default_factory=StoreConfig)
    scan_log: ScanLogConfig = field(default_factory=ScanLogConfig)
    classes: ClassesConfig = field(default_factory=ClassesConfig)
    frame_id: str = "map"

    # -- making one ------------------------------------------------------------------------
    def replace(self, **flat) -> MapperConfig:
        """This configuration with settings changed by their flat names (``free_space=False``,
        ``local_bounds=...``, ``device="cpu"``, ...); an unknown name raises ``TypeError``."""
        groups: dict[str, dict] = {}
        top: dict = {}
        for name, value in flat.items():
            if name not in _FLAT:
                raise TypeError(f"MapperConfig has no setting {name!r} (known: {', '.join(sorted(_FLAT))})")
            group, attribute = _FLAT[name]
            if name == "local_bounds":
                value = tuple(tuple(float(v) for v in corner) for corner in value)
            elif name == "max_map_megabytes":
                value = float(value)
            elif name in ("ignore_classes", "movable_classes", "ground_classes") and value is not None:
                value = tuple(int(c) for c in value)
            if group is None:
                top[attribute] = value
            else:
                groups.setdefault(group, {})[attribute] = value
        changed = {group: dataclasses.replace(getattr(self, group), **values) for group, values in groups.items()}
        return dataclasses.replace(self, **changed, **top)

    @classmethod
    def paper(cls, **flat) -> MapperConfig:
        """The paper's ConvBKI: no free space, class 0 alone ignored, no movable or ground
        classes; ``flat`` changes settings as ``replace`` does."""
        plain = cls().replace(free_space=False, ignore_classes=(0,), movable_classes=(), ground_classes=())
        return plain.replace(**flat)

    @classmethod
    def from_params_file(cls, path: str | Path, node_name: str = "convbki_mapper") -> MapperConfig:
        """The mapping settings of a node parameters file (``config/mapper.yaml``'s layout:
        ``NODE: ros__parameters: ...``, or ``/**``); the node's other parameters are skipped."""
        data = yaml.safe_load(Path(path).read_text()) or {}
        section = data.get(node_name) or data.get("/**") or {}
        parameters = section.get("ros__parameters") or {}
        return cls.from_parameters(parameters)

    @classmethod
    def from_parameters(cls, parameters: dict) -> MapperConfig:
        """From the node's parameter names and values (unknown names are not mapping settings)."""
        flat = {name: parameters[name] for name in _FLAT if name in parameters}
        if "map_frame" in parameters:
            flat["frame_id"] = parameters["map_frame"] or "map"
        if "local_bounds" in flat:
            bounds = [float(v) for v in flat["local_bounds"]]
            flat["local_bounds"] = (bounds[:3], bounds[3:])
        return cls().replace(**flat)

    # -- derived settings, resolved in one place -------------------------------------------
    def ignore_classes(self) -> tuple[int, ...]:
        if self.classes.ignore_classes is not None:
            return self.classes.ignore_classes
        from convbki_core.io.labels import load_label_map

        return load_label_map(self.classes.label_map).ignore_classes

    def movable_classes(self) -> tuple[int, ...]:
        """The classes of things that move (car, person, ...): a moving point's object is
        grown through them (``present_movers.whole_movers``)."""
        if self.classes.movable_classes is not None:
            return self.classes.movable_classes
        from convbki_core.io.labels import load_label_map

        return load_label_map(self.classes.label_map).movable_classes

    def ground_classes(self) -> tuple[int, ...]:
        """The classes of the ground (road, sidewalk, ...): with free space, rays leave the
        voxels whose most likely occupied class is one of them (``free_space``)."""
        if self.classes.ground_classes is not None:
            return self.classes.ground_classes
        from convbki_core.io.labels import load_label_map

        return load_label_map(self.classes.label_map).ground_classes

    def forgetting_classes(self) -> tuple[int, ...]:
        """The classes the movers' rules apply to: none without free space or without the rules."""
        if not (self.free_space.enabled and self.free_space.forget_movers):
            return ()
        return self.movable_classes()

    def kernel_path(self) -> Path:
        from convbki_core.paths import kernel_path

        return Path(self.kernel_file) if self.kernel_file else kernel_path(PAPER_KERNEL)

    def mapping_record(self, resolution: float, filter_size: int) -> dict:
        """The settings that decide what a scan does to the map, resolved and JSON-ready (a map
        file keeps them, so that its logged scans can be mapped again the same way); ``resolution``
        and ``filter_size``: the mapper's, which the kernel decides unless set here."""
        record = {name: value for name, value in self.flat().items() if name in MAPPING_SETTINGS}
        record.update(resolution=float(resolution), filter_size=int(filter_size),
                      local_bounds=[list(corner) for corner in self.window.local_bounds],
                      ignore_classes=list(self.ignore_classes()), movable_classes=list(self.movable_classes()),
                      ground_classes=list(self.ground_classes()))
        return record

    @classmethod
    def from_mapping_record(cls, record: dict) -> MapperConfig:
        """The configuration of a ``mapping_record`` (a map file's), the rest at the defaults;
        raises ValueError naming what does not fit."""
        if not isinstance(record, dict):
            raise ValueError("the mapping settings are not a mapping")
        unknown = set(record) - set(MAPPING_SETTINGS)
        if unknown:
            raise ValueError(f"unknown mapping settings {sorted(unknown)}")
        try:
            return cls().replace(**record)
        except (TypeError, ValueError) as error:
            raise ValueError(f"mapping settings that do not fit: {error}") from None

    def flat(self) -> dict:
        """Every setting by its flat name."""
        values = {}
        for name, (group, attribute) in _FLAT.items():
            values[name] = getattr(self if group is None else getattr(self, group), attribute)
        return values


DEFAULTS = MapperConfig()
