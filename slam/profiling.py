"""Counting what the inner loops ask of the device, and timing where a run's wall time goes.

The tracker's and the mapper's iterations run inside named scopes (``scope``): a profiler
range (``torch.profiler.record_function``, about a microsecond when no profiler runs) and a
thread-local name that ``slam.devicecheck`` reads. Two counts, both taken on the CPU, so that
no change ever adds a host sync unnoticed even where no GPU is at hand:

* ``aten_counts``: from a ``torch.profiler`` trace, the aten operators and the device-to-host
  reads among them (``aten::_local_scalar_dense``, under ``float()``, ``bool()``, ``.item()``;
  ``aten::nonzero``, under boolean indexing and ``torch.nonzero``), per scope and in all;
* ``slam.devicecheck.DeviceMixChecker``: Python-level reads of a device tensor's values into
  the host (``bool``, ``float``, ``int``, ``.item()``, ``.tolist()``, ``.numpy()``, ``.cpu()``),
  which on a CPU tensor dispatch no aten operator a profiler could see (``.tolist()``,
  ``.numpy()``, ``.cpu()``) but copy and synchronise on a GPU, and uploads of host data.

``benchmarks/bench_syncs.py`` reports both per iteration and per frame; ``tests/test_syncs.py``
holds the device path's iterations at zero.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Iterator

import torch

TRACKING_ITERATION = "voxfusion.tracking.iteration"
"""One step of the tracker's optimiser (Adam or Levenberg-Marquardt)."""
MAPPING_ITERATION = "voxfusion.mapping.iteration"
"""One step of the joint optimisation of the mapper (window or global bundle adjustment)."""

SYNC_OPS = ("aten::_local_scalar_dense", "aten::nonzero")
"""The aten operators that read device memory into the host (``aten::item`` calls the first;
it is listed by ``aten_counts`` but not added again)."""

_local = threading.local()


def current_scope() -> str | None:
    """The innermost ``scope`` this thread is in (None: none)."""
    stack = getattr(_local, "stack", None)
    return stack[-1] if stack else None


@contextlib.contextmanager
def scope(name: str) -> Iterator[None]:
    """A profiler range named ``name`` that ``slam.devicecheck`` also sees."""
    stack = getattr(_local, "stack", None)
    if stack is None:
        stack = _local.stack = []
    stack.append(name)
    try:
        with torch.profiler.record_function(name):
            yield
    finally:
        stack.pop()


@dataclass
class ScopeCounts:
    """Operators counted inside the ranges of one name (or in all, ``scope=None``)."""

    ranges: int = 0
    aten_ops: int = 0
    syncs: int = 0
    """``SYNC_OPS`` summed, but for those inside a torch optimiser's step (``optimizer_reads``)."""
    optimizer_reads: int = 0
    """``SYNC_OPS`` inside ``Optimizer.step``: Adam reads its step counter, a CPU tensor
    unless fused or capturable, so on a GPU these read host memory and wait for nothing."""
    by_op: Counter = field(default_factory=Counter)
    """The ``syncs`` by operator name."""

    def per_range(self) -> dict[str, float]:
        n = max(self.ranges, 1)
        return {"ranges": self.ranges, "aten_ops": self.aten_ops / n, "syncs": self.syncs / n}


def aten_counts(events, names: tuple[str, ...] = (TRACKING_ITERATION, MAPPING_ITERATION)) -> dict[str | None, ScopeCounts]:
    """Aten operators and device-to-host reads of a profiler trace (``prof.events()``), in all
    (key None) and inside the ranges of each of ``names`` (an operator counts for the
    innermost named range around it)."""
    out: dict[str | None, ScopeCounts] = {None: ScopeCounts()}
    out.update({n: ScopeCounts() for n in names})
    for ev in events:
        name = ev.name
        if name in out and name is not None:
            out[name].ranges += 1
            continue
        if not name.startswith("aten::"):
            continue
        targets = [out[None]]
        in_optimizer = False
        parent = ev.cpu_parent
        while parent is not None:
            in_optimizer = in_optimizer or parent.name.startswith("Optimizer.step#")
            if parent.name in out:
                targets.append(out[parent.name])
                break
            parent = parent.cpu_parent
        sync = name in SYNC_OPS
        for counts in targets:
            counts.aten_ops += 1
            if sync and in_optimizer:
                counts.optimizer_reads += 1
            elif sync:
                counts.syncs += 1
                counts.by_op[name] += 1
    return out


@dataclass
class StageClock:
    """Wall seconds spent in each named stage of a loop, summed over the run (``run.json``'s
    ``timings_s``): where a frame's time goes, at the cost of two clock reads a stage."""

    totals: dict[str, float] = field(default_factory=dict)

    def add(self, name: str, seconds: float) -> None:
        self.totals[name] = self.totals.get(name, 0.0) + seconds

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the ``with`` block into ``name`` (also when it raises)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)
