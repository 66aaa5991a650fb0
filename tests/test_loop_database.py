"""The appearance check of loop detection: global descriptors and the keyframe database."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from slam.data.frame import Frame
from slam.data.synthetic import default_intrinsics, make_scene, make_trajectory, rasterise_view
from slam.features import FrameFeatures, detect_features
from slam.loop.database import (
    DEFAULT_DESCRIPTOR, BinaryWordsDescriptor, Candidate, CombinedDescriptor, GlobalDescriptor,
    KeyframeDatabase, KeyframeEntry, ThumbnailDescriptor, TorchScriptDescriptor, make_descriptor)

W, H = 320, 240


def _no_features() -> FrameFeatures:
    return FrameFeatures(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3)), np.zeros(0))


def _moved(T: np.ndarray, dx: float, yaw_deg: float) -> np.ndarray:
    """T_world_cam moved ``dx`` metres along the camera's x and turned ``yaw_deg`` about its y."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    M = np.eye(4)
    M[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    M[0, 3] = dx
    return T @ M


@pytest.fixture(scope="module")
def views():
    """(frame, features) of a place, the same place seen 5 cm and 3 deg away, and the far side
    of the room (synthetic:loop, seed 0, frames 0 and 250)."""
    scene, K = make_scene("room", 0), default_intrinsics(W, H)
    T = make_trajectory("loop", 500, 0)
    out = []
    for i, pose in enumerate((T[0], _moved(T[0], 0.05, 3.0), T[250])):
        v = rasterise_view(scene, K, pose, W, H)
        frame = Frame(i, float(i), v.rgb, v.depth, K, pose)
        out.append((frame, detect_features(frame, 1000, 10.0)))
    return out


def _entry(descriptor, frame_index: int, map_id: int = 0, agent: int = 0) -> KeyframeEntry:
    return KeyframeEntry(map_id, agent, frame_index, frame_index / 30.0, np.asarray(descriptor, np.float32), _no_features())


def _unit(*v: float) -> np.ndarray:
    a = np.asarray(v, np.float32)
    return a / np.linalg.norm(a)


# --------------------------------------------------------------------------- descriptors
@pytest.mark.parametrize("name", [DEFAULT_DESCRIPTOR, "orb-bow", "thumbnail"])
def test_descriptor_is_deterministic_and_unit_norm(views, name):
    frame, features = views[0]
    d = make_descriptor(name)
    assert isinstance(d, GlobalDescriptor) and d.name == name
    a, b = d.describe(frame, features), make_descriptor(name).describe(frame, features)
    assert a.dtype == np.float32 and a.ndim == 1
    np.testing.assert_array_equal(a, b)
    assert np.linalg.norm(a) == pytest.approx(1.0, abs=1e-5)


def test_default_descriptor_recognises_a_place(views):
    """Itself: 1; the same place from 5 cm and 3 deg away: far above the far side of the room,
    and the database's default threshold lets the first through and not the second."""
    d = make_descriptor()
    (fa, ga), (fb, gb), (fc, gc) = views
    a, b, c = d.describe(fa, ga), d.describe(fb, gb), d.describe(fc, gc)
    assert float(a @ a) == pytest.approx(1.0, abs=1e-5)
    assert float(a @ b) > float(a @ c) + 0.15
    db = KeyframeDatabase()
    db.add(_entry(b, 0, map_id=1))
    db.add(_entry(c, 0, map_id=2))
    found = db.query(a, map_id=0, frame_index=100, top_k=2)
    assert [x.entry.map_id for x in found] == [1, 2]
    assert [x.passed for x in found] == [True, False]


def test_binary_words_are_near_for_near_orb_descriptors():
    rng = np.random.default_rng(0)
    bow = BinaryWordsDescriptor()
    base = rng.integers(0, 256, size=(200, 32), dtype=np.uint8)
    flip = np.zeros((200, 256), np.uint8)
    flip[np.arange(200)[:, None], rng.integers(0, 256, size=(200, 5))] = 1  # <= 5 bits flipped each
    near = base ^ np.packbits(flip, axis=1)
    other = rng.integers(0, 256, size=(200, 32), dtype=np.uint8)
    f = lambda d: FrameFeatures(np.zeros((len(d), 2)), d, np.zeros((len(d), 3)), np.ones(len(d)))  # noqa: E731
    va, vn, vo = (bow.describe(None, f(d)) for d in (base, near, other))
    assert va.shape == (bow.dim,) == (4 * 4096,)
    assert float(va @ vn) > 0.6 > 0.1 > float(va @ vo)


def test_blank_frame_gives_zero_descriptor_that_matches_nothing(views):
    K = default_intrinsics(W, H)
    blank = Frame(0, 0.0, np.full((H, W, 3), 0.5, np.float32), np.zeros((H, W), np.float32), K)
    features = detect_features(blank, 1000, 10.0)
    assert len(features.pixels) == 0
    for name in (DEFAULT_DESCRIPTOR, "orb-bow", "thumbnail"):
        v = make_descriptor(name).describe(blank, features)
        assert np.all(np.isfinite(v)) and not v.any()
    d = make_descriptor()
    zero = d.describe(blank, features)
    db = KeyframeDatabase()
    db.add(_entry(zero, 0, map_id=1))
    db.add(_entry(d.describe(*views[0]), 0, map_id=2))
    # The blank query matches nothing; a real query does not match the blank keyframe.
    assert all(not c.passed and c.similarity == 0.0 for c in db.query(zero, map_id=0, frame_index=100))
    hits = {c.entry.map_id: c for c in db.query(d.describe(*views[1]), map_id=0, frame_index=100)}
    assert hits[1].similarity == 0.0 and not hits[1].passed and hits[2].passed


def test_combined_descriptor_renormalises_without_features(views):
    frame, _ = views[0]
    v = CombinedDescriptor((ThumbnailDescriptor(), BinaryWordsDescriptor()), (1.0, 2.0)).describe(frame, _no_features())
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(v[:8 * 6 * 3], ThumbnailDescriptor().describe(frame, _no_features()), atol=1e-6)


def test_make_descriptor_names_and_config():
    class Config:
        descriptor = "thumbnail"
        netvlad_weights = None

    assert make_descriptor(Config()).name == "thumbnail"
    assert make_descriptor(None).name == DEFAULT_DESCRIPTOR
    with pytest.raises(ValueError, match="unknown global descriptor"):
        make_descriptor("netvlad-online")


# ------------------------------------------------------------------------- torchscript
class _TinyNet(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.proj = torch.nn.Linear(3, 8)
        torch.nn.init.normal_(self.proj.weight, generator=torch.Generator().manual_seed(0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x.mean(dim=(2, 3)))  # (1, 3, H, W) -> (1, 8)


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
def test_torchscript_descriptor_plugs_in(tmp_path, views):
    path = tmp_path / "tiny.pt"
    torch.jit.script(_TinyNet()).save(str(path))
    d = TorchScriptDescriptor(path, size=(64, 48), mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25))
    assert isinstance(d, GlobalDescriptor) and d.name == "torchscript:tiny.pt"
    v = d.describe(*views[0])
    assert v.shape == (8,) and v.dtype == np.float32
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_array_equal(v, d.describe(*views[0]))

    class Config:
        descriptor = DEFAULT_DESCRIPTOR
        netvlad_weights = str(path)

    assert isinstance(make_descriptor(Config()), TorchScriptDescriptor)


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
def test_torchscript_descriptor_errors(tmp_path, views):
    with pytest.raises(FileNotFoundError, match="never downloaded"):
        TorchScriptDescriptor(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="TorchScript"):
        TorchScriptDescriptor(bad)

    class Flat(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x.mean(dim=(0, 2, 3))  # (3,): not (1, D)

    path = tmp_path / "flat.pt"
    torch.jit.script(Flat()).save(str(path))
    with pytest.raises(ValueError, match=r"\(1, D\)"):
        TorchScriptDescriptor(path).describe(*views[0])


# --------------------------------------------------------------------------- database
def test_empty_database():
    db = KeyframeDatabase()
    assert len(db) == 0 and db.query(_unit(1, 0), map_id=0, frame_index=10) == []
    assert db.similarities(_unit(1, 0)).shape == (0,)


def test_gap_rule():
    """Own map and agent: only >= min_frame_gap frames older; other maps and agents: always."""
    db = KeyframeDatabase(min_similarity=0.1, ratio=0.0)
    q = _unit(1, 0, 0)
    for frame_index, map_id, agent in [(69, 0, 0), (70, 0, 0), (71, 0, 0), (99, 1, 0), (99, 0, 1), (120, 2, 0)]:
        db.add(_entry(_unit(1, 0.1 * (frame_index % 7), 0), frame_index, map_id, agent))
    found = db.query(q, map_id=0, agent=0, frame_index=100, top_k=10, min_frame_gap=30)
    got = sorted((c.entry.frame_index, c.entry.map_id, c.entry.agent) for c in found)
    assert got == [(69, 0, 0), (70, 0, 0), (99, 0, 1), (99, 1, 0), (120, 2, 0)]
    assert len(db.query(q, map_id=0, agent=0, frame_index=100, top_k=10, min_frame_gap=0)) == 6


def test_top_k_ordering():
    db = KeyframeDatabase(min_similarity=0.0, ratio=0.0)
    q = _unit(1, 0, 0)
    angles = [80, 10, 50, 30, 70, 20]
    for i, a in enumerate(angles):
        db.add(_entry(_unit(np.cos(np.radians(a)), np.sin(np.radians(a)), 0), i, map_id=1))
    found = db.query(q, map_id=0, frame_index=0, top_k=4)
    assert all(isinstance(c, Candidate) for c in found)
    assert [c.entry.frame_index for c in found] == [1, 5, 3, 2]
    sims = [c.similarity for c in found]
    assert sims == sorted(sims, reverse=True)
    np.testing.assert_allclose(sims, np.cos(np.radians([10, 20, 30, 50])), atol=1e-6)
    np.testing.assert_allclose(db.similarities(q), np.cos(np.radians(angles)), atol=1e-6)


def _of_map(found: list[Candidate], map_id: int) -> Candidate:
    (c,) = [x for x in found if x.entry.map_id == map_id]
    return c


def test_adaptive_threshold():
    """A candidate must beat max(floor, ratio * s_ref), s_ref = similarity to the query's own
    map's latest keyframe; every candidate reports why."""
    db = KeyframeDatabase(min_similarity=0.3, ratio=0.65)
    q = _unit(1, 0, 0)
    db.add(_entry(_unit(np.cos(np.radians(55)), np.sin(np.radians(55)), 0), 0, map_id=1))  # sim 0.574
    # The query's own map has no keyframes yet: the floor alone.
    (c,) = db.query(q, map_id=0, frame_index=100)
    assert np.isnan(c.s_ref) and c.threshold == pytest.approx(0.3) and c.passed
    # A latest own keyframe the query resembles at 0.98: threshold 0.637, the candidate fails.
    db.add(_entry(_unit(np.cos(np.radians(11)), np.sin(np.radians(11)), 0.0), 95, map_id=0))
    c = _of_map(db.query(q, map_id=0, frame_index=100), 1)
    assert c.s_ref == pytest.approx(np.cos(np.radians(11)), abs=1e-6)
    assert c.threshold == pytest.approx(0.65 * np.cos(np.radians(11)), abs=1e-6)
    assert not c.passed and c.similarity < c.threshold
    # Only the latest one counts: a newer own keyframe the query resembles at 0.64 -> 0.416.
    db.add(_entry(_unit(np.cos(np.radians(50)), 0, np.sin(np.radians(50))), 97, map_id=0))
    c = _of_map(db.query(q, map_id=0, frame_index=100), 1)
    assert c.s_ref == pytest.approx(np.cos(np.radians(50)), abs=1e-6) and c.passed
    # Another agent's map 0 is not the query's map: no reference there.
    c = _of_map(db.query(q, map_id=0, agent=1, frame_index=100), 1)
    assert np.isnan(c.s_ref) and c.threshold == pytest.approx(0.3)
    # A reducer over several latest keyframes.
    db3 = KeyframeDatabase(min_similarity=0.0, ratio=1.0, reference_keyframes=2, reference="min")
    for e in db.entries:
        db3.add(e)
    c = _of_map(db3.query(q, map_id=0, frame_index=100), 1)
    assert c.s_ref == pytest.approx(np.cos(np.radians(50)), abs=1e-6)


def test_database_rejects_bad_descriptors():
    db = KeyframeDatabase()
    db.add(_entry(_unit(1, 0, 0), 0))
    with pytest.raises(ValueError, match=r"\(3,\)"):
        db.add(_entry(_unit(1, 0), 1))
    with pytest.raises(ValueError, match="non-finite"):
        db.query(np.array([np.nan, 0, 0], np.float32), map_id=0, frame_index=5)
    with pytest.raises(ValueError):
        KeyframeDatabase(min_similarity=1.5)


def test_database_grows_past_its_buffer():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(60, 64)).astype(np.float32)
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    db = KeyframeDatabase()
    for i, x in enumerate(X):
        db.add(_entry(x, i, map_id=1))
    assert len(db) == 60 and len(db.entries) == 60
    np.testing.assert_allclose(db.similarities(X[7]), X @ X[7], atol=1e-5)
