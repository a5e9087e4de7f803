"""compiled(): numba loops import and run even where no cache folder is writable."""
from __future__ import annotations

import numba
import numpy as np

from fhld_ros import compiled as compiled_module


def _double(values: np.ndarray) -> np.ndarray:
    return values * 2


def test_a_loop_compiles_without_a_writable_cache(monkeypatch):
    def njit(**options):
        if options.get('cache'):  # what numba raises when no cache locator can write
            raise RuntimeError("cannot cache function '_double': no locator available")
        return numba.njit(**options)
    monkeypatch.setattr(compiled_module, 'njit', njit)
    double = compiled_module.compiled(_double)
    np.testing.assert_array_equal(double(np.arange(3.0)), [0.0, 2.0, 4.0])
    assert double.targetoptions['nogil']
