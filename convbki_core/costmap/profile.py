"""A traversability profile: what each class costs a given robot, which classes are its
ground, and the height band in which evidence is in its way; read from a YAML file.

The costs are on a planner's scale, as Nav2 reads an occupancy grid: 0 free .. ``LETHAL``
(100); a class cost of at most ``FREE_MAX`` is free, of at least ``LETHAL_MIN`` lethal, and
costly between (``columns`` reads a voxel's classes as these kinds).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

LETHAL = 100
# Cost kinds, as a planner reads them (Nav2's map_server: free at most 25 of 100): a class cost of
# at most FREE_MAX is free, of at least LETHAL_MIN lethal, and costly between.
FREE_MAX = 25
LETHAL_MIN = 90


class ProfileError(ValueError):
    """A traversability profile that cannot be used: one line."""


@dataclass(frozen=True)
class TraversabilityProfile:
    """What a class costs a given robot (0 free .. 100 lethal), which classes are ground, and
    the robot's height band."""

    name: str
    class_costs: np.ndarray  # (C,) float64 in [0, 100]; class 0 (empty space) is 0
    ground_classes: tuple[int, ...]
    robot_height: float = 2.0  # metres above the ground in which evidence is in the way
    min_obstacle_height: float = 0.25  # metres: lower steps (a kerb) are not obstacles
    risk_sigma: float = 1.0  # standard deviations of the lethal share added as a margin
    # Voxels with less evidence than this (summed kernel weights of the points, past the prior)
    # are left out as unobserved: the kernel spreads a surface's evidence thinly over the
    # voxels around it, and such a voxel would pass for ground or obstacle on a whiff.
    min_evidence: float = 0.5


def load_profile(path: str | Path, class_names: tuple[str, ...]) -> TraversabilityProfile:
    """A profile from YAML: ``name``, ``costs`` {class name: 0..100} for every class but
    ``class_names[0]``, ``ground`` [class names], ``robot_height``, ``min_obstacle_height``,
    ``risk_sigma``. Raises ProfileError with one line naming the file and the problem."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as error:
        raise ProfileError(f"{path}: cannot read the traversability profile ({error.strerror or error})") from None
    except yaml.YAMLError as error:
        raise ProfileError(f"{path}: not YAML ({str(error).splitlines()[0]})") from None
    if not isinstance(data, dict) or not isinstance(data.get("costs"), dict):
        raise ProfileError(f"{path}: a traversability profile needs a `costs` mapping of class names to 0..100")
    index = {name: number for number, name in enumerate(class_names)}
    costs = np.zeros(len(class_names))
    for name, cost in data["costs"].items():
        if name not in index or index[name] == 0:
            raise ProfileError(f"{path}: unknown class '{name}' in costs (classes: {', '.join(class_names[1:])})")
        if isinstance(cost, bool) or not isinstance(cost, (int, float)) or not 0 <= cost <= LETHAL:
            raise ProfileError(f"{path}: cost of '{name}' must be a number from 0 to {LETHAL}, got {cost!r}")
        costs[index[name]] = float(cost)
    missing = [name for name in class_names[1:] if name not in data["costs"]]
    if missing:
        raise ProfileError(f"{path}: no cost for {', '.join(missing)} (every class needs one)")
    ground = data.get("ground") or []
    unknown = [name for name in ground if name not in index or index[name] == 0]
    if unknown or not ground:
        raise ProfileError(f"{path}: `ground` must list ground classes, " +
                           (f"unknown: {', '.join(map(str, unknown))}" if unknown else "got none"))
    settings = {}
    for key, default, low in (("robot_height", 2.0, 0.0), ("min_obstacle_height", 0.25, 0.0), ("risk_sigma", 1.0, 0.0),
                              ("min_evidence", 0.5, 0.0)):
        value = data.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < low:
            raise ProfileError(f"{path}: {key} must be a number >= {low:g}, got {value!r}")
        settings[key] = float(value)
    if settings["min_obstacle_height"] >= settings["robot_height"]:
        raise ProfileError(f"{path}: min_obstacle_height must be below robot_height")
    return TraversabilityProfile(str(data.get("name", path.stem)), costs, tuple(index[name] for name in ground),
                                 **settings)
