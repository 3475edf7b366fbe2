"""Per-frame loop-closure detection: features -> words -> FAB-MAP (or BoW) -> verification -> decision.

The core class every adapter shares (eval over image folders, the Zenoh node, MCAP replay).
It does no I/O: it takes decoded images and returns FrameResult records. What the frames
build (places, keypoints, insertion queue, caps, state) is its map
(runtime/aefabmap_runtime/core/map/place_map.py).
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Protocol

import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError, StateError
from aefabmap_runtime.core.kernels import compiled
from aefabmap_runtime.core.verify.acontrario import SAMPLE_SIZE
from aefabmap_runtime.core.kernels.bits import nearest_two_kernel
from aefabmap_runtime.core.rank.bow import BowIndex
from aefabmap_runtime.core.decide.candidates import CandidateConfig, CandidatePolicy, Search, tied_rival, top_places
from aefabmap_runtime.core.fleet.fleet_map import Fetch, FleetMap, RemoteMatch
from aefabmap_runtime.core.rank.fabmap import FabMap2, distinct_sorted
from aefabmap_runtime.core.features.feature_kinds import FeatureKind
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor, Features
from aefabmap_runtime.core.features.learned_description import LearnedDescription
from aefabmap_runtime.core.map.keypoint_store import KeypointStore, PlaceKeypoints
from aefabmap_runtime.core.map.map_events import MapListener
from aefabmap_runtime.core.map.place_map import Insertion, PlaceMap
from aefabmap_runtime.core.records.map_state import MapState
from aefabmap_runtime.core.records.messages import Candidate, FrameResult  # records live with the wire messages
from aefabmap_runtime.core.verify.model_errors import epipolar_kernel, transfer_kernel
from aefabmap_runtime.core.words.quantizer import quantize_raw
from aefabmap_runtime.core.rank.scorer import FABMAP_SCORES, BowScorer, FabMapScorer, Ranking, Scorer
from aefabmap_runtime.core.decide.sequence import Link, SequenceConfig, SequenceEvidence
from aefabmap_runtime.core.decide.temporal import TemporalFilter
from aefabmap_runtime.core.rank.tree import ChowLiuTree
from aefabmap_runtime.core.verify.verification import (
    NO_WORD,
    GeometryResult,
    VerificationConfig,
    distinct_kernel,
    independence_radius,
    more_significant,
    verify_pair,
    verify_pair_bruteforce,
)
from aefabmap_runtime.core.verify.word_matches import same_word_kernel

class TrainedModel(Protocol):
    """What the detector needs from a trained model (a bundle reader provides it).

    training_observations: list of sorted word-id arrays, the new-place model's samples.
    learned_description: the learned descriptor's projection (features.descriptor "learned"), else None.
    quantizer(variant, threads) -> an object with quantize((N, D) float32) -> (N,) word ids.
    """

    manifest: dict
    features: FeatureConfig
    tree: ChowLiuTree
    training_observations: list[np.ndarray]
    learned_description: LearnedDescription | None

    @property
    def vocabulary_size(self) -> int: ...

    @property
    def word_detection(self) -> dict: ...

    def quantizer(self, variant: str = "fp32", threads: int = 1): ...


SCORERS = ("fabmap", "bow")


@dataclass(frozen=True)
class DetectorConfig:
    """Settings of the per-frame detector.

    scorer: "fabmap" (FAB-MAP 2.0 probability) or "bow" (tf-idf cosine similarity).
    exclude: frames a frame waits before it enters the map (delayed insertion); also the
        exclusion window: a query never sees its `exclude` predecessors.
    loop_threshold: a loop is declared when the best place's score reaches this.
    quantizer_variant: "fp32" or "int8" (autoencoder bundles); "flat" searches a k-means bundle
        with an inverted index exhaustively instead; "flat-fp32" does so with a float32 product
        (binary kinds otherwise use an int8 product with an exact re-rank, the same words).
        threads: onnxruntime threads.
    motion_model, naive_bayes, smoothing: FAB-MAP options (docs/fabmap2.md).
    fabmap_score: what `score` holds with the fabmap scorer: "probability" (the normalised
        posterior P of the best place, docs/evaluation.md's FAB-MAP score) or "llr" (log-likelihood
        ratio of the best place against the new-place model, in nats: it keeps ranking frames
        where P has saturated at 0.99 + 0.01 / (n + 1)).
    max_places: hard cap of the map in places (None: unbounded).
    memory_mb: hard cap of the map's memory in MiB, as accounted by `map_bytes()` (None: unbounded).
        When either cap is reached the place least recently inserted or matched as a loop
        is evicted before a new one is added (with either scorer).
    verification: geometric verification of the best candidates (runtime/aefabmap_runtime/core/verify/verification.py);
        on by default. When enabled, `loop` means "verified" and loop_threshold is not used:
        the places `candidates` picks are checked whatever their score, because the posterior
        saturates and ranks better than it thresholds. Each place then keeps its keypoints
        (runtime/aefabmap_runtime/core/map/keypoint_store.py) inside memory_mb.
    candidates: which places a frame is verified against and in what order
        (runtime/aefabmap_runtime/core/decide/candidates.py: track prior, FAB-MAP's top_k, islands, the track's reach).
    sequence: evidence over consecutive frames (runtime/aefabmap_runtime/core/decide/sequence.py): when no single pair
        passes, a run of query frames whose checked places line up with a run of stored frames
        may pass together. SequenceConfig(frames=0) switches it off.
    temporal_frames: temporal consistency (runtime/aefabmap_runtime/core/decide/temporal.py): a verified match counts only
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
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    temporal_frames: int = 0
    temporal_tolerance: int = 10

    def __post_init__(self) -> None:
        if self.scorer not in SCORERS:
            raise ConfigError(f"scorer must be one of {SCORERS}, got {self.scorer!r}")
        if self.exclude < 0:
            raise ConfigError(f"exclude must be >= 0 frames, got {self.exclude}")
        # Also read back from logs (replay), so the types are checked, not assumed.
        if self.max_places is not None and (
            not isinstance(self.max_places, int) or isinstance(self.max_places, bool) or self.max_places < 1
        ):
            raise ConfigError(f"max_places must be an integer >= 1, got {str(self.max_places)[:40]}")
        if self.memory_mb is not None and (
            not isinstance(self.memory_mb, (int, float)) or isinstance(self.memory_mb, bool)
            or not math.isfinite(self.memory_mb) or self.memory_mb <= 0
        ):
            raise ConfigError(f"memory_mb must be a finite number > 0, got {str(self.memory_mb)[:40]}")
        if self.fabmap_score not in FABMAP_SCORES:
            raise ConfigError(f"fabmap_score must be one of {FABMAP_SCORES}, got {self.fabmap_score!r}")
        if self.threads < 1:
            raise ConfigError(f"threads must be >= 1, got {self.threads}")
        if not isinstance(self.verification, VerificationConfig):
            raise ConfigError(f"verification must be a VerificationConfig, got {type(self.verification).__name__}")
        if not isinstance(self.candidates, CandidateConfig):
            raise ConfigError(f"candidates must be a CandidateConfig, got {type(self.candidates).__name__}")
        if not isinstance(self.sequence, SequenceConfig):
            raise ConfigError(f"sequence must be a SequenceConfig, got {type(self.sequence).__name__}")
        if self.temporal_frames < 0 or self.temporal_tolerance < 0:
            raise ConfigError("temporal_frames and temporal_tolerance must be >= 0")
        if self.temporal_frames and not self.verification.enabled:
            raise ConfigError("temporal consistency works on verified matches: enable verification")

    def to_dict(self) -> dict:
        """Every setting as plain JSON types (nested configs as objects, tuples as lists): the
        form the map state records and RunConfig carries."""
        return json.loads(json.dumps(asdict(self)))


