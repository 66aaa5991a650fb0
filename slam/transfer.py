"""Many small tensors across the host-device boundary in one copy per dtype.

Each ``.cpu()`` of a device tensor waits for the device, and each upload of pageable host
memory waits for the device's queue: a map snapshot of a dozen arrays paid a dozen of each.
``to_host`` and ``to_device`` pack same-dtype tensors into one flat buffer, move it once and
split it again (on the CPU both are plain copies).
"""

from __future__ import annotations

from collections import defaultdict
from typing import Mapping

import numpy as np
import torch


def to_host(tensors: Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """Detached numpy copies of named tensors, one device read per dtype."""
    groups: dict[torch.dtype, list[str]] = defaultdict(list)
    for name, t in tensors.items():
        groups[t.dtype].append(name)
    out: dict[str, np.ndarray] = {}
    for dtype, names in groups.items():
        parts = [tensors[n].detach().reshape(-1) for n in names]
        flat = torch.cat(parts).cpu().numpy() if len(parts) > 1 else parts[0].cpu().numpy().copy()
        start = 0
        for n in names:
            size = tensors[n].numel()
            out[n] = flat[start:start + size].reshape(tuple(tensors[n].shape)).copy() if len(parts) > 1 \
                else flat.reshape(tuple(tensors[n].shape))
            start += size
    return out


def to_device(arrays: Mapping[str, np.ndarray], device: torch.device) -> dict[str, torch.Tensor]:
    """Tensors on ``device`` of named numpy arrays, one upload per dtype."""
    groups: dict[np.dtype, list[str]] = defaultdict(list)
    for name, a in arrays.items():
        groups[np.asarray(a).dtype].append(name)
    out: dict[str, torch.Tensor] = {}
    for dtype, names in groups.items():
        parts = [np.ascontiguousarray(arrays[n]).reshape(-1) for n in names]
        flat = torch.from_numpy(np.concatenate(parts) if len(parts) > 1 else parts[0].copy()).to(device)
        start = 0
        for n in names:
            shape = np.asarray(arrays[n]).shape
            size = int(np.prod(shape)) if len(shape) else 1
            out[n] = flat[start:start + size].reshape(shape)
            start += size
    return out
