"""The node's start-up settings, read from its parameters and checked before anything heavy.

Every parameter a node needs at start is declared and checked here: the kernel file, the
mapper's configuration, the pose source and the sensor mount, the costmap's profile. Nothing
here loads torch or compiles a kernel, so a bad start-up value is one line (and exit code 2)
within a fraction of a second of starting; ``MappingCore`` builds the mapper from the
settings afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from convbki_core.config import DEFAULTS, MapperConfig
from convbki_core.costmap.profile import TraversabilityProfile
from convbki_core.io.kernel_file import KernelConfig, load_kernel_file
from convbki_core.paths import kernel_path
from convbki_ros.outputs.costmap import profile_of
from convbki_ros.param_checks import check_choice, check_local_bounds, check_mount, min_move_problem
from convbki_ros.params import (
    KERNEL_DECIDES,
    MIN_AUTOSAVE_PERIOD,
    REPLACED,
    SPECS,
    StartupError,
    declare,
    explicitly_set,
    kernel_defaults,
    optional,
    unknown_parameters,
)


@dataclass(frozen=True)
class StartSettings:
    """What the node's parameters say at start, checked."""

    kernel_file: str
    kernel: KernelConfig
    mapper: MapperConfig
    pose_source: str  # odometry or tf
    map_frame: str  # '' where the map is built in the odometry's frame
    mount: np.ndarray | None  # base_to_sensor as a 4x4 pose, None when unset
    costmap_profile: TraversabilityProfile


def read_start_settings(node, label_map) -> StartSettings:
    """Declare the node's parameters (``kernel_file`` first: the kernel gives the defaults of the
    grid's) and check them; raises ``StartupError`` or ``KernelFileError`` with one line.
    Unknown names and explicit overrides of the kernel's grid are warned about once."""
    declare(node, SPECS["kernel_file"])
    kernel_file = node.param("kernel_file") or str(kernel_path("semantic_kitti_compound"))
    kernel = load_kernel_file(kernel_file)
    from_kernel = kernel_defaults(kernel)
    node.declare_all(from_kernel)
    unknown = unknown_parameters(node)
    for name in [name for name in unknown if name in REPLACED]:
        node.get_logger().warning(f"parameter {name} is no longer read: set {REPLACED[name]}")
        unknown.remove(name)
    if unknown:
        node.get_logger().warning(f"unknown parameters ignored (misspelt?): {', '.join(unknown)}; the node "
                                  f"declares: {', '.join(sorted(SPECS))}")
    if node.param("num_classes") != kernel.num_classes:
        raise StartupError(f"{kernel_file}: kernel has {kernel.num_classes} classes, num_classes is "
                           f"{node.param('num_classes')}")
    explicit = explicitly_set(node)
    overridden = [f"{name} {node.param(name)} (kernel: {from_kernel[name]})" for name in KERNEL_DECIDES
                  if name in explicit and node.param(name) != from_kernel[name]]
    if overridden:
        node.get_logger().warning(f"set explicitly, overriding the kernel file {kernel_file}: "
                                  f"{', '.join(overridden)}; the kernel's lengths were trained for its grid")
    check_choice("label_space", node.param("label_space"))
    check_choice("update_path", node.param("update_path"))
    check_choice("on_pose_jump", node.param("on_pose_jump"))
    mapper = config_from_node(node, label_map)
    pose_source = check_choice("pose_source", node.param("pose_source"))
    map_frame = node.param("map_frame")
    if pose_source == "tf" and not map_frame:
        raise StartupError("pose_source tf needs map_frame: the frame TF gives each cloud's pose in (e.g. map)")
    mount = check_mount(optional(node, "base_to_sensor"))
    autosave = node.param("autosave_period")
    if 0.0 < autosave < MIN_AUTOSAVE_PERIOD:
        raise StartupError(f"parameter autosave_period: {autosave:g} s is too often: 0 (never) or at least "
                           f"{MIN_AUTOSAVE_PERIOD:g} s")
    problem = min_move_problem(node.param("correction_min_move"))
    if problem:
        raise StartupError(problem)
    return StartSettings(kernel_file, kernel, mapper, pose_source, map_frame, mount,
                         profile_of(node, label_map.class_names))


def config_from_node(node, label_map) -> MapperConfig:
    """The mapper's configuration from the node's parameters: the one place where ROS
    parameter names meet ``MapperConfig`` (checked values; the label map's classes)."""
    return DEFAULTS.replace(
        local_bounds=check_local_bounds(node.param("local_bounds")), prior=node.param("prior"),
        resolution=node.param("resolution"), filter_size=node.param("filter_size"),
        device=node.param("device"), update_path=node.param("update_path"), frame_id=node.param("map_frame") or "map",
        ignore_classes=label_map.ignore_classes, movable_classes=label_map.movable_classes,
        ground_classes=label_map.ground_classes, track_changes=True,
        free_space=node.param("free_space"), max_concentration=node.param("max_concentration"),
        forget_movers=node.param("forget_movers"), scan_log=node.param("scan_log"),
        scan_log_scans=node.param("scan_log_scans"), scan_log_megabytes=node.param("scan_log_megabytes"),
        scan_log_disk_gigabytes=node.param("scan_log_disk_gigabytes"),
        max_map_megabytes=node.param("max_map_megabytes"))
