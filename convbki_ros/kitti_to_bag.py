"""``python -m convbki_ros.kitti_to_bag``: the ``kitti_to_bag`` tool, which lives in
``convbki_ros.tools.kitti_to_bag``."""

from convbki_ros.tools.kitti_to_bag import *  # noqa: F403 - the old import path, kept for one release
from convbki_ros.tools.kitti_to_bag import main

if __name__ == "__main__":
    raise SystemExit(main())
