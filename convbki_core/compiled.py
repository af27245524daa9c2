"""Compiled kernels: whether numba is here, where its machine code is cached, and how
parallel kernels are called from several threads.

The update, the voxeliser, the window gather, the store's packing and the output records
each keep their compiled kernel beside the numpy code it must equal, in the module of the
step it implements, decorated with this module's ``njit``. This module decides, once per
process and before any kernel is defined:

* whether the kernels can be compiled at all. Without numba (no wheel for the platform)
  every step runs its numpy twin, much slower, after one log line;
* where their machine code is cached. numba keeps it beside the sources (``__pycache__``)
  or in ``~/.cache/numba``, and refuses to define a cached kernel when neither can be
  written (a read-only install with no writable home: a container, systemd's
  ``ProtectHome``). Then a private folder in the temporary directory is used, and where
  even that cannot be written the kernels are compiled without a cache, at every start.
  ``NUMBA_CACHE_DIR`` chooses the folder; ``kernel_cache().note`` is the one line that
  says what happened when the usual places could not be used;
* that parallel kernels never run from two threads at once under numba's ``workqueue``
  threading layer (its fallback when neither OpenMP nor TBB loads), which aborts the
  process when that happens: ``parallel_region()`` around each call from Python.
"""

from __future__ import annotations

import logging
import os
import stat
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

try:
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a pinned dependency; this is the fallback
    numba = None
    HAVE_NUMBA = False
    logging.getLogger("convbki_core").warning(
        "numba is not available: the CPU update uses the slower numpy code (install numba==0.68.1)")

CACHE_VARIABLE = "NUMBA_CACHE_DIR"
# The threading layers that may be entered from several threads at once (numba's documentation).
THREAD_SAFE_LAYERS = ("tbb", "omp")


@dataclass(frozen=True)
class KernelCache:
    """Where compiled kernels are kept (``folder``; None: compiled at every start) and, when
    numba's usual places could not be written, the one line that says so (``note``)."""

    folder: str | None
    note: str | None = None
    shown: str | None = None  # how the place reads in a log line, where it is not one folder

    @property
    def place(self) -> str | None:
        return self.shown or self.folder


def _writable(folder: Path) -> bool:
    """numba's own test of a cache folder: it can be created and a file written in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _private_folder(folder: Path) -> bool:
    """``folder`` exists or can be made, belongs to this user and nobody else may write in it.

    Cached kernels are loaded as pickles, so a folder in a shared temporary directory that
    someone else could write to would let them run code in this process."""
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        info = folder.lstat()
    except OSError:
        return False
    return (stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid()
            and not info.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and _writable(folder))


def _choose_cache() -> KernelCache:
    """The first writable place in numba's order (``NUMBA_CACHE_DIR``, beside the sources, the
    user's cache), else a private folder in the temporary directory, else no cache."""
    from numba.core import config
    from numba.misc.appdirs import AppDirs

    given = config.CACHE_DIR
    problems = []
    if given:
        if _writable(Path(given)):
            return KernelCache(given)
        problems.append(f"{CACHE_VARIABLE}={given} is not writable")
    beside = Path(__file__).resolve().parent / "__pycache__"
    if _writable(beside):  # numba then keeps each module's kernels beside it, in its stage's __pycache__
        return KernelCache(str(beside), shown=f"{beside.parent}/**/__pycache__")
    user = Path(AppDirs(appname="numba", appauthor=False).user_cache_dir)
    if _writable(user):
        return KernelCache(str(user))
    problems.append(f"neither {beside.parent} nor {user.parent} is writable")
    try:
        fallback = Path(tempfile.gettempdir()) / f"convbki_ros-kernels-{os.getuid()}"
    except OSError:  # no usable temporary directory at all
        fallback = None
    if fallback is not None and _private_folder(fallback):
        config.CACHE_DIR = str(fallback)
        return KernelCache(str(fallback), f"compiled-kernel cache: {'; '.join(problems)}, so the kernels are cached "
                           f"in {fallback}, which may not outlive a reboot; set {CACHE_VARIABLE} to a writable "
                           "folder to keep them")
    return KernelCache(None, f"compiled-kernel cache: {'; '.join(problems)} and no private temporary folder could "
                       "be made, so every start compiles the kernels again (about a minute); set "
                       f"{CACHE_VARIABLE} to a writable folder")


_CACHE = _choose_cache() if HAVE_NUMBA else KernelCache(None)


def kernel_cache() -> KernelCache:
    """Where this process keeps its compiled kernels (chosen once, at import)."""
    return _CACHE


if HAVE_NUMBA:
    prange = numba.prange
    get_num_threads = numba.get_num_threads

    def njit(**options):
        """``numba.njit(**options)``, cached wherever this process can keep the machine code."""
        return numba.njit(cache=_CACHE.folder is not None, **options)


_PARALLEL = threading.RLock()
_layer_is_thread_safe: bool | None = None  # known once numba has started its threads


@contextmanager
def parallel_region() -> Iterator[None]:
    """Around a call of a parallel kernel from Python.

    Under a thread-safe threading layer this does nothing. Until the layer is known (numba
    picks it at the first parallel call) and under ``workqueue``, calls take turns, so the
    node's update and publishing threads can never enter parallel kernels together.
    """
    global _layer_is_thread_safe
    if _layer_is_thread_safe:
        yield
        return
    with _PARALLEL:
        yield
    if _layer_is_thread_safe is None:
        layer = threading_layer()
        if layer is not None:
            _layer_is_thread_safe = layer in THREAD_SAFE_LAYERS


def threading_layer() -> str | None:
    """The threading layer numba runs parallel kernels on (None before the first one ran)."""
    if not HAVE_NUMBA:
        return None
    try:
        return numba.threading_layer()
    except ValueError:
        return None
