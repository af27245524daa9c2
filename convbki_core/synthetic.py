"""``python -m convbki_core.synthetic``: the ``synth`` tool, which lives in ``convbki_core.tools.synth``."""

from convbki_core.tools.synth import *  # noqa: F403 - the old import path, kept for one release
from convbki_core.tools.synth import main

if __name__ == "__main__":
    raise SystemExit(main())
