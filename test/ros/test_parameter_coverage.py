"""Every parameter of the node is exercised by a test: set at start in one, and, where it may
change at run time, changed while the node runs in one, each with an effect that test checks.

The two registries below name, per parameter, the test that does it ("file.py::test_name"),
optionally "via NAME" where the value is given by a helper of that test (a function, class or
constant of the test's file, or "other_file.py::NAME"). A parameter added to
``convbki_ros.params`` without entries here fails this test; an entry whose test does not exist,
or whose source does not set that parameter, fails it too.
"""

import ast
import re
from functools import cache
from pathlib import Path

from convbki_ros.params import SPECS

TESTS = Path(__file__).resolve().parent
STARTUP = "test_node_startup.py::test_every_bad_start_is_one_line_and_exit_2 via BAD_STARTS"  # refused values
MAP_SETTINGS = "test_node_parameters.py::test_map_settings_at_start_shape_the_map_and_its_outputs"
RUN_TIME = "test_node_parameters.py::test_queue_timing_and_robustness_settings_at_start_and_at_run_time"
RESETS = "test_node_resets.py::test_resets_on_request_no_odometry_warnings_autosave_and_save_on_sigterm"
UNREADABLE = "test_node_bad_map_files.py::test_bad_map_files_met_in_three_starts_are_each_set_aside_under_a_name_of_" \
    "their_own"
OVERRIDES = "test_node_startup.py::test_unknown_names_and_kernel_overrides_are_said_and_run_time_changes_take_effect" \
    " via nodes"
CORRECTED = "test_node_corrections.py::test_a_drift_drive_through_the_node_is_corrected_to_the_map_built_from_scratch"
RESTARTED = "test_node_corrections.py::test_a_saved_log_is_corrected_after_a_restart_and_bad_paths_change_nothing"
FILES = "test_node_files.py::test_load_map_clear_box_and_a_run_time_map_file_show_in_the_published_map"
HOSTILE_FILES = "test_hostile.py::test_no_request_writes_outside_the_folder_or_over_a_file_that_is_not_the_nodes"
HOSTILE_INPUTS = "test_hostile.py::test_inputs_over_their_caps_are_refused_before_they_cost"

