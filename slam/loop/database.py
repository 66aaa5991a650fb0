"""The appearance check of loop detection: global keyframe descriptors and a keyframe database.

Paper: Robust Loop Detection, Appearance Check. Every keyframe gets a global descriptor, an
L2-normalised vector, so that the cosine similarity of two keyframes is a dot product; the
database keeps them with their map, agent, frame index and ORB features (which the geometric
verification needs later) and answers, for a new keyframe, the most similar older ones.

Descriptors (:class:`GlobalDescriptor`):

* :class:`TorchScriptDescriptor` runs a user's TorchScript model (the paper's NetVLAD, or any
  network taking an image tensor (1, 3, H, W) to a vector (1, D)). Nothing is downloaded: a
  user who has weights exports them with ``torch.jit.script``/``trace`` and gives the path.
* The offline default, :data:`DEFAULT_DESCRIPTOR` = ``"orb-bow+thumbnail"``, needs no weights
  and no training data. Its cosine is ``1/3`` that of a colour thumbnail
  (:class:`ThumbnailDescriptor`, 8 x 6 cells, the image's layout and colours) plus ``2/3``
  that of a bag of binary words over the keyframe's ORB descriptors
  (:class:`BinaryWordsDescriptor`: each word is 12 fixed, seeded bits of the 256-bit
  descriptor, in 4 independent tables, so two ORB descriptors within a few bits of each other
  share most words and unrelated ones almost none; sqrt term frequencies).

Why this default (``benchmarks/bench_place_recognition.py``): keyframes every 5th frame, each
querying those >= 30 frames older; a true match has camera centres < 1 m and viewing
directions < 30 deg apart. Top-1 accuracy and R@5 (a true match in the top 5) over the 341
queries with a true match of synthetic:loop, synthetic:orbit, TUM fr1/rpy and a two-lap
synthetic room, and on the two-lap ``laps`` hall (434; the hall as it was on this writing):

=========================================  ======  =====  ===========  ==========
descriptor                                 top-1   R@5    hall top-1   hall R@5
=========================================  ======  =====  ===========  ==========
orb-bow+thumbnail (default)                0.96    0.99   0.97         0.98
thumbnail (colour 8 x 6)                   0.94    0.98   0.93         0.94
thumbnail (grey 16 x 12)                   0.91    0.95   0.81         0.85
orb-bow (words alone)                      0.85    0.94   0.77         0.80
orb-bow with an idf learnt online          0.83    0.94   0.77         0.80
VLAD over ORB, 32 k-majority centres       0.77    0.88   0.69         0.76
learnt on the run's first 10 keyframes
=========================================  ======  =====  ===========  ==========

The words are viewpoint-invariant and find revisits from a shifted viewpoint; the thumbnail
separates neighbouring places whose ORB corners (procedural checkers, stripes, repeated
furniture) look alike to the words; together they beat either, most clearly in recall at a
threshold (the benchmark's table). An idf did not pay for its state (it also lowered the
combination's top-1 on synthetic:loop from 0.93 to 0.89), and folding the words into fewer
dimensions (4096) cost 0.1-0.2 of top-1. The vector has 4 * 4096 + 144 dimensions with at
most 4 non-zeros per feature, so the database keeps it sparse. Cost: 0.3 ms per keyframe at
320 x 240 and 0.9 ms at 640 x 480, beside the ORB detection (1.5-6 ms) that the geometric
verification needs anyway.

The threshold adapts to the scene (DBoW's normalised score): a candidate must exceed
``max(min_similarity, ratio * s_ref)`` where ``s_ref`` is the query's similarity to its own
map's latest keyframe, what a view of this very place scores. Where views look alike (plain
corridors, repeated furniture) every similarity rises, and the threshold with it; elsewhere
the floor decides (:class:`KeyframeDatabase` has the numbers).

Numpy only (torch only inside :class:`TorchScriptDescriptor`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, Sequence, runtime_checkable

import cv2
import numpy as np

from ..data.frame import Frame
from ..features import FrameFeatures

DEFAULT_DESCRIPTOR = "orb-bow+thumbnail"
"""Name of the offline default descriptor (:func:`make_descriptor`)."""

_ORB_BITS = 256


@runtime_checkable
class GlobalDescriptor(Protocol):
    """What the keyframe database needs of a global descriptor.

    ``describe(frame, features)`` returns a (D,) float32 vector of unit L2 norm (so cosine
    similarity is a dot product), or all zeros when the frame holds nothing to describe (a
    blank image): such a vector scores 0 against everything and never passes a threshold.
    The same frame always gives the same vector, and D is fixed per descriptor.
    """

    name: str

    def describe(self, frame: Frame, features: FrameFeatures) -> np.ndarray: ...


def _unit(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """(D,) float32 of unit norm, or zeros when ``v`` is (numerically) zero."""
    v = np.asarray(v, np.float64)
    n = float(np.linalg.norm(v))
    return (v / n).astype(np.float32) if n > eps else np.zeros(v.shape, np.float32)


@dataclass(frozen=True)
class BinaryWordsDescriptor:
    """Bag of binary words over a frame's ORB descriptors, with a vocabulary that needs no
    training: bit-sampling locality-sensitive hashing.

    Table ``t`` reads ``bits`` fixed bit positions (drawn once from ``seed``) of each 256-bit
    ORB descriptor as a word in ``0 .. 2**bits - 1``. Two descriptors of the same corner
    (a few bits apart) share a table's word with probability ``(1 - d/256) ** bits`` (d = 20:
    0.38 at 12 bits), unrelated ones (d ~ 128) with ``2 ** -bits``; ``tables`` independent
    tables make the histogram robust to any one word's luck. The vector is the sqrt of the
    word counts over all tables, (tables * 2**bits,) float32, L2-normalised; zeros for a frame
    without features.
    """

    tables: int = 4
    bits: int = 12
    seed: int = 0
    name: str = "orb-bow"
    positions: np.ndarray = field(init=False, repr=False, compare=False)
    """(tables, bits) int64 bit positions read by each table."""

    def __post_init__(self) -> None:
        if not 1 <= self.bits <= 16 or self.tables < 1:
            raise ValueError(f"BinaryWordsDescriptor: bits must be in 1..16 and tables >= 1, got {self.bits}, {self.tables}")
        rng = np.random.default_rng(self.seed)
        positions = np.stack([rng.choice(_ORB_BITS, self.bits, replace=False) for _ in range(self.tables)])
        object.__setattr__(self, "positions", positions)

    @property
    def dim(self) -> int:
        return self.tables << self.bits

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, tables) int64 word ids (offset per table, so unique over tables) of (N, 32)
        uint8 ORB descriptors."""
        d = np.asarray(descriptors, np.uint8)
        if d.ndim != 2 or d.shape[1] * 8 != _ORB_BITS:
            raise ValueError(f"BinaryWordsDescriptor: descriptors must be (N, 32) uint8, got {d.shape}")
        bits = np.unpackbits(d, axis=1)[:, self.positions].astype(np.int64)  # (N, T, B)
        return bits @ (1 << np.arange(self.bits)) + (np.arange(self.tables) << self.bits)

    def describe(self, frame: Frame, features: FrameFeatures) -> np.ndarray:
        if len(features.descriptors) == 0:
            return np.zeros(self.dim, np.float32)
        counts = np.bincount(self.words(features.descriptors).ravel(), minlength=self.dim)
        return _unit(np.sqrt(counts))


