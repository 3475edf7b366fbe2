"""The runtime image recipe (Dockerfile at the repo root). No Docker engine runs here or in CI, so
the image is not built by the tests: these check the recipe's essentials as written."""

from __future__ import annotations

import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TRAINER_ONLY = ("torch", "onnx", "onnxscript", "scipy", "matplotlib")


def _instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) in order, continuation lines joined, comments dropped."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        keyword, _, args = (pending + line).partition(" ")
        out.append((keyword.upper(), args.strip()))
        pending = ""
    return out


def _stages(instructions: list[tuple[str, str]]) -> list[list[tuple[str, str]]]:
    stages: list[list[tuple[str, str]]] = []
    for ins in instructions:
        if ins[0] == "FROM":
            stages.append([])
        if stages:
            stages[-1].append(ins)
    return stages


DOCKERFILE = REPO / "Dockerfile"


def test_base_image_is_pinned_to_the_locked_python_on_debian_12():
    ins = _instructions(DOCKERFILE)
    args = dict(arg.split("=", 1) for kw, arg in ins if kw == "ARG" and "=" in arg)
    base = args["PYTHON_IMAGE"]
    assert re.fullmatch(r"python:3\.11(\.\d+)?-slim-bookworm(@sha256:[0-9a-f]{64})?", base), base
    assert all(arg.split()[0] == "${PYTHON_IMAGE}" for kw, arg in ins if kw == "FROM")
    # The lock is resolved for the image's Python.
    assert "--python-version 3.11" in (REPO / "deploy" / "lock.sh").read_text()


def test_installs_the_hashed_lock_and_no_trainer_packages():
    runs = " ".join(arg for kw, arg in _instructions(DOCKERFILE) if kw == "RUN")
    assert "--require-hashes" in runs and "--only-binary=:all:" in runs and "requirements-board.txt" in runs
    assert "pip check" in runs
    installs = [cmd for cmd in re.split(r"&&|;", runs) if re.search(r"pip (install|wheel)", cmd)]
    words = set(re.findall(r"[A-Za-z0-9_.\[\]-]+", " ".join(installs)))
    assert not words & set(TRAINER_ONLY), "the image installs the runtime set only"
    assert not any(re.search(r"\[(train|dev|plot)", w) for w in words), "no extras in the image"
    assert "import torch" in runs, "the build fails if torch slipped into the runtime venv"
    assert (REPO / "deploy" / "requirements-board.txt").is_file()


def test_final_stage_runs_aefabmap_as_a_non_root_user():
    final = _stages(_instructions(DOCKERFILE))[-1]
    users = [arg for kw, arg in final if kw == "USER"]
    assert users, "the runtime stage must set USER"
    uid = users[-1].split(":")[0]
    assert uid not in ("root", "0")
    assert json.loads(dict(final)["ENTRYPOINT"]) == ["aefabmap"]


def test_health_or_smoke_test_is_stated():
    text = DOCKERFILE.read_text()
    keywords = [kw for kw, _ in _instructions(DOCKERFILE)]
    assert "HEALTHCHECK" in keywords
    assert re.search(r"docker run --rm \S+ demo", text), "the smoke test (`docker run IMAGE demo`) must be documented"


def test_build_context_leaves_out_the_venv_and_git():
    ignored = {line.strip() for line in (REPO / ".dockerignore").read_text().splitlines()}
    assert {".git", ".venv"} <= ignored
    assert "aefabmap" not in ignored and "runtime" not in ignored
