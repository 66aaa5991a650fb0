"""Find tensors made on the host that a GPU run would mix with device tensors, on a CPU.

On CUDA, ``torch.zeros(6)`` (no ``device=``) lands on the CPU, and the first operator that
meets it with a CUDA tensor of more than zero dimensions raises "Expected all tensors to be
on the same device" (as ``Tracker._levenberg_marquardt``'s motion prior once did). On a machine
without a GPU every tensor is on the CPU and nothing fails, so ``DeviceMixChecker`` replays
CUDA's placement rules as a taint on the CPU tensors. The code under test is given
``PIPELINE_DEVICE`` (``cpu:0``), which stands for the GPU:

* **device**: a factory call with ``device=cpu:0``, ``Tensor.to(cpu:0)``; and a device
  tensor's ``.device`` reads ``cpu:0``, so ``torch.zeros(n, device=t.device)`` follows ``t``;
* **host**: a factory call without ``device=`` (``torch.zeros``, ``torch.tensor``,
  ``torch.arange``, ``torch.rand*``, ...) or with plain ``cpu``, ``torch.from_numpy``,
  ``Tensor.cpu()``, ``Tensor.to("cpu")``;
* every other result takes its inputs' place (device if any input is on the device, else
  host if any is; tensors made before the checker started are neutral); ``*_like`` and
  ``Tensor.new_*`` without ``device=`` take their input's; ``param.data = t`` (what
  ``Module.to`` does) gives the parameter ``t``'s.

An operator whose inputs hold a device tensor and a host tensor of one dimension or more is
a **mix** (a host 0-dim tensor is allowed, as CUDA allows it; so are index tensors of
``t[index]`` and the source of ``copy_``, which CUDA moves). Each mix is recorded with the
innermost frames of ``slam/`` or ``ar/`` that made the call; ``check()`` raises with them.

It also counts, by ``slam.profiling.scope``, the transfers a GPU would make: **reads**
(a device tensor's value brought to the host: ``bool``, ``float``, ``int``, ``.item()``,
``.tolist()``, ``.numpy()``, ``.cpu()``, ``.to("cpu")``: a sync each) and **uploads** (a
host tensor moved to the device, or ``torch.tensor``/``torch.as_tensor`` of host data with
``device=``: from pageable memory, a copy that waits for the device's queue). Reads of host
tensors (an optimiser's step count) are free on any machine and not counted.

Run the code under test with ``VOXFUSION_KERNELS=torch``: the numba kernels only ever see
CPU tensors and make host tensors by design (their hand-offs count as reads).

A test tool (``tests/test_devices.py``, ``tests/test_syncs.py``,
``benchmarks/bench_syncs.py``); nothing in the pipeline imports it.
"""

from __future__ import annotations

import os
import traceback
from collections import Counter
from dataclasses import dataclass, field

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

from .profiling import current_scope

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_ATTR = "_voxfusion_place"
HOST, DEVICE = "host", "device"

_FACTORIES = {
    torch.zeros, torch.ones, torch.empty, torch.full, torch.arange, torch.tensor, torch.eye, torch.linspace,
    torch.logspace, torch.rand, torch.randn, torch.randint, torch.randperm, torch.as_tensor, torch.empty_strided,
    torch.scalar_tensor, torch.tril_indices, torch.triu_indices,
}
_LIKE = {torch.zeros_like, torch.ones_like, torch.empty_like, torch.full_like, torch.rand_like, torch.randn_like,
         torch.randint_like}
_NEW = {"new_zeros", "new_ones", "new_empty", "new_full", "new_tensor"}
_NO_MIX = {"copy_", "_has_compatible_shallow_copy_type", "to", "cpu", "cuda", "__repr__", "__format__", "__str__", "numpy", "tolist", "item",
           "__bool__", "__float__", "__int__", "__index__", "__len__", "__array__", "__get__", "__set__",
           "size", "dim", "numel", "data_ptr", "is_contiguous", "element_size", "stride", "storage_offset"}
