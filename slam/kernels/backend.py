"""Which kernels run: ``VOXFUSION_KERNELS`` read, numba imported on first use, and whether a
call's tensors take the numba path (the package doc says how the choice is made).

Its own module so that the kernels (``fused``) and the package's ``warm_up``, which imports
them, both depend on it and not on each other.
"""

from __future__ import annotations

import os
import threading

import torch

BACKENDS = ("auto", "numba", "torch")
_ENV = "VOXFUSION_KERNELS"
_numba_module = None
_numba_error: str | None = None
_lock = threading.Lock()


def requested() -> str:
    """The backend ``VOXFUSION_KERNELS`` asks for (``auto`` when unset)."""
    value = os.environ.get(_ENV, "auto").strip().lower() or "auto"
    if value not in BACKENDS:
        raise ValueError(f"{_ENV}={value!r}: expected one of {', '.join(BACKENDS)}")
    return value


def numba_kernels():
    """The ``numba_cpu`` module, or None when numba does not import (the reason in
    ``numba_unavailable_reason``)."""
    global _numba_module, _numba_error
    if _numba_module is None and _numba_error is None:
        with _lock:
            if _numba_module is None and _numba_error is None:
                try:
                    from . import numba_cpu
                    _numba_module = numba_cpu
                except Exception as error:  # ImportError, or numba failing against this numpy
                    _numba_error = f"{type(error).__name__}: {error}"
    return _numba_module


def numba_unavailable_reason() -> str | None:
    numba_kernels()
    return _numba_error


def use_numba(*tensors: torch.Tensor) -> bool:
    """Whether the numba path applies to these tensors under the requested backend."""
    choice = requested()
    if choice == "torch":
        return False
    fits = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
    if choice == "numba":
        if numba_kernels() is None:
            raise RuntimeError(f"{_ENV}=numba but numba is unavailable ({_numba_error})")
        return fits
    return fits and numba_kernels() is not None


def sync_numba_threads() -> int:
    """Give numba torch's thread count (``torch.set_num_threads`` rules both); returns it.
    At one thread numba is left alone: ``numba.set_num_threads`` starts its thread pool, and
    the kernels run serial copies (``numba_cpu._TwoWays``)."""
    import numba

    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    if n > 1:
        numba.set_num_threads(n)
    return n
