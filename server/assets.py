"""Uploaded virtual objects (GLB / OBJ / PLY) for AR, stored as ``DATA_DIR/assets/<id>.<ext>``.

A file is parsed by ``ar.load_asset`` before it is stored, so only loadable meshes get an id;
the client's file name supplies the extension (from a fixed list) and nothing else.
"""

from __future__ import annotations

import re
import secrets
import threading
from pathlib import Path

from ar import AssetError, load_asset
from ar.assets import SUPPORTED_EXTENSIONS

ASSET_ID = re.compile(r"^[0-9a-f]{16}$")


def display_name(filename: str) -> str:
    """The client's file name as messages show it: its last part, one line, at most 80 characters."""
    name = Path(filename.replace("\\", "/")).name.replace("\n", " ").replace("\r", " ").strip()
    suffix = Path(name).suffix
    return name if len(name) <= 80 else name[:80 - len(suffix) - 3] + "..." + suffix


class AssetStore:
    def __init__(self, directory: Path) -> None:
        self._directory = directory
        self._cache: dict[str, object] = {}
        self._lock = threading.Lock()

    def add(self, data: bytes, filename: str) -> tuple[str, int, int]:
        """Validate and store an asset; returns (id, vertices, faces). Raises AssetError."""
        extension = Path(filename or "").suffix.lower().lstrip(".")
        if extension not in SUPPORTED_EXTENSIONS:
            raise AssetError(f"{filename!r}: unsupported asset type, expected a file ending in "
                             f"{', '.join('.' + e for e in SUPPORTED_EXTENSIONS)}")
        mesh = load_asset(data, display_name(filename))
        asset_id = secrets.token_hex(8)
        self._directory.mkdir(parents=True, exist_ok=True)
        (self._directory / f"{asset_id}.{extension}").write_bytes(data)
        with self._lock:
            self._cache[asset_id] = mesh
        return asset_id, len(mesh.vertices), mesh.num_faces

    def resolve(self, asset_id: str):
        """The ObjectMesh of an uploaded asset; KeyError for an unknown id."""
        if not isinstance(asset_id, str) or not ASSET_ID.match(asset_id):
            raise KeyError(asset_id)
        with self._lock:
            if asset_id in self._cache:
                return self._cache[asset_id]
        for extension in SUPPORTED_EXTENSIONS:
            path = self._directory / f"{asset_id}.{extension}"
            if path.is_file():
                mesh = load_asset(path)
                with self._lock:
                    self._cache[asset_id] = mesh
                return mesh
        raise KeyError(asset_id)
