"""numba's cache of compiled kernels at start: a usable directory, and a log that says when a start compiles.

numba uses ``NUMBA_CACHE_DIR`` only when it can write there: a read-only
directory (an image's, under a read-only root filesystem) is skipped whole,
and numba falls back to ``__pycache__`` beside the sources, then
``~/.cache/numba`` (so every kernel compiles again), and with neither
writable a cached kernel cannot even be imported ("no locator available").
:func:`usable_cache_dir` therefore copies a read-only cache into a fresh
temporary directory (about 12 MB, kept for the next start) and points numba there, before any kernel
is imported: the image's cache is used as it is wherever it is writable, and
copied where it is not. Nothing may mount a volume over the image's cache
directory (``tests/service/test_deploy.py`` checks the manifests).

A kernel compiles at start when the cache holds no code for it from this
CPU model (the cache is keyed by the source, the CPU name and its features):
a cache filled at image build on another machine does not count.
:func:`load_kernels` says so in the log before it starts and when it is done.
"""

from __future__ import annotations

import logging
import os
import shutil
import stat
import sys
import tempfile
import time
from typing import Callable

logger = logging.getLogger("passive_locator")

#: What the README measured for a start that compiles every kernel (seconds to the first /healthz 200 on a
#: shared 2-core machine); said in the log so that whoever watches a slow start knows what to expect.
COLD_START_S = (75, 140)


def writable(directory: str) -> bool:
    """Whether numba can use ``directory`` as its cache (it creates it, then writes a file there)."""
    try:
        os.makedirs(directory, exist_ok=True)
        tempfile.TemporaryFile(dir=directory).close()
    except OSError:
        return False
    return True


def usable_cache_dir() -> str | None:
    """``NUMBA_CACHE_DIR``, or a writable copy of it when it is read-only (then the variable names the copy).

    Call before numba is imported (it reads the variable once); when numba already is, its configuration is
    pointed at the copy as well. None when the variable is not set (numba's own default applies).
    """
    directory = os.environ.get("NUMBA_CACHE_DIR")
    if not directory or writable(directory):
        return directory or None
    copy = _copy_dir()
    if os.path.isdir(directory):
        shutil.copytree(directory, copy, dirs_exist_ok=True, copy_function=_copy_new)
    logger.info("numba cache %s is read-only: using a copy in %s", directory, copy)
    os.environ["NUMBA_CACHE_DIR"] = copy
    if "numba.core.config" in sys.modules:
        sys.modules["numba.core.config"].CACHE_DIR = copy
    return copy


def _copy_dir() -> str:
    """One directory per user in the temporary directory, kept across restarts of a container (whose /tmp
    volume outlives it: a fresh copy each start would fill it); a fresh one when that path is not ours alone."""
    path = os.path.join(tempfile.gettempdir(), f"passive-locator-numba-cache-{os.getuid()}")
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        found = os.lstat(path)
        if not stat.S_ISDIR(found.st_mode) or found.st_uid != os.getuid() or found.st_mode & 0o022:
            return tempfile.mkdtemp(prefix="numba-cache-")
    return path


def _copy_new(source: str, target: str) -> None:
    """Copy a cache file unless the copy has it already (from an earlier start, maybe with more entries)."""
    if not os.path.exists(target):
        shutil.copy2(source, target)


def dask_setup(worker=None) -> None:
    """``dask worker --preload service.ops.kernel_cache``: the workers' kernels use the image's cache too."""
    usable_cache_dir()


#: The modules whose kernels :func:`load_kernels` reports on.
PACKAGES = ("core.", "service.")


def _cached_kernels(packages: tuple[str, ...]) -> list:
    """The cache-enabled numba dispatchers of the modules imported so far whose names start with ``packages``."""
    from numba.core.dispatcher import Dispatcher

    found = {}
    for name, module in list(sys.modules.items()):
        if module is None or not name.startswith(packages):
            continue
        for value in list(vars(module).values()):
            if isinstance(value, Dispatcher) and getattr(value, "_cache", None) is not None \
                    and type(value._cache).__name__ != "NullCache":
                found[id(value)] = value
    return list(found.values())


def has_code_for_this_cpu(kernel) -> bool:
    """Whether the cache holds code of ``kernel``'s current source for this CPU (False when unsure)."""
    try:
        overloads = kernel._cache._cache_file._load_index()
        magic = kernel.targetctx.codegen().magic_tuple()
        return any(key[1] == magic for key in overloads)
    except Exception:  # numba's internals moved: say "compiling" rather than stay silent
        return False


def _lookups(kernels) -> dict[int, tuple[int, int]]:
    """Cache misses (compilations) and hits of each kernel so far, by identity."""
    return {id(k): (sum(k.stats.cache_misses.values()), sum(k.stats.cache_hits.values())) for k in kernels}


def load_kernels(compile_kernels: Callable[[], None], packages: tuple[str, ...] = PACKAGES) -> None:
    """Run ``compile_kernels`` (which loads every kernel, from the cache or by compiling it), with a log line
    before, saying whether this start compiles, and one after, saying what it took.

    Parameters
    ----------
    compile_kernels : callable
    packages : tuple of str
        Module name prefixes whose kernels are reported on.
    """
    from numba.core import config

    kernels = _cached_kernels(packages)
    missing = sum(not has_code_for_this_cpu(kernel) for kernel in kernels)
    where = config.CACHE_DIR or "__pycache__ beside the sources"
    if not kernels or 2 * missing > len(kernels):  # an empty cache, or one from another CPU model or build
        logger.warning("compiling kernels: %d of the %d imported so far have no code for this CPU in the numba "
                       "cache (%s); the port opens when they are done (%d-%d s measured on a shared 2-core "
                       "machine)", missing, len(kernels), where, *COLD_START_S)
    else:  # a few kernels that no start loads (they compile on first use) may be missing
        logger.info("loading %d kernels from the numba cache (%s)%s", len(kernels) - missing, where,
                    f"; {missing} more have no code there for this CPU" if missing else "")
    before = _lookups(kernels)
    started = time.monotonic()
    compile_kernels()
    after = _lookups(_cached_kernels(packages))
    compiled = sum(misses - before.get(key, (0, 0))[0] for key, (misses, _) in after.items())
    loaded = sum(hits - before.get(key, (0, 0))[1] for key, (_, hits) in after.items())
    logger.log(logging.WARNING if compiled else logging.INFO,
               "kernels ready in %.1f s: %d compiled, %d loaded from the cache (%s)",
               time.monotonic() - started, compiled, loaded, where)
