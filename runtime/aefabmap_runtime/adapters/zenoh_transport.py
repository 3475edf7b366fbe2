"""Zenoh adapters: session config, the frame subscriber and the result publisher.

Key layout (decided here, used by ``aefabmap run`` and ``aefabmap publish``):

- frames on the image key given by the user, e.g. ``robot/camera/image``;
- per-frame results (JSON, ``application/json``) on the *sibling* key ``lcd``, i.e. the last
  chunk of the image key replaced: ``robot/camera/image`` -> ``robot/camera/lcd``
  (a one-chunk key ``camera`` -> ``lcd``);
- periodic stats (JSON) on ``<results key>/stats``: ``robot/camera/lcd/stats``.

The results key must be concrete: an image key whose parent chunks contain wildcards
(``robot/*/image``) needs an explicit results key. The image key itself may end in a
wildcard (``robot/camera/*``); the subscriber then ignores samples on the results and
stats keys so the node never eats its own output.

Sequence numbers: ``publish`` attaches a small JSON attachment to every frame,
``{"seq": <int, from 0>, "stamp_ns": <capture time, ns since the Unix epoch>, "src": <id>}``.
Attachments are untrusted: one that is not such a JSON object, or a field out of range,
is counted (``FrameSubscriber.bad_attachments``) and ignored, the frame keeping its receive
time (see :meth:`FrameMeta.from_attachment`). ``RingChannel(n)`` drops old frames
silently; the subscriber counts gaps in ``seq`` per ``src`` to report how many frames were
dropped (in the ring, in the network, or by a publisher restart, which resets ``seq`` and is
not counted as a drop).
"""

from __future__ import annotations

import dataclasses
import json
import re
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from aefabmap_runtime.errors import ConfigError, TransportError
from aefabmap_runtime.adapters.zenoh_exposure import TLS_PROTOCOLS, endpoints, exposure, is_loopback, mutual_tls

#: Zenoh's customary port; the CLI's loopback default (see cli_session_config).
DEFAULT_PORT = 7447
RESULT_CHUNK = "lcd"
STATS_SUFFIX = "stats"
_ENDPOINT_RE = re.compile(r"^[a-z0-9\-]+/.+$")


@dataclass(frozen=True)
class SessionConfig:
    """How to open a Zenoh session.

    connect / listen: endpoints such as ``tcp/127.0.0.1:7447``.
    config_file: a zenoh JSON5 config file loaded first; the fields below override it.
    mode: ``peer`` (default, no router needed), ``client`` or ``router``.
    multicast_scouting: None = off, unless a config file is given and no endpoint (then the
    file decides).

    Exposure: without a config file the session listens on exactly ``listen`` (none: it
    listens nowhere, where zenoh's own default would be every interface) and does not join
    multicast scouting. See :func:`cli_session_config` for the CLI's loopback default.
    allow_exposure: accept a session that listens where other hosts reach it without
    authentication, or joins multicast scouting (runtime/aefabmap_runtime/adapters/zenoh_exposure.py); without
    it such a session is a ConfigError.
    """

    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    mode: str | None = None  # None: the config file's mode, else "peer"
    multicast_scouting: bool | None = None
    allow_exposure: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "connect", _split_endpoints(self.connect, "connect"))
        object.__setattr__(self, "listen", _split_endpoints(self.listen, "listen"))
        if self.mode is not None and self.mode not in ("peer", "client", "router"):
            raise ConfigError(f"zenoh mode must be peer, client or router, got {self.mode!r}")

    def to_dict(self) -> dict:
        return {
            "connect": list(self.connect),
            "listen": list(self.listen),
            "config_file": self.config_file,
            "mode": self.mode,
            "multicast_scouting": self.multicast_scouting,
            "allow_exposure": self.allow_exposure,
        }


