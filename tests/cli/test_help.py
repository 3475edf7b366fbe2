"""Every command's --help, walked over the real parser: each option explained, options grouped, exit codes stated."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from aefabmap.cli.main import build_parser
from aefabmap.cli.options import EXIT_CODES

#: A command with more options than this puts every one in a named group, not argparse's default "options".
HANDFUL = 6
DEFAULT_GROUPS = ("options", "optional arguments")


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, parser) of `parser` and of every nested subcommand."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


def _options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in parser._actions if a.option_strings and not isinstance(a, argparse._HelpAction)]


COMMANDS = [path for path, _ in _parsers(build_parser())]


def _parser(path: tuple[str, ...]) -> argparse.ArgumentParser:
    return dict(_parsers(build_parser()))[path]


def _words(text: str) -> str:
    return " ".join(text.split())


def test_the_walk_reaches_every_command_and_nested_subcommand():
    assert {("train",), ("bench", "soak"), ("bench", "inference"), ("log", "repair"), ("slam",)} <= set(COMMANDS)
    assert sum(len(_options(p)) for _, p in _parsers(build_parser())) > 200


@pytest.mark.parametrize("path", COMMANDS, ids=lambda p: " ".join(p) or "aefabmap")
def test_every_option_and_argument_has_help(path):
    parser = _parser(path)
    arguments = [a for a in parser._actions
                 if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
    missing = [a.option_strings[0] if a.option_strings else a.dest for a in arguments
               if not (a.help or "").strip() or a.help == argparse.SUPPRESS]
    assert missing == []


@pytest.mark.parametrize("path", COMMANDS, ids=lambda p: " ".join(p) or "aefabmap")
def test_a_command_with_more_than_a_handful_of_options_groups_every_one_by_name(path):
    parser = _parser(path)
    if len(_options(parser)) <= HANDFUL:
        return
    group_of = {id(a): g.title for g in parser._action_groups for a in g._group_actions}
    ungrouped = [a.option_strings[0] for a in _options(parser) if group_of.get(id(a)) in DEFAULT_GROUPS]
    assert ungrouped == []
    assert all((group_of[id(a)] or "").strip() for a in _options(parser))


@pytest.mark.parametrize("path", COMMANDS, ids=lambda p: " ".join(p) or "aefabmap")
def test_every_help_ends_with_the_exit_codes(path):
    assert _words(_parser(path).format_help()).endswith(_words(EXIT_CODES))


@pytest.mark.parametrize("path", [(), ("bench", "soak"), ("log", "repair")], ids=lambda p: " ".join(p) or "aefabmap")
def test_the_command_line_prints_the_exit_codes_in_its_help(path):
    out = subprocess.run([sys.executable, "-m", "aefabmap.cli.main", *path, "--help"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert _words(out.stdout).endswith(_words(EXIT_CODES))