@dataclass(frozen=True)
class InputFormat:
    """What `process_words` takes (a map journal records and checks frames by it).

    kind: the feature kind of the descriptors (dtype, width). vocabulary_size: word ids lie in
    [0, vocabulary_size). observed_keypoints: the bundle's keypoint budget: FAB-MAP observes the
    words of the first ones (strongest first); keypoints beyond it carry NO_WORD.
    """

    kind: FeatureKind
    vocabulary_size: int
    observed_keypoints: int


@dataclass(frozen=True)
class PreparedFrame:
    """A frame's features and the word of every keypoint (`words_of`), computed before its turn
    (LoopClosureDetector.prepare). stages_ms: the times of those stages (features, quantise)."""

    features: Features
    words: np.ndarray
    stages_ms: dict[str, float]


@dataclass(frozen=True)
class Location:
    """Where one image is in the own map (LoopClosureDetector.locate): the verified place, its
    frame and the pair's geometry (with a calibrated camera, the image's pose in the place's
    camera frame), or None for each when no place verified; checked: the pair checks made."""

    place: int | None
    frame: int | None
    geometry: GeometryResult | None
    checked: int


class LoopClosureDetector:
    """Stateful per-frame detector for one model bundle (not thread-safe).

    A frame goes extract -> words -> rank -> candidates -> verify -> decide -> result over the
    detector's `map` (runtime/aefabmap_runtime/core/map/place_map.py: places, keypoints, insertion queue, caps, state).
    Adapters follow the map through listeners (`add_listener`) and may attach other robots'
    places as a second candidate source (`attach_remote`).
    """

    def __init__(self, bundle: TrainedModel, config: DetectorConfig | None = None) -> None:
        self.bundle = bundle
        self.config = config or DetectorConfig()
        c = self.config
        v = c.verification
        # FAB-MAP observes the strongest `max_features` keypoints, as the bundle was trained;
        # verification may extract and match more of them (VerificationConfig.keypoints).
        self._observed_keypoints = bundle.features.max_features
        extract = bundle.features
        if v.enabled and v.keypoints is not None and v.keypoints > extract.max_features:
            extract = replace(extract, max_features=v.keypoints)
        self.extractor = FeatureExtractor(extract, upright=v.enabled and v.upright, learned=bundle.learned_description)
        self._extractors = threading.local()  # each thread's extractor (`prepare`)
        # A frame's step and a `locate` read the map's index and keypoints: one at a time.
        self._map_lock = threading.Lock()
        self._extractors.extractor = self.extractor
        self.quantizer = bundle.quantizer(c.quantizer_variant, c.threads)
        self.kind = bundle.features.spec
        scorer = self._build_scorer()
        store = None
        if v.enabled:
            store = KeypointStore(self.kind, bundle.vocabulary_size, v.keypoints)
            # Verification's kernels: match counting and model errors for every kind, the two
            # matchers for binary ones.
            binary = (nearest_two_kernel, same_word_kernel) if self.kind.distance == "hamming" else ()
            compiled.prepare(distinct_kernel, transfer_kernel, epipolar_kernel, *binary)
        self.map = PlaceMap(scorer, store, scorer_name=c.scorer, vocabulary_size=int(bundle.vocabulary_size),
                            exclude=c.exclude, max_places=c.max_places, memory_mb=c.memory_mb)
        self.temporal = TemporalFilter(c.temporal_frames, c.temporal_tolerance) if c.temporal_frames else None
        self.chain = SequenceEvidence(c.sequence) if c.sequence.frames and v.enabled else None
        self._last_scores: np.ndarray | None = None
        self.policy = CandidatePolicy(c.candidates)
        self._remote: tuple[FleetMap, Fetch] | None = None

    def new_scorer(self) -> Scorer:
        """An empty scorer like the own map's; other robots' places get one each (fleet_map.py).
        A FAB-MAP scorer shares the own one's read-only tables and new-place model."""
        if isinstance(self.map.scorer, FabMapScorer):
            return FabMapScorer(self.map.scorer.fabmap.empty_like(), self.config.fabmap_score)
        return self._build_scorer()

    def _build_scorer(self) -> Scorer:
        """A new empty scorer of this detector's kind and settings, built from the bundle: the one
        place that knows which scorer it is (runtime/aefabmap_runtime/core/rank/scorer.py)."""
        c, bundle = self.config, self.bundle
        if c.scorer == "fabmap":
            det = bundle.word_detection
            fabmap = FabMap2(bundle.tree, bundle.training_observations, pzge=det["pzge"], pzgne=det["pzgne"],
                             smoothing=c.smoothing, naive_bayes=c.naive_bayes, motion_model=c.motion_model)
            return FabMapScorer(fabmap, c.fabmap_score)
        return BowScorer(BowIndex(bundle.vocabulary_size, bundle.training_observations))

    # -- the map, read through ---------------------------------------------------------------

    @property
    def manifest(self) -> dict:
        return self.bundle.manifest

    @property
    def input_format(self) -> InputFormat:
        return InputFormat(self.kind, self.map.vocabulary_size, self._observed_keypoints)

    @property
    def scorer(self) -> Scorer:
        """The map's place index."""
        return self.map.scorer

    @property
    def store(self) -> KeypointStore | None:
        """The map's keypoint store (None: verification off)."""
        return self.map.store

    @property
    def n_places(self) -> int:
        """Places in the map now."""
        return self.map.n_places

    @property
    def next_sequence(self) -> int:
        """Sequence number the next frame gets (frames continue across a saved state)."""
        return self.map.next_sequence

    @property
    def frames_inserted(self) -> int:
        """Frames that have entered the map since it was started (evicted ones included)."""
        return self.map.frames_inserted

    @property
    def map_epoch(self) -> int:
        """The map's epoch: names its frame numbering (PlaceMap.map_epoch)."""
        return self.map.map_epoch

    def last_scores(self) -> np.ndarray | None:
        """Scores of every place id (probability or similarity) from the last processed frame."""
        return self._last_scores

    def place_frames(self) -> np.ndarray:
        """(n_places,) sequence number of the frame that created each place id."""
        return self.map.place_frames()

    def map_bytes(self) -> int:
        """Memory of the map in bytes (PlaceMap.map_bytes: what memory_mb caps)."""
        return self.map.map_bytes()

    # -- followers and the second candidate source -------------------------------------------

    def add_listener(self, listener: MapListener) -> None:
        """Tell `listener` of every frame and map change from now on (core/map/map_events.py)."""
        self.map.listeners.add(listener)

    def remove_listener(self, listener: MapListener) -> None:
        self.map.listeners.remove(listener)

    def attach_remote(self, places: FleetMap, fetch: Fetch) -> None:
        """Make other robots' places a second candidate source: a frame the own map verified
        nothing for (and with keypoints enough to verify with) is matched against `places`
        (FleetMap.match; built with `new_scorer` and `map.room`), whose keypoints `fetch` gets
        (several places at once, within one deadline);
        its result then carries that robot's verified place. ConfigError without verification."""
        if self.map.store is None:
            raise ConfigError("other robots' places need verification: they are verified before they count")
        self._remote = (places, fetch)

    def detach_remote(self, places: FleetMap | None = None) -> None:
        """Stop asking the remote source (only when it is `places`, if given)."""
        if self._remote is not None and (places is None or self._remote[0] is places):
            self._remote = None

    # -- a frame -----------------------------------------------------------------------------

    def words_of(self, features: Features) -> np.ndarray:
        """Word id of every keypoint (N,) int64 (repeats kept): the bundle's keypoint budget (the
        first `features.max_features`, strongest first) is quantised; keypoints beyond it, kept
        for verification only, get NO_WORD (the brute-force retry matches them)."""
        n = min(len(features), self._observed_keypoints)
        words = np.full(len(features), NO_WORD, np.int64)
        if n:
            words[:n] = quantize_raw(self.quantizer, self.kind, features.descriptors[:n])
        return words

    def attach_keypoints(self, place: int, features: Features, words: np.ndarray) -> None:
        """Give a stored place the keypoints of `features` (words: their `words_of`), replacing
        any it held. For tools that build a map from words alone (`process_words` without
        features stores no keypoints, and a place without keypoints is never verified), such as
        the pipeline benchmark, whose stored places must be verified as a live map's are."""
        if self.map.store is None:
            raise ConfigError("verification is off: this detector stores no keypoints")
        if not self.map.holds(place):
            raise InputError(f"place {place} is not in the map")
        self.map.store.put(place, self._pack(features, words))

    def process(self, image: np.ndarray, stamp_ns: int = 0) -> FrameResult:
        """Run one grayscale (H, W) uint8 image through the detector."""
        self.map.listeners.before_frame()
        frame = self._prepare(image, self.extractor)
        return self._step(frame.words, stamp_ns, frame.features, dict(frame.stages_ms))

    def prepare(self, image: np.ndarray) -> PreparedFrame:
        """The part of `process` that needs no map: the image's features and words. Thread-safe
        (each thread extracts with its own extractor), so frames can be prepared ahead on other
        threads and then taken in order by `process_prepared`, with the results `process` gives.
        Raises InputError for an image the extractor refuses."""
        extractor = getattr(self._extractors, "extractor", None)
        if extractor is None:
            extractor = self._extractors.extractor = FeatureExtractor(self.extractor.config, self.extractor.upright,
                                                                      self.extractor.learned)
        return self._prepare(image, extractor)

    def process_prepared(self, frame: PreparedFrame, stamp_ns: int = 0) -> FrameResult:
        """The rest of `process` for a frame `prepare` gave (frames in the order they were taken)."""
        self.map.listeners.before_frame()
        return self._step(frame.words, stamp_ns, frame.features, dict(frame.stages_ms))

    def refuse_prepared(self) -> None:
        """A frame `prepare` refused takes its turn: the map's listeners hear of it as of any frame
        (`process` tells them before it extracts)."""
        self.map.listeners.before_frame()

    def _prepare(self, image: np.ndarray, extractor: FeatureExtractor) -> PreparedFrame:
        t0 = time.perf_counter()
        feats = extractor.extract(image)
        t1 = time.perf_counter()
        words = self.words_of(feats)
        t2 = time.perf_counter()
        return PreparedFrame(feats, words, {"features": (t1 - t0) * 1e3, "quantise": (t2 - t1) * 1e3})

    def process_words(self, words: np.ndarray, stamp_ns: int = 0, features: Features | None = None) -> FrameResult:
        """Score one frame given its keypoints' word ids, then queue it for delayed insertion.

        words: (N,) word id of every keypoint (NO_WORD beyond the bundle's budget, see
        `words_of`); features: the frame's keypoints (same order and count as words, strongest
        first) for geometric verification. Without features the frame is neither verified nor
        stored for verifying later frames (verified is then always False). With features,
        FAB-MAP observes the words of the bundle's keypoint budget (the first
        `features.max_features`); verification uses every keypoint.
        """
        self.map.listeners.before_frame()
        return self._step(words, stamp_ns, features, None)

    def locate(self, frame: PreparedFrame) -> Location:
        """Where a prepared image (`prepare`) is in the own map, changing nothing: no frame
        number, no track, no insertion, no listener hears of it. FAB-MAP's best `top_k` places
        are each verified by words and, failing that, all-pairs, against a bar stricter by the
        log10 of the pair checks; the most significant verified place wins. Safe beside the
        frames' own steps (one at a time)."""
        with self._map_lock:
            observed = frame.words[: self._observed_keypoints]
            order = self.map.scorer.rank(observed).order
            top = [int(p) for p in top_places(order, self.config.candidates.top_k) if np.isfinite(order[p])]
            held = [(p, self.map.keypoints(p)) for p in top if self.map.holds(p)]
            held = [(p, kps) for p, kps in held if kps is not None and len(kps)]
            checks = max(2 * len(held), 1)
            v = self.config.verification
            check = self.place_check(frame.features, frame.words,
                                     replace(v, max_log10_nfa=v.max_log10_nfa - math.log10(checks)))
            best: tuple[int, GeometryResult] | None = None
            for place, kps in held:
                g = check(kps, False)
                if not g.verified:
                    g = check(kps, False, True)
                if g.verified and (best is None or g.nfa < best[1].nfa):
                    best = (place, g)
            if best is None:
                return Location(None, None, None, 2 * len(held))
            return Location(best[0], int(self.map.place_frames()[best[0]]), best[1], 2 * len(held))

    def _step(self, words: np.ndarray, stamp_ns: int, features: Features | None,
              stages: dict[str, float] | None) -> FrameResult:
        """One frame under the map's lock (see `locate`): `_step_locked`."""
        with self._map_lock:
            return self._step_locked(words, stamp_ns, features, stages)

    def _step_locked(self, words: np.ndarray, stamp_ns: int, features: Features | None,
                     stages: dict[str, float] | None) -> FrameResult:
        """One frame: insert the frames now due, rank, verify, decide, queue this frame, build its
        result. stages: times of the stages before (process()); then the result's timings gain
        inference."""
        t0 = time.perf_counter()
        if features is not None and len(features) != words.size:
            raise InputError(f"features ({len(features)}) and words ({words.size}) differ in count")
        observed = words[: self._observed_keypoints] if features is not None else words
        self.map.listeners.frame_taken(self.map.next_sequence, words, int(stamp_ns), features)
        seq, inserted = self.map.begin_frame()
        ranked = self.map.scorer.rank(observed)
        top = top_places(ranked.order, self.config.candidates.top_k)  # verification and evidence share it
        self._last_scores = ranked.scores
        query_kps = self._pack(features, words) if self.map.store is not None and features is not None else None
        verdict = self._verify(seq, features, words, ranked.order, top) if self.map.store is not None else None
        loop = self._decide(seq, ranked, verdict)
        self.map.queue(seq, observed, query_kps)
        remote_ms = self._match_remote(seq, observed, features, words, verdict)
        timings = _timings(stages, t0, verdict, remote_ms)
        return self._result(seq, stamp_ns, len(features) if features is not None else int(words.size),
                            observed, ranked, top, inserted, loop, verdict, timings)

    def _pack(self, features: Features, words: np.ndarray) -> PlaceKeypoints:
        return self.map.store.pack(features.keypoints, words, features.descriptors, features.image_shape,
                                   features.upright)

    def _decide(self, seq: int, ranked: Ranking, verdict: "_Verdict | None") -> bool:
        """Whether query `seq` closes a loop onto an own place: verified, or without verification
        the best score reaching loop_threshold. That place counts as used now (the caps evict
        the least recently used)."""
        if verdict is not None:
            loop, place = verdict.verified, verdict.place
        else:
            loop, place = ranked.best is not None and ranked.score >= self.config.loop_threshold, ranked.best
        if loop:
            self.map.mark_used(place, seq)
        return loop

    def _verify(self, seq: int, features: Features | None, words: np.ndarray, ranking: np.ndarray,
                top: np.ndarray) -> "_Verdict":
        """Geometric (+ temporal) verification of query `seq`: the candidate policy picks the
        places (runtime/aefabmap_runtime/core/decide/candidates.py), `verify_pair` judges each pair."""
        t0 = time.perf_counter()
        verdict = _Verdict()
        frames = self.map.place_frames()
        if features is not None and ranking.size and len(features) <= SAMPLE_SIZE["H"]:
            verdict.reason = "no_evidence"  # texture-poor frame: nothing to verify with
        elif features is not None and len(features) and ranking.size:
            verdict.search = self.policy.search(seq, top, ranking, frames, self.map.store.__contains__,
                                                self._pair_check(features, words))
        best = verdict.search.best
        verdict.geometry_ok = best is not None and bool(best.verified)
        if verdict.geometry_ok and tied_rival(verdict.search, frames, self.policy.config.margin_log10_nfa):
            verdict.geometry_ok, verdict.reason = False, "tie"  # which stored frame is a coin toss
        if self.chain is not None:
            self._chain_step(verdict, frames)
        verdict.verified = verdict.geometry_ok
        if self.temporal is not None:
            matched = int(frames[verdict.search.best_place]) if verdict.geometry_ok else None
            verdict.temporal_ok = self.temporal.update(matched)
            verdict.verified = verdict.geometry_ok and verdict.temporal_ok
        verdict.place = verdict.search.best_place if verdict.verified else None
        if verdict.geometry_ok:
            c = self.policy.config
            self.policy.track.confirm(seq, int(frames[verdict.search.best_place]), c.track_memory, c.track_reach)
        verdict.timing_ms = (time.perf_counter() - t0) * 1e3
        return verdict

    def _chain_step(self, verdict: "_Verdict", frames: np.ndarray) -> None:
        """Record this query's checked places as chain links; when no single pair passed, take the
        place ending the most significant accepted chain (runtime/aefabmap_runtime/core/decide/sequence.py)."""
        attempts = verdict.search.attempts
        links = [Link(a.place, int(frames[a.place]), float(a.result.nfa)) for a in attempts
                 if np.isfinite(a.result.nfa)]
        chain = self.chain.update(links)
        if verdict.geometry_ok or chain is None:
            return
        link, total = chain
        verdict.search.best = min((a.result for a in attempts if a.place == link.place), key=lambda g: g.nfa)
        verdict.search.best_place = link.place
        verdict.geometry_ok, verdict.sequence_nfa = True, total

    def _match_remote(self, seq: int, observed: np.ndarray, features: Features | None, words: np.ndarray,
                      verdict: "_Verdict | None") -> float | None:
        """The second candidate source (attach_remote): when the own map verified nothing and the
        query has keypoints enough to verify with, the most significant verified place of
        another robot goes into the verdict; then the remote places are fitted into the room the
        own map leaves. Returns the time taken (ms), None without a remote source."""
        if self._remote is None or verdict is None:
            return None
        t0 = time.perf_counter()
        places, fetch = self._remote
        if not verdict.verified and features is not None and len(features) > SAMPLE_SIZE["H"]:
            v = self.config.verification
            verdict.remote = places.match(
                observed, lambda bar: self.place_check(features, words, replace(v, max_log10_nfa=bar)),
                fetch, v.max_log10_nfa, seq)
        places.fit()
        return (time.perf_counter() - t0) * 1e3

    def _pair_check(self, features: Features, words: np.ndarray):
        """The policy's PairCheck for this query: verify it against one stored place."""
        verify = self.place_check(features, words)

        def check(pid: int, bruteforce: bool, retry_only: bool, upright: bool) -> GeometryResult | None:
            place = self.map.store.get(pid)
            if place is None or len(place) == 0:
                return None
            return verify(place, bruteforce, retry_only, upright)

        return check

    def place_check(self, features: Features, words: np.ndarray, verification: VerificationConfig | None = None):
        """check(place, bruteforce, retry_only, upright=False) -> GeometryResult: this query
        (features, its `words_of`) verified against the keypoints of a place (PlaceKeypoints), ours
        or another robot's; retry_only: all-pairs matching alone (the reach's retry); upright: a
        failed all-pairs retry is retried with the upright descriptors when both sides have them.
        verification: other settings than the detector's (a stricter bar for other robots' places)."""
        v = self.config.verification if verification is None else verification
        q_xy, q_desc, q_shape = features.keypoints, features.descriptors, features.image_shape
        radius = independence_radius(self.kind.window_radius(features.sizes), v)
        distance = self.kind.distance

        def check(place: PlaceKeypoints, bruteforce: bool, retry_only: bool = False,
                  upright: bool = False) -> GeometryResult:
            q_up, p_up = (features.upright, place.upright) if upright else (None, None)
            if retry_only:
                return verify_pair_bruteforce(q_xy, q_desc, q_shape, place.xy, place.descriptors, place.image_shape,
                                              v, distance=distance, radius=radius, q_upright=q_up, p_upright=p_up)
            return verify_pair(q_xy, words, q_desc, q_shape, place.xy, place.words, place.descriptors,
                               place.image_shape, v, bruteforce=bruteforce, distance=distance, radius=radius,
                               q_upright=q_up, p_upright=p_up)

        return check

    # -- the result --------------------------------------------------------------------------

    def _result(self, seq: int, stamp_ns: int, n_keypoints: int, observed: np.ndarray, ranked: Ranking,
                top: np.ndarray, inserted: Insertion, loop: bool, verdict: "_Verdict | None",
                timings: dict[str, float]) -> FrameResult:
        """The frame's FrameResult, built in one place (a loop to another robot's place included)."""
        best = ranked.best
        frames = self.map.place_frames()
        geometry = _verdict_fields(verdict, frames) if verdict is not None else {}
        return FrameResult(
            sequence=seq,
            stamp_ns=int(stamp_ns),
            n_keypoints=int(n_keypoints),
            n_words=int(distinct_sorted(np.asarray(observed)).size),
            best_place=best,
            best_frame=int(frames[best]) if best is not None else None,
            score=float(ranked.score),
            p_new=ranked.p_new,
            loop=bool(loop or (verdict is not None and verdict.remote is not None)),
            probability=ranked.probability,
            llr=ranked.llr,
            inserted_frame=inserted.frame,
            inserted_place=inserted.place,
            evicted_place=inserted.evicted,
            n_places=self.n_places,
            score_kind=self.config.fabmap_score if self.config.scorer == "fabmap" else "similarity",
            timings_ms=timings,
            candidates=self._candidates(ranked, top, verdict.search if verdict is not None else None, frames),
            **geometry,
        )

    def _candidates(self, ranked: Ranking, top_places: np.ndarray, search: Search | None,
                    frames: np.ndarray) -> list[Candidate]:
        """The top places of the ranking (log-likelihood or similarity) and every place checked."""
        ranking = ranked.order
        top = [int(p) for p in top_places if np.isfinite(ranking[p])]  # removed places are -inf
        # A place checked twice (same-word, then the reach's retry) shows its last source and its
        # most significant result.
        attempts: dict[int, tuple] = {}
        for a in search.attempts if search is not None else []:
            prev = attempts[a.place][1] if a.place in attempts else None
            attempts[a.place] = (a.source, a.result if more_significant(a.result, prev) else prev)
        pids = top + [p for p in attempts if p not in top]
        out = []
        for pid in pids:
            c = Candidate(place=pid, frame=int(frames[pid]), rank=int(np.sum(ranking > ranking[pid])))
            if ranked.loglik_new is not None:  # FAB-MAP: order is the log-likelihood
                c.probability = float(ranked.scores[pid])
                c.llr = float(ranking[pid] - ranked.loglik_new)
            else:
                c.similarity = float(ranking[pid])
            if pid in attempts:
                c.source, g = attempts[pid]
                c.checked, c.verified = True, bool(g.verified)
                c.inliers, c.matches, c.model = int(g.inliers), int(g.matches), g.model
                c.nfa = float(g.nfa) if np.isfinite(g.nfa) else None
                c.inlier_points = None if g.inlier_points is None else g.inlier_points.tolist()
            out.append(c)
        return out

    # -- state -------------------------------------------------------------------------------

    def state(self) -> MapState:
        """The whole map as arrays + scalars (runtime/aefabmap_runtime/core/records/map_state.py; the keypoints are packed by
        ``MapState.resolve()``, e.g. in the thread that writes them): the map's (PlaceMap.state),
        the track prior, the temporal and chain history and the settings. Loading it (load_state)
        into a detector on the same bundle and settings continues the run with bit-identical
        results."""
        st = self.map.state()
        st.scalars.update(track_seq=self.policy.track.seq, track_frame=self.policy.track.frame,
                          track_anchor=self.policy.track.anchor, track_direction=self.policy.track.direction,
                          # The settings the map was built with, whole (JSON; RunConfig's detector part).
                          config=json.dumps(self.config.to_dict(), sort_keys=True))
        if self.temporal is not None:
            st.put("temporal", self.temporal.state())
        if self.chain is not None:
            st.put("chain", self.chain.state())
        return st

    def load_state(self, st: MapState) -> None:
        """Replace the map by a checked state (see state()); raises StateError on any mismatch
        with this detector's bundle or settings, or an array out of shape or bounds."""

        def track(seq: int) -> tuple[int, int]:
            return st.scalar("track_seq", int, lo=-2, hi=seq), st.scalar("track_frame", int, lo=-1, hi=max(seq, 1))

        learn = self.policy.track.learn
        # A map saved before the track had a direction ran forwards and learnt none: its track
        # goes on as one that starts at its last match.
        directed = "track_direction" in st.scalars
        direction = st.scalar("track_direction", int, lo=-1, hi=2) if directed else (0 if learn else 1)
        if not learn and direction != 1:
            raise StateError("map state: the track's direction does not fit this detector's settings (forwards only)")
        track_seq, track_frame = self.map.load_state(st, track)
        anchor = st.scalar("track_anchor", int, lo=-1, hi=max(track_seq, 1)) if directed else track_frame
        if self.temporal is not None:
            self.temporal.load_state(st.part("temporal"))
        if self.chain is not None:
            chain = st.part("chain")
            if chain.arrays:
                self.chain.load_state(chain)
            else:  # a map saved without chains (another setting, an older version) starts with none
                self.chain.reset()
        self.policy.track.seq, self.policy.track.frame = track_seq, track_frame
        self.policy.track.anchor, self.policy.track.direction = anchor, direction
        self._last_scores = None


