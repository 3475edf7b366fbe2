"""A running node's "where am I?" queryable: one image in, its verified place out, nothing stored.

Key: ``<results key>/locate`` (zenoh_transport.locate_key_for). A query's payload is one image
encoded as frames are (JPEG, PNG, or raw with its encoding; adapters/frames.py decode_frame),
the query's encoding naming it (none: a JPEG or PNG). The answer is one LocateAnswer (core/records/messages.py): the
verified place, its frame and, with a calibrated camera, the pose (LoopClosureDetector.locate);
the map, the frame numbers and the track are left as they were. Useful on a node localizing
against a frozen map (--localize) when tracking is lost, and on a mapping node alike.

Everything in a query is hostile. At most MAX_LOCATE_BYTES of payload, `rate_hz` queries per
second (a token bucket) and QUEUE waiting: the others are answered at once with an error reply
naming why (too_large, busy, bad_image: ...) and counted. One worker thread decodes, extracts
and locates; the frames' own steps go on beside it (the detector takes one at a time).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field

import zenoh

from aefabmap_runtime.adapters.frames import decode_frame, decode_image
from aefabmap_runtime.core.records.messages import LocateAnswer
from aefabmap_runtime.errors import AefabmapError, TransportError

log = logging.getLogger("aefabmap.locate")

#: Largest image a query may carry (bytes): a raw 1920 x 1080 RGB frame fits.
MAX_LOCATE_BYTES = 8 << 20
#: Queries waiting for the worker; more are answered "busy".
QUEUE = 2
#: Queries per second accepted on average (bursts of as many).
RATE_HZ = 5.0
#: Longest encoding string read from a query.
_MAX_ENCODING = 128


@dataclass
class LocateCounts:
    """What the queryable did: answers given, and queries refused by reason."""

    answered: int = 0
    refused: dict[str, int] = field(default_factory=dict)

    def refuse(self, reason: str) -> None:
        self.refused[reason] = self.refused.get(reason, 0) + 1


class LocateService:
    """Declares the locate queryable on `session` at `key` for `detector`; close() undeclares it
    and stops the worker. TransportError when the queryable cannot be declared."""

    def __init__(self, session: zenoh.Session, detector, key: str, *, rate_hz: float = RATE_HZ,
                 max_bytes: int = MAX_LOCATE_BYTES) -> None:
        self.detector, self.key, self.max_bytes = detector, key, max_bytes
        self.counts = LocateCounts()
        self._lock = threading.Lock()  # counts and tokens: Zenoh threads and the worker
        self._rate, self._tokens, self._t = float(rate_hz), float(rate_hz), time.monotonic()
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE)
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._work, name="aefabmap-locate", daemon=True)
        self._worker.start()
        try:
            self._queryable = session.declare_queryable(key, self._on_query)
        except zenoh.ZError as exc:
            self._stop.set()
            raise TransportError(f"cannot declare the locate queryable {key}: {str(exc)[:200]}") from exc

    def _refuse(self, query: zenoh.Query, reason: str, detail: str = "") -> None:
        with self._lock:
            self.counts.refuse(reason)
        try:
            query.reply_err(f"{reason}: {detail}"[:300] if detail else reason)
        except Exception:  # noqa: BLE001 - the asker may be gone
            pass

    def _take_token(self) -> bool:
        with self._lock:
            now = time.monotonic()
            self._tokens = min(self._rate, self._tokens + (now - self._t) * self._rate)
            self._t = now
            if self._tokens < 1.0:
                return False
            self._tokens -= 1.0
            return True

    def _on_query(self, query: zenoh.Query) -> None:
        """On a Zenoh thread: check the size and the rate, queue the query for the worker."""
        try:
            payload = query.payload
            size = len(payload) if payload is not None else 0
            if size == 0:
                return self._refuse(query, "bad_image", "the query carries no image")
            if size > self.max_bytes:
                return self._refuse(query, "too_large", f"{size} bytes, at most {self.max_bytes}")
            if not self._take_token():
                return self._refuse(query, "busy", f"at most {self._rate:g} queries/s")
            encoding = str(query.encoding)[:_MAX_ENCODING] if query.encoding is not None else ""
            self._queue.put_nowait((query, payload.to_bytes(), encoding, time.monotonic()))
        except queue.Full:
            self._refuse(query, "busy", f"{QUEUE} queries waiting")
        except Exception as exc:  # noqa: BLE001 - a query must never take the node down
            self._refuse(query, "bad_query", str(exc)[:100])

    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                query, data, encoding, t0 = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                answer = self._locate(data, encoding, t0)
            except AefabmapError as exc:
                self._refuse(query, "bad_image", str(exc))
                continue
            except Exception as exc:  # noqa: BLE001 - one image must never stop the service
                log.debug("locate failed: %s", str(exc)[:200])
                self._refuse(query, "failed", type(exc).__name__)
                continue
            try:
                query.reply(self.key, answer.to_json_bytes())
                with self._lock:
                    self.counts.answered += 1
            except Exception as exc:  # noqa: BLE001 - the asker may be gone
                log.debug("locate answer not sent: %s", str(exc)[:200])
            finally:
                del query  # the query ends (its final reply) once dropped

    def _locate(self, data: bytes, encoding: str, t0: float) -> LocateAnswer:
        # No encoding given (Zenoh's default): a JPEG or PNG, told by its magic.
        image = decode_frame(data, encoding) if encoding not in ("", "zenoh/bytes") else decode_image(data)
        where = self.detector.locate(self.detector.prepare(image))
        g = where.geometry
        answer = LocateAnswer(checked=where.checked, places=int(self.detector.n_places))
        if g is not None:
            answer.verified, answer.place, answer.frame = True, where.place, where.frame
            answer.inliers, answer.nfa, answer.geometry_model = int(g.inliers), float(g.nfa), g.model
            if g.rotation is not None:
                answer.relative_rotation = [[float(v) for v in row] for row in g.rotation]
                answer.relative_translation = [float(v) for v in g.translation]
        answer.latency_ms = round((time.monotonic() - t0) * 1e3, 3)
        return answer

    def close(self) -> None:
        self._stop.set()
        try:
            self._queryable.undeclare()
        except (zenoh.ZError, AttributeError):
            pass
        self._worker.join(timeout=5)
        while not self._queue.empty():  # queries never answered: end them
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break

    def __enter__(self) -> LocateService:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
