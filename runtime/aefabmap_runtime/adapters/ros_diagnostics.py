"""The node's health as ROS 2 tools read it (diagnostic_msgs/DiagnosticArray on /diagnostics),
built from its stats without any transport: the rmw_zenoh and bridge publishers send it, and the
ros2-profile log records it (mcap_log.py), so reading or writing a log never imports Zenoh."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

from aefabmap_runtime.adapters.ros_cdr import DiagnosticStatus, encode_diagnostic_array_cdr

#: Where ROS tools (rqt_robot_monitor, the diagnostic aggregator) read health: absolute, so it
#: stays ``/diagnostics`` in any namespace.
DIAGNOSTICS_TOPIC = "/diagnostics"
#: diagnostic_msgs/DiagnosticStatus levels.
DIAG_OK, DIAG_WARN, DIAG_ERROR = 0, 1, 2


def diagnostic_level(stats: dict, previous: dict | None) -> tuple[int, str]:
    """(level, message) of a stats message: ERROR when the log failed; WARN when frames were
    dropped or refused since the previous stats, or the log is not ok; else OK."""
    state = stats.get("log_state")
    if state == "failed":
        return DIAG_ERROR, "the log failed (no file open; retried)"
    reasons = []
    for key, what in (("dropped", "frames dropped"), ("bad_total", "frames refused")):
        new = int(stats.get(key) or 0) - int((previous or {}).get(key) or 0)
        if new > 0:
            reasons.append(f"{new} {what}")
    if state not in (None, "ok"):
        reasons.append(f"log {state}")
    return (DIAG_WARN, "; ".join(reasons)) if reasons else (DIAG_OK, "ok")


def diagnostic_values(stats: dict, status=None) -> tuple[tuple[str, str], ...]:
    """The key/value pairs of the node's DiagnosticStatus: counters, bad frames by reason,
    latency, memory and log state from the stats; places, map MB and per-stage ms (medians
    over recent frames) from the status when given."""
    latency = stats.get("latency_ms") or {}
    pairs = [(k, stats.get(k)) for k in ("frames_received", "frames_processed", "dropped", "publisher_restarts",
                                         "bad_total", "loops", "fps", "rss_mb", "uptime_s")]
    pairs += [(f"bad {reason}", n) for reason, n in sorted((stats.get("bad") or {}).items()) if n]
    pairs += [("latency p50 ms", latency.get("p50")), ("latency p95 ms", latency.get("p95"))]
    if status is not None:
        pairs += [("places", status.places), ("map_mb", status.map_mb)]
        pairs += [(f"stage {name} ms", ms) for name, ms in sorted(status.stage_ms.items())]
    pairs += [("log_state", stats.get("log_state")), ("log_errors", stats.get("log_errors"))]
    return tuple((k, "" if v is None else str(v)) for k, v in pairs)


def node_diagnostic(stats: dict, status, previous: dict | None, *, name: str, hardware_id: str, node: str = "",
                    distro: str = "") -> DiagnosticStatus:
    """The node's DiagnosticStatus for one stats message (see diagnostic_level, diagnostic_values)."""
    level, message = diagnostic_level(stats, previous)
    values = diagnostic_values(stats, status) + (("node", node), ("ros_distro", distro))
    return DiagnosticStatus(level, name, message, hardware_id, values)


def json_text(doc: dict | bytes) -> str:
    """A message as the JSON text a std_msgs/String carries (bytes: already JSON)."""
    return doc.decode("utf-8") if isinstance(doc, bytes) else json.dumps(doc, separators=(",", ":"))


def diagnostics_cdr(stats: dict | bytes | str, status_source: Callable[[], object] | None, previous: dict | None, *,
                    name: str, hardware_id: str, node: str, distro: str = "") -> tuple[bytes, dict]:
    """One stats message as the DiagnosticArray CDR a ROS 2 publisher sends (node_diagnostic),
    with the node's status when `status_source` gives it; returns (the CDR, the stats as a dict:
    the next call's `previous`, which the level compares against)."""
    doc = json.loads(stats) if isinstance(stats, (bytes, str)) else stats
    status = None
    if status_source is not None:
        try:
            status = status_source()
        except Exception:  # noqa: BLE001 - the diagnostics go out without the status's extras
            status = None
    entry = node_diagnostic(doc, status, previous, name=name, hardware_id=hardware_id, node=node, distro=distro)
    return encode_diagnostic_array_cdr(int(doc.get("stamp_ns") or time.time_ns()), [entry]), doc
