"""The session a node opens from its endpoints (runtime/aefabmap_runtime/adapters/node_session.py):
loopback by default, the rmw_zenoh router's peer for ROS 2, a client in a fleet that only connects."""

from __future__ import annotations

import logging

import pytest

from aefabmap_runtime.adapters.node_session import Endpoints, node_session
from aefabmap_runtime.adapters.rmw_zenoh import ROS_PEER_LISTEN
from aefabmap_runtime.adapters.zenoh_transport import DEFAULT_PORT, open_session
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.node_process import free_tcp_port

LOOPBACK = f"tcp/127.0.0.1:{DEFAULT_PORT}"
FLEET = FleetConfig(name="lab", robot="a")


def test_a_plain_node_listens_on_loopback_and_a_ros_node_joins_the_router_as_a_peer():
    assert node_session(Endpoints()).listen == (LOOPBACK,)
    ros = node_session(Endpoints(), ros=True)
    assert (ros.mode, ros.connect, ros.listen) == ("peer", (LOOPBACK,), (ROS_PEER_LISTEN,))
    given = node_session(Endpoints(connect=("tcp/127.0.0.1:7000",), listen=("tcp/127.0.0.1:7001",)), ros=True)
    assert (given.mode, given.listen) == (None, ("tcp/127.0.0.1:7001",))  # the endpoints given win


def test_a_fleet_node_that_only_connects_joins_as_a_client(caplog):
    only_connect = Endpoints(connect=("tcp/127.0.0.1:7000",))
    with caplog.at_level(logging.INFO, logger="aefabmap.run"):
        assert node_session(only_connect, fleet=FLEET).mode == "client"
    assert "joining through tcp/127.0.0.1:7000 as a Zenoh client" in caplog.text
    assert node_session(only_connect).mode is None
    assert node_session(Endpoints(connect=("tcp/127.0.0.1:7000",), listen=("tcp/127.0.0.1:7001",)),
                        fleet=FLEET).mode is None


def test_an_accepted_exposure_is_logged_once_and_a_refused_one_fails_to_open(caplog):
    exposed = Endpoints(listen=(f"tcp/0.0.0.0:{free_tcp_port()}",))
    logger = logging.getLogger("test.session")
    with caplog.at_level(logging.WARNING, logger="test.session"):
        refused = node_session(exposed, logger=logger)
        accepted = node_session(Endpoints(listen=exposed.listen, allow_exposure=True), logger=logger)
    warnings = [r.getMessage() for r in caplog.records if r.name == "test.session"]
    assert len(warnings) == 1 and warnings[0].startswith("network exposure accepted (--allow-exposure)")
    assert accepted.allow_exposure
    with pytest.raises(ConfigError, match="--allow-exposure"):
        open_session(refused)
