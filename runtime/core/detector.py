"""Per-frame loop-closure detection: features -> words -> FAB-MAP (or BoW) with delayed insertion.

The core class every adapter shares (eval over image folders, the Zenoh node, MCAP replay).
It does no I/O: it takes decoded images and returns FrameResult records.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Protocol

import numpy as np

from aefabmap.errors import ConfigError, InputError
from aefabmap.runtime.core.bow import BowIndex
from aefabmap.runtime.core.fabmap import FabMap2
from aefabmap.runtime.core.features import (
    FeatureConfig,
    FeatureExtractor,
    Features,
    descriptor_vectors,
)
from aefabmap.runtime.core.keypoint_store import KeypointStore, PlaceKeypoints
from aefabmap.runtime.core.temporal import TemporalFilter
from aefabmap.runtime.core.tree import ChowLiuTree
from aefabmap.runtime.core.verification import (
    GeometryResult,
    VerificationConfig,
    verify_pair,
)


class DetectorModel(Protocol):
    """What the detector needs from a trained model (a bundle reader provides it).

    training_observations: list of sorted word-id arrays, the new-place model's samples.
    quantizer(variant, threads) -> an object with quantize((N, D) float32) -> (N,) word ids.
    """

    manifest: dict
    features: FeatureConfig
    tree: ChowLiuTree
    training_observations: list[np.ndarray]

    @property
    def vocabulary_size(self) -> int: ...

    @property
    def detector(self) -> dict: ...

    def quantizer(self, variant: str = "fp32", threads: int = 1): ...


SCORERS = ("fabmap", "bow")
FABMAP_SCORES = ("probability", "llr")


@dataclass(frozen=True)
class DetectorConfig:
    """Settings of the per-frame detector.

    scorer: "fabmap" (FAB-MAP 2.0 probability) or "bow" (tf-idf cosine similarity).
    exclude: frames a frame waits before it enters the map (delayed insertion); also the
        exclusion window: a query never sees its `exclude` predecessors.
    loop_threshold: a loop is declared when the best place's score reaches this.
    quantizer_variant: "fp32" or "int8" (autoencoder bundles). threads: onnxruntime threads.
    motion_model, naive_bayes, smoothing: FAB-MAP options (fabmap2.md).
    fabmap_score: what `score` holds with the fabmap scorer: "probability" (the normalised
        posterior P of the best place, evaluation.md's FAB-MAP score) or "llr" (log-likelihood
        ratio of the best place against the new-place model, in nats: it keeps ranking frames
        where P has saturated at 0.99 + 0.01 / (n + 1)).
    max_places: hard cap of the map in places (None: unbounded).
    memory_mb: hard cap of the map's memory in MiB, as accounted by `map_bytes()` (None: unbounded).
        When either cap is reached the place least recently inserted or matched as a loop
        is evicted before a new one is added.
    verification: geometric verification of the best candidates (runtime/core/verification.py);
        on by default. When enabled, `loop` means "verified" and loop_threshold is not used:
        the top_k places by FAB-MAP log-likelihood (or BoW similarity) are checked whatever
        their score, because the posterior saturates and ranks better than it thresholds;
        before them, the places following the last verified match (the track prior,
        `VerificationConfig.track`). Each place then keeps its keypoints
        (runtime/core/keypoint_store.py) inside memory_mb.
    temporal_frames: temporal consistency (runtime/core/temporal.py): a verified match counts only
        when the `temporal_frames` preceding frames were verified to frames within
        `temporal_tolerance` frames of it. 0 (default) switches the check off.
    """

    scorer: str = "fabmap"
    exclude: int = 50
    loop_threshold: float = 0.99
    quantizer_variant: str = "fp32"
    threads: int = 1
    motion_model: bool = False
    naive_bayes: bool = False
    smoothing: float = 0.99
    fabmap_score: str = "probability"
    max_places: int | None = None
    memory_mb: float | None = None
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    temporal_frames: int = 0
    temporal_tolerance: int = 10

    def __post_init__(self) -> None:
        if self.scorer not in SCORERS:
            raise ConfigError(f"scorer must be one of {SCORERS}, got {self.scorer!r}")
        if self.exclude < 0:
            raise ConfigError(f"exclude must be >= 0 frames, got {self.exclude}")
        if self.max_places is not None and self.max_places < 1:
            raise ConfigError(f"max_places must be >= 1, got {self.max_places}")
        if self.memory_mb is not None and self.memory_mb <= 0:
            raise ConfigError(f"memory_mb must be > 0, got {self.memory_mb}")
        if self.fabmap_score not in FABMAP_SCORES:
            raise ConfigError(f"fabmap_score must be one of {FABMAP_SCORES}, got {self.fabmap_score!r}")
        if (self.max_places is not None or self.memory_mb is not None) and self.scorer != "fabmap":
            raise ConfigError("max_places / memory_mb are supported with the fabmap scorer only")
        if self.threads < 1:
            raise ConfigError(f"threads must be >= 1, got {self.threads}")
        if not isinstance(self.verification, VerificationConfig):
            raise ConfigError(f"verification must be a VerificationConfig, got {type(self.verification).__name__}")
        if self.temporal_frames < 0 or self.temporal_tolerance < 0:
            raise ConfigError("temporal_frames and temporal_tolerance must be >= 0")
        if self.temporal_frames and not self.verification.enabled:
            raise ConfigError("temporal consistency works on verified matches: enable verification")


@dataclass
class Candidate:
    """One place the detector considered for a frame (evidence for evaluation and logs).

    place / frame: place id and the sequence number of the frame that made it. rank: 0-based
    position in the FAB-MAP log-likelihood (or BoW similarity) ranking of all places.
    probability: FAB-MAP posterior; llr: log-likelihood ratio against the new place (nats);
    similarity: BoW cosine (None for the other scorer). checked: geometrically verified this
    frame, source: why ("track", "fabmap" or "island"; None when not checked). verified,
    inliers, matches, model ("F" / "H"), nfa (the geometric check's chance figure when it
    gives one): outcome of that check. inlier_points: (inliers, 4) float32 rows
    (x_q, y_q, x_p, y_p), only with `VerificationConfig.keep_inlier_points`.
    """

    place: int
    frame: int
    rank: int
    probability: float | None = None
    llr: float | None = None
    similarity: float | None = None
    checked: bool = False
    source: str | None = None
    verified: bool = False
    inliers: int = 0
    matches: int = 0
    model: str | None = None
    nfa: float | None = None
    inlier_points: np.ndarray | None = None


@dataclass
class FrameResult:
    """What the detector says about one frame.

    sequence: index of the frame in the stream (0-based); stamp_ns: its time stamp.
    best_place / best_frame: best candidate place and the sequence number of the frame that
        created it (None when the map is empty); score: see DetectorConfig.fabmap_score, or the
        cosine similarity (BoW); probability: FAB-MAP's posterior of the best place; llr: its
        log-likelihood ratio against the new place (nats); p_new: FAB-MAP's new-place
        probability (None for BoW).
    loop: score >= loop_threshold, or, with verification enabled, `verified`.
    inserted_frame / inserted_place: the frame that entered the map during this step (delayed
        insertion) and its place id. timings_ms: per stage (ms).
    verified: a candidate passed geometric verification (and the temporal check when enabled).
    verified_place / verified_frame: that candidate (None when none passed).
    inliers / matches: inliers of the accepted geometry and putative matches; when nothing
        passed, those of the best attempt (diagnostics). geometry_model: "F" (fundamental
        matrix) or "H" (homography); geometry: its 3x3 matrix as nested lists, row-major,
        mapping the place's image to the query's, in original pixels (x_q^T F x_p = 0 or
        x_q ~ H x_p); None unless verified. candidates_tried: places verified this frame.
    geometry_ok: the geometric check passed (before the temporal check); temporal_ok: the
        temporal check passed (None when it is off).
    candidates: the top places of the ranking (VerificationConfig.top_k of them) and every
        other place checked this frame (track, island), see Candidate.
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
    probability: float | None = None
    llr: float | None = None
    inserted_frame: int | None = None
    inserted_place: int | None = None
    evicted_place: int | None = None
    n_places: int = 0
    timings_ms: dict = field(default_factory=dict)
    verified: bool = False
    verified_place: int | None = None
    verified_frame: int | None = None
    inliers: int = 0
    matches: int = 0
    geometry_model: str | None = None
    geometry: list | None = None
    candidates_tried: int = 0
    geometry_ok: bool = False
    temporal_ok: bool | None = None
    candidates: list[Candidate] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


