"""The mapper node's parameters: one table, declared with descriptors, checked at start.

Every parameter has a meaning with its unit, a range where it is a number, and says whether
it may change at run time. The run-time ones take effect at once (timers are re-created);
the others are read-only, since changing them would need a new map. ``resolution``,
``filter_size`` and ``num_classes`` default to the kernel file's values: a kernel is trained
for its grid, so a parameter only overrides it when it is set explicitly (and a differing
value is said once at start).

A bad start-up value becomes one ``StartupError`` line; the node's ``main`` exits with
code 2 on it.
"""

from __future__ import annotations

from dataclasses import dataclass

from convbki_core.config import DEFAULTS, UPDATE_PATHS
from convbki_core.io.kernel_file import KernelConfig

NODE_NAME = "convbki_mapper"
MIN_AUTOSAVE_PERIOD = 1.0  # seconds: a shorter period (other than 0, never) is refused
KERNEL_DECIDES = ("num_classes", "resolution", "filter_size")  # defaults come from the kernel file
NOT_SET = None  # default of an optional list parameter (declared typed, without a value)
# Parameters every rclpy node declares or reads itself: never "unknown".
ROS_OWN = ("use_sim_time", "start_type_description_service")


class StartupError(ValueError):
    """A bad parameter or input at start: one line, exit code 2."""


@dataclass(frozen=True)
class Spec:
    """One parameter: default, meaning with unit, range, and whether it may change at run time."""

    name: str
    default: object
    meaning: str
    low: float | None = None
    high: float | None = None
    step: int = 0  # integer ranges: 2 with an odd low = odd values only
    choices: tuple[str, ...] = ()
    run_time: bool = False  # may change while the node runs

    def describe(self) -> str:
        text = self.meaning
        if self.low is not None:
            text += f" [{self.low:g} .. {self.high:g}]"
        if self.choices:
            text += f" (one of: {', '.join(self.choices)})"
        return text + ("" if self.run_time else " (read-only at run time)")