@dataclass(frozen=True)
class ThumbnailDescriptor:
    """The image shrunk to ``width`` x ``height`` cells (the mean of each cell of the centred
    crop they tile exactly), colour or grey, minus its mean, L2-normalised:
    (height * width * 3,) float32 (or (height * width,) grey), row-major cells.

    Invariant to brightness gain and offset, not to viewpoint: it says which colours lie where
    in the view. Zeros for a (near-)uniform image.
    """

    width: int = 8
    height: int = 6
    colour: bool = True
    name: str = "thumbnail"

    def describe(self, frame: Frame, features: FrameFeatures) -> np.ndarray:
        rgb = np.asarray(frame.rgb, np.float32)
        img = rgb if self.colour else rgb @ np.array([0.299, 0.587, 0.114], np.float32)
        h, w = img.shape[:2]
        ch, cw = h // self.height, w // self.width
        if ch < 1 or cw < 1:
            raise ValueError(f"ThumbnailDescriptor: a {w}x{h} image has fewer pixels than {self.width}x{self.height} cells")
        # Cell means of the centred crop that the cells tile exactly (numpy: no thread pool).
        y0, x0 = (h - ch * self.height) // 2, (w - cw * self.width) // 2
        crop = np.ascontiguousarray(img[y0:y0 + ch * self.height, x0:x0 + cw * self.width])
        rows = crop.reshape(self.height, ch, -1).sum(axis=1, dtype=np.float64)  # (height, width * cw * C)
        t = rows.reshape(self.height, self.width, cw, -1).sum(axis=2).ravel() / (ch * cw)
        t -= t.mean()
        if np.sqrt(np.mean(t * t)) < 1e-4:  # uniform image: only rounding noise is left
            return np.zeros(t.shape, np.float32)
        return _unit(t)