def _split_endpoints(values, what: str) -> tuple[str, ...]:
    if values is None:
        return ()
    if isinstance(values, str):
        values = [values]
    out: list[str] = []
    for v in values:
        for ep in str(v).split(","):
            ep = ep.strip()
            if not ep:
                continue
            if not _ENDPOINT_RE.match(ep):
                raise ConfigError(f"--{what} endpoint must look like tcp/127.0.0.1:7447, got {ep!r}")
            proto, _, rest = ep.partition("/")
            if proto in ("tcp", "udp", "tls", "quic", "ws"):
                port = rest.split("?")[0].split("#")[0].rpartition(":")[2]
                if not port.isdigit() or int(port) > 65535:
                    raise ConfigError(f"--{what} endpoint {ep!r} needs a port number 0..65535 after ':'")
            out.append(ep)
    return tuple(out)


#: listen/endpoints of a zenoh config that does not set them (zenoh's own default).
_ZENOH_DEFAULT_LISTEN = json.loads(zenoh.Config().get_json("listen/endpoints"))


def build_zenoh_config(sc: SessionConfig) -> zenoh.Config:
    """Build a zenoh.Config from a SessionConfig; raises ConfigError on bad values."""
    try:
        if sc.config_file:
            path = Path(sc.config_file)
            if not path.is_file():
                raise ConfigError(f"zenoh config file {path} does not exist")
            conf = zenoh.Config.from_file(str(path))
        else:
            conf = zenoh.Config()
    except zenoh.ZError as exc:
        raise ConfigError(f"cannot load zenoh config {sc.config_file}: {_short(exc)}") from exc
    try:
        if sc.mode is not None or not sc.config_file:  # never override the file's own mode silently
            conf.insert_json5("mode", json.dumps(sc.mode or "peer"))
        if sc.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(sc.connect)))
        if sc.listen or not sc.config_file:
            conf.insert_json5("listen/endpoints", json.dumps(list(sc.listen)))
        scouting = sc.multicast_scouting
        if scouting is None and (sc.connect or sc.listen or not sc.config_file
                                 or json.loads(conf.get_json("scouting/multicast/enabled")) is None):
            scouting = False  # a file that does not turn multicast scouting on leaves it off
        if scouting is not None:
            conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(scouting)))
        if sc.config_file and not sc.listen:
            _no_default_listen(conf, sc.config_file)
        reasons = exposure(conf)
    except zenoh.ZError as exc:
        raise ConfigError(f"invalid zenoh configuration: {_short(exc)}") from exc
    if reasons and not sc.allow_exposure:
        source = f"zenoh config {sc.config_file}" if sc.config_file else "the zenoh session"
        raise ConfigError(f"{source} would expose the node ({'; '.join(reasons)}): give --allow-exposure to accept "
                          "that, or listen on loopback or with mutual TLS (deploy/zenoh-tls-acl.json5)")
    return conf


def session_exposure(sc: SessionConfig) -> list[str]:
    """Why the session of sc is reachable without authentication ([]: it is not); ConfigError as
    build_zenoh_config, except for the exposure itself."""
    return exposure(build_zenoh_config(dataclasses.replace(sc, allow_exposure=True)))


def session_authenticated(sc: SessionConfig) -> bool:
    """Whether the session of sc meets other hosts only over mutual TLS: it has a TLS/QUIC
    endpoint, requires a certificate its CA signed, and every other endpoint is loopback.
    ConfigError as build_zenoh_config, except for exposure."""
    conf = build_zenoh_config(dataclasses.replace(sc, allow_exposure=True))
    remote = [e for e in (*endpoints(conf, "connect"), *endpoints(conf, "listen"))
              if not is_loopback(e) or e.partition("/")[0] in TLS_PROTOCOLS]
    return mutual_tls(conf) and bool(remote) and all(e.partition("/")[0] in TLS_PROTOCOLS for e in remote)


