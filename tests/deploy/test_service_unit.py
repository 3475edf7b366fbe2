"""The systemd unit (deploy/aefabmap.service): its command line is one the CLI accepts, it is
hardened, and `systemd-analyze security` rates its exposure <= 4.0."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from aefabmap.cli.main import build_parser
from aefabmap_runtime.errors import BundleError, ConfigError
from tests.deploy.unit_file import UNIT_PATH, read_unit, run_argv

MAX_EXPOSURE = 4.0


@pytest.fixture(scope="module")
def service() -> dict[str, list[str]]:
    return read_unit()["Service"]


def _one(service: dict[str, list[str]], key: str) -> str:
    values = service.get(key)
    assert values, f"{key}= missing from {UNIT_PATH.name}"
    return values[-1]


def test_exec_start_is_accepted_by_the_cli(service):
    # argparse exits (SystemExit 2) on an unknown option, e.g. a --state the CLI does not have yet.
    args = build_parser().parse_args(run_argv(service))
    assert args.command == "run"
    assert args.mcap.startswith("/var/log/aefabmap/"), "the log must go to LogsDirectory="
    assert args.image_every == 30, "one image a second from a 30 Hz camera"
    # Zenoh on loopback only: a local router, and no listener reachable from the network.
    assert args.connect == ["tcp/127.0.0.1:7447"]
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in args.listen) and args.listen


def test_runs_unprivileged_with_its_own_directories(service):
    assert _one(service, "DynamicUser") == "yes"
    assert "User" not in service
    assert _one(service, "StateDirectory") == "aefabmap"
    assert _one(service, "LogsDirectory") == "aefabmap"
    assert _one(service, "UMask") == "0077"


def test_does_not_restart_on_a_bad_config_or_bundle(service):
    assert _one(service, "Restart") == "on-failure"
    prevented = {int(code) for code in _one(service, "RestartPreventExitStatus").split()}
    assert prevented == {ConfigError.exit_code, BundleError.exit_code} == {2, 3}


def test_hardening_settings(service):
    expected = {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "PrivateDevices": "yes",
        "ProtectKernelTunables": "yes",
        "ProtectKernelModules": "yes",
        "ProtectKernelLogs": "yes",
        "ProtectControlGroups": "yes",
        "RestrictNamespaces": "yes",
        "LockPersonality": "yes",
        "MemoryDenyWriteExecute": "yes",
        "SystemCallArchitectures": "native",
        "CapabilityBoundingSet": "",
        "IPAddressDeny": "any",
    }
    got = {key: service.get(key, [None])[-1] for key in expected}
    assert got == expected
    assert set(_one(service, "RestrictAddressFamilies").split()) == {"AF_INET", "AF_INET6", "AF_UNIX", "AF_NETLINK"}
    assert service["SystemCallFilter"][0] == "@system-service"


def _exposure(unit: Path) -> float:
    out = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", "--no-pager", str(unit)],
        check=False, capture_output=True, text=True, timeout=60,
    )
    match = re.search(r"Overall exposure level for \S+: ([0-9.]+)", out.stdout + out.stderr)
    assert match, f"no exposure figure in systemd-analyze output:\n{out.stdout}\n{out.stderr}"
    return float(match.group(1))


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_exposure_is_low(tmp_path):
    exposure = _exposure(UNIT_PATH)
    print(f"systemd-analyze security exposure of {UNIT_PATH.name}: {exposure}")
    assert exposure <= MAX_EXPOSURE
    # The figure must move with the unit: the same unit with no hardening is rated unsafe.
    bare = tmp_path / "aefabmap.service"
    bare.write_text("[Service]\nExecStart=/opt/aefabmap/bin/aefabmap run\n")
    assert _exposure(bare) > MAX_EXPOSURE
