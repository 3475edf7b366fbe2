"""The map's journal (``--state DIR``): every frame the detector takes between two snapshots,
appended as it is processed, so that a failing disk or a kill -9 loses only what could not be
written.

What is journaled: the detector's *inputs*, not its state. A frame record holds the frame's
sequence number, stamp, keypoint words and keypoints (positions, sizes, raw descriptors, the
upright descriptors when the frame has them (format 2), image shape):
``detector.process_words`` over them makes exactly the state changes the frame made
(insertion queue, places, evictions, keypoint store, last-used order, track prior, temporal
and chain history), so loading = the current snapshot, then the journal's frames replayed.

Files in DIR (next to the snapshots of runtime/aefabmap_runtime/adapters/state_dir.py)::

    journal-000000000120   a segment: the frames from 120 on, in order

A segment is a sequence of records ``u32 length | u32 crc32(payload) | payload`` (little
endian). The first record is the header (``H`` + JSON: format, version, bundle id, first frame,
detector settings); the others are frames (``F`` + fixed fields + arrays). A record cut off by
a full disk or a kill -9, or damaged, fails its length or checksum: reading stops there (the
frames before it are kept), as it does at an empty segment. A record that passes its checksum
but does not fit (another bundle, settings or feature kind, a word id out of range, out of
order) is refused with StateError: that is not a torn write.

A segment is created under a temporary name (header written, fsync'ed) and renamed; a new one
starts each time a snapshot is taken (its first frame is the snapshot's), and a durable
snapshot removes the segments before it (map_state.MapStateDir.save). Loading walks from the
snapshot's frame through the segments that continue it; a segment starting after a gap (frames
that were not written) cannot be replayed and is removed once the map has loaded.
"""

from __future__ import annotations

import errno
import json
import os
import re
import struct
import threading
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import InputError, StateError
from aefabmap_runtime.adapters.durable_files import fsync_dir, open_regular
from aefabmap_runtime.core.features.features import Features
from aefabmap_runtime.core.map.map_events import MapListener

FORMAT = "aefabmap-map-journal"
#: 2: a frame record may hold upright descriptors (its features flag is 2); 1 is still read.
FORMAT_VERSION = 2
SEGMENT_RE = re.compile(r"^journal-(\d{12})$")
_RECORD = struct.Struct("<II")  # payload length (bytes), crc32 of the payload
# b"F", sequence, stamp (ns), keypoints, features (0: none, 1: yes, 2: with upright), height, width (px)
_FRAME = struct.Struct("<cqqIBII")
_MAX_HEADER_BYTES = 1 << 20
#: Largest frame record read (bytes): above 100 000 SIFT keypoints, the extractor's limit.
MAX_RECORD_BYTES = 64 << 20
_MAX_IMAGE_SIDE = 1 << 16
#: Tests inject a failing disk here (the one call that writes records).
_os_write = os.write


def segment_name(first: int) -> str:
    """File name of the segment whose first frame is ``first``."""
    return f"journal-{first:012d}"


def segments(path: Path) -> list[tuple[int, Path]]:
    """The journal segments in DIR as (first frame, path), in frame order."""
    found = [(int(m.group(1)), p) for p in path.iterdir() if (m := SEGMENT_RE.match(p.name))]
    return sorted(found)


def remove_segments_before(path: Path, first: int) -> None:
    """Remove the segments that start before frame ``first`` (a durable snapshot holds them);
    best effort: a segment left behind is skipped when loading."""
    for base, p in segments(path):
        if base < first:
            _unlink_quietly(p)


def _unlink_quietly(p: Path) -> None:
    try:
        p.unlink()
    except OSError:
        pass


def _record(payload: bytes) -> bytes:
    return _RECORD.pack(len(payload), zlib.crc32(payload)) + payload


def _settings_json(detector) -> str:
    return json.dumps(detector.config.to_dict(), sort_keys=True)


def _header(bundle: str, first: int, detector) -> bytes:
    doc = {"format": FORMAT, "version": FORMAT_VERSION, "bundle": bundle, "first": first,
           "config": _settings_json(detector)}
    return b"H" + json.dumps(doc).encode()


