"""What the detector and its map tell the adapters that follow them (pure).

An adapter that records frames (the map journal) or offers the places to other robots (the
fleet) attaches a `MapListener` to the detector (`LoopClosureDetector.add_listener`) instead of
reading the detector's insides. Every call comes from the thread that processes frames, in this
order for one frame: `before_frame`, `frame_taken`, then `place_evicted` / `place_inserted` as
the frames whose delay has passed enter the map (runtime/aefabmap_runtime/core/map/place_map.py).
A listener must not raise: the frame is being processed.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from aefabmap_runtime.core.features.features import Features
from aefabmap_runtime.core.map.keypoint_store import PlaceKeypoints


class MapListener(Protocol):
    """The events of a detector's map; subclass it and override the ones needed (the others do nothing)."""

    def before_frame(self) -> None:
        """A frame is about to be processed (even one the detector then refuses)."""

    def frame_taken(self, sequence: int, words: np.ndarray, stamp_ns: int, features: Features | None) -> None:
        """The detector took frame `sequence`: words (N,) int64 of every keypoint (NO_WORD beyond the
        bundle's budget), its stamp (ns) and its keypoints (None: words alone). Enough to replay
        it with `process_words`."""

    def place_inserted(self, place: int, frame: int, words: np.ndarray, keypoints: PlaceKeypoints | None) -> None:
        """Frame `frame` entered the map as place id `place`: its observed words (M,) int64
        (repeats kept) and its stored keypoints (None: the place keeps none)."""

    def place_evicted(self, place: int) -> None:
        """Place id `place` left the map (a cap); the id may be reused by a later insertion."""

    def map_loaded(self) -> None:
        """The whole map was replaced by a loaded state (places, frame numbers and map epoch)."""


class MapListeners:
    """The listeners attached to one map, each told every event in the order they were added."""

    def __init__(self) -> None:
        self._all: list[MapListener] = []

    def add(self, listener: MapListener) -> None:
        if not any(held is listener for held in self._all):
            self._all.append(listener)

    def remove(self, listener: MapListener) -> None:
        """Detach `listener` (no-op when it is not attached)."""
        self._all = [held for held in self._all if held is not listener]

    def before_frame(self) -> None:
        for listener in self._all:
            listener.before_frame()

    def frame_taken(self, sequence: int, words: np.ndarray, stamp_ns: int, features: Features | None) -> None:
        for listener in self._all:
            listener.frame_taken(sequence, words, stamp_ns, features)

    def place_inserted(self, place: int, frame: int, words: np.ndarray, keypoints: PlaceKeypoints | None) -> None:
        for listener in self._all:
            listener.place_inserted(place, frame, words, keypoints)

    def place_evicted(self, place: int) -> None:
        for listener in self._all:
            listener.place_evicted(place)

    def map_loaded(self) -> None:
        for listener in self._all:
            listener.map_loaded()