def _no_default_listen(conf: zenoh.Config, config_file: str) -> None:
    """A config file that leaves the listen endpoints at zenoh's own default (every interface)
    does not get it: a peer or router that connects somewhere listens nowhere; one that neither
    connects nor chooses where to listen is a ConfigError naming the file."""
    mode = json.loads(conf.get_json("mode")) or "peer"
    if mode == "client" or json.loads(conf.get_json("listen/endpoints")) != _ZENOH_DEFAULT_LISTEN:
        return
    if json.loads(conf.get_json("connect/endpoints")) not in ([], {}, None):
        conf.insert_json5("listen/endpoints", "[]")
        return
    raise ConfigError(f"zenoh config {config_file} chooses no listen or connect endpoints (zenoh's default would "
                      "listen on every interface): set listen/endpoints in the file, or give --listen / --connect")


def cli_session_config(
    role: str,
    *,
    connect=(),
    listen=(),
    config_file: str | None = None,
    default_port: int = DEFAULT_PORT,
    allow_exposure: bool = False,
) -> SessionConfig:
    """The session of ``aefabmap run`` (role ``"listen"``) or ``publish`` (``"connect"``).

    Loopback only by default: with no endpoint and no config file, the node listens on
    ``tcp/127.0.0.1:<default_port>`` and a publisher connects there, so the two commands find
    each other on one machine and nothing is reachable from the network; no multicast
    scouting. Any ``--connect``/``--listen``/``--config`` replaces that default; a session that
    would expose the node needs ``allow_exposure`` (``--allow-exposure``).
    """
    if role not in ("listen", "connect"):
        raise ConfigError(f"session role must be 'listen' or 'connect', got {role!r}")
    connect, listen = tuple(connect or ()), tuple(listen or ())
    if not connect and not listen and not config_file:
        loopback = (f"tcp/127.0.0.1:{default_port}",)
        return SessionConfig(listen=loopback) if role == "listen" else SessionConfig(connect=loopback)
    return SessionConfig(connect=connect, listen=listen, config_file=config_file, allow_exposure=allow_exposure)


def open_session(sc: SessionConfig) -> zenoh.Session:
    """Open a Zenoh session; ConfigError for bad values, TransportError when it fails to open."""
    conf = build_zenoh_config(sc)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        eps = ", ".join([*(f"listen {e}" for e in sc.listen), *(f"connect {e}" for e in sc.connect)]) or "defaults"
        raise TransportError(f"cannot open zenoh session ({eps}): {_short(exc)}") from exc


def _short(exc: BaseException) -> str:
    text = str(exc)
    return text.split(" at /")[0][:300]


def result_key_for(image_key: str) -> str:
    """Results key of an image key: its sibling ``lcd`` (see module docstring)."""
    key = image_key.strip().strip("/")
    if not key:
        raise ConfigError("image key must not be empty")
    parent, _, last = key.rpartition("/")
    if last == RESULT_CHUNK:
        raise ConfigError(f"image key {image_key!r} ends in '{RESULT_CHUNK}', which is the results key")
    if "*" in parent or "$" in parent:
        raise ConfigError(f"image key {image_key!r} has wildcards before its last chunk: give a results key")
    return f"{parent}/{RESULT_CHUNK}" if parent else RESULT_CHUNK


def stats_key_for(result_key: str) -> str:
    """Stats key of a results key: ``<result_key>/stats``."""
    return f"{result_key}/{STATS_SUFFIX}"


def locate_key_for(result_key: str) -> str:
    """The node's "where am I?" queryable of a results key: ``<result_key>/locate``
    (runtime/aefabmap_runtime/adapters/locate_service.py)."""
    return f"{result_key}/locate"


# --------------------------------------------------------------------------- frame meta