_INDEXING = {"__getitem__", "__setitem__"}
_READS = {"__bool__", "__float__", "__int__", "__index__", "__complex__", "item", "tolist", "numpy", "cpu", "__array__"}
_UPLOADING_FACTORIES = {torch.tensor, torch.as_tensor}


def place(t: torch.Tensor) -> str | None:
    """``host``, ``device`` or None (unknown) of a tensor under ``DeviceMixChecker``."""
    return getattr(t, _ATTR, None)


PIPELINE_DEVICE = torch.device("cpu", 0)
"""The device the code under test is given: the GPU's stand-in."""


def _explicit_place(device) -> str | None:
    """The place a ``device=`` argument stands for (None: absent)."""
    if device is None:
        return None
    return DEVICE if torch.device(device) == PIPELINE_DEVICE else HOST


def _device_arg_of_to(args, kwargs):
    """The device ``Tensor.to`` was given, or None when it only changes the dtype."""
    if "device" in kwargs and kwargs["device"] is not None:
        return kwargs["device"]
    for a in args[1:]:
        if isinstance(a, (str, torch.device)):
            return a
        if isinstance(a, torch.Tensor):
            return place(a) or DEVICE
    return None


_SHAPE_OPS = {"nonzero", "unique", "unique_consecutive", "masked_select", "bincount", "argwhere", "nonzero_static"}


def _data_dependent_shape(name: str, args, kwargs) -> bool:
    """Whether the call's output size depends on tensor values (a device read on a GPU)."""
    if name in _SHAPE_OPS - {"nonzero_static"}:
        return True
    if name == "repeat_interleave":
        return isinstance(args[1] if len(args) > 1 else kwargs.get("repeats"), torch.Tensor) \
            and kwargs.get("output_size") is None
    if name in _INDEXING and len(args) > 1:
        index = args[1] if isinstance(args[1], tuple) else (args[1],)
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in index)
    return False


def _to_target(args, kwargs) -> str | None:
    """``HOST`` or ``DEVICE``: where ``Tensor.to(...)`` moves its tensor (None: it only
    changes the dtype)."""
    device = _device_arg_of_to(args, kwargs)
    if device in (HOST, DEVICE):
        return device
    return _explicit_place(device)


@dataclass
class Mix:
    op: str
    shapes: list
    where: list[str]

    def __str__(self) -> str:
        return f"{self.op} {self.shapes} at " + " <- ".join(self.where)


