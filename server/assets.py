"""Uploaded virtual objects (GLB / OBJ / PLY) for AR, stored as ``DATA_DIR/assets/<id>.<ext>``.

A file is parsed by ``ar.load_asset`` before it is stored, so only loadable meshes get an id;
the client's file name supplies the extension (from a fixed list) and nothing else. The store
is bounded (``server.budget``): a count and a total size on disk, and a small cache of parsed
meshes in memory; ``DELETE /api/assets/{id}`` frees a place.

Every parse (the upload's check, and a stored asset's next use once it has left the cache)
runs in the decode helper (``server.decoding``): untrusted bytes go through trimesh there,
under its memory cap and ``ASSET_PARSE_TIMEOUT_S``, after ``ar.load_asset``'s size checks.
What comes back is an ``ar.ObjectMesh``: numpy arrays (vertices, faces, colours) and the
winding it derived there, so the API process does no work on the geometry. Parses queue one
at a time (``server.helper_queue``); a request waits at most ``ASSET_WAIT_S`` beyond the
parse's own limit, then gets ``server.helper_pool.PoolBusy`` (503).
"""

from __future__ import annotations

import re
import secrets
import threading
from collections import OrderedDict
from pathlib import Path

from ar import AssetError, ObjectMesh, load_asset
from ar.assets import SUPPORTED_EXTENSIONS
from server.budget import ASSET_CACHE_BYTES, ASSET_CACHE_ENTRIES, MAX_ASSET_STORE_BYTES, MAX_ASSETS
from server.decoding import DecodeFailed, shared_helper
from server.helper_queue import HelperQueue

ASSET_ID = re.compile(r"^[0-9a-f]{16}$")
ASSET_PARSE_TIMEOUT_S = 30.0
"""Longest one asset parse may take in the helper (the largest allowed mesh takes seconds)."""
ASSET_WAIT_S = 10.0
"""Longest a request waits for its turn at the helper before it gets 503."""


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


def parse_in_helper(source: bytes | str, name: str, timeout_s: float) -> ObjectMesh:
    """``ar.load_asset(source, name)`` in the decode helper; AssetError (naming ``name``) when
    it fails, runs out of time or memory there."""
    try:
        mesh = shared_helper().call(load_asset, source, name, timeout_s=timeout_s)
    except DecodeFailed as error:
        raise AssetError(f"{name} could not be parsed: {error}") from None
    for array in (mesh.vertices, mesh.faces, mesh.vertex_colors, mesh.vertex_normals):
        if array is not None:
            array.flags.writeable = False  # as ObjectMesh keeps them (a pickle does not)
    return mesh


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
        self.parse_queue = HelperQueue("parsing assets", ASSET_WAIT_S, ASSET_PARSE_TIMEOUT_S)

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

    def _parse(self, source: bytes | str, name: str) -> ObjectMesh:
        return self.parse_queue.run(lambda: parse_in_helper(source, name, self.parse_queue.timeout_s))

    def add(self, data: bytes, filename: str) -> tuple[str, int, int]:
        """Validate and store an asset; returns (id, vertices, faces). Raises AssetError,
        AssetsFull, PoolBusy."""
        extension = Path(filename or "").suffix.lower().lstrip(".")
        if extension not in SUPPORTED_EXTENSIONS:
            raise AssetError(f"{filename!r}: unsupported asset type, expected a file ending in "
                             f"{', '.join('.' + e for e in SUPPORTED_EXTENSIONS)}")
        mesh = self._parse(data, display_name(filename))
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

    def _cached(self, asset_id: str) -> ObjectMesh | None:
        with self._lock:
            if asset_id in self._cache:
                self._cache.move_to_end(asset_id)
                return self._cache[asset_id]
        return None

    def resolve(self, asset_id: str) -> ObjectMesh:
        """The ObjectMesh of an uploaded asset; KeyError for an unknown id. Raises AssetError
        (a stored file that no longer parses) and PoolBusy."""
        if not isinstance(asset_id, str) or not ASSET_ID.match(asset_id):
            raise KeyError(asset_id)
        mesh = self._cached(asset_id)
        if mesh is not None:
            return mesh
        for extension in SUPPORTED_EXTENSIONS:
            path = self._directory / f"{asset_id}.{extension}"
            if path.is_file():
                # On the queue's thread, the cache is read again (requests that queued for the
                # same asset parse it once) and filled even when the request stopped waiting.
                return self.parse_queue.run(self._parse_stored, asset_id, path)
        raise KeyError(asset_id)

    def _parse_stored(self, asset_id: str, path: Path) -> ObjectMesh:
        mesh = self._cached(asset_id) or parse_in_helper(str(path), path.name, self.parse_queue.timeout_s)
        with self._lock:
            self._remember(asset_id, mesh)
        return mesh

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
