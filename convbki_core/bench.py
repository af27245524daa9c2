"""``python -m convbki_core.bench``: the ``bench`` tool, which lives in ``convbki_core.tools.bench``."""

from convbki_core.tools.bench import *  # noqa: F403 - the old import path, kept for one release
from convbki_core.tools.bench import main

if __name__ == "__main__":
    raise SystemExit(main())