def _descriptor_dtype(detector) -> np.dtype:
    return np.dtype(detector.input_format.kind.dtype).newbyteorder("<")


def encode_frame(detector, seq: int, words: np.ndarray, stamp_ns: int, feats: Features | None) -> bytes:
    """The record payload of frame ``seq`` as the detector took it (MapListener.frame_taken)."""
    n = int(words.size)
    if feats is None:
        head = _FRAME.pack(b"F", seq, stamp_ns, n, 0, 0, 0)
        return head + np.asarray(words, "<i4").tobytes()
    h, w = feats.image_shape
    dtype = _descriptor_dtype(detector)
    upright = () if feats.upright is None else (np.ascontiguousarray(feats.upright, dtype).tobytes(),)
    return b"".join((
        _FRAME.pack(b"F", seq, stamp_ns, n, 1 + bool(upright), int(h), int(w)),
        np.asarray(words, "<i4").tobytes(),
        np.asarray(feats.keypoints, "<f4").tobytes(),
        np.asarray(feats.sizes, "<f4").tobytes(),
        np.ascontiguousarray(feats.descriptors, dtype).tobytes(),
        *upright,
    ))


def decode_frame(payload: bytes, detector, label: str) -> tuple[int, np.ndarray, int, Features | None]:
    """(sequence, words, stamp_ns, features) of a frame record, checked against ``detector``
    (feature kind, vocabulary, shapes, finite values); StateError naming ``label`` otherwise."""
    if len(payload) < _FRAME.size or payload[:1] != b"F":
        raise StateError(f"{label}: not a frame record")
    _, seq, stamp_ns, n, has, height, width = _FRAME.unpack_from(payload)
    fmt = detector.input_format
    dtype, cols = _descriptor_dtype(detector), int(fmt.kind.width)
    per_kp = 4 + (2 * 4 + 4 + has * cols * dtype.itemsize if has else 0)
    if has > 2 or len(payload) != _FRAME.size + n * per_kp:
        raise StateError(f"{label}: frame record of {len(payload)} bytes does not hold {n} keypoints "
                         "of this bundle's feature kind")
    at = _FRAME.size
    words = np.frombuffer(payload, "<i4", n, at).astype(np.int64)
    _check_words(words, fmt.vocabulary_size, n if not has else min(n, fmt.observed_keypoints), label)
    if not has:
        return seq, words, stamp_ns, None
    if not (1 <= height < _MAX_IMAGE_SIDE and 1 <= width < _MAX_IMAGE_SIDE):
        raise StateError(f"{label}: image shape {height}x{width} is out of range")
    at += 4 * n
    xy = np.frombuffer(payload, "<f4", 2 * n, at).reshape(n, 2).astype(np.float32)
    sizes = np.frombuffer(payload, "<f4", n, at + 8 * n).astype(np.float32)
    desc = np.frombuffer(payload, dtype, n * cols, at + 12 * n).reshape(n, cols).astype(fmt.kind.dtype)
    upright = None
    if has == 2:
        at += 12 * n + n * cols * dtype.itemsize
        upright = np.frombuffer(payload, dtype, n * cols, at).reshape(n, cols).astype(fmt.kind.dtype)
    inside = np.all((xy >= -1) & (xy[:, :1] <= width + 1) & (xy[:, 1:] <= height + 1))
    if not (np.isfinite(xy).all() and inside and np.isfinite(sizes).all() and np.all(sizes >= 0)):
        raise StateError(f"{label}: keypoints outside the image or not finite")
    if desc.dtype.kind == "f" and not (np.isfinite(desc).all() and (upright is None or np.isfinite(upright).all())):
        raise StateError(f"{label}: descriptors not finite")
    return seq, words, stamp_ns, Features(xy, sizes, desc, (height, width), upright)


def _check_words(words: np.ndarray, v: int, observed: int, label: str) -> None:
    """Observed words in [0, v), v the vocabulary size; beyond them (verification only) NO_WORD (-1) too."""
    if words.size and (int(words.max()) >= v or int(words.min()) < -1 or
                       (observed and int(words[:observed].min()) < 0)):
        raise StateError(f"{label}: word ids out of the bundle's vocabulary of {v}")