# parameter: the test that sets it at start (-p name:=value, a params file, parameter_overrides)
SET_AT_START = {
    "kernel_file": STARTUP,
    "num_classes": "test_node.py::test_bad_parameters_exit_2_with_a_message",
    "resolution": STARTUP,
    "filter_size": OVERRIDES,
    "local_bounds": "test_node.py::test_node_maps_a_bag_like_the_offline_mapper_and_serves_its_map via start_mapper",
    "prior": MAP_SETTINGS,
    "label_space": STARTUP,
    "map_frame": "test_node_tf.py::test_a_robot_maps_in_map_through_tf_with_and_without_odometry via nodes",
    "pose_source": "test_node_tf.py::test_a_robot_maps_in_map_through_tf_with_and_without_odometry via nodes",
    "transform_timeout": "test_node_tf.py::test_a_cloud_whose_transform_never_comes_is_dropped_and_said via nodes",
    "base_to_sensor": "test_node_frames.py::test_a_lidar_on_a_mount_maps_like_odometry_of_the_lidar_itself via nodes",
    "max_variance": MAP_SETTINGS,
    "publish_period": OVERRIDES,
    "map_period": OVERRIDES,
    "updates_depth": "test_node_parameters.py::test_updates_depth_is_the_history_of_the_updates_publisher",
    "view_radius": "test_node_updates.py::test_updates_rebuild_the_map_and_the_view_is_bounded",
    "view_max_points": "test_node_updates.py::test_updates_rebuild_the_map_and_the_view_is_bounded",
    "free_space": "test_node_updates.py::test_updates_rebuild_the_map_and_the_view_is_bounded",
    "max_concentration": MAP_SETTINGS,
    "forget_movers": MAP_SETTINGS,
    "moving_labels": "test_node_free_space.py::test_points_labelled_moving_stay_out_of_the_map_unless_moving_"
                     "labels_is_off via nodes",
    "device": "test_node_startup.py::test_every_bad_start_is_one_line_and_exit_2",
    "update_path": MAP_SETTINGS,
    "input_qos": MAP_SETTINGS,
    "map_file": UNREADABLE,
    "autosave_period": RESETS,
    "save_on_shutdown": "test_node_files.py::test_a_map_file_in_a_read_only_folder_is_refused_at_start_and_the_"
                        "file_kept",
    "clear_box_min": "test_ros2_cli.py::test_ros2_param_service_and_topic_commands_work_against_the_node",
    "clear_box_max": "test_ros2_cli.py::test_ros2_param_service_and_topic_commands_work_against_the_node",
    "ply_file": MAP_SETTINGS,
    "publish_local": MAP_SETTINGS,
    "local_period": RUN_TIME,
    "costmap_profile": STARTUP,
    "costmap_size": "test_node_costmap.py::test_the_costmap_topic_and_service_equal_the_offline_grids",
    "costmap_max_cells": MAP_SETTINGS,
    "cloud_queue_size": RUN_TIME,
    "cloud_queue_megabytes": RUN_TIME,
    "pose_wait_timeout": RUN_TIME,
    "stats_period": OVERRIDES,
    "diagnostics_period": "test_first_contact.py::test_a_node_without_compiled_kernels_keeps_up_with_a_bag_played_the_"
                          "moment_it_is_ready via Replay",
    "max_points_per_cloud": RUN_TIME,
    "max_pose_jump": RUN_TIME,
    "on_pose_jump": RESETS,
    "stamp_backwards_tolerance": RUN_TIME,
    "reset_on_stamp_backwards": RESETS,
    "odometry_timeout": RESETS,
    "refuse_bad_map_file": UNREADABLE,
    "map_file_mismatch": "test_node_bad_map_files.py::test_a_map_of_another_set_up_stops_the_start_and_two_mistaken_" \
                         "restarts_lose_no_map",
    "scan_log": MAP_SETTINGS,
    "scan_log_scans": CORRECTED + " via start_node",
    "scan_log_megabytes": CORRECTED + " via start_node",
    "scan_log_disk_gigabytes": CORRECTED + " via start_node",
    "scan_log_folder": RESTARTED,
    "correction_tolerance": RESTARTED + " via start_node",
    "correction_min_move": RESTARTED + " via start_node",
    "map_folder": HOSTILE_FILES + " via target",
    "max_kept_maps": "test_hostile.py::test_resets_and_forgotten_boxes_followed_by_saves_never_lose_the_last_map via "
                     "target",
    "max_cloud_megabytes": HOSTILE_INPUTS + " via target",
    "max_path_poses": HOSTILE_INPUTS + " via target",
    "max_map_megabytes": "test_hostile.py::test_odometry_over_new_ground_fills_the_map_to_its_bound_and_mapping_"
                         "goes_on via target",
}

# parameter: the test that changes it while the node runs (set_parameters, ros2 param set)
CHANGED_AT_RUN_TIME = {
    "transform_timeout": "test_node_tf.py::test_a_cloud_whose_transform_never_comes_is_dropped_and_said",
    "max_variance": "test_node_files.py::test_reset_then_ctrl_c_keeps_the_saved_map_and_late_subscribers_get_the_"
                    "current_map",
    "publish_period": OVERRIDES,
    "map_period": OVERRIDES,
    "view_radius": "test_node_updates.py::test_updates_rebuild_the_map_and_the_view_is_bounded",
    "map_file": FILES,
    "autosave_period": RUN_TIME,
    "save_on_shutdown": RUN_TIME,
    "clear_box_min": FILES,
    "clear_box_max": FILES,
    "ply_file": MAP_SETTINGS,
    "publish_local": RUN_TIME,
    "local_period": RUN_TIME,
    "pose_wait_timeout": RUN_TIME,
    "stats_period": OVERRIDES,
    "diagnostics_period": RUN_TIME,
    "max_pose_jump": RUN_TIME,
    "on_pose_jump": RESETS,
    "stamp_backwards_tolerance": RUN_TIME,
    "reset_on_stamp_backwards": RUN_TIME,
    "odometry_timeout": RUN_TIME,
    "correction_tolerance": RESTARTED + " via set_parameters",
    "correction_min_move": RESTARTED + " via set_parameters",
}