class LoopClosureDetector:
    """Stateful per-frame detector for one model bundle (not thread-safe)."""

    def __init__(self, bundle: DetectorModel, config: DetectorConfig | None = None) -> None:
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
        self._pending: deque[tuple[int, np.ndarray, PlaceKeypoints | None]] = deque()
        v = c.verification
        self.store: KeypointStore | None = None
        if v.enabled:
            desc_bytes = 32 if bundle.features.kind == "orb" else 128
            self.store = KeypointStore(desc_bytes, bundle.vocabulary_size, v.max_keypoints)
        self.temporal = TemporalFilter(c.temporal_frames, c.temporal_tolerance) if c.temporal_frames else None
        # place id -> sequence of the frame that made it / last sequence inserted or matched.
        self._place_frame = np.zeros(0, np.int64)
        self._last_used = np.zeros(0, np.int64)
        self._sequence = 0
        self._last_scores: np.ndarray | None = None
        # Frame sequence / stored frame of the last geometrically verified match (track prior).
        self._track_seq = -2
        self._track_frame = -1

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
        return self._place_frame[: self._id_range()]

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
        res = self.process_words(words, stamp_ns, feats)
        t3 = time.perf_counter()
        res.n_keypoints = len(feats)
        verify_ms = res.timings_ms.get("verification")
        res.timings_ms = {
            "features": (t1 - t0) * 1e3,
            "quantise": (t2 - t1) * 1e3,
            "inference": (t3 - t2) * 1e3 - (verify_ms or 0.0),
        }
        if verify_ms is not None:
            res.timings_ms["verification"] = verify_ms
        return res

    def process_words(self, words: np.ndarray, stamp_ns: int = 0, features: Features | None = None) -> FrameResult:
        """Score one frame given its keypoints' word ids, then queue it for delayed insertion.

        words: (N,) word id of every keypoint; features: the frame's keypoints (same order and
        count as words) for geometric verification. Without features the frame is neither
        verified nor stored for verifying later frames (verified is then always False).
        """
        seq = self._sequence
        self._sequence += 1
        inserted_frame = inserted_place = evicted = None
        while self._pending and self._pending[0][0] <= seq - self.config.exclude:
            inserted_frame, pending_words, pending_kps = self._pending.popleft()
            evicted = self._make_room()
            inserted_place = self._insert(pending_words, inserted_frame)
            if self.store is not None:
                # A reused id must not keep the keypoints of the place it belonged to before.
                self.store.remove(inserted_place)
                if pending_kps is not None:
                    self.store.put(inserted_place, pending_kps)
        uniq = np.unique(words)
        probability = llr = None
        p_places = loglik_new = None
        if self.fabmap is not None:
            loc = self.fabmap.localize(uniq, add=False)
            best, p_new = loc.best_place, loc.p_new
            if best is not None:
                probability = loc.best_probability
                llr = float(loc.loglik[best] - loc.loglik_new)
            score = (llr if self.config.fabmap_score == "llr" else probability) if best is not None else 0.0
            self._last_scores = loc.p_places
            ranking = loc.loglik
            p_places, loglik_new = loc.p_places, loc.loglik_new
        else:
            sims = self.bow.similarity(words)
            best = int(np.argmax(sims)) if sims.size else None
            score, p_new = (float(sims[best]) if best is not None else 0.0), None
            self._last_scores = sims
            ranking = sims
        loop = best is not None and score >= self.config.loop_threshold
        check = None
        query_kps = None
        if self.store is not None:
            if features is not None:
                if len(features) != words.size:
                    raise InputError(f"features ({len(features)}) and words ({words.size}) differ in count")
                query_kps = self.store.pack(features.keypoints, words, features.descriptors, features.image_shape)
            t0 = time.perf_counter()
            check = self._verify(features, words, ranking, seq)
            check.timing_ms = (time.perf_counter() - t0) * 1e3
            loop = check.verified
        if loop:
            self._last_used[check.place if check is not None else best] = seq
        self._pending.append((seq, words if self.bow is not None else uniq, query_kps))
        res = FrameResult(
            sequence=seq,
            stamp_ns=int(stamp_ns),
            n_keypoints=int(words.size),
            n_words=int(uniq.size),
            best_place=best,
            best_frame=int(self._place_frame[best]) if best is not None else None,
            score=float(score),
            p_new=p_new,
            loop=bool(loop),
            probability=probability,
            llr=llr,
            inserted_frame=inserted_frame,
            inserted_place=inserted_place,
            evicted_place=evicted,
            n_places=self.n_places,
        )
        if check is not None:
            check.fill(res, self._place_frame)
        res.candidates = self._candidates(ranking, p_places, loglik_new, check)
        return res

    def _candidates(self, ranking: np.ndarray, p_places, loglik_new, check: _Check | None) -> list[Candidate]:
        """The top places of `ranking` (log-likelihood or similarity) and every place checked."""
        finite = np.flatnonzero(np.isfinite(ranking))  # removed places are -inf
        k = min(self.config.verification.top_k, finite.size)
        top = finite[np.argpartition(-ranking[finite], k - 1)[:k]] if 0 < k < finite.size else finite
        top = [int(p) for p in top[np.argsort(-ranking[top], kind="stable")]]
        attempts = {pid: (source, g) for pid, source, g in (check.attempts if check is not None else [])}
        pids = top + [p for p in attempts if p not in top]
        out = []
        for pid in pids:
            c = Candidate(place=pid, frame=int(self._place_frame[pid]), rank=int(np.sum(ranking > ranking[pid])))
            if p_places is not None:
                c.probability = float(p_places[pid])
                c.llr = float(ranking[pid] - loglik_new)
            else:
                c.similarity = float(ranking[pid])
            if pid in attempts:
                c.source, g = attempts[pid]
                c.checked, c.verified = True, bool(g.verified)
                c.inliers, c.matches, c.model = int(g.inliers), int(g.matches), g.model
                nfa = getattr(g, "nfa", None)  # a chance figure, when the geometric check computes one
                c.nfa = None if nfa is None else float(nfa)
                c.inlier_points = g.inlier_points
            out.append(c)
        return out

    def _verify(self, features: Features | None, words: np.ndarray, ranking: np.ndarray, seq: int) -> "_Check":
        """Geometric (+ temporal) verification of one query.

        Candidates, in order, the first that passes is taken: the tracked places (stored frames
        following the previous query's verified match, `VerificationConfig.track`), then the
        top_k places by FAB-MAP log-likelihood, each failed one followed by its island
        neighbours (`VerificationConfig.island`). A place is verified at most once per query.
        """
        v = self.config.verification
        check = _Check()
        lag = seq - self._track_seq  # query frames since the last verified match
        expect = self._track_frame + lag if 1 <= lag <= v.track_memory else None
        if features is not None and len(features) and ranking.size:
            q_xy, q_desc, q_shape = features.keypoints, features.descriptors, features.image_shape
            tried: set[int] = set()
            cap = v.max_trials if v.max_trials is not None else np.inf

            def attempt(pid: int, source: str, bruteforce: bool = False) -> bool:
                if pid in tried or check.tried >= cap or not np.isfinite(ranking[pid]):
                    return False
                tried.add(pid)
                place = self.store.get(pid)
                if place is None or len(place) == 0:
                    return False
                check.tried += 1
                g = verify_pair(q_xy, words, q_desc, q_shape, place.xy, place.words, place.descriptors,
                                place.image_shape, v, bruteforce=bruteforce)
                check.attempts.append((int(pid), source, g))
                if check.best is None or g.verified or g.inliers > check.best.inliers:
                    check.best, check.best_place, check.source = g, int(pid), source
                return g.verified

            done = False
            if expect is not None and v.track:
                # Tracked places get the brute-force retry as well (`bruteforce_track`).
                for frame in [*range(expect, expect + v.track), expect - 1]:
                    if any(attempt(int(p), "track", v.bruteforce_track) for p in self._places_of_frames(frame, frame)):
                        done = True
                        break
            if not done:
                k = min(v.top_k, ranking.size)
                top = np.argpartition(-ranking, k - 1)[:k] if k < ranking.size else np.arange(ranking.size)
                top = top[np.argsort(-ranking[top], kind="stable")]
                for rank, pid in enumerate(top):
                    if not np.isfinite(ranking[pid]) or check.tried >= cap:
                        break  # removed places (-inf) sort last
                    if attempt(int(pid), "fabmap", rank < v.bruteforce_fallback):
                        break  # the first candidate that passes is taken: true loops cost one check
                    if v.island and rank < v.island_candidates and self._island_try(int(pid), v.island, attempt):
                        break
        check.geometry_ok = check.best is not None and check.best.verified
        check.verified = check.geometry_ok
        if self.temporal is not None:
            matched = int(self._place_frame[check.best_place]) if check.geometry_ok else None
            check.temporal_ok = self.temporal.update(matched)
            check.verified = check.geometry_ok and check.temporal_ok
        check.place = check.best_place if check.verified else None
        if check.geometry_ok:
            self._track_seq, self._track_frame = seq, int(self._place_frame[check.best_place])
        return check

    def _places_of_frames(self, lo: int, hi: int) -> np.ndarray:
        """Place ids (alive in the keypoint store) made by frames lo..hi, nearest to lo first."""
        frames = self._place_frame[: self._id_range()]
        pids = np.flatnonzero((frames >= lo) & (frames <= hi))
        pids = pids[np.argsort(frames[pids] - lo, kind="stable")]
        return np.array([p for p in pids if int(p) in self.store], np.int64)

    def _island_try(self, pid: int, radius: int, attempt) -> bool:
        """Try the stored temporal neighbours of place pid (within +-radius frames), nearest first."""
        f = int(self._place_frame[pid])
        frames = self._place_frame[: self._id_range()]
        pids = np.flatnonzero((np.abs(frames - f) <= radius) & (frames >= 0))
        pids = pids[np.argsort(np.abs(frames[pids] - f), kind="stable")]
        return any(attempt(int(p), "island") for p in pids if int(p) != pid)

    def _id_range(self) -> int:
        return self.fabmap.n_places if self.fabmap is not None else self.bow.n_places

    def _insert(self, words: np.ndarray, frame: int) -> int:
        pid = self.fabmap.add(words) if self.fabmap is not None else self.bow.add(words)
        if pid >= self._last_used.size:
            grow = max(64, self._last_used.size)
            self._last_used = np.concatenate([self._last_used, np.full(grow, -1, np.int64)])
            self._place_frame = np.concatenate([self._place_frame, np.full(grow, -1, np.int64)])
        self._last_used[pid] = frame
        self._place_frame[pid] = frame
        return pid

    def map_bytes(self) -> int:
        """Memory of the map (index postings, word lists, per-place arrays), in bytes.

        The one place where per-place memory is accounted: whatever else is kept per place
        (e.g. keypoints for verification) must be added here so that memory_mb holds.
        """
        index = self.fabmap.nbytes() if self.fabmap is not None else 0
        kps = self.store.nbytes() if self.store is not None else 0
        return index + self._last_used.nbytes + self._place_frame.nbytes + kps

    def _over_budget(self, extra_places: int = 1) -> bool:
        c = self.config
        if c.max_places is not None and self.n_places + extra_places > c.max_places:
            return True
        if c.memory_mb is not None and self.n_places > 0:
            # Leave room for one more place of the average size before inserting it.
            per_place = self.map_bytes() / self.n_places
            return self.map_bytes() + per_place > c.memory_mb * 2**20
        return False

    def _make_room(self) -> int | None:
        """Evict least-recently-used places until one more fits; returns the last evicted id."""
        evicted = None
        while self.fabmap is not None and self.n_places > 0 and self._over_budget():
            alive = self.fabmap.places.alive
            used = np.where(alive, self._last_used[: alive.size], np.iinfo(np.int64).max)
            evicted = int(np.argmin(used))
            self.fabmap.remove(evicted)
            if self.store is not None:
                self.store.remove(evicted)
        return evicted


@dataclass
class _Check:
    """Outcome of verifying one query (internal)."""

    best: GeometryResult | None = None
    best_place: int | None = None
    place: int | None = None
    tried: int = 0
    source: str | None = None
    geometry_ok: bool = False
    temporal_ok: bool | None = None
    verified: bool = False
    timing_ms: float = 0.0
    attempts: list = field(default_factory=list)  # (place id, source, GeometryResult) in order

    def fill(self, res: FrameResult, place_frame: np.ndarray) -> None:
        res.verified = bool(self.verified)
        res.geometry_ok = bool(self.geometry_ok)
        res.temporal_ok = self.temporal_ok
        res.candidates_tried = self.tried
        res.timings_ms["verification"] = self.timing_ms
        if self.best is not None:
            res.inliers, res.matches = int(self.best.inliers), int(self.best.matches)
            res.geometry_model = self.best.model
        if self.verified and self.place is not None:
            res.verified_place = int(self.place)
            res.verified_frame = int(place_frame[self.place])
            res.geometry = [[float(x) for x in row] for row in self.best.matrix]
