"""What the costmap tests share: the SemanticKITTI classes, the grid's resolution, the car's
traversability profile, and that profile with another risk margin."""

from convbki_core.costmap.profile import load_profile
from convbki_core.io.labels import load_label_map
from convbki_core.paths import config_dir

NAMES = load_label_map("semantic_kitti").class_names
CLASS = {name: number for number, name in enumerate(NAMES)}
RESOLUTION = 0.2
CAR = load_profile(config_dir() / "traversability" / "car.yaml", NAMES)


def with_sigma(profile, sigma: float):
    from dataclasses import replace

    return replace(profile, risk_sigma=sigma)