@cache
def definitions(file: str) -> dict[str, str]:
    """Source of every top-level function, class and constant of a test file, by name."""
    text = (TESTS / file).read_text()
    found = {}
    for node in ast.parse(text).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            found[node.name] = ast.get_source_segment(text, node)
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                if isinstance(target, ast.Name):
                    found[target.id] = ast.get_source_segment(text, node)
    return found


def sources(entry: str) -> list[str]:
    """The source of the entry's test, and of the helper it names; fails when either is missing."""
    reference, _, helper = entry.partition(" via ")
    file, _, test = reference.partition("::")
    found = definitions(file)
    assert test.startswith("test_") and test in found, f"{entry}: no test {test} in {file}"
    texts = [found[test]]
    if helper:
        helper_file, _, name = helper.rpartition("::")
        helper_file = helper_file or file
        assert name in definitions(helper_file), f"{entry}: no {name} in {helper_file}"
        assert re.search(rf"\b{name}\b", found[test]), f"{entry}: {test} does not use {name}"
        texts.append(definitions(helper_file)[name])
    return texts


def sets_at_start(source: str, name: str) -> bool:
    """``-p name:=``, a params file's ``name: value`` line, or parameter_overrides with it."""
    return bool(re.search(rf"\b{name}:=", source) or re.search(rf"(^|\\n|\s){name}: \S", source, re.M)
                or ("parameter_overrides" in source and re.search(rf"Parameter\(\"{name}\"", source)))


def changes_at_run_time(source: str, name: str) -> bool:
    """``set_parameters(name=...)``, a parameter message or ``set_parameter("name", ...)``, or
    ``ros2 param set <node> name``."""
    for call in ast.walk(ast.parse(source)):
        if not isinstance(call, ast.Call):
            continue
        function = call.func.attr if isinstance(call.func, ast.Attribute) else getattr(call.func, "id", "")
        if function == "set_parameters" and any(keyword.arg == name for keyword in call.keywords):
            return True
        if function in ("set_parameter", "Parameter"):
            given = [*call.args[:1], *(k.value for k in call.keywords if k.arg == "name")]
            if any(isinstance(value, ast.Constant) and value.value == name for value in given):
                return "SetParameters" in source or function == "set_parameter"
    return bool(re.search(rf"param set [^\"\n]*\b{name}\b", source))


def test_every_parameter_is_set_at_start_in_a_test():
    assert set(SET_AT_START) == set(SPECS), {"no test sets them at start": sorted(set(SPECS) - set(SET_AT_START)),
                                             "not parameters": sorted(set(SET_AT_START) - set(SPECS))}
    missing = [f"{name}: {entry}" for name, entry in SET_AT_START.items()
               if not any(sets_at_start(source, name) for source in sources(entry))]
    assert not missing, "these tests do not set the parameter at start:\n" + "\n".join(missing)


def test_every_run_time_parameter_is_changed_at_run_time_in_a_test():
    run_time = {name for name, spec in SPECS.items() if spec.run_time}
    assert set(CHANGED_AT_RUN_TIME) == run_time, {
        "no test changes them at run time": sorted(run_time - set(CHANGED_AT_RUN_TIME)),
        "not run-time parameters": sorted(set(CHANGED_AT_RUN_TIME) - run_time)}
    missing = [f"{name}: {entry}" for name, entry in CHANGED_AT_RUN_TIME.items()
               if not any(changes_at_run_time(source, name) for source in sources(entry))]
    assert not missing, "these tests do not change the parameter at run time:\n" + "\n".join(missing)
