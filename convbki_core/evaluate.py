"""``python -m convbki_core.evaluate``: the ``evaluate`` tool, which lives in ``convbki_core.tools.evaluate``."""

from convbki_core.tools.evaluate import *  # noqa: F403 - the old import path, kept for one release
from convbki_core.tools.evaluate import main

if __name__ == "__main__":
    raise SystemExit(main())