@dataclass
class DeviceMixChecker(TorchFunctionMode):
    mixes: list[Mix] = field(default_factory=list)
    reads: Counter = field(default_factory=Counter)
    """Device-to-host reads by scope name (None: outside every scope; ``total()`` for all)."""
    uploads: Counter = field(default_factory=Counter)
    """Host-to-device copies by scope name."""
    shapes: Counter = field(default_factory=Counter)
    """Operators on device tensors whose output's size depends on their values (boolean
    indexing, ``nonzero``, ``unique``, ``repeat_interleave`` without ``output_size``, ...):
    each reads a count back from the device, by scope name."""
    sites: dict = field(default_factory=dict)
    """scope -> Counter of ``kind op at file:line`` for every read and upload (messages)."""

    def _transfer(self, kind: str, name: str) -> None:
        where = current_scope()
        {"read": self.reads, "upload": self.uploads, "shape": self.shapes}[kind][where] += 1
        site = (_where() or ["?"])[0]
        self.sites.setdefault(where, Counter())[f"{kind} {name} at {site}"] += 1

    def __post_init__(self) -> None:
        super().__init__()

    def __enter__(self):
        # ``nn.Parameter(t)`` makes a new tensor object outside any torch function: it
        # takes ``t``'s place here (restored on exit).
        original = torch.nn.Parameter.__new__
        self._parameter_new = original

        def parameter_new(cls, data=None, requires_grad=True):
            param = original(cls, data, requires_grad)
            if isinstance(data, torch.Tensor) and place(data) is not None:
                setattr(param, _ATTR, place(data))
            return param

        torch.nn.Parameter.__new__ = staticmethod(parameter_new)
        return super().__enter__()

    def __exit__(self, *exc):
        torch.nn.Parameter.__new__ = staticmethod(self._parameter_new)
        return super().__exit__(*exc)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        first = args[0] if args and isinstance(args[0], torch.Tensor) else None
        target = _to_target(args, kwargs) if name == "to" else None
        if first is not None and place(first) == DEVICE and (name in _READS or target == HOST):
            self._transfer("read", name)
        elif first is not None and place(first) == HOST and (name == "cuda" or target == DEVICE):
            self._transfer("upload", name)
        elif func in _UPLOADING_FACTORIES and _explicit_place(kwargs.get("device")) == DEVICE and not (
                args and isinstance(args[0], torch.Tensor) and place(args[0]) == DEVICE):
            self._transfer("upload", name)
        elif first is not None and place(first) == DEVICE and _data_dependent_shape(name, args, kwargs):
            self._transfer("shape", name)
        out = func(*args, **kwargs)
        descriptor = getattr(getattr(func, "__self__", None), "__name__", None)
        if name == "__get__" and descriptor == "device" and args and place(args[0]) == DEVICE:
            return PIPELINE_DEVICE
        if name == "__set__" and descriptor == "data" and len(args) == 2 and place(args[1]) is not None:
            setattr(args[0], _ATTR, place(args[1]))
            return out
        result_place = self._place_of_result(func, name, args, kwargs)
        if name in ("cpu", "cuda", "to") and out is args[0] and result_place != place(out):
            # On the CPU a move to the CPU returns the tensor itself; on a GPU it is a copy.
            # An alias takes the new place and the tensor keeps its own.
            out = out.view_as(out)
        if result_place is not None:
            for t in tree_flatten(out)[0]:
                if isinstance(t, torch.Tensor):
                    try:
                        setattr(t, _ATTR, result_place)
                    except (AttributeError, RuntimeError):
                        pass
        return out

    def _place_of_result(self, func, name: str, args, kwargs) -> str | None:
        if func in _FACTORIES:
            return _explicit_place(kwargs.get("device")) or HOST
        if func is torch.from_numpy:
            return HOST
        if func in _LIKE or name in _NEW:
            explicit = _explicit_place(kwargs.get("device"))
            return explicit or (place(args[0]) if isinstance(args[0], torch.Tensor) else None)
        if name == "cpu":
            return HOST
        if name == "cuda":
            return DEVICE
        if name == "to":
            target = _to_target(args, kwargs)
            if target is not None:
                return target
            return place(args[0]) if isinstance(args[0], torch.Tensor) else None
        checked = list(args)
        if name in _INDEXING and len(checked) > 1:
            checked.pop(1)
        tensors = [t for t in tree_flatten((checked, kwargs))[0] if isinstance(t, torch.Tensor)]
        places = [place(t) for t in tensors]
        if DEVICE in places:
            if name not in _NO_MIX and any(p == HOST and t.dim() > 0 for p, t in zip(places, tensors)):
                self.mixes.append(Mix(name, [(place(t), tuple(t.shape)) for t in tensors], _where()))
            return DEVICE
        inplace = name.endswith("_") and not name.endswith("__")
        if inplace and tensors and places[0] is not None:
            return places[0]
        # A 0-dim host scalar follows the other operand on CUDA (Adam's step count).
        if any(p == HOST and t.dim() > 0 for p, t in zip(places, tensors)) or \
                (tensors and all(p == HOST for p in places)):
            return HOST
        return None

    def check(self) -> None:
        """Raise AssertionError listing every distinct mix (by call site)."""
        seen: dict[str, Mix] = {}
        for m in self.mixes:
            seen.setdefault(" <- ".join(m.where), m)
        if seen:
            raise AssertionError(f"{len(seen)} host tensors met device tensors (a CUDA run fails there):\n"
                                 + "\n".join(f"  {m}" for m in seen.values()))


def _where() -> list[str]:
    """The innermost three frames in slam/ or ar/ (file:line function)."""
    frames = [f for f in traceback.extract_stack()[:-3]
              if ("/slam/" in f.filename or "/ar/" in f.filename) and "device_mix" not in f.filename]
    return [f"{os.path.relpath(f.filename, _ROOT)}:{f.lineno} {f.name}" for f in reversed(frames[-3:])]