@dataclass
class _Verdict:
    """Verification of one query (internal): the policy's search, then the temporal check; a
    verified place of another robot (`remote`) when the own map verified nothing."""

    search: Search = field(default_factory=Search)
    geometry_ok: bool = False
    temporal_ok: bool | None = None
    verified: bool = False
    place: int | None = None
    timing_ms: float = 0.0
    reason: str | None = None
    sequence_nfa: float | None = None
    remote: RemoteMatch | None = None


def _timings(stages: dict[str, float] | None, t0: float, verdict: _Verdict | None, remote_ms: float | None
             ) -> dict[str, float]:
    """The result's timings (ms): the stages before (process(): features, quantise), inference
    (the step since t0 less verification and the remote match), verification, remote."""
    timings = {} if stages is None else dict(stages)
    verify_ms = verdict.timing_ms if verdict is not None else 0.0
    if stages is not None:
        timings["inference"] = (time.perf_counter() - t0) * 1e3 - verify_ms - (remote_ms or 0.0)
    if verdict is not None:
        timings["verification"] = verify_ms
    if remote_ms is not None:
        timings["remote"] = remote_ms
    return timings


def _verdict_fields(verdict: _Verdict, place_frame: np.ndarray) -> dict:
    """FrameResult's verification fields: the own map's verdict, or the remote match that
    replaces it (then the own search's tries and sequence evidence stay)."""
    best = verdict.search.best
    out = dict(verified=bool(verdict.verified), geometry_ok=bool(verdict.geometry_ok), temporal_ok=verdict.temporal_ok,
               candidates_tried=verdict.search.tried, geometry_reason=verdict.reason, sequence_nfa=verdict.sequence_nfa)
    if best is not None:
        out.update(inliers=int(best.inliers), matches=int(best.matches), geometry_model=best.model,
                   nfa=float(best.nfa) if np.isfinite(best.nfa) else None,
                   geometry_reason="" if verdict.verified else verdict.reason or (
                       "temporal" if best.verified or verdict.sequence_nfa is not None else best.reason))
    if verdict.verified and verdict.place is not None:
        out.update(verified_place=int(verdict.place), verified_frame=int(place_frame[verdict.place]),
                   **_pose_fields(best))
    if verdict.remote is not None:
        g = verdict.remote.geometry
        out.update(verified=True, geometry_ok=True, temporal_ok=None, verified_robot=verdict.remote.robot,
                   verified_frame=verdict.remote.frame, verified_place=None, inliers=int(g.inliers),
                   matches=int(g.matches), geometry_model=g.model, nfa=float(g.nfa), geometry_reason="",
                   **_pose_fields(g))
    return out


def _pose_fields(g: GeometryResult) -> dict:
    """The verified pair's model matrix and, when calibrated, the relative pose (plain lists)."""
    out = {"geometry": [[float(x) for x in row] for row in g.matrix]}
    if g.rotation is not None and g.translation is not None:
        out.update(relative_rotation=[[float(x) for x in row] for row in g.rotation],
                   relative_translation=[float(x) for x in g.translation])
    return out
