"""Adam as every loop here builds it: torch's fused step where the device has one.

The fused step updates each parameter in one kernel instead of a dozen element-wise passes,
the same formula (``tests/test_optimizers.py`` holds it to the plain step). On the CPU it
is what the dense tables of corner embeddings and fine-colour rows need, which every step
updates whole (decisions.md#optimizers).
"""

from __future__ import annotations

from typing import Any, Iterable

import torch

_FUSED_DEVICES = ("cpu", "cuda")


def adam(params: Iterable[Any], lr: float = 1e-3) -> torch.optim.Adam:
    """``torch.optim.Adam(params, lr)``, fused where every parameter is a floating-point tensor
    on a device with the fused kernel; ``params`` as Adam takes them (tensors or groups)."""
    params = list(params)
    tensors = [p for item in params for p in (item["params"] if isinstance(item, dict) else [item])]
    fused = bool(tensors) and all(p.device.type in _FUSED_DEVICES and p.is_floating_point() for p in tensors)
    return torch.optim.Adam(params, lr=lr, fused=True if fused else None)
