"""``python -m convbki_ros.play_bag``: the ``play_bag`` tool, which lives in ``convbki_ros.tools.play_bag``."""

from convbki_ros.tools.play_bag import *  # noqa: F403 - the old import path, kept for one release
from convbki_ros.tools.play_bag import main

if __name__ == "__main__":
    raise SystemExit(main())
