"""Compact per-place keypoint store for geometric verification (pure, in memory).

Per place one numpy structured array, one record per keypoint:

========= ================= =========================================================
field     type              meaning
========= ================= =========================================================
xy        2 x uint16        position as a fraction of the image's longer side, in
                            units of 1/65535 (0.01 px at 640 px, 0.06 px at 4000 px)
word      uint16 / int32    visual word id (uint16 when the vocabulary has < 65536 words);
                            a keypoint kept for geometry only (verification.NO_WORD) is
                            stored as the type's largest value (uint16) or -1 (int32)
desc      B x uint8         the feature kind's store form (FeatureKind.compress):
                            ORB's 32 bytes as extracted; SIFT's 128 floats rescaled
                            per row to uint8
========= ================= =========================================================

So an ORB keypoint costs 4 + 2 + 32 = 38 bytes (1000 keypoints, the verification default:
38 000 bytes per place) and a SIFT keypoint 134 bytes, plus PLACE_OVERHEAD_BYTES per place for
the array header, the image shape and the dictionary slot. A place may also hold the upright
descriptors of its keypoints (`PlaceKeypoints.upright`, same store form: 32 more bytes per ORB
keypoint), which the brute-force retry matches when the oriented ones fail. `nbytes()` is kept
as a running total so the detector's memory cap can ask for it on every insertion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import InputError, StateError
from aefabmap_runtime.core.features.feature_kinds import FeatureKind
from aefabmap_runtime.core.records.map_state import MapState, check_ptr, pack_ragged
from aefabmap_runtime.core.verify.verification import NO_WORD

# numpy array header (~112 B) + PlaceKeypoints object + dict slot + shape tuple, rounded up.
PLACE_OVERHEAD_BYTES = 256
# uint16 code of NO_WORD (vocabularies up to 65535 words store word ids as uint16).
_NO_WORD_UINT16 = 65535
_XY_SCALE = 65535.0


@dataclass
class PlaceKeypoints:
    """Keypoints of one frame in store form.

    records: structured (K,) array with fields xy (uint16 x2), word, desc (see module doc).
    image_shape: (height, width) of the original image in pixels.
    upright: None, or (K, B) uint8: the keypoints' upright descriptors in store form
        (`Features.upright`).
    """

    records: np.ndarray
    image_shape: tuple[int, int]
    upright: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.records.shape[0])

    @property
    def xy(self) -> np.ndarray:
        """(K, 2) float32 positions in original pixels."""
        return self.records["xy"].astype(np.float32) * np.float32(max(self.image_shape) / _XY_SCALE)

    @property
    def words(self) -> np.ndarray:
        """(K,) int64 word ids (NO_WORD for keypoints kept for geometry only)."""
        w = self.records["word"].astype(np.int64)
        if self.records.dtype["word"] == np.uint16:
            w[w == _NO_WORD_UINT16] = NO_WORD
        return w

    @property
    def descriptors(self) -> np.ndarray:
        """(K, D) uint8 stored descriptors."""
        return self.records["desc"]

    @property
    def nbytes(self) -> int:
        upright = 0 if self.upright is None else int(self.upright.nbytes)
        return int(self.records.nbytes) + upright + PLACE_OVERHEAD_BYTES


class KeypointStore:
    """place id -> PlaceKeypoints, with a running byte count.

    kind: the FeatureKind of the descriptors: their store form and bytes (`store_bytes`).
    vocabulary_size: decides the word-id type (uint16 up to 65536 words, else int32).
    max_keypoints: keep at most this many keypoints per place (the first ones: the extractor
        orders them strongest first); None keeps all.
    """

    def __init__(self, kind: FeatureKind, vocabulary_size: int, max_keypoints: int | None = None) -> None:
        if not isinstance(kind, FeatureKind):
            raise InputError(f"kind must be a FeatureKind, got {type(kind).__name__}")
        self.kind = kind
        word_type = np.uint16 if vocabulary_size <= _NO_WORD_UINT16 else np.int32
        self.dtype = np.dtype([("xy", np.uint16, (2,)), ("word", word_type), ("desc", np.uint8, (kind.store_bytes,))])
        # How NO_WORD is stored in the word field.
        self._no_word = _NO_WORD_UINT16 if word_type == np.uint16 else NO_WORD
        self.max_keypoints = max_keypoints
        self.vocabulary_size = vocabulary_size
        self._places: dict[int, PlaceKeypoints] = {}
        self._nbytes = 0

    @property
    def bytes_per_keypoint(self) -> int:
        return int(self.dtype.itemsize)

    @property
    def no_word_code(self) -> int:
        """How a keypoint without a word is stored in the word field."""
        return int(self._no_word)

    def pack(self, keypoints: np.ndarray, words: np.ndarray, descriptors: np.ndarray, image_shape,
             upright: np.ndarray | None = None) -> PlaceKeypoints:
        """Build the store form of one frame (not yet stored; see `put`).

        keypoints: (N, 2) float positions in original pixels; words: (N,) ids;
        descriptors: (N, width) raw descriptors of the store's kind; image_shape: (height, width);
        upright: None or (N, width) upright descriptors of the same keypoints (`Features.upright`).
        """
        n = int(keypoints.shape[0])
        if words.shape[0] != n or descriptors.shape[0] != n or (upright is not None and upright.shape[0] != n):
            ups = "" if upright is None else f", upright descriptors ({upright.shape[0]})"
            raise InputError(f"keypoints ({n}), words ({words.shape[0]}), descriptors ({descriptors.shape[0]}){ups} "
                             "differ in count")
        if self.max_keypoints is not None:
            n = min(n, self.max_keypoints)
        shape = (int(image_shape[0]), int(image_shape[1]))
        rec = np.zeros(n, self.dtype)
        if n:
            scale = _XY_SCALE / max(max(shape), 1)
            rec["xy"] = np.clip(np.rint(np.asarray(keypoints[:n], np.float64) * scale), 0, _XY_SCALE)
            w = np.asarray(words[:n], np.int64)
            rec["word"] = np.where(w == NO_WORD, self._no_word, w)
            rec["desc"] = self.kind.compress(descriptors[:n])
        up = None
        if upright is not None:
            up = np.ascontiguousarray(self.kind.compress(upright[:n]), np.uint8).reshape(n, self.kind.store_bytes)
        return PlaceKeypoints(rec, shape, up)

    def put(self, place_id: int, place: PlaceKeypoints) -> None:
        """Store (or replace) the keypoints of a place."""
        self.remove(place_id)
        self._places[int(place_id)] = place
        self._nbytes += place.nbytes

    def get(self, place_id: int) -> PlaceKeypoints | None:
        return self._places.get(int(place_id))

    def remove(self, place_id: int) -> None:
        """Forget a place (no-op when absent): evicted places must leave the store."""
        old = self._places.pop(int(place_id), None)
        if old is not None:
            self._nbytes -= old.nbytes

    def __len__(self) -> int:
        return len(self._places)

    def __contains__(self, place_id: int) -> bool:
        return int(place_id) in self._places

    def place_ids(self) -> list[int]:
        """The ids of the places stored, in the order they were put."""
        return list(self._places)

    def state(self) -> MapState:
        """Stored places as arrays: ids (P,), their keypoints packed (pack_places).

        Deferred (MapState.resolve): only references are taken now; records are never changed
        in place once stored (put replaces, remove drops), so packing them later is safe."""
        places = list(self._places.items())

        def pack() -> MapState:
            st = self.pack_places([p for _, p in places])
            st.arrays["place_ids"] = np.array([pid for pid, _ in places], np.int64)
            return st

        return MapState(deferred=[("", pack)])

    def pack_places(self, places: list[PlaceKeypoints | None]) -> MapState:
        """Keypoints of several places (None: a frame without keypoints kept) as flat arrays:
        has (P,) bool, image_shape (P, 2), ptr (P + 1,), xy (K, 2) uint16, word (K,), desc (K, B) uint8;
        has_upright (P,) bool and upright (U, B) uint8: the upright descriptors of the places that
        have them, in place order (each place's rows as many as its keypoints)."""
        st = MapState()
        st.arrays["has"] = np.array([p is not None for p in places], bool)
        st.arrays["image_shape"] = np.array([p.image_shape if p is not None else (0, 0) for p in places], np.int64).reshape(-1, 2)
        st.arrays["ptr"], rec = pack_ragged([None if p is None else p.records for p in places], self.dtype)
        st.arrays["xy"], st.arrays["word"], st.arrays["desc"] = rec["xy"].copy(), rec["word"].copy(), rec["desc"].copy()
        ups = [None if p is None else p.upright for p in places]
        st.arrays["has_upright"] = np.array([u is not None for u in ups], bool)
        parts = [u for u in ups if u is not None and len(u)]
        st.arrays["upright"] = np.concatenate(parts) if parts else np.zeros((0, self.kind.store_bytes), np.uint8)
        return st

    def unpack_places(self, st: MapState, n_places: int) -> list[PlaceKeypoints | None]:
        """Checked inverse of pack_places for ``n_places`` places; raises StateError."""
        has = st.array("has", "b", (n_places,))
        shape = st.array("image_shape", "iu", (n_places, 2), lo=0, hi=1 << 16)
        word = st.array("word", "iu", (None,), lo=NO_WORD, hi=max(self.vocabulary_size, _NO_WORD_UINT16 + 1), as_int64=False)
        if np.any(((word >= self.vocabulary_size) | (word < 0)) & (word != self._no_word)):
            raise StateError(f"map state: keypoint word ids outside the vocabulary of {self.vocabulary_size} words")
        k = word.size
        ptr = check_ptr(st, "ptr", n_places, k)
        xy = st.array("xy", "iu", (k, 2), lo=0, hi=int(_XY_SCALE) + 1, as_int64=False)
        desc = st.array("desc", "u", (k, self.kind.store_bytes), as_int64=False)
        counts = np.diff(ptr)
        if np.any(counts[~has] != 0) or (self.max_keypoints is not None and np.any(counts > self.max_keypoints)):
            raise StateError("map state: keypoint counts do not fit the store's settings")
        rec = np.zeros(k, self.dtype)
        rec["xy"], rec["word"], rec["desc"] = xy, word, desc
        upright_ptr, upright = self._unpack_upright(st, has, counts)
        return [
            PlaceKeypoints(rec[ptr[i]:ptr[i + 1]].copy(), (int(shape[i, 0]), int(shape[i, 1])),
                           None if upright_ptr[i] < 0 else upright[upright_ptr[i]:upright_ptr[i] + counts[i]].copy())
            if has[i] else None
            for i in range(n_places)
        ]

    def _unpack_upright(self, st: MapState, has: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(first upright row of each place, -1 for none; the upright rows), checked. A state
        written before places held upright descriptors has neither array: no place has them."""
        n_places = has.size
        if "has_upright" not in st.arrays and "upright" not in st.arrays:
            return np.full(n_places, -1, np.int64), np.zeros((0, self.kind.store_bytes), np.uint8)
        flags = st.array("has_upright", "b", (n_places,))
        if np.any(flags & ~has):
            raise StateError("map state: upright descriptors for a place without keypoints")
        rows = counts * flags
        upright = st.array("upright", "u", (int(rows.sum()), self.kind.store_bytes), as_int64=False)
        first = (np.cumsum(rows) - rows).astype(np.int64)
        return np.where(flags, first, -1), upright

    def load_state(self, st: MapState, n_places: int) -> None:
        """Replace the contents by a checked state; place ids must lie below ``n_places``."""
        pids = st.array("place_ids", "iu", (None,), lo=0, hi=max(n_places, 1))
        if np.unique(pids).size != pids.size or (pids.size and n_places == 0):
            raise StateError("map state: keypoint store place ids repeat or lie outside the map")
        places = self.unpack_places(st, pids.size)
        if not all(p is not None for p in places):
            raise StateError("map state: a stored place has no keypoints record")
        self._places, self._nbytes = {}, 0
        for pid, place in zip(pids.tolist(), places):
            self.put(pid, place)

    def nbytes(self) -> int:
        """Bytes held by every stored place (records + PLACE_OVERHEAD_BYTES each)."""
        return self._nbytes
