"""The one way this package compiles a hot loop: numba, without the GIL, machine code cached."""
from __future__ import annotations

from collections.abc import Callable

from numba import njit


def compiled(fn: Callable) -> Callable:
    """fn compiled without the GIL, the machine code cached beside its module or in the user's
    cache folder; where neither is writable (a read-only install, no home), compiled per
    process instead of refusing to import. No fast-math: float32 results stay numpy's."""
    try:
        return njit(nogil=True, cache=True, error_model='numpy')(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True, error_model='numpy')(fn)
