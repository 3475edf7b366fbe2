"""The runtime's shape, checked by reading imports (no module is executed).

core/ is pure (no adapters, no tools, no I/O libraries); adapters/ wrap it (never tools);
tools/ sit beside. The board runtime never imports torch, onnx or the trainer; nothing under
runtime/ imports the offline SLAM tool (aefabmap.slam) or its libraries (gtsam, evo).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
RUNTIME = REPO / "runtime"

# Third-party or stdlib modules that mean I/O or transport: core must not import them.
CORE_FORBIDDEN = ("zenoh", "mcap", "mcap_protobuf", "foxglove", "foxglove_schemas_protobuf", "socket",
                  "subprocess", "tqdm", "matplotlib", "torch", "onnx", "rosbags")
# What the board runtime (core + adapters) must never pull in.
BOARD_FORBIDDEN = ("torch", "onnx", "onnxscript", "scipy", "matplotlib", "aefabmap.trainer", "aefabmap.export")
# The SLAM extra (aefabmap[slam]): an offline laptop tool on top of the runtime, never under it.
SLAM_ONLY = ("gtsam", "evo", "aefabmap.slam")


def _imports(path: Path) -> set[str]:
    """Absolute module names imported anywhere in a file (top level or inside functions)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def _modules(layer: str) -> list[Path]:
    files = sorted((RUNTIME / layer).rglob("*.py"))
    assert files, f"runtime/{layer} has no modules"
    return files


def _violations(layer: str, forbidden: tuple[str, ...]) -> list[str]:
    out = []
    for f in _modules(layer):
        for name in _imports(f):
            if any(name == bad or name.startswith(bad + ".") for bad in forbidden):
                out.append(f"{f.relative_to(REPO)} imports {name}")
    return out


def test_core_imports_neither_adapters_nor_tools_nor_io_libraries():
    bad = _violations("core", ("aefabmap.runtime.adapters", "aefabmap.runtime.tools", *CORE_FORBIDDEN))
    assert not bad, "\n".join(bad)


def test_adapters_never_import_tools():
    assert not (bad := _violations("adapters", ("aefabmap.runtime.tools",))), "\n".join(bad)


@pytest.mark.parametrize("layer", ["core", "adapters"])
def test_board_runtime_never_imports_the_trainer_stack(layer):
    assert not (bad := _violations(layer, BOARD_FORBIDDEN)), "\n".join(bad)


@pytest.mark.parametrize("layer", ["core", "adapters", "tools"])
def test_runtime_never_imports_the_slam_tool_or_its_libraries(layer):
    assert not (bad := _violations(layer, SLAM_ONLY)), "\n".join(bad)


def test_no_modules_left_in_the_flat_runtime_folder():
    flat = [p.name for p in RUNTIME.glob("*.py") if p.name != "__init__.py"]
    assert not flat, f"runtime/ should hold only sub-packages; found {flat}"


def test_checker_sees_a_violation():
    """The checker itself works: a synthetic file that breaks the rule is caught."""
    probe = RUNTIME / "core" / "_layering_probe.py"
    probe.write_text("from aefabmap.runtime.adapters import frames\n")
    try:
        assert _violations("core", ("aefabmap.runtime.adapters",))
    finally:
        probe.unlink()


def test_every_module_resolves_statically_from_the_repo_root():
    """Static readers (IDEs, type checkers) find every aefabmap.* module as a file under the
    repo root: aefabmap/runtime, aefabmap/trainer and aefabmap/export point at the design card's
    top-level folders, with no import hook or package-dir remapping in between."""
    for sub in ("runtime", "trainer", "export"):
        link = REPO / "aefabmap" / sub
        assert link.resolve() == (REPO / sub).resolve(), f"aefabmap/{sub} must lead to {sub}/"
    for f in (REPO / "runtime").rglob("*.py"):
        dotted = "aefabmap.runtime." + ".".join(f.relative_to(RUNTIME).with_suffix("").parts)
        static = REPO.joinpath(*dotted.split(".")).with_suffix(".py")
        assert static.is_file(), f"{dotted} does not resolve to {static}"
    pyproject = (REPO / "pyproject.toml").read_text()
    assert '"aefabmap.runtime" = "runtime"' not in pyproject, "package-dir remapping is back"


def test_offline_replay_does_not_import_zenoh():
    """replay/eval run on a laptop without a network stack: loading a detector and replaying a log
    must not import the transport (it used to, through node.py)."""
    import subprocess
    import sys

    code = ("import sys; import aefabmap.cli.replay, aefabmap.cli.eval; "
            "from aefabmap.runtime.adapters import replay, bundle_reader; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('zenoh', 'torch', 'onnx')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout
