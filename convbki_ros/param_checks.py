"""The node's parameter values checked beyond their type and range: choices, box corners, the
local window, the sensor mount. Each says what is wrong in one line (``StartupError`` at start,
the reason of a refused change at run time)."""

from __future__ import annotations

import numpy as np

from convbki_ros.params import SPECS, StartupError


def choice_problem(name: str, value: str) -> str | None:
    """Why ``value`` is not one of parameter ``name``'s choices (None when it is)."""
    choices = SPECS[name].choices
    return None if value in choices else f"parameter {name}: {value!r} is not one of {', '.join(choices)}"


def check_choice(name: str, value: str) -> str:
    problem = choice_problem(name, value)
    if problem:
        raise StartupError(problem)
    return value


def check_local_bounds(bounds) -> tuple[tuple[float, ...], tuple[float, ...]]:
    bounds = [float(v) for v in bounds]
    if len(bounds) != 6:
        raise StartupError(f"parameter local_bounds needs 6 numbers (min xyz, max xyz), got {len(bounds)}")
    low, high = bounds[:3], bounds[3:]
    if not all(np.isfinite(bounds)) or not all(a < b for a, b in zip(low, high, strict=True)):
        raise StartupError(f"parameter local_bounds: each min must be below its max, got {bounds}")
    return tuple(low), tuple(high)


def min_move_problem(value: float) -> str | None:
    """Why correction_min_move cannot be ``value`` (its only negative value is -1.0, half a voxel)."""
    if value < 0.0 and value != -1.0:
        return f"parameter correction_min_move: {value:g} m: -1.0 (half a voxel) or a distance of at least 0"
    return None


def check_box(name: str, values) -> str | None:
    """Why ``values`` is not a box corner [x, y, z] (finite, metres); None when it is."""
    values = list(values)
    if len(values) != 3:
        return f"parameter {name} needs 3 finite numbers [x, y, z], got {len(values)}"
    if not all(np.isfinite(values)):
        return f"parameter {name} needs 3 finite numbers [x, y, z], got {values}"
    return None


def check_mount(values) -> np.ndarray | None:
    """``base_to_sensor`` as a 4x4 pose (child frame <- cloud frame), None when unset."""
    if values is None:
        return None
    from convbki_core.geometry.poses import pose_from_translation_quaternion
    from convbki_ros.inputs.pose_buffer import pose_problem

    values = [float(v) for v in values]
    if len(values) != 7:
        raise StartupError(f"parameter base_to_sensor needs 7 numbers [x, y, z, qx, qy, qz, qw], got {len(values)}")
    problem = pose_problem(values[:3], values[3:])
    if problem:
        raise StartupError(f"parameter base_to_sensor: {problem}")
    quaternion = np.asarray(values[3:]) / np.linalg.norm(values[3:])
    return pose_from_translation_quaternion(values[:3], quaternion)
