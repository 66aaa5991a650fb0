"""Uploaded virtual objects (GLB / OBJ / PLY) for AR, stored as ``DATA_DIR/assets/<id>.<ext>``.

A file is parsed by ``ar.load_asset`` before it is stored, so only loadable meshes get an id;
the client's file name supplies the extension (from a fixed list) and nothing else. The store
is bounded (``server.budget``): a count and a total size on disk, and a small cache of parsed
meshes in memory; ``DELETE /api/assets/{id}`` frees a place.
"""

from __future__ import annotations

import re
import secrets
import threading
from collections import OrderedDict
from pathlib import Path

from ar import AssetError, load_asset
from ar.assets import SUPPORTED_EXTENSIONS
from server.budget import ASSET_CACHE_BYTES, ASSET_CACHE_ENTRIES, MAX_ASSET_STORE_BYTES, MAX_ASSETS

ASSET_ID = re.compile(r"^[0-9a-f]{16}$")


def display_name(filename: str) -> str:
    """The client's file name as messages show it: its last part, one line, at most 80 characters."""
    name = Path(filename.replace("\\", "/")).name.replace("\n", " ").replace("\r", " ").strip()
    suffix = Path(name).suffix
    return name if len(name) <= 80 else name[:80 - len(suffix) - 3] + "..." + suffix


def mesh_bytes(mesh: object) -> int:
    """Memory a parsed mesh's arrays take."""
    arrays = (getattr(mesh, name, None) for name in ("vertices", "faces", "vertex_colors", "vertex_normals"))
    return sum(int(a.nbytes) for a in arrays if a is not None and hasattr(a, "nbytes"))


class AssetsFull(RuntimeError):
    """The store holds MAX_ASSETS files or MAX_ASSET_STORE_BYTES (409: a client error, a quota, not a server fault)."""


class AssetStore:
    """Assets on disk, at most MAX_ASSETS files and MAX_ASSET_STORE_BYTES in all, with the
    most recently used meshes kept parsed in memory, at most ASSET_CACHE_ENTRIES of them and
    ASSET_CACHE_BYTES (the rest are parsed again from disk when used)."""

    def __init__(self, directory: Path, max_assets: int = MAX_ASSETS, max_bytes: int = MAX_ASSET_STORE_BYTES,
                 cache_entries: int = ASSET_CACHE_ENTRIES) -> None:
        self._directory = directory
        self.max_assets = max_assets
        self.max_bytes = max_bytes
        self._cache: OrderedDict[str, object] = OrderedDict()
        self._cache_entries = cache_entries
        self._lock = threading.Lock()

    def _files(self) -> list[Path]:
        if not self._directory.is_dir():
            return []
        return [p for p in self._directory.iterdir()
                if p.is_file() and ASSET_ID.match(p.stem) and p.suffix.lstrip(".") in SUPPORTED_EXTENSIONS]

    def _remember(self, asset_id: str, mesh: object) -> None:
        """Keep ``mesh`` parsed, dropping the least recently used past the cache's count or
        bytes (under the lock)."""
        self._cache[asset_id] = mesh
        self._cache.move_to_end(asset_id)
        while len(self._cache) > 1 and (len(self._cache) > self._cache_entries
                                        or sum(map(mesh_bytes, self._cache.values())) > ASSET_CACHE_BYTES):
            self._cache.popitem(last=False)

    def add(self, data: bytes, filename: str) -> tuple[str, int, int]:
        """Validate and store an asset; returns (id, vertices, faces). Raises AssetError, AssetsFull."""
        extension = Path(filename or "").suffix.lower().lstrip(".")
        if extension not in SUPPORTED_EXTENSIONS:
            raise AssetError(f"{filename!r}: unsupported asset type, expected a file ending in "
                             f"{', '.join('.' + e for e in SUPPORTED_EXTENSIONS)}")
        mesh = load_asset(data, display_name(filename))
        asset_id = secrets.token_hex(8)
        with self._lock:
            files = self._files()
            used = sum(p.stat().st_size for p in files)
            if len(files) >= self.max_assets or used + len(data) > self.max_bytes:
                raise AssetsFull(f"the server holds {len(files)} assets ({used // (1024 * 1024)} MiB); the limit is "
                                 f"{self.max_assets} assets and {self.max_bytes // (1024 * 1024)} MiB: delete some "
                                 f"with DELETE /api/assets/{{id}}")
            self._directory.mkdir(parents=True, exist_ok=True)
            (self._directory / f"{asset_id}.{extension}").write_bytes(data)
            self._remember(asset_id, mesh)
        return asset_id, len(mesh.vertices), mesh.num_faces

    def resolve(self, asset_id: str):
        """The ObjectMesh of an uploaded asset; KeyError for an unknown id."""
        if not isinstance(asset_id, str) or not ASSET_ID.match(asset_id):
            raise KeyError(asset_id)
        with self._lock:
            if asset_id in self._cache:
                self._cache.move_to_end(asset_id)
                return self._cache[asset_id]
        for extension in SUPPORTED_EXTENSIONS:
            path = self._directory / f"{asset_id}.{extension}"
            if path.is_file():
                mesh = load_asset(path)
                with self._lock:
                    self._remember(asset_id, mesh)
                return mesh
        raise KeyError(asset_id)

    def delete(self, asset_id: str) -> None:
        """Remove an asset's file and parsed mesh; KeyError for an unknown id."""
        if not isinstance(asset_id, str) or not ASSET_ID.match(asset_id):
            raise KeyError(asset_id)
        with self._lock:
            self._cache.pop(asset_id, None)
            paths = [self._directory / f"{asset_id}.{e}" for e in SUPPORTED_EXTENSIONS]
            found = [p for p in paths if p.is_file()]
            if not found:
                raise KeyError(asset_id)
            for path in found:
                path.unlink(missing_ok=True)

    def cached(self) -> int:
        """Meshes held parsed in memory now."""
        with self._lock:
            return len(self._cache)
