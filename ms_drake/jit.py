"""numba's njit with an on-disk cache where one is writable.

Compiled code is cached next to the module that defines the function (`__pycache__`, numba's
cache=True); where no cache directory is writable (numba tries NUMBA_CACHE_DIR, the package's
__pycache__ and ~/.cache, and raises RuntimeError at decoration when none is) the function is
compiled without a cache instead, in every process.
"""

from __future__ import annotations

import numba


def njit_cached(f):
    try:
        return numba.njit(cache=True, nogil=True, fastmath=False)(f)
    except RuntimeError:  # "cannot cache function ...: no locator available": no writable cache dir
        return numba.njit(cache=False, nogil=True, fastmath=False)(f)
