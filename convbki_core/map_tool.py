"""``python -m convbki_core.map_tool``: the ``map_tool`` tool, which lives in ``convbki_core.tools.map_tool``."""

from convbki_core.tools.map_tool import *  # noqa: F403 - the old import path, kept for one release
from convbki_core.tools.map_tool import main

if __name__ == "__main__":
    raise SystemExit(main())
