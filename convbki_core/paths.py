"""Where the package's config files are, from a source tree or a colcon install."""

from __future__ import annotations

import os
from pathlib import Path


def config_dir() -> Path:
    """The folder holding the shipped YAML (label maps, kernels, node parameters).

    Looked up in order: ``$CONVBKI_CONFIG_DIR``; ``config/`` beside the source tree; the
    colcon/ament install prefix ``share/convbki_ros/config``.
    """
    override = os.environ.get("CONVBKI_CONFIG_DIR")
    if override:
        return Path(override)
    here = Path(__file__).resolve()
    source_tree = here.parents[1] / "config"
    if (source_tree / "kernels").is_dir():
        return source_tree
    # <prefix>/lib/pythonX.Y/site-packages/convbki_core/paths.py -> <prefix>/share/...
    for ancestor in here.parents:
        candidate = ancestor / "share" / "convbki_ros" / "config"
        if candidate.is_dir():
            return candidate
    return source_tree


def traversability_profile(name: str) -> Path:
    """A shipped traversability profile by name (``car``, ``small_robot``), or ``name`` as a
    YAML file's path."""
    shipped = config_dir() / "traversability" / f"{name}.yaml"
    return shipped if "/" not in name and not name.endswith(".yaml") and shipped.is_file() else Path(name)


def kernel_path(name: str) -> Path:
    """A shipped kernel file by stem, e.g. ``semantic_kitti_compound``."""
    return config_dir() / "kernels" / f"{name}.yaml"