# -- reading -----------------------------------------------------------------------------------

class _Cut(Exception):
    """A record cut off or damaged (internal: reading the segment stops before it)."""


def _records(path: Path, label: str):
    """Yield the payloads of a segment's records, in order; stops (raising _Cut) at the first
    record cut off or damaged. Regular files only (durable_files.open_regular)."""

    try:
        fd = open_regular(path)
    except OSError as exc:
        raise StateError(f"{label}: cannot open: {exc.strerror or exc}") from None
    with os.fdopen(fd, "rb") as fh:
        left = os.fstat(fh.fileno()).st_size
        index = 0
        while left:
            head = fh.read(_RECORD.size)
            length, crc = _RECORD.unpack(head) if len(head) == _RECORD.size else (None, None)
            if length is None or length > MAX_RECORD_BYTES or length > left - _RECORD.size:
                raise _Cut(f"record {index} is cut off")
            payload = fh.read(length)
            if len(payload) != length or zlib.crc32(payload) != crc:
                raise _Cut(f"record {index} is damaged (checksum)")
            left -= _RECORD.size + length
            index += 1
            yield payload


def _check_header(payload: bytes, directory, detector, base: int, label: str) -> None:
    from aefabmap_runtime.core.run_config import recorded_settings_differences

    if len(payload) > _MAX_HEADER_BYTES or payload[:1] != b"H":
        raise StateError(f"{label} does not start with a journal header")
    try:
        doc = json.loads(payload[1:])
    except (ValueError, UnicodeDecodeError):
        raise StateError(f"{label}: journal header is not valid JSON") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise StateError(f"{label} is not an aefabmap map journal")
    version = doc.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= FORMAT_VERSION:
        raise StateError(f"{label}: journal format version {str(version)[:20]!r} is not one this aefabmap reads")
    if doc.get("bundle") != directory.bundle:
        raise StateError(f"{label} was written with another model bundle; remove it to load the snapshot alone")
    if doc.get("first") != base:
        raise StateError(f"{label}: header says it starts at frame {str(doc.get('first'))[:20]}, its name {base}")
    differ = recorded_settings_differences(doc.get("config"), detector.config)
    if differ:
        raise StateError(f"{label} was written with other detector settings ({', '.join(differ)}): restart with "
                         "them to replay it, or remove it to load the snapshot alone")


@dataclass
class JournalReplay:
    """What loading the journal did: frames replayed (from ``first`` to ``next`` - 1), why it
    stopped before the end of the files (``cut``: a record cut off or damaged; None: clean),
    and how many segments that no longer continue the map were removed."""

    first: int
    next: int
    cut: str | None = None
    removed: int = 0

    @property
    def frames(self) -> int:
        return self.next - self.first


def replay_journal(detector, directory, remove_unreachable: bool = True) -> JournalReplay:
    """Replay the journal of ``directory`` (map_state.MapStateDir, open) into ``detector``,
    which holds the current snapshot's map (or an empty one): the frames from
    ``detector.next_sequence`` on, segment after segment, up to the first frame not written.
    Raises StateError for a journal that does not belong (see the module doc); once the map
    has loaded, removes the segments it could not reach (unless not `remove_unreachable`)."""
    first = expected = detector.next_sequence
    cut = None
    for base, path in segments(directory.path):
        if base > expected:  # the frames before `base` were not written: what follows cannot be replayed
            cut = f"frames {expected} to {base - 1} were not written"
            break
        try:
            expected, cut = _replay_segment(detector, directory, base, path, expected, path.name), None
        except _Cut as exc:
            expected, cut = detector.next_sequence, f"{path.name}: {exc}"
    removed = 0
    for base, path in segments(directory.path) if remove_unreachable else ():
        if base > expected:
            _unlink_quietly(path)
            removed += 1
    return JournalReplay(first, expected, cut, removed)


