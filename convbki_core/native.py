"""Compiled kernels: whether numba is here.

The update, the voxeliser, the window gather, the store's packing and the output records
each keep their compiled kernel beside the numpy code it must equal, in the module of the
step it implements; this module only decides, once, whether those kernels can be compiled.
Without numba (no wheel for the platform) every step runs its numpy twin, much slower,
after one log line.
"""

from __future__ import annotations

import logging

try:
    import numba  # noqa: F401 - imported to learn whether it is installed

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a pinned dependency; this is the fallback
    HAVE_NUMBA = False
    logging.getLogger("convbki_core").warning(
        "numba is not available: the CPU update uses the slower numpy code (install numba==0.68.1)")