PARAMETERS: tuple[Spec, ...] = (
    Spec("kernel_file", "", "kernel file (YAML); \"\" = the shipped compound kernel "
         "(share/convbki_ros/config/kernels/semantic_kitti_compound.yaml)"),
    Spec("num_classes", 20, "number of semantic classes C, class 0 = unlabeled; count; default: the kernel's",
         2, 1024),
    Spec("resolution", 0.2, "voxel edge length; metres; default: the kernel file's", 0.01, 10.0),
    Spec("filter_size", 5, "convolution filter edge f (odd); voxels; default: the kernel file's", 1, 31, step=2),
    Spec("local_bounds", [*DEFAULTS.window.local_bounds[0], *DEFAULTS.window.local_bounds[1]],
         "local map window around the sensor, [min_x, min_y, min_z, max_x, max_y, max_z]; metres"),
    Spec("prior", DEFAULTS.window.prior,
         "Dirichlet prior concentration of every class in every voxel; unitless", 1e-9, 1e6),
    Spec("label_space", "raw",
         "meaning of the input `label` field: raw (SemanticKITTI raw ids) or learning (0..num_classes-1)",
         choices=("raw", "learning")),
    Spec("map_frame", "", "frame the map is built and published in; \"\" = the odometry's frame (header.frame_id); "
         "another frame: each cloud is taken into it by TF at its stamp (map_frame -> odometry frame, e.g. a "
         "SLAM's map -> odom), times the odometry; with pose_source tf it must be set"),
    Spec("pose_source", "odometry", "where a cloud's pose comes from: odometry (the odom topic, interpolated at "
         "the cloud's stamp, times the sensor's mount) or tf (TF alone: map_frame -> the cloud's frame at its "
         "stamp, for robots that publish no Odometry)", choices=("odometry", "tf")),
    Spec("transform_timeout", 1.0, "how long a cloud waits for the TF it needs (map_frame -> odometry frame, the "
         "mount, or with pose_source tf its whole pose) before it is dropped with a warning, in the node's clock; "
         "seconds; 0.0 = as long as the queue has room for it", 0.0, 3600.0, run_time=True),
    Spec("base_to_sensor", NOT_SET,
         "mount of the cloud's frame on the odometry's child frame, [x, y, z, qx, qy, qz, qw] (metres, unit "
         "quaternion): what a tf2 static transform child_frame_id -> cloud frame holds; used when a cloud's "
         "frame is not the odometry's child frame; unset = from TF (/tf_static or /tf) at the cloud's stamp"),
    Spec("max_variance", 0.0,
         "leave out voxels whose variance of the expected class exceeds this; unitless; 0.0 = no filter",
         0.0, 0.25, run_time=True),
    Spec("publish_period", 1.0, "period of semantic_map/updates (what changed) and semantic_map/view (the map "
         "around the sensor); seconds", 0.05, 3600.0, run_time=True),
    Spec("map_period", 5.0, "period of semantic_map and semantic_map/variance (the whole map, for late joiners; "
         "sent only when it changed and someone listens); seconds", 0.05, 3600.0, run_time=True),
    Spec("updates_depth", 10, "history depth of semantic_map/updates (reliable, volatile); messages", 1, 1000),
    Spec("view_radius", 30.0, "semantic_map/view holds the voxels within this horizontal distance of the sensor; "
         "metres", 0.5, 10000.0, run_time=True),
    Spec("view_max_points", 600_000, "at most this many voxels in semantic_map/view, the nearest first; count",
         1, 100_000_000),
    Spec("free_space", DEFAULTS.free_space.enabled,
         "the rays between the sensor and its returns add evidence that the voxels they "
         "cross are empty, so moving objects leave no trail (the ground's surface stays); "
         "false: the paper's ConvBKI; bool"),
    Spec("max_concentration", DEFAULTS.free_space.max_concentration,
         "with free_space: a voxel that rays first find empty while its concentrations "
         "sum to more than this is scaled down to it, so a bounded number of rays can empty what a mover left "
         "(OctoMap's clamping); 0 = never; unitless (points of evidence)", 0.0, 1e12),
    Spec("forget_movers", DEFAULTS.free_space.forget_movers,
         "with free_space: the voxels of movable classes (car, person, ...) forget their "
         "evidence where a return shows another class, and empty where they float over space the rays found "
         "empty (the top of a bus that has gone); false: free space alone; bool"),
    Spec("moving_labels", True, "with label_space raw: points whose label is a moving id (SemanticKITTI's "
         "252-259, from a multi-scan segmentation network) are evidence for their own scan only and stay out "
         "of the map, so what moves leaves no trail; false: they are mapped as their static classes; bool"),
    Spec("device", DEFAULTS.compute.device, "torch device: auto (CUDA when present, else CPU), cpu, cuda[:N]"),
    Spec("update_path", DEFAULTS.compute.update_path,
         "how the update runs: auto (fast on the CPU, torch on CUDA), fast (compiled "
         "sparse scatter, CPU), torch (the window resident on the torch device, any device) or dense "
         "(depthwise conv3d, the paper's formulation, the reference)", choices=UPDATE_PATHS),
    Spec("input_qos", "reliable",
         "QoS of cloud_in and odom: reliable (bag replay) or sensor_data (live, best effort)",
         choices=("reliable", "sensor_data")),
    Spec("map_file", "", "map file loaded at start when present, written by ~/save_map (the file it replaces is kept "
         "as <map_file>.prev) and read by ~/load_map; its folder is created at start, and one that cannot be "
         "written is refused; at run time only a file in map_folder (a relative name is taken there), never a "
         "file that is not a ConvBKI map file; \"\" = none; path", run_time=True),
    Spec("map_folder", "", "the folder every file the node writes lies in (map_file, its .prev and kept maps, "
         "ply_file, segment files); fixed at start: no service or parameter writes outside it, nor makes a "
         "folder; \"\" = map_file's folder, else ply_file's, else no file is written on request; path"),
    Spec("max_kept_maps", 5, "~/save_map after the map lost evidence (a reset, a forgotten box, another file) keeps "
         "the map file it replaces as <map_file>.kept-<UTC time>; with this many kept already the save is refused "
         "rather than lose one; count", 1, 1000),
    Spec("autosave_period", 0.0, "save the map to map_file every this many seconds; 0.0 = never, else at least "
         f"{MIN_AUTOSAVE_PERIOD:g} s", 0.0, 1e6, run_time=True),
    Spec("save_on_shutdown", True, "save the map to map_file when the node stops (SIGINT/SIGTERM); bool",
         run_time=True),
    Spec("clear_box_min", NOT_SET, "lower corner [x, y, z] of the box ~/clear_box forgets (voxels whose centre lies "
         "inside), in the map frame; metres", run_time=True),
    Spec("clear_box_max", NOT_SET, "upper corner [x, y, z] of the box ~/clear_box forgets, in the map frame; metres",
         run_time=True),
    Spec("ply_file", "", "file written by ~/export_ply; \"\" = map_file with the suffix .ply, else convbki_map.ply in "
         "map_folder; at run time only a file in map_folder, never a file that is not this node's PLY; path",
         run_time=True),
    Spec("publish_local", True, "publish semantic_map/local (the window around the sensor) after updates; bool",
         run_time=True),
    Spec("local_period", 0.5, "shortest time between two semantic_map/local messages: after updates, the "
         "newest window is sent at most this often; seconds; 0.0 = after every update", 0.0, 3600.0,
         run_time=True),
    Spec("costmap_profile", "car", "traversability profile of semantic_map/costmap and ~/get_costmap: car or "
         "small_robot (share/convbki_ros/config/traversability), or a profile YAML file's path"),
    Spec("costmap_size", 0.0, "edge of the square semantic_map/costmap rolling with the sensor; metres; 0.0 = the "
         "local window's footprint (local_bounds' x extent), and at most that", 0.0, 1e5),
    Spec("costmap_max_cells", 25_000_000, "~/get_costmap refuses (one line) a whole-map grid of more cells than this; "
         "count", 1, 1_000_000_000),
    Spec("cloud_queue_size", 100, "clouds waiting to be integrated or for their odometry (10 s at 10 Hz); when "
         "full the oldest is dropped; count", 1, 10000),
    Spec("cloud_queue_megabytes", 1024.0, "bytes of cloud data the queue may hold; when full the oldest cloud is "
         "dropped; megabytes (1e6 bytes); 0.0 = no limit but cloud_queue_size", 0.0, 1e6),
    Spec("pose_wait_timeout", 0.0, "how long a cloud waits for odometry covering its stamp before it is dropped, "
         "in the node's clock (the data's time under use_sim_time); seconds; 0.0 = as long as the queue has "
         "room for it", 0.0, 3600.0, run_time=True),
    Spec("stats_period", 10.0, "period of the counters line in the log (scans in, integrated, dropped); "
         "seconds", 0.1, 3600.0, run_time=True),
    Spec("diagnostics_period", 1.0, "period of the /diagnostics report (counters, queue, timings, health); "
         "seconds", 0.05, 3600.0, run_time=True),
    Spec("max_points_per_cloud", 2_000_000,
         "clouds with more points (width * height) are dropped on arrival with a warning, before any decoding, "
         "so that a runaway source cannot exhaust memory; count; 0 = no limit", 0, 1_000_000_000),
    Spec("max_cloud_megabytes", 256.0,
         "clouds with more data than this are dropped on arrival with a warning, as are clouds whose data does not "
         "match their header (row_step * height bytes); megabytes (1e6 bytes)", 0.001, 1e5),
    Spec("max_map_megabytes", DEFAULTS.store.max_megabytes,
         "the most memory the map's voxels away from the window may take: at this bound the map stops growing "
         "(voxels of new ground that leave the window are forgotten, said on /diagnostics) while mapping goes on "
         "in the window; megabytes (1e6 bytes); 0.0 = no bound", 0.0, 1e7),
    Spec("max_pose_jump", 10.0,
         "two consecutive odometry poses further apart than this are a break: warned, and clouds stamped between "
         "them are dropped rather than placed half way; after a gap in the odometry (over 10 of its periods and "
         "1 s) the break is an outage, else a jump (see on_pose_jump); metres; 0.0 = no check", 0.0, 1e6,
         run_time=True),
    Spec("on_pose_jump", "keep",
         "what a pose jump within continuous odometry does to the map: keep it (the scans after the jump are "
         "added where the odometry now says), reset it (a new map starts at the new pose), or new_file (the map "
         "so far is saved to map_file, and a new map starts that is saved to the next <map_file "
         "stem>.segment-N file); an outage (odometry that stopped, then resumed far away) keeps the map",
         choices=("keep", "reset", "new_file"), run_time=True),
    Spec("stamp_backwards_tolerance", 1.0,
         "odometry stamped more than this before the newest odometry means time went backwards (a restarted "
         "bag): the odometry history and the waiting clouds are dropped; seconds", 0.0, 1e6, run_time=True),
    Spec("reset_on_stamp_backwards", False,
         "when time goes backwards, also clear the map; false keeps it (a replayed bag adds to it); bool",
         run_time=True),
    Spec("odometry_timeout", 5.0,
         "while clouds arrive but no usable odometry has for this long, warn (and report ERROR on /diagnostics) "
         "every this many seconds; seconds", 0.1, 3600.0, run_time=True),
    Spec("refuse_bad_map_file", False,
         "exit (code 2) when map_file exists but cannot be read (truncated, corrupted, not a map file), instead of "
         "starting with an empty map; bool"),
    Spec("scan_log", DEFAULTS.scan_log.enabled,
         "keep every integrated scan (its points, labels or probabilities, stamp and pose; about 9 bytes a "
         "point) so that a SLAM's Path on pose_corrections can move it, and save the log with map_file; false: "
         "corrections are refused; bool"),
    Spec("scan_log_scans", DEFAULTS.scan_log.max_scans,
         "the most scans the log keeps: older ones fall out, frozen into the map where no correction can move "
         "them; count; 0 = no bound but the bytes", 0, 10_000_000),
    Spec("scan_log_megabytes", DEFAULTS.scan_log.max_megabytes,
         "the most memory the log (and the map as it was where its segments begin) takes: past it the oldest "
         "scans are only in scan_log_folder (read back by a correction), or, with scan_log_disk_gigabytes 0, "
         "fall out frozen (and the log is saved inside map_file); megabytes (1e6 bytes); 0.0 = no bound",
         0.0, 1e7),
    Spec("scan_log_disk_gigabytes", DEFAULTS.scan_log.disk_gigabytes,
         "the most the log takes in scan_log_folder (its scans, about 9.5 bytes a point, and the map where each "
         "segment begins): past it the oldest scans fall out, frozen into the map; a map_file saved names the "
         "folder's files, it never copies them; gigabytes (1e9 bytes); 0.0 = no folder, the log in memory only",
         0.0, 1e5),
    Spec("scan_log_folder", "",
         "where the scan log's files go (made at start, owner only): empty = beside map_file as "
         "<map_file>.scan_log, or without map_file a folder of this process under $XDG_CACHE_HOME (~/.cache) "
         "removed at shutdown; path"),
    Spec("max_path_poses", 100_000,
         "a Path on pose_corrections with more poses is refused before it is decoded; count", 1, 10_000_000),
    Spec("correction_tolerance", 0.05,
         "a Path on pose_corrections leaves a logged scan alone where it moves none of its points within the "
         "local window by this much or more (a fraction of a voxel); metres", 0.0, 1e3, run_time=True),
    Spec("correction_min_move", -1.0,
         "a Path on pose_corrections maps scans again only when it moves some logged scan's points within the "
         "local window by this much or more from where the map has them (or the correction under way puts them); "
         "a Path that moves less is counted and costs a look at the log, no line (a SLAM re-sends its path many "
         "times a second, each nudging every pose); metres; -1.0 = half a voxel (resolution / 2), no other negative "
         "value", -1.0, 1e3,
         run_time=True),
    Spec("map_file_mismatch", "refuse",
         "what a map_file that holds a whole map of another set-up (its resolution, num_classes, prior or frame "
         "differ from this node's) does at start: refuse (exit code 2, naming what differs and the parameter that "
         "would load it) or set_aside (start with an empty map; the first save moves the file to "
         "<map_file>.other-setup-<UTC time>, never over another file)", choices=("refuse", "set_aside")),
)
SPECS = {spec.name: spec for spec in PARAMETERS}
# The parameters under headings, as config/mapper.yaml and docs/node.md list them.
PARAMETER_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Grid, window and kernel", (
        "kernel_file", "num_classes", "resolution", "filter_size", "local_bounds", "prior",)),
    ("Free space and moving objects", (
        "free_space", "max_concentration", "forget_movers", "moving_labels",)),
    ("Device and update path", (
        "device", "update_path",)),
    ("Inputs and frames", (
        "label_space", "input_qos", "map_frame", "pose_source", "transform_timeout", "base_to_sensor",)),
    ("Map outputs", (
        "max_variance", "publish_period", "map_period", "updates_depth", "view_radius", "view_max_points",
        "publish_local", "local_period",)),
    ("Planner's costmap", (
        "costmap_profile", "costmap_size", "costmap_max_cells",)),
    ("Files and map edits", (
        "map_file", "map_folder", "autosave_period", "save_on_shutdown", "refuse_bad_map_file", "map_file_mismatch",
        "max_kept_maps", "ply_file", "clear_box_min", "clear_box_max",)),
    ("Queue and robustness (bad input never stops the node, and never changes the map)", (
        "cloud_queue_size", "cloud_queue_megabytes", "max_points_per_cloud", "max_cloud_megabytes",
        "max_map_megabytes", "pose_wait_timeout", "max_pose_jump", "on_pose_jump", "stamp_backwards_tolerance",
        "reset_on_stamp_backwards", "odometry_timeout",)),
    ("SLAM corrections (a Path of optimised keyframe poses moves the scans the map holds)", (
        "scan_log", "scan_log_scans", "scan_log_megabytes", "scan_log_disk_gigabytes", "scan_log_folder",
        "max_path_poses", "correction_tolerance",
        "correction_min_move",)),
    ("Logs and diagnostics", (
        "stats_period", "diagnostics_period",)),
)


