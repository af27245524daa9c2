"""``python -m convbki_core.train``: the ``train`` tool, which lives in ``convbki_core.tools.train``."""

from convbki_core.tools.train import *  # noqa: F403 - the old import path, kept for one release
from convbki_core.tools.train import main

if __name__ == "__main__":
    raise SystemExit(main())
