"""Which kernels run the field's hot path: numba's fused CPU kernels or plain torch.

``VOXFUSION_KERNELS`` chooses: ``auto`` (the default) takes numba when it imports and the
tensors are float32 on the CPU, ``numba`` insists (and raises where numba is missing),
``torch`` always takes the plain path. CUDA tensors always take torch. The plain path is the
reference every numba kernel is tested against (``tests/test_kernels.py``).

numba is imported on first use, not with ``slam``, and its compiled kernels are cached on
disk (``numba_cpu``), so a process pays at most a few seconds once per machine; call
``warm_up`` to pay it before the first frame rather than inside it.
"""

from __future__ import annotations

import time

from .backend import BACKENDS, numba_kernels, numba_unavailable_reason, requested, sync_numba_threads, use_numba

__all__ = ["BACKENDS", "numba_kernels", "numba_unavailable_reason", "requested", "sync_numba_threads", "use_numba",
           "warm_up"]


def warm_up() -> float:
    """Compile (or load from numba's cache) every kernel on a tiny input; returns seconds.
    A no-op returning 0 where the numba path is not selected."""
    if requested() == "torch" or numba_kernels() is None:
        return 0.0
    from .fused import warm_up_kernels

    t0 = time.perf_counter()
    warm_up_kernels()
    return time.perf_counter() - t0