@dataclass(frozen=True)
class CombinedDescriptor:
    """Several descriptors concatenated, part ``i`` scaled by ``sqrt(weights[i] / sum)``: for
    two frames where every part is non-zero the cosine is the weighted mean of the parts'
    cosines. A part that is zero (no features) drops out and the rest is renormalised.
    """

    parts: tuple[GlobalDescriptor, ...]
    weights: tuple[float, ...]
    name: str = DEFAULT_DESCRIPTOR

    def __post_init__(self) -> None:
        if len(self.parts) != len(self.weights) or not self.parts or min(self.weights) <= 0:
            raise ValueError("CombinedDescriptor: one positive weight per part")

    def describe(self, frame: Frame, features: FrameFeatures) -> np.ndarray:
        w = np.sqrt(np.asarray(self.weights, np.float64) / sum(self.weights))
        return _unit(np.concatenate([wi * p.describe(frame, features) for p, wi in zip(self.parts, w)]))


def default_descriptor() -> CombinedDescriptor:
    """The offline default: colour thumbnail 1/3, ORB binary words 2/3 (module docstring)."""
    return CombinedDescriptor((ThumbnailDescriptor(), BinaryWordsDescriptor()), (1.0, 2.0))


class TorchScriptDescriptor:
    """A user's TorchScript model as a global descriptor (e.g. an exported NetVLAD).

    The model takes the frame's image as a float32 tensor (1, 3, H, W), RGB in [0, 1] (then
    ``(x - mean) / std`` per channel when given, resized to ``size`` = (width, height) first
    when given), and returns (1, D); the output is L2-normalised here. Nothing is ever
    downloaded: ``path`` must be a file on this machine.
    """

    def __init__(self, path: str | Path, *, name: str | None = None, device: str = "cpu",
                 size: tuple[int, int] | None = None, mean: Sequence[float] | None = None,
                 std: Sequence[float] | None = None) -> None:
        import torch

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(
                f"TorchScript descriptor model not found: {self.path} (global-descriptor weights are never "
                "downloaded; export your model with torch.jit.script or torch.jit.trace and give its path)")
        try:
            with warnings.catch_warnings():  # torch >= 2.10 marks TorchScript deprecated; it is the format asked for
                warnings.simplefilter("ignore", DeprecationWarning)
                self._model = torch.jit.load(str(self.path), map_location=device).eval()
        except Exception as err:  # torch raises RuntimeError/ValueError variants for bad files
            raise ValueError(f"{self.path}: not a loadable TorchScript model ({err})") from err
        self.name = name or f"torchscript:{self.path.name}"
        self.device = torch.device(device)
        self.size = size
        self._mean = None if mean is None else torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1)
        self._std = None if std is None else torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1)

    def describe(self, frame: Frame, features: FrameFeatures) -> np.ndarray:
        import torch

        rgb = np.asarray(frame.rgb, np.float32)
        if self.size is not None:
            rgb = cv2.resize(rgb, tuple(self.size), interpolation=cv2.INTER_AREA)
        x = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))[None]
        if self._mean is not None:
            x = x - self._mean
        if self._std is not None:
            x = x / self._std
        with torch.inference_mode():
            y = self._model(x.to(self.device))
        if not isinstance(y, torch.Tensor) or y.ndim != 2 or y.shape[0] != 1:
            shape = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise ValueError(f"{self.path}: the model must return a (1, D) tensor, got {shape}")
        v = y[0].detach().float().cpu().numpy()
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{self.path}: the model returned non-finite values")
        return _unit(v)


