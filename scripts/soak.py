#!/usr/bin/env python3
"""Soak run: map a long synthetic drive at full speed, record memory and update time as the map grows.

    .venv/bin/python scripts/soak.py --scans 2000 --out out/soak

Not a test: a full-size drive of thousands of scans is far too long for one. The measuring
loop lives in ``convbki_core.tools.soak_measure`` so that test/core/test_soak.py runs a short
version of it. See ``--help`` for the columns and outputs.
"""

import sys
from pathlib import Path

# Run from a checkout without installing: the package sits next to this folder.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from convbki_core.tools.soak import main

if __name__ == "__main__":
    sys.exit(main())