def descriptor(spec: Spec):
    """The rcl ParameterDescriptor of ``spec`` (meaning, unit, range, read-only)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

    result = ParameterDescriptor(description=spec.describe(), read_only=not spec.run_time)
    if spec.default is NOT_SET:
        result.type = ParameterType.PARAMETER_DOUBLE_ARRAY
    if spec.low is not None and isinstance(spec.default, float):
        result.floating_point_range = [FloatingPointRange(from_value=float(spec.low), to_value=float(spec.high))]
    elif spec.low is not None:
        result.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=spec.step)]
    return result


def declare(node, spec: Spec, default: object = None):
    """Declare one parameter on ``node``; a value given on the command line or in a params
    file that has the wrong type or is out of range becomes one ``StartupError`` line."""
    from rclpy.exceptions import InvalidParameterTypeException, ParameterException
    from rclpy.parameter import Parameter

    value = spec.default if default is None else default
    if value is NOT_SET:
        value = Parameter.Type.DOUBLE_ARRAY
    given = _integers_as_doubles(node, spec)
    try:
        return node.declare_parameter(spec.name, value, descriptor(spec))
    except InvalidParameterTypeException:
        expected = "a list of numbers" if isinstance(spec.default, list) or spec.default is NOT_SET else \
            {bool: "true or false", int: "an integer", float: "a number", str: "a string"}[type(spec.default)]
        raise StartupError(f"parameter {spec.name}: {given.value!r} is {_type_name(given)}, expected "
                           f"{expected}") from None
    except ParameterException:
        odd = " (odd values only)" if spec.step == 2 else ""
        raise StartupError(f"parameter {spec.name}: {given.value!r} is out of range {spec.low:g} .. "
                           f"{spec.high:g}{odd}") from None


def _type_name(parameter) -> str:
    from rclpy.parameter import Parameter

    return {Parameter.Type.STRING: "a string", Parameter.Type.INTEGER: "an integer", Parameter.Type.DOUBLE: "a number",
            Parameter.Type.BOOL: "a boolean"}.get(parameter.type_, f"of type {parameter.type_.name.lower()}")


def integers_as_doubles(parameter):
    """``parameter`` (an rclpy Parameter), with integers given for a number (list) parameter made
    doubles: ``-p publish_period:=2`` and ``ros2 param set ... publish_period 2`` mean 2.0, while
    rcl types a bare integer as INTEGER and rclpy then refuses it for a double parameter, a
    surprise to every ROS user."""
    from rclpy.parameter import Parameter

    spec = SPECS.get(parameter.name)
    if spec is None:
        return parameter
    if isinstance(spec.default, float) and parameter.type_ == Parameter.Type.INTEGER:
        return Parameter(parameter.name, Parameter.Type.DOUBLE, float(parameter.value))
    if (isinstance(spec.default, list) or spec.default is NOT_SET) and parameter.type_ == Parameter.Type.INTEGER_ARRAY:
        return Parameter(parameter.name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in parameter.value])
    return parameter


def _integers_as_doubles(node, spec: Spec):
    """The value given for ``spec`` at start (None when none), integers made doubles
    (``integers_as_doubles``)."""
    overrides = getattr(node, "_parameter_overrides", None) or {}
    given = overrides.get(spec.name)
    if given is not None:
        given = overrides[spec.name] = integers_as_doubles(given)
    return given


def explicitly_set(node) -> set[str]:
    """Names given on the command line or in a params file for this node."""
    return set(getattr(node, "_parameter_overrides", {}) or {})


# Parameters that were replaced: what to set instead, said when an old name is given.
REPLACED = {
    "reset_on_pose_jump": "on_pose_jump (keep, reset or new_file; reset_on_pose_jump true = on_pose_jump reset)",
}


def unknown_parameters(node) -> list[str]:
    """Names given for this node that it does not declare (a misspelt name, a removed option)."""
    declared = set(SPECS) | set(ROS_OWN)
    return sorted(name for name in explicitly_set(node)
                  if name not in declared and not name.startswith("qos_overrides."))


def kernel_defaults(config: KernelConfig) -> dict[str, object]:
    return {"num_classes": int(config.num_classes), "resolution": float(config.resolution),
            "filter_size": int(config.filter_size)}


def optional(node, name: str):
    """The value of an optional parameter (declared without a default), None while unset."""
    from rclpy.exceptions import ParameterUninitializedException

    try:
        return node.get_parameter(name).value
    except ParameterUninitializedException:
        return None