DESCRIPTORS = {
    DEFAULT_DESCRIPTOR: default_descriptor,
    "orb-bow": BinaryWordsDescriptor,
    "thumbnail": ThumbnailDescriptor,
}
"""Offline descriptors by name (:func:`make_descriptor`)."""


def make_descriptor(config=None) -> GlobalDescriptor:
    """The global descriptor a ``LoopConfig`` (or a descriptor name, or None) asks for.

    A config with ``netvlad_weights`` set gives a :class:`TorchScriptDescriptor` of that file;
    otherwise ``config.descriptor`` names one of :data:`DESCRIPTORS` (None:
    :data:`DEFAULT_DESCRIPTOR`).
    """
    if config is None or isinstance(config, str):
        name = config or DEFAULT_DESCRIPTOR
    else:
        weights = getattr(config, "netvlad_weights", None)
        if weights:
            return TorchScriptDescriptor(weights)
        name = getattr(config, "descriptor", None) or DEFAULT_DESCRIPTOR
    if name not in DESCRIPTORS:
        raise ValueError(f"unknown global descriptor {name!r}; valid: {', '.join(DESCRIPTORS)}")
    return DESCRIPTORS[name]()


# ---------------------------------------------------------------------------- the database
@dataclass(frozen=True, eq=False)
class KeyframeEntry:
    """One keyframe in the database (equal only to itself: it holds arrays).

    descriptor (D,) float32 of unit norm (or zeros); features: the keyframe's ORB features
    (pixels (N, 2), descriptors (N, 32), points_cam (N, 3), sigmas (N,)), kept for the
    geometric verification of a loop candidate.
    """

    map_id: int
    agent: int
    frame_index: int
    timestamp: float
    descriptor: np.ndarray
    features: FrameFeatures


@dataclass(frozen=True)
class Candidate:
    """A database keyframe scored against a query, with why it passed or not.

    ``similarity``: cosine of the two descriptors; ``s_ref``: the query's similarity to its own
    map's latest keyframe(s) (NaN when that map has none yet); ``threshold`` =
    ``max(min_similarity, ratio * s_ref)`` (``min_similarity`` when s_ref is NaN);
    ``passed``: similarity > threshold.
    """

    entry: KeyframeEntry
    similarity: float
    s_ref: float
    threshold: float
    passed: bool


_REDUCERS = {"min": np.min, "median": np.median, "mean": np.mean, "max": np.max}


