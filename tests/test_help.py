"""Every command's ``--help`` fits a screen: under 60 lines at 80 and 100
columns, never wider than 100 characters however wide the terminal, with a
description that is a whole sentence. Options left out of a help are named
in its epilog, and the docs page it points to has each of them."""

import argparse
import os
import re

import pytest

from helpers import REPO, main_functions

MAX_LINES = 60
MAX_WIDTH = 100


class _Captured(Exception):
    pass


def parsers():
    """``(label, parser)`` of every command and of real.build's subcommands."""
    found = []
    original = argparse.ArgumentParser.parse_args

    def capture(self, args=None, namespace=None):
        raise _Captured(self)

    argparse.ArgumentParser.parse_args = capture
    try:
        for name, main in main_functions().items():
            with pytest.raises(_Captured) as caught:
                main([])
            found.append((name, caught.value.args[0]))
    finally:
        argparse.ArgumentParser.parse_args = original
    for name, parser in list(found):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                found += [(f"{name} {sub}", p) for sub, p in action.choices.items()]
    return found


PARSERS = parsers()


@pytest.mark.parametrize("columns", [80, 100, 240])
def test_every_help_is_under_60_lines_and_at_most_100_wide(columns, monkeypatch):
    """``cpl-train --help`` was 163 lines and 147 characters wide."""
    monkeypatch.setenv("COLUMNS", str(columns))
    assert len(PARSERS) >= 11
    too_long = []
    for name, parser in PARSERS:
        lines = parser.format_help().splitlines()
        width = max(map(len, lines))
        if len(lines) >= MAX_LINES or width > min(columns, MAX_WIDTH):
            too_long.append(f"{name}: {len(lines)} lines, {width} wide")
    assert not too_long, too_long


def test_every_description_is_a_whole_sentence():
    """``cpl-reproduce --help`` described itself with a cut sentence (its
    docstring's first line, ending in a comma)."""
    cut = []
    for name, parser in PARSERS:
        text = " ".join((parser.description or "").split())
        whole = (re.fullmatch(r"[A-Z].*[.?]", text) and text.count("(") == text.count(")")
                 and text.count("``") % 2 == 0)
        if not whole:
            cut.append(f"{name}: {text!r}")
    assert not cut, cut


def test_options_left_out_of_a_help_are_named_in_its_epilog_and_in_the_docs():
    """A help kept short names the options it leaves out, and the docs page
    its epilog points to (docs/*.md) has every one of them."""
    left_out = 0
    for name, parser in PARSERS:
        hidden = [action.option_strings[0] for action in parser._actions
                  if action.help == argparse.SUPPRESS and action.option_strings]
        if not hidden:
            continue
        epilog = " ".join((parser.epilog or "").split())
        page = re.search(r"docs/[a-z_-]+\.md", epilog)
        assert page, (name, epilog)
        with open(os.path.join(REPO, page.group(0))) as f:
            docs = f.read()
        for flag in hidden:
            left_out += 1
            assert re.search(rf"(?<![\w-]){flag}(?![\w-])", epilog), (name, flag)
            assert f"`{flag}" in docs, (name, flag, page.group(0))
    assert left_out >= 10   # (cpl-train's)


def test_every_option_of_train_is_in_the_options_table():
    """docs/training.md's options table lists every option of ``cpl-train``,
    shown in its help or not."""
    parser = dict(PARSERS)["train.py"]
    with open(os.path.join(REPO, "docs", "training.md")) as f:
        table = f.read().split("## Options", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| `--")]
    for action in parser._actions:
        flag = action.option_strings[-1] if action.option_strings else None
        if flag and flag not in ("-h", "--help"):
            assert any(re.match(rf"\| `{flag}[ `]", row) for row in rows), flag