def _replay_segment(detector, directory, base: int, path: Path, expected: int, label: str) -> int:
    """Replay one segment's frames from ``expected`` on; returns the next frame expected."""
    records = _records(path, label)
    header = next(records, None)
    if header is None:  # an empty file: its header was never written whole, as a cut-off one
        raise _Cut("empty file, no journal header")
    _check_header(header, directory, detector, base, label)
    for i, payload in enumerate(records):
        seq, words, stamp_ns, feats = decode_frame(payload, detector, f"{label} record {i + 1}")
        if seq != base + i:
            raise StateError(f"{label} record {i + 1}: frame {seq} out of order (expected {base + i})")
        if seq < expected:
            continue  # the snapshot holds it
        try:
            detector.process_words(words, stamp_ns, feats)
        except InputError as exc:
            raise StateError(f"{label} record {i + 1}: {exc}") from None
        expected = seq + 1
    return expected


# -- writing -----------------------------------------------------------------------------------

@dataclass
class _Segment:
    """A segment this process writes: first frame, next frame, places after its last record."""

    path: Path
    first: int
    next: int
    places: int
    nbytes: int = 0


@dataclass
class StateReport:
    """How much of the map the state directory holds now.

    frames_processed: frames the detector has taken (its next sequence number);
    frames_kept: frames a restart loads (the snapshot + journal frames written without a gap);
    places_kept / places_in_map: places in the map a restart loads / in the map now;
    frames_not_written: frames_processed - frames_kept; write_failures: writes that failed;
    error: the last write error (e.g. "disk full"), None when none failed.
    """

    frames_processed: int
    frames_kept: int
    places_kept: int
    places_in_map: int
    frames_not_written: int
    write_failures: int
    error: str | None

    def to_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """The one log line at stop."""
        text = (f"state: {self.places_kept} places kept on disk, {self.places_in_map} in the map after "
                f"{self.frames_processed} frames, {self.frames_not_written} frames not written")
        return text + (f" ({self.error})" if self.frames_not_written and self.error else "")


