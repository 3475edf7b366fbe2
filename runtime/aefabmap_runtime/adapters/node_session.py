"""The Zenoh session a node opens from its endpoints (`run`, and `replay --fleet`).

With none given the node listens on loopback only (zenoh_transport.cli_session_config). A ROS 2
run joins the rmw_zenoh router instead, which owns that port. A fleet node that only connects
joins as a Zenoh client. A session accepted with --allow-exposure says at start how it is exposed;
a fleet node whose session has no mutual TLS says that the fleet's peers are not authenticated.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

from aefabmap_runtime.adapters.rmw_zenoh import ROS_PEER_LISTEN
from aefabmap_runtime.adapters.zenoh_transport import (
    SessionConfig,
    cli_session_config,
    session_authenticated,
    session_exposure,
)
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig

#: The node's log, under the name its operators know from `run`.
log = logging.getLogger("aefabmap.run")


@dataclass(frozen=True)
class Endpoints:
    """The endpoints a command was given: connect / listen (``tcp/HOST:PORT``), a zenoh JSON5
    config file, and whether a session other hosts reach without authentication is accepted."""

    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    allow_exposure: bool = False


def node_session(endpoints: Endpoints, *, ros: bool = False, fleet: FleetConfig | None = None,
                 logger: logging.Logger = log) -> SessionConfig:
    """The session of a node reading frames over plain Zenoh, or over ROS 2 (`ros`), in `fleet`
    (None: none); an accepted exposure is logged to `logger`. ConfigError for bad endpoints."""
    session = cli_session_config("connect" if ros else "listen", connect=endpoints.connect,
                                 listen=endpoints.listen, config_file=endpoints.config_file,
                                 allow_exposure=endpoints.allow_exposure)
    if ros and not endpoints.config_file and not endpoints.listen:
        # A peer of rmw_zenoh's graph on this host (router reachable, listening on loopback only).
        session = dataclasses.replace(session, mode="peer", listen=(ROS_PEER_LISTEN,))
    warn_exposure(session, logger)
    if fleet is not None and not session_authenticated(session):
        logger.warning("fleet %s: its peers are not authenticated (no mutual TLS): anyone who reaches the router can "
                       "offer places in any robot's name; see deploy/zenoh-fleet-router.json5", fleet.name)
    return fleet_session(session, fleet)


def warn_exposure(session: SessionConfig, logger: logging.Logger) -> None:
    """Log, at start, how a session accepted with --allow-exposure is exposed."""
    if session.allow_exposure:
        reasons = session_exposure(session)
        if reasons:
            logger.warning("network exposure accepted (--allow-exposure): the node %s", "; ".join(reasons))


def fleet_session(session: SessionConfig, fleet: FleetConfig | None) -> SessionConfig:
    """The session a fleet node opens: one that only connects (no listen endpoint, no config file,
    no mode given) joins as a Zenoh client, since peers behind a router exchange nothing unless
    each listens where the others reach it (docs/fleet.md)."""
    if fleet is None or session.mode is not None or session.config_file or session.listen or not session.connect:
        return session
    log.info("fleet %s: no listen endpoint: joining through %s as a Zenoh client", fleet.name,
             ", ".join(session.connect))
    return dataclasses.replace(session, mode="client")
