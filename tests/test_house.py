"""The house's shape: the layering contracts in pyproject.toml hold (import-linter reads every
import, those inside functions too, and runs no project code), and every import of the project's
own modules resolves to a file from its dotted name alone, as static readers resolve it."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: Each package and the one folder that holds it (setup.py's ROOTS).
ROOTS = {
    "aefabmap": REPO / "aefabmap",
    "aefabmap_runtime": REPO / "runtime" / "aefabmap_runtime",
    "aefabmap_trainer": REPO / "trainer" / "aefabmap_trainer",
    "aefabmap_export": REPO / "export" / "aefabmap_export",
}
CORE = ROOTS["aefabmap_runtime"] / "core"


def _lint(*extra: str) -> subprocess.CompletedProcess:
    # A subprocess: import-linter's graph must see the files as they are now (a probe included).
    code = ("import sys; from importlinter.cli import lint_imports; "
            f"sys.exit(lint_imports(config_filename={str(REPO / 'pyproject.toml')!r}, no_cache=True, no_logo=True))")
    return subprocess.run([sys.executable, "-c", code, *extra], capture_output=True, text=True, timeout=300, cwd=REPO)


@pytest.mark.slow
def test_layering_contracts_hold():
    out = _lint()
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "0 broken" in out.stdout


@pytest.mark.slow
def test_a_stage_importing_upward_breaks_a_contract():
    probe = CORE / "kernels" / "_layering_probe.py"
    probe.write_text("from aefabmap_runtime.core.detector import LoopClosureDetector\n")
    try:
        out = _lint()
    finally:
        probe.unlink()
    assert out.returncode != 0 and "BROKEN" in out.stdout, out.stdout[-3000:]
    assert "aefabmap_runtime.core.kernels._layering_probe" in out.stdout


def _project_files() -> list[Path]:
    return sorted(p for root in ROOTS.values() for p in root.rglob("*.py") if "__pycache__" not in p.parts)


def _resolve(dotted: str) -> Path | None:
    """The file a static reader opens for `dotted`: the package's folder, then the path."""
    top, _, rest = dotted.partition(".")
    base = ROOTS[top].joinpath(*rest.split(".")) if rest else ROOTS[top]
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return base if base.is_dir() else None  # a folder without __init__.py (shipped data)


def test_every_project_import_resolves_to_a_file_from_its_name():
    unresolved = []
    for f in _project_files() + sorted((REPO / "tests").rglob("*.py")) + sorted((REPO / "scripts").rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
                package = _resolve(node.module) if node.module.split(".")[0] in ROOTS else None
                if package is not None and package.name == "__init__.py":  # `from pkg import module` names a file too
                    names += [f"{node.module}.{a.name}" for a in node.names if (package.parent / f"{a.name}.py").is_file()]
            else:
                continue
            for name in names:
                if name.split(".")[0] in ROOTS and _resolve(name) is None:
                    unresolved.append(f"{f.relative_to(REPO)}: {name}")
    assert not unresolved, "\n".join(unresolved)


def test_each_package_lives_in_one_folder_and_the_repo_has_no_symlinks():
    tracked = subprocess.run(["git", "ls-files", "-s"], capture_output=True, text=True, cwd=REPO)
    if tracked.returncode != 0:
        pytest.skip("not a git checkout")
    links = [line.split("\t")[1] for line in tracked.stdout.splitlines() if line.startswith("120000")]
    assert not links, f"symlinks in the repository: {links}"
    for name, folder in ROOTS.items():
        others = [p for p in REPO.glob(f"*/{name}") if p != folder and p.is_dir() and ".venv" not in p.parts]
        assert folder.is_dir() and not others, f"{name}: {folder} and {others}"


def test_no_modules_left_in_the_flat_core_folder():
    flat = sorted(p.name for p in CORE.glob("*.py") if p.name not in ("__init__.py", "detector.py", "run_config.py",
                                                                      "profiles.py"))
    assert not flat, f"runtime/aefabmap_runtime/core holds the composition and stage folders only; found {flat}"


def test_offline_replay_does_not_import_zenoh():
    """replay/eval run on a laptop without a network stack: loading a detector and replaying a log
    must not import the transport (it used to, through node.py)."""
    code = ("import sys; import aefabmap.cli.replay, aefabmap.cli.eval; "
            "from aefabmap_runtime.adapters import replay, bundle_reader; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('zenoh', 'torch', 'onnx')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout
