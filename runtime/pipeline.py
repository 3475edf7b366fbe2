"""Per-frame loop-closure detection: features -> words -> FAB-MAP (or BoW) with delayed insertion.

The core class every adapter shares (eval over image folders, the Zenoh node, MCAP replay).
It does no I/O: it takes decoded images and returns FrameResult records.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import asdict, dataclass, field

import numpy as np

from aefabmap.errors import ConfigError
from aefabmap.runtime.bow import BowIndex
from aefabmap.runtime.bundle import ModelBundle, load_bundle
from aefabmap.runtime.fabmap import FabMap2
from aefabmap.runtime.features import FeatureExtractor, Features, descriptor_vectors

SCORERS = ("fabmap", "bow")


@dataclass(frozen=True)
class DetectorConfig:
    """Settings of the per-frame detector.

    scorer: "fabmap" (FAB-MAP 2.0 probability) or "bow" (tf-idf cosine similarity).
    exclude: frames a frame waits before it enters the map (delayed insertion); also the
        exclusion window: a query never sees its `exclude` predecessors.
    loop_threshold: a loop is declared when the best place's score reaches this.
    quantizer_variant: "fp32" or "int8" (autoencoder bundles). threads: onnxruntime threads.
    motion_model, naive_bayes, smoothing: FAB-MAP options (fabmap2.md).
    max_places: hard cap of the map (None: unbounded). When full, the place least recently
        inserted or matched is evicted before a new one is added.
    """

    scorer: str = "fabmap"
    exclude: int = 50
    loop_threshold: float = 0.99
    quantizer_variant: str = "fp32"
    threads: int = 1
    motion_model: bool = False
    naive_bayes: bool = False
    smoothing: float = 0.99
    max_places: int | None = None

    def __post_init__(self) -> None:
        if self.scorer not in SCORERS:
            raise ConfigError(f"scorer must be one of {SCORERS}, got {self.scorer!r}")
        if self.exclude < 0:
            raise ConfigError(f"exclude must be >= 0 frames, got {self.exclude}")
        if self.max_places is not None and self.max_places < 1:
            raise ConfigError(f"max_places must be >= 1, got {self.max_places}")
        if self.threads < 1:
            raise ConfigError(f"threads must be >= 1, got {self.threads}")


@dataclass
class FrameResult:
    """What the detector says about one frame.

    sequence: index of the frame in the stream (0-based); stamp_ns: its time stamp.
    best_place / best_frame: best candidate place and the sequence number of the frame that
        created it (None when the map is empty); score: its probability (FAB-MAP) or cosine
        similarity (BoW); p_new: FAB-MAP's new-place probability (None for BoW).
    loop: score >= loop_threshold. inserted_frame / inserted_place: the frame that entered the
        map during this step (delayed insertion) and its place id. timings_ms: per stage.
    """

    sequence: int
    stamp_ns: int
    n_keypoints: int
    n_words: int
    best_place: int | None
    best_frame: int | None
    score: float
    p_new: float | None
    loop: bool
    inserted_frame: int | None = None
    inserted_place: int | None = None
    evicted_place: int | None = None
    n_places: int = 0
    timings_ms: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


class LoopClosureDetector:
    """Stateful per-frame detector for one model bundle (not thread-safe)."""

    def __init__(self, bundle: ModelBundle, config: DetectorConfig | None = None) -> None:
        self.bundle = bundle
        self.config = config or DetectorConfig()
        c = self.config
        self.extractor = FeatureExtractor(bundle.features)
        self.quantizer = bundle.quantizer(c.quantizer_variant, c.threads)
        det = bundle.detector
        if c.scorer == "fabmap":
            self.fabmap: FabMap2 | None = FabMap2(
                bundle.tree,
                bundle.training_observations,
                pzge=det["pzge"],
                pzgne=det["pzgne"],
                smoothing=c.smoothing,
                naive_bayes=c.naive_bayes,
                motion_model=c.motion_model,
            )
            self.bow = None
        else:
            self.fabmap = None
            self.bow = BowIndex(bundle.vocabulary_size, bundle.training_observations)
        self._pending: deque[tuple[int, np.ndarray]] = deque()
        self._place_frame: list[int] = []  # place id -> sequence of the frame that made it
        self._last_used = np.zeros(0, np.int64)  # place id -> last sequence inserted/matched
        self._sequence = 0
        self._last_scores: np.ndarray | None = None

    @classmethod
    def from_bundle(cls, path, config: DetectorConfig | None = None) -> "LoopClosureDetector":
        return cls(load_bundle(path), config)

    @property
    def manifest(self) -> dict:
        return self.bundle.manifest

    @property
    def n_places(self) -> int:
        if self.fabmap is not None:
            return self.fabmap.places.n_alive
        return self.bow.n_places

    def last_scores(self) -> np.ndarray | None:
        """Scores of every place id (probability or similarity) from the last processed frame."""
        return self._last_scores

    def place_frames(self) -> np.ndarray:
        """(n_places,) sequence number of the frame that created each place id."""
        return np.asarray(self._place_frame, np.int64)

    def words_of(self, features: Features) -> np.ndarray:
        """Word id of every keypoint (N,) int32 (repeats kept)."""
        if len(features) == 0:
            return np.zeros(0, np.int32)
        return self.quantizer.quantize(descriptor_vectors(features.descriptors, self.bundle.features.kind))

    def process(self, image: np.ndarray, stamp_ns: int = 0) -> FrameResult:
        """Run one grayscale (H, W) uint8 image through the detector."""
        t0 = time.perf_counter()
        feats = self.extractor.extract(image)
        t1 = time.perf_counter()
        words = self.words_of(feats)
        t2 = time.perf_counter()
        res = self.process_words(words, stamp_ns)
        t3 = time.perf_counter()
        res.n_keypoints = len(feats)
        res.timings_ms = {
            "features": (t1 - t0) * 1e3,
            "quantise": (t2 - t1) * 1e3,
            "inference": (t3 - t2) * 1e3,
        }
        return res

    def process_words(self, words: np.ndarray, stamp_ns: int = 0) -> FrameResult:
        """Score one frame given its keypoints' word ids, then queue it for delayed insertion."""
        seq = self._sequence
        self._sequence += 1
        inserted_frame = inserted_place = evicted = None
        while self._pending and self._pending[0][0] <= seq - self.config.exclude:
            inserted_frame, pending_words = self._pending.popleft()
            evicted = self._evict_if_full(seq)
            inserted_place = self._insert(pending_words, inserted_frame)
        uniq = np.unique(words)
        if self.fabmap is not None:
            loc = self.fabmap.localize(uniq, add=False)
            best, score, p_new = loc.best_place, loc.best_probability, loc.p_new
            self._last_scores = loc.p_places
        else:
            sims = self.bow.similarity(words)
            best = int(np.argmax(sims)) if sims.size else None
            score, p_new = (float(sims[best]) if best is not None else 0.0), None
            self._last_scores = sims
        loop = best is not None and score >= self.config.loop_threshold
        if loop:
            self._last_used[best] = seq
        self._pending.append((seq, words if self.bow is not None else uniq))
        return FrameResult(
            sequence=seq,
            stamp_ns=int(stamp_ns),
            n_keypoints=int(words.size),
            n_words=int(uniq.size),
            best_place=best,
            best_frame=self._place_frame[best] if best is not None else None,
            score=float(score),
            p_new=p_new,
            loop=bool(loop),
            inserted_frame=inserted_frame,
            inserted_place=inserted_place,
            evicted_place=evicted,
            n_places=self.n_places,
        )

    def _insert(self, words: np.ndarray, frame: int) -> int:
        pid = self.fabmap.add(words) if self.fabmap is not None else self.bow.add(words)
        self._place_frame.append(frame)
        if pid >= self._last_used.size:
            self._last_used = np.concatenate([self._last_used, np.full(max(64, self._last_used.size), -1, np.int64)])
        self._last_used[pid] = frame
        return pid

    def _evict_if_full(self, seq: int) -> int | None:
        cap = self.config.max_places
        if cap is None or self.n_places < cap:
            return None
        if self.fabmap is None:
            raise ConfigError("max_places is only supported with the fabmap scorer")
        alive = self.fabmap.places.alive
        used = np.where(alive, self._last_used[: alive.size], np.iinfo(np.int64).max)
        victim = int(np.argmin(used))
        self.fabmap.remove(victim)
        return victim
