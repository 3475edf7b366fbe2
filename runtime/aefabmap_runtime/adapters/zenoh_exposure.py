"""Whether a Zenoh session configuration exposes the node to the network (pure, on a zenoh.Config).

Zenoh authenticates nobody by default: whoever reaches a listening endpoint can publish frames
(and so create false loop closures) or results. A session is *exposed* when it listens on an
endpoint another host can reach without authenticating, or joins multicast scouting (it then
announces itself and accepts peers found on the local network). Not exposed: loopback and
Unix-socket endpoints, and TLS/QUIC endpoints with mutual TLS (``transport/link/tls/enable_mtls``
and a root CA: every peer must show a certificate that CA signed). The CLI refuses an exposed
session unless ``--allow-exposure`` is given (zenoh_transport.build_zenoh_config); the same flag
is needed for a Foxglove live view bound beyond loopback (node_builder.view_exposure).
"""

from __future__ import annotations

import ipaddress
import json

import zenoh

#: Endpoint protocols that only the local host can reach.
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")
#: Protocols whose links can require a client certificate (mutual TLS).
TLS_PROTOCOLS = ("tls", "quic")


def _get(conf: zenoh.Config, path: str):
    return json.loads(conf.get_json(path))


def endpoints(conf: zenoh.Config, which: str = "listen") -> list[str]:
    """The endpoints the session will listen on or connect to (`which`; zenoh's per-mode form
    resolved for its mode)."""
    eps = _get(conf, f"{which}/endpoints")
    if isinstance(eps, dict):
        eps = eps.get(_get(conf, "mode") or "peer") or []
    return [str(e) for e in eps or []]


def listen_endpoints(conf: zenoh.Config) -> list[str]:
    """The endpoints the session will listen on."""
    return endpoints(conf, "listen")


def endpoint_host(endpoint: str) -> str | None:
    """The host part of "proto/host:port[?...][#...]" (brackets of an IPv6 address removed), or
    None for endpoints without one (Unix sockets)."""
    proto, _, rest = endpoint.partition("/")
    if proto in LOCAL_PROTOCOLS:
        return None
    addr = rest.split("?")[0].split("#")[0]
    host = addr.rpartition(":")[0] if ":" in addr else addr
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def is_loopback(endpoint: str) -> bool:
    """True when only this host can reach the endpoint (loopback address, localhost, Unix socket)."""
    host = endpoint_host(endpoint)
    return host is None or is_loopback_host(host)


def is_loopback_host(host: str) -> bool:
    """True when a server bound to `host` is reachable from this host only (a loopback address or
    localhost); the same rule as an endpoint's, for the live view's --foxglove-host."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name other than localhost may resolve anywhere; "" is every interface


def mutual_tls(conf: zenoh.Config) -> bool:
    """True when TLS/QUIC links require a client certificate signed by a configured CA."""
    tls = _get(conf, "transport/link/tls") or {}
    return bool(tls.get("enable_mtls")) and bool(tls.get("root_ca_certificate"))


def exposure(conf: zenoh.Config) -> list[str]:
    """Why the configured session is reachable without authentication ([] when it is not)."""
    reasons = []
    authenticated = mutual_tls(conf)
    for ep in listen_endpoints(conf):
        if is_loopback(ep) or (authenticated and ep.partition("/")[0] in TLS_PROTOCOLS):
            continue
        reasons.append(f"listens on {ep} without client authentication")
    if _get(conf, "scouting/multicast/enabled"):
        reasons.append("joins multicast scouting")
    return reasons
