"""A fleet with mutual TLS and access control on one machine, from the shipped configs
(deploy/zenoh-fleet-router.json5, deploy/zenoh-fleet-robot.json5): certificates made with the
openssl command (one CA; CN = the robot id), and the two configs with their paths and ports
replaced. Used by scripts/fleet_experiment.py --tls and the deploy tests; a real fleet follows
deploy/README.md instead.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
ROUTER_CONFIG = DEPLOY / "zenoh-fleet-router.json5"
ROBOT_CONFIG = DEPLOY / "zenoh-fleet-robot.json5"
#: Where the shipped configs expect the certificates.
SHIPPED_TLS_DIR = "/etc/aefabmap/tls/"


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def make_certificates(d: Path, names: tuple[str, ...], ca: str = "ca") -> None:
    """A CA (CA.pem / CA.key) and, per name, NAME.pem / NAME.key with CN=NAME, valid for localhost."""
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", f"{ca}.key", "-out", f"{ca}.pem", "-days", "2", "-subj", f"/CN={ca}-test-ca", cwd=d)
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                               "keyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n")
    for name in names:
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
                 f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d)
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
                 "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", "ext.cnf", cwd=d)


def router_config(d: Path, port: int) -> Path:
    """The shipped fleet router config, listening on loopback `port`, with the certificates of d."""
    text = ROUTER_CONFIG.read_text().replace(SHIPPED_TLS_DIR, f"{d}/").replace("tls/0.0.0.0:7448",
                                                                                 f"tls/127.0.0.1:{port}")
    out = d / "fleet-router.json5"
    out.write_text(text)
    return out


def robot_config(d: Path, robot: str, router_port: int, listen: str) -> Path:
    """The shipped robot config for `robot` (its certificate ROBOT.pem in d), connecting to the
    router on loopback `router_port` and listening on `listen` for its camera."""
    text = (ROBOT_CONFIG.read_text().replace(f"{SHIPPED_TLS_DIR}robot.", f"{d}/{robot}.")
            .replace(SHIPPED_TLS_DIR, f"{d}/").replace("fleet-router.example:7448", f"localhost:{router_port}")
            .replace("tcp/127.0.0.1:7447", listen))
    out = d / f"robot-{robot}.json5"
    out.write_text(text)
    return out