#: Largest attachment parsed (bytes): ours is ~80 bytes; a bigger one is refused unread.
MAX_ATTACHMENT_BYTES = 1024
#: Longest source id kept (characters); ours are 12 hex digits.
MAX_SRC_CHARS = 64
#: Sequence numbers and stamps must fit a signed 64-bit integer (stamps: ns since the Unix
#: epoch, i.e. up to the year 2262); the MCAP log stores times as unsigned 64-bit.
_INT64_LIMIT = 2**63


@dataclass(frozen=True)
class FrameMeta:
    """What the publisher attached: sequence number, capture stamp (ns, Unix epoch), source id.

    problem: why (part of) the attachment was refused ("" when it was fine or absent); the
    refused fields are None / "" so the frame falls back to its receive time. Not compared.
    """

    seq: int | None = None
    stamp_ns: int | None = None
    src: str = ""
    problem: str = field(default="", compare=False)

    def to_attachment(self) -> bytes:
        return json.dumps({"seq": self.seq, "stamp_ns": self.stamp_ns, "src": self.src}).encode()

    @classmethod
    def from_attachment(cls, data: bytes | None) -> FrameMeta:
        """Parse an attachment; never raises: every field is untrusted.

        No attachment is fine (an unsequenced publisher). Otherwise the attachment must be a
        JSON object of at most MAX_ATTACHMENT_BYTES; ``seq`` and ``stamp_ns`` must be null or
        integers in [0, 2**63); ``src`` a string of at most MAX_SRC_CHARS. A field that breaks
        these rules is dropped and ``problem`` says why; unknown keys are ignored.
        """
        if not data:
            return cls()
        if len(data) > MAX_ATTACHMENT_BYTES:
            return cls(problem=f"attachment of {len(data)} bytes exceeds {MAX_ATTACHMENT_BYTES} bytes")
        try:
            obj = json.loads(data)
        except (ValueError, RecursionError):  # not UTF-8 / not JSON / too deeply nested
            return cls(problem="attachment is not JSON")
        if not isinstance(obj, dict):
            return cls(problem=f"attachment is a JSON {type(obj).__name__}, not an object")
        problems: list[str] = []
        seq = _int64_field(obj, "seq", problems)
        stamp = _int64_field(obj, "stamp_ns", problems)
        src = obj.get("src", "")
        if src is None:
            src = ""
        elif not isinstance(src, str) or len(src) > MAX_SRC_CHARS:
            problems.append(f"src must be a string of at most {MAX_SRC_CHARS} characters")
            src = ""
        return cls(seq=seq, stamp_ns=stamp, src=src, problem="; ".join(problems))


def _int64_field(obj: dict, name: str, problems: list[str]) -> int | None:
    """obj[name] when it is an integer in [0, 2**63) (not a bool), None otherwise (noted)."""
    value = obj.get(name)
    if value is None:
        return None
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < _INT64_LIMIT:
        return value
    problems.append(f"{name} must be an integer in [0, 2**63), got {_clip_repr(value)}")
    return None


