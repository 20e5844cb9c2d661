"""One way to compile the CKM's hot loops: numba without the GIL, cached on disk where it can be."""

from __future__ import annotations

import numba


def compiled(fn):
    """``fn`` compiled without the GIL, cached on disk where numba finds a writable place (the
    package's ``__pycache__`` or the user's cache), else compiled once per process (about 1 s)."""
    try:
        return numba.njit(nogil=True, cache=True)(fn)
    except RuntimeError:  # "cannot cache function ...: no locator available": a read-only install
        return numba.njit(nogil=True)(fn)
