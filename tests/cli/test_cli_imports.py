"""The CLI's shape: each command module parses its options and prints; it imports no other
command's helpers, only the shared options module (aefabmap/cli/options.py). main.py's registry
is the one place that loads the commands."""

from __future__ import annotations

import ast
from pathlib import Path

from aefabmap.cli.main import SUBCOMMAND_MODULES

CLI = Path(__file__).resolve().parents[2] / "aefabmap" / "cli"
SHARED = {"options"}


def _cli_imports(path: Path) -> list[str]:
    """The aefabmap.cli modules `path` imports (statements anywhere, relative ones included)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith("aefabmap.cli")]
        elif isinstance(node, ast.ImportFrom):
            module = "aefabmap.cli" + (f".{node.module}" if node.module else "") if node.level else node.module or ""
            if module == "aefabmap.cli":  # from aefabmap.cli import run
                found += [f"aefabmap.cli.{a.name}" for a in node.names]
            elif module.startswith("aefabmap.cli."):
                found.append(module)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "import_module":
            found.append("importlib.import_module")
    return found


def test_cli_modules_import_only_the_shared_options_module():
    wrong = []
    for path in sorted(CLI.glob("*.py")):
        for name in _cli_imports(path):
            if path.stem == "main" and name == "importlib.import_module":
                continue  # the registry: SUBCOMMAND_MODULES
            if name.removeprefix("aefabmap.cli.") not in SHARED:
                wrong.append(f"{path.name} imports {name}")
    assert not wrong, "\n".join(wrong)


def test_every_cli_module_is_a_registered_command_or_the_shared_options():
    modules = {p.stem for p in CLI.glob("*.py")} - {"__init__", "main"}
    assert modules - SHARED == set(SUBCOMMAND_MODULES)
    assert not SHARED & set(SUBCOMMAND_MODULES)


def test_the_check_sees_every_form_of_import(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import aefabmap.cli.run\nfrom aefabmap.cli import replay\nfrom .demo import x\n"
                     "def f():\n    from aefabmap.cli.bench import _model\n    importlib.import_module('m')\n")
    assert _cli_imports(probe) == ["aefabmap.cli.run", "aefabmap.cli.replay", "aefabmap.cli.demo",
                                   "aefabmap.cli.bench", "importlib.import_module"]