def _clip_repr(value, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


@dataclass
class ReceivedFrame:
    """One sample from the image key.

    payload: the raw bytes; encoding: the zenoh encoding string; key: the sample key;
    meta: the publisher's attachment; recv_ns: time.time_ns() when taken from the ring;
    recv_mono_ns: time.monotonic_ns() at the same moment (for latency); error: set by a
    subscriber that had to unwrap the frame (ROS 2 CDR) and could not (a FrameError: the
    frame is counted as bad under its reason).
    """

    payload: bytes
    encoding: str
    key: str
    meta: FrameMeta
    recv_ns: int
    recv_mono_ns: int
    error: Exception | None = None

    @property
    def stamp_ns(self) -> int:
        """Capture stamp: the publisher's, else the receive time (ns, Unix epoch)."""
        return self.meta.stamp_ns if self.meta.stamp_ns is not None else self.recv_ns


@dataclass
class DropCounter:
    """Counts sequence gaps per source.

    dropped: frames skipped (gaps in seq, counted from the first frame received from a
    source: frames published before the subscriber saw that source are not drops); restarts: seq
    went backwards (publisher restart) or jumped ahead by more than MAX_GAP (no publisher skips
    that many frames: a reset or a forged seq, which must not swell `dropped`);
    unsequenced: frames without a seq (their drops cannot be counted).
    At most MAX_SOURCES sources are tracked (the least recently seen is forgotten), so a
    peer inventing source ids cannot grow the table without bound.
    """

    MAX_SOURCES = 256
    #: Largest gap counted as drops: a day of frames at 100 Hz.
    MAX_GAP = 100 * 86_400

    dropped: int = 0
    restarts: int = 0
    unsequenced: int = 0
    _last: dict[str, int] = field(default_factory=dict)

    def update(self, meta: FrameMeta) -> int:
        """Account one received frame; returns the number of frames dropped just before it."""
        if meta.seq is None:
            self.unsequenced += 1
            return 0
        last = self._last.pop(meta.src, None)
        self._last[meta.src] = meta.seq  # re-inserted: dict order = least recently seen first
        if len(self._last) > self.MAX_SOURCES:
            del self._last[next(iter(self._last))]
        if last is None:
            return 0
        if meta.seq <= last or meta.seq - last > self.MAX_GAP:
            self.restarts += 1
            return 0
        gap = meta.seq - last - 1
        self.dropped += gap
        return gap


def poll_ring(sub, key: str, timeout_s: float, waiter: threading.Event, max_poll_s: float,
              accept=None) -> zenoh.Sample | None:
    """The oldest sample of a RingChannel subscriber that ``accept`` takes (all when None), or
    None after ``timeout_s`` or once ``waiter`` is set.

    The ring handler has no blocking receive with a timeout, so it is polled with an exponential
    back-off from 0.2 ms to ``max_poll_s``, waiting on ``waiter`` (a stop event wakes it at once).
    Raises TransportError when the subscriber fails.
    """
    deadline = time.monotonic() + max(0.0, timeout_s)
    wait = 0.0002
    while True:
        try:
            sample = sub.try_recv()
        except zenoh.ZError as exc:
            raise TransportError(f"subscriber on {key!r} failed: {_short(exc)}") from exc
        if sample is not None:
            if accept is None or accept(sample):
                return sample
            continue
        now = time.monotonic()
        if now >= deadline or waiter.is_set():
            return None
        waiter.wait(min(wait, deadline - now))
        wait = min(wait * 2, max_poll_s)


class FrameSubscriber:
    """Subscriber on the image key with a ``RingChannel(queue_size)``: newest frames win.

    ``receive(timeout_s)`` polls the ring (zenoh's ``recv`` has no timeout) with a short
    back-off of ``poll_s`` (seconds) at most, so it adds at most ~poll_s of latency.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        *,
        queue_size: int = 2,
        ignore_keys: tuple[str, ...] = (),
        poll_s: float = 0.002,
    ) -> None:
        if not isinstance(queue_size, int) or queue_size < 1:
            raise ConfigError(f"queue size must be a positive integer, got {queue_size!r}")
        self.key = key
        self.queue_size = queue_size
        self.poll_s = poll_s
        self._ignore = set(ignore_keys)
        self.drops = DropCounter()
        self.received = 0
        self.ignored = 0
        self.bad_attachments = 0
        self.last_bad_attachment = ""
        self._wake = threading.Event()
        try:
            self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(queue_size))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {key!r}: {_short(exc)}") from exc

    def receive(self, timeout_s: float, stop_event: threading.Event | None = None) -> ReceivedFrame | None:
        """Return the oldest frame still in the ring, or None after timeout_s (or stop)."""
        sample = poll_ring(self._sub, self.key, timeout_s, stop_event or self._wake, self.poll_s, self._accept)
        return None if sample is None else self._to_frame(sample, str(sample.key_expr))

    def _accept(self, sample: zenoh.Sample) -> bool:
        if str(sample.key_expr) in self._ignore:
            self.ignored += 1
            return False
        return True

    def _to_frame(self, sample: zenoh.Sample, key: str) -> ReceivedFrame:
        att = sample.attachment
        meta = FrameMeta.from_attachment(att.to_bytes() if att is not None else None)
        if meta.problem:
            self.bad_attachments += 1
            self.last_bad_attachment = meta.problem
        self.drops.update(meta)
        self.received += 1
        return ReceivedFrame(
            payload=sample.payload.to_bytes(),
            encoding=str(sample.encoding),
            key=key,
            meta=meta,
            recv_ns=time.time_ns(),
            recv_mono_ns=time.monotonic_ns(),
        )

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass


class JsonPublisher:
    """Publishes JSON documents (``application/json``) on one key, dropping under congestion."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.key = key
        try:
            self._pub = session.declare_publisher(
                key, encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=zenoh.CongestionControl.DROP
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare publisher on {key!r}: {_short(exc)}") from exc

    def put(self, doc: dict | bytes) -> None:
        """Publish a dict, or JSON bytes already made (a message's ``to_json_bytes()``)."""
        data = doc if isinstance(doc, bytes) else json.dumps(doc, separators=(",", ":")).encode()
        try:
            self._pub.put(data)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {self.key!r}: {_short(exc)}") from exc

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except zenoh.ZError:
            pass


class ResultPublisher:
    """Publishes per-frame results on the results key and stats on ``<results key>/stats``."""

    def __init__(self, session: zenoh.Session, result_key: str) -> None:
        self.result_key = result_key
        self.stats_key = stats_key_for(result_key)
        self._results = JsonPublisher(session, result_key)
        self._stats = JsonPublisher(session, self.stats_key)

    def publish_result(self, result: dict | bytes) -> None:
        self._results.put(result)

    def publish_stats(self, stats: dict | bytes) -> None:
        self._stats.put(stats)

    def close(self) -> None:
        self._results.close()
        self._stats.close()


class FramePublisher:
    """Publishes frames on the image key with a FrameMeta attachment (seq from 0, stamp, src).

    congestion: ``drop`` (default: a live camera should never block) or ``block``.
    """

    def __init__(self, session: zenoh.Session, key: str, *, congestion: str = "drop", src: str | None = None) -> None:
        if congestion not in ("drop", "block"):
            raise ConfigError(f"congestion must be 'drop' or 'block', got {congestion!r}")
        self.key = key
        self.src = src or uuid.uuid4().hex[:12]
        self.seq = 0
        cc = zenoh.CongestionControl.DROP if congestion == "drop" else zenoh.CongestionControl.BLOCK
        self._matched = threading.Event()
        try:
            self._pub = session.declare_publisher(key, congestion_control=cc)
            self._listener = self._pub.declare_matching_listener(self._on_matching)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare publisher on {key!r}: {_short(exc)}") from exc
        if self._pub.matching_status.matching:
            self._matched.set()

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._matched.set()
        else:
            self._matched.clear()

    def wait_for_subscriber(self, timeout_s: float) -> bool:
        """Block until a subscriber matches the key (True) or timeout_s elapses (False)."""
        return self._matched.wait(timeout_s)

    def put(self, payload: bytes, encoding: str, stamp_ns: int | None = None) -> int:
        """Publish one frame; returns its sequence number."""
        seq = self.seq
        meta = FrameMeta(seq=seq, stamp_ns=stamp_ns if stamp_ns is not None else time.time_ns(), src=self.src)
        try:
            self._pub.put(payload, encoding=zenoh.Encoding(encoding), attachment=meta.to_attachment())
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish frame on {self.key!r}: {_short(exc)}") from exc
        self.seq += 1
        return seq

    def close(self) -> None:
        try:
            self._listener.undeclare()
            self._pub.undeclare()
        except zenoh.ZError:
            pass
