"""Map checkpoints (``map.pt``): everything needed to render views and extract meshes later.

The file is a ``torch.save`` of plain data only (dicts, lists, str, int, float, bool, None,
CPU tensors) so that it loads with ``torch.load(weights_only=True)``, which cannot run code
from the file::

    {"format": "voxfusion-map", "version": CHECKPOINT_VERSION,
     "config": SLAMConfig.to_dict(), "maps": [SubMap.state_dict(), ...], "extra": {...}}

``extra`` holds run metadata (trajectory, frame count, ...); numpy arrays in it are stored as
tensors and come back as numpy arrays. Keyframe images are not stored, only their poses.
Writes are atomic (temporary file, then ``os.replace``), so a reader never sees half a file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import ConfigError, config_from_dict
from .maps import MapSet, SubMap

CHECKPOINT_VERSION = 1
CHECKPOINT_FORMAT = "voxfusion-map"
# Marks a numpy array stored as a tensor inside ``extra``.
_NDARRAY_KEY = "__ndarray__"


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt, of another format or of an unsupported version."""


# ---------------------------------------------------------------- extra data
def _pack_extra(value: Any, where: str) -> Any:
    """Turn ``value`` into data ``weights_only`` loading accepts, or raise TypeError naming it."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            raise TypeError(f"checkpoint extra {where}: object arrays cannot be stored")
        return {_NDARRAY_KEY: torch.from_numpy(np.ascontiguousarray(value)).clone()}
    if torch.is_tensor(value):
        return value.detach().cpu().clone()
    if isinstance(value, (list, tuple)):
        return [_pack_extra(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError(f"checkpoint extra {where}: dictionary keys must be strings")
        if _NDARRAY_KEY in value:
            raise TypeError(f"checkpoint extra {where}: the key {_NDARRAY_KEY!r} is reserved")
        return {k: _pack_extra(v, f"{where}.{k}") for k, v in value.items()}
    raise TypeError(f"checkpoint extra {where}: cannot store a {type(value).__name__}")


def _unpack_extra(value: Any) -> Any:
    """Inverse of ``_pack_extra`` (tuples come back as lists)."""
    if isinstance(value, dict):
        if set(value) == {_NDARRAY_KEY}:
            return value[_NDARRAY_KEY].numpy()
        return {k: _unpack_extra(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_unpack_extra(v) for v in value]
    return value


# ---------------------------------------------------------------------- save
def save_checkpoint(mapset: MapSet, path: str | Path, *, extra: dict | None = None) -> Path:
    """Write ``mapset`` (and ``extra`` metadata) to ``path`` atomically; returns the path.

    Raises TypeError when ``extra`` holds something other than plain data, numpy arrays and
    tensors (the message names the entry).
    """
    path = Path(path)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": mapset.config.to_dict(),
        "maps": [submap.state_dict() for submap in mapset.maps],
        "links": [[int(a), int(b)] for a, b in mapset.links],
        "extra": _pack_extra(dict(extra or {}), "extra"),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as handle:
            torch.save(payload, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


# ---------------------------------------------------------------------- load
def _read_payload(path: str | Path) -> dict:
    """The checked top-level dictionary of a checkpoint file, tensors on the CPU."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a damaged file; all mean "corrupt"
        raise CheckpointError(f"checkpoint {path} is corrupt or not a torch file: {exc}") from exc
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not a voxfusion map checkpoint")
    version = payload.get("version")
    if not isinstance(version, int):
        raise CheckpointError(f"checkpoint {path} has no format version")
    if version > CHECKPOINT_VERSION:
        raise CheckpointError(f"checkpoint {path} has format version {version}, newer than the "
                              f"supported {CHECKPOINT_VERSION}; update voxfusion to read it")
    if version != CHECKPOINT_VERSION:
        raise CheckpointError(f"checkpoint {path} has unknown format version {version} "
                              f"(supported: {CHECKPOINT_VERSION})")
    for key, kind in (("config", dict), ("maps", list), ("extra", dict)):
        if not isinstance(payload.get(key), kind):
            raise CheckpointError(f"checkpoint {path}: {key!r} is missing or not a {kind.__name__}")
    return payload


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> MapSet:
    """The ``MapSet`` stored at ``path``, on ``device`` (whatever device wrote the file)."""
    payload = _read_payload(path)
    try:
        config = config_from_dict(payload["config"])
    except (ConfigError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {path}: bad config: {exc}") from exc
    try:
        maps = [SubMap.from_state_dict(state, config, device=device) for state in payload["maps"]]
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        raise CheckpointError(f"checkpoint {path}: bad submap state: {exc!r}") from exc
    links = payload.get("links") or []  # absent in checkpoints written before multi-maps
    try:
        links = [(int(a), int(b)) for a, b in links]
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: bad map links: {exc!r}") from exc
    return MapSet(config, maps, links)


def load_checkpoint_extra(path: str | Path) -> dict:
    """The ``extra`` metadata saved with the checkpoint at ``path`` (numpy arrays restored)."""
    return _unpack_extra(_read_payload(path)["extra"])