class KeyframeDatabase:
    """Keyframes of every map and agent, queried by cosine similarity of global descriptors.

    Eligibility: a keyframe of the query's own map and agent is a candidate only when at least
    ``min_frame_gap`` frames older than the query (the recent ones simply look alike); other
    maps' and other agents' keyframes always are.

    Threshold: ``max(min_similarity, ratio * s_ref)``, where ``s_ref`` reduces (``reference``:
    min, median, mean or max) the query's similarities to the ``reference_keyframes`` latest
    keyframes of its own map and agent older than it (NaN, and the floor alone, for a map's
    first keyframe). The defaults are tuned for the default descriptor (another descriptor, a
    NetVLAD say, needs its own: ``benchmarks/bench_place_recognition.py --sweep``). Measured
    with keyframes every 5th frame, top-1 precision P and recall R on queries with candidates
    >= 30 frames older and on revisits (>= 150 frames older), with how many revisit queries
    accepted a false top-1; "room+TUM" pools synthetic:loop, synthetic:orbit, TUM fr1/rpy and a
    two-lap synthetic room (341 / 122 queries with a match), "hall" is the two-lap ``laps``
    hall (434 / 237):

    ===========================  ====================================  ====================================
    rule                         room+TUM: P, R, rev. P, rev. R, false  hall: P, R, rev. P, rev. R, false
    ===========================  ====================================  ====================================
    0.65 x latest, floor 0.35    0.97  0.74  0.99  0.90  1              1.00  0.75  0.99  0.94  2
    fixed 0.35                   0.97  0.75  0.99  0.90  1              0.98  0.82  0.94  0.94  14
    fixed 0.34                   0.97  0.79  0.96  0.90  5              0.98  0.82  0.94  0.94  15
    fixed 0.32                   0.97  0.89  0.85  0.92  20             0.98  0.85  0.94  0.95  15
    ===========================  ====================================  ====================================

    In the room and on TUM the ratio hardly binds above the floor: the floor does the work, and
    0.35 is where false revisit candidates stop (0.32: 20, 0.34: 5, 0.35: 1) while revisit
    recall stays 0.90. In the hall, whose corridors look alike, the ratio to the latest
    keyframe cuts the false revisit candidates from 14 to 2 at the same revisit recall, for
    some recall of near-in-time matches (30-40 frames back, which tracking covers anyway);
    pooled over all five, a fixed threshold must rise to 0.43 to keep revisit precision at
    0.98, and then recalls 0.84 of the revisits against 0.93. The min, median or mean of the
    latest 2-3 keyframes scored as the latest alone (within 0.01-0.04; keyframes every 10th
    frame: the same), so the default is DBoW's rule, the latest one. The hall was measured as
    generated at this writing; its generator was still being tuned.

    Descriptors are stored sparse (their non-zero entries), so a query costs O(non-zeros).
    """

    def __init__(self, *, min_similarity: float = 0.35, ratio: float = 0.65, reference_keyframes: int = 1,
                 reference: str = "median") -> None:
        if not 0.0 <= min_similarity < 1.0 or ratio < 0.0:
            raise ValueError(f"KeyframeDatabase: min_similarity must be in [0, 1) and ratio >= 0, got {min_similarity}, {ratio}")
        if reference_keyframes < 1 or reference not in _REDUCERS:
            raise ValueError(f"KeyframeDatabase: reference_keyframes >= 1 and reference in {sorted(_REDUCERS)}")
        self.min_similarity = float(min_similarity)
        self.ratio = float(ratio)
        self.reference_keyframes = int(reference_keyframes)
        self.reference = reference
        self._entries: list[KeyframeEntry] = []
        self._dim: int | None = None
        self._maps = np.zeros(0, np.int64)
        self._agents = np.zeros(0, np.int64)
        self._frames = np.zeros(0, np.int64)
        # Sparse rows: non-zero values, their columns and their entry's row, grown by doubling.
        self._cols = np.zeros(1024, np.int32)
        self._vals = np.zeros(1024, np.float32)
        self._rows = np.zeros(1024, np.int32)
        self._nnz = 0

    @staticmethod
    def from_config(config) -> "KeyframeDatabase":
        """The database a ``LoopConfig`` sets: ``similarity_threshold`` is the floor and
        ``neighbour_ratio`` the ratio."""
        return KeyframeDatabase(min_similarity=config.similarity_threshold, ratio=config.neighbour_ratio)

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def entries(self) -> tuple[KeyframeEntry, ...]:
        """Every keyframe added, in order."""
        return tuple(self._entries)

    def _check(self, descriptor: np.ndarray, what: str) -> np.ndarray:
        d = np.asarray(descriptor, np.float32)
        if d.ndim != 1 or (self._dim is not None and d.shape[0] != self._dim):
            want = f"({self._dim},)" if self._dim is not None else "(D,)"
            raise ValueError(f"KeyframeDatabase.{what}: descriptor must be {want}, got {d.shape}")
        if not np.all(np.isfinite(d)):
            raise ValueError(f"KeyframeDatabase.{what}: descriptor has non-finite values")
        return d

    def add(self, entry: KeyframeEntry) -> None:
        """Store a keyframe (its descriptor must have the dimension of the first one added)."""
        d = self._check(entry.descriptor, "add")
        self._dim = d.shape[0]
        cols = np.flatnonzero(d)
        need = self._nnz + len(cols)
        if need > len(self._cols):
            size = max(need, 2 * len(self._cols))
            self._cols, self._vals, self._rows = (np.resize(a, size) for a in (self._cols, self._vals, self._rows))
        sl = slice(self._nnz, need)
        self._cols[sl], self._vals[sl], self._rows[sl] = cols, d[cols], len(self._entries)
        self._nnz = need
        self._entries.append(entry)
        self._maps = np.append(self._maps, int(entry.map_id))
        self._agents = np.append(self._agents, int(entry.agent))
        self._frames = np.append(self._frames, int(entry.frame_index))

    def similarities(self, descriptor: np.ndarray) -> np.ndarray:
        """(N,) float64 cosine similarity of ``descriptor`` to every entry, in order."""
        if not self._entries:
            return np.zeros(0)
        q = self._check(descriptor, "query")
        n = self._nnz
        prod = q[self._cols[:n]].astype(np.float64) * self._vals[:n]
        return np.bincount(self._rows[:n], weights=prod, minlength=len(self._entries))

    def reference_similarity(self, similarities: np.ndarray, *, map_id: int, agent: int, frame_index: int) -> float:
        """s_ref: the reduced similarity of the query (its ``similarities`` to every entry) to
        the latest ``reference_keyframes`` entries of its own map and agent older than it;
        NaN when there are none."""
        own = np.flatnonzero((self._maps == map_id) & (self._agents == agent) & (self._frames < frame_index))
        if len(own) == 0:
            return float("nan")
        latest = own[np.argsort(self._frames[own], kind="stable")[-self.reference_keyframes:]]
        return float(_REDUCERS[self.reference](similarities[latest]))

    def threshold(self, s_ref: float) -> float:
        """``max(min_similarity, ratio * s_ref)`` (``min_similarity`` when s_ref is NaN)."""
        return self.min_similarity if np.isnan(s_ref) else max(self.min_similarity, self.ratio * s_ref)

    def query(self, descriptor: np.ndarray, *, map_id: int, agent: int = 0, frame_index: int,
              top_k: int = 5, min_frame_gap: int = 30) -> list[Candidate]:
        """The ``top_k`` most similar eligible keyframes, best first (ties: older first), each
        with its score, the threshold and whether it passed; [] for an empty database.

        Args:
            descriptor: (D,) float32 of the query keyframe (not yet added).
            map_id, agent, frame_index: the query's map, agent and frame index (the gap rule
                and s_ref use them).
        """
        if top_k < 1 or min_frame_gap < 0:
            raise ValueError(f"KeyframeDatabase.query: top_k >= 1 and min_frame_gap >= 0, got {top_k}, {min_frame_gap}")
        if not self._entries:
            return []
        sims = self.similarities(descriptor)
        s_ref = self.reference_similarity(sims, map_id=map_id, agent=agent, frame_index=frame_index)
        thr = self.threshold(s_ref)
        own = (self._maps == map_id) & (self._agents == agent)
        eligible = np.flatnonzero(~own | (self._frames <= frame_index - min_frame_gap))
        order = eligible[np.argsort(-sims[eligible], kind="stable")[:top_k]]
        return [Candidate(self._entries[i], float(sims[i]), s_ref, thr, bool(sims[i] > thr)) for i in order]