def _error_text(exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return "disk full"
    return exc.strerror or str(exc)


class MapJournal(MapListener):
    """Appends each frame the detector takes to the journal of ``directory`` (open
    map_state.MapStateDir) and keeps count of what the directory holds.

    It listens to the detector (core/map/map_events.py): `frame_taken` hands it each frame's
    input, which it writes when the Snapshotter drives it: ``after_frame()`` after every frame,
    ``rotate()`` when it takes a snapshot's state, ``snapshot_durable()`` once that snapshot is
    on disk; ``close()`` stops listening. A failed write never
    raises: the segment is cut back to its last whole record, ``on_error`` gets a StateError,
    and frames are not written until the next snapshot has been taken (a frame after a missing
    one could not be replayed). sync_every_s: fdatasync the segment at most this often (s); a
    record is in the page cache once written, so a kill -9 loses none of them.
    """

    def __init__(self, directory, detector, *, sync_every_s: float = 5.0, clock=time.monotonic,
                 on_error=None) -> None:
        self.directory, self.detector = directory, detector
        self.sync_every_s, self.clock, self.on_error = sync_every_s, clock, on_error
        self.write_failures = 0
        self.error: str | None = None
        self._lock = threading.Lock()  # the segment list: snapshot_durable runs in the snapshot thread
        self._segments: list[_Segment] = []
        self._fd: int | None = None
        self._next = detector.next_sequence
        self._durable = (detector.next_sequence, detector.n_places)  # what DIR holds at start (loaded)
        self._t_sync = clock()
        # (sequence, words, stamp_ns, features) of the last frame the detector took, until written
        self._taken: tuple[int, np.ndarray, int, Features | None] | None = None
        self.rotate()
        detector.add_listener(self)

    def frame_taken(self, sequence: int, words: np.ndarray, stamp_ns: int, features: Features | None) -> None:
        self._taken = (sequence, words, stamp_ns, features)

    @property
    def behind(self) -> bool:
        """True when frames taken are not all on disk (a snapshot would catch up)."""
        return self._kept()[0] < self.detector.next_sequence

    def after_frame(self) -> None:
        """Append the frame the detector took since the last call (none: nothing to do)."""
        now = self.detector.next_sequence
        if now == self._next:
            return
        seq, self._next = self._next, now
        taken, self._taken = self._taken, None
        if self._fd is None:
            return
        if now != seq + 1 or taken is None or taken[0] != seq:  # a frame went past unrecorded
            self._fail(OSError(errno.EIO, f"frame {seq} was not recorded"), seq)
            return
        self._append(encode_frame(self.detector, *taken), seq)

    def rotate(self) -> None:
        """Start a new segment at the detector's next frame (a snapshot's state is taken now)."""
        self.after_frame()
        self._close_fd()
        first = self.detector.next_sequence
        path = self.directory.path / segment_name(first)
        try:
            self._fd = self._create(path, first)
        except OSError as exc:
            self._fail(exc, first)
            return
        with self._lock:
            self._segments = [s for s in self._segments if s.first != first]
            self._segments.append(_Segment(path, first, first, self.detector.n_places))

    def snapshot_durable(self, sequence: int, places: int) -> None:
        """A snapshot of the map at frame ``sequence`` (``places`` places) is on disk."""
        with self._lock:
            if sequence >= self._durable[0]:
                self._durable = (sequence, places)
            self._segments = [s for s in self._segments if s.next > sequence or s is self._current()]

    def report(self) -> StateReport:
        """The counts now (call between frames)."""
        kept, places = self._kept()
        done = self.detector.next_sequence
        return StateReport(done, kept, places, self.detector.n_places, done - kept, self.write_failures, self.error)

    def close(self) -> None:
        """Stop listening; sync and close the segment (one with no frame that a snapshot covers is removed)."""
        self.detector.remove_listener(self)
        current = self._current()
        self._close_fd()
        if current is not None and current.next == current.first and current.first <= self._durable[0]:
            _unlink_quietly(current.path)

    # -- internals ---------------------------------------------------------------------------

    def _current(self) -> _Segment | None:
        return self._segments[-1] if self._fd is not None and self._segments else None

    def _kept(self) -> tuple[int, int]:
        """(frames, places) a restart loads: the last durable snapshot, then segments without a gap."""
        with self._lock:
            seq, places = self._durable
            for s in sorted(self._segments, key=lambda s: s.first):
                if s.first <= seq < s.next:
                    seq, places = s.next, s.places
        return seq, places

    def _create(self, path: Path, first: int) -> int:
        """A new segment holding its header (written, fsync'ed, renamed into place); its fd."""

        tmp = self.directory.path / f".journal-tmp-{os.getpid()}"
        _unlink_quietly(tmp)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        try:
            _write_all(fd, _record(_header(self.directory.bundle, first, self.detector)))
            os.fsync(fd)
            os.replace(tmp, path)
            fsync_dir(self.directory.path)
        except BaseException:
            os.close(fd)
            _unlink_quietly(tmp)
            raise
        return fd

    def _append(self, payload: bytes, seq: int) -> None:
        seg = self._current()
        at = os.lseek(self._fd, 0, os.SEEK_END)
        try:
            _write_all(self._fd, _record(payload))
            if self.clock() - self._t_sync >= self.sync_every_s:
                os.fdatasync(self._fd)
                self._t_sync = self.clock()
        except OSError as exc:
            try:
                os.ftruncate(self._fd, at)  # drop the part written: frees the space it took
            except OSError:
                pass  # the reader stops at the cut-off record all the same
            self._fail(exc, seq)
            return
        with self._lock:
            seg.next, seg.places = seq + 1, self.detector.n_places

    def _fail(self, exc: OSError, seq: int) -> None:
        self._close_fd(sync=False)
        self.write_failures += 1
        self.error = _error_text(exc)
        if self.on_error is not None:
            self.on_error(StateError(f"cannot write frame {seq} to the map journal in {self.directory.path}: "
                                     f"{self.error}; frames from {seq} on are not kept until a snapshot is written"))

    def _close_fd(self, sync: bool = True) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            if sync:
                os.fdatasync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)


def _write_all(fd: int, data: bytes) -> None:
    """Write all of ``data`` (a short write is continued; OSError as the disk raises it)."""
    view = memoryview(data)
    while view:
        n = _os_write(fd, view)
        view = view[n:]
