"""Every generated page of paper_results/ says so on its first line and
regenerates, byte for byte, from the committed files.

A generated page's first line names the command that wrote it
(``cpl_keras.files.generated_line``). The writer of that command has a
``regenerate(page_path)`` that renders the page again from committed files
only (its JSON twin, committed logs or predictions): no weights, datasets or
run directories, which a fresh clone does not have. The reproduction
folders' pages (``python -m cpl_keras.reproduce``) are rebuilt whole by
tests/test_paper_results.py; every other generated page is rebuilt here.
"""

import importlib
import shlex
from pathlib import Path

import pytest

from cpl_keras import files
from helpers import REPO, load_script

RESULTS = Path(REPO) / "paper_results"
PAGES = sorted(RESULTS.rglob("*.md"))
#: Commands whose pages another test rebuilds (the whole folder at once).
REBUILT_ELSEWHERE = ("python -m cpl_keras.reproduce",)
#: Module-run commands: the module holding their writer's ``regenerate``.
MODULES = {"cpl_keras.learning_curves": "cpl_keras.learning_curves"}
#: Top-level scripts whose pages the package renders.
SCRIPTS = {"evaluate.py": "cpl_keras.report"}
#: Written pages that have a JSON file of their name beside them, and why.
WRITTEN_WITH_JSON = {
    "cpu/discussion.md": "an input of the reproduction's REPORT.md",
    "faithful-2000/test-inception_v3/table2.md": "corrected by hand; the JSON holds the numbers "
                                                 "of the old pooling, which the page states",
    "faithful-2000/test-small_resnet/table2.md": "corrected by hand; the JSON holds the numbers "
                                                 "of the old pooling, which the page states",
}


def _command(page):
    return files.generated_command(page.read_text())


def _regenerate(command):
    """The ``regenerate`` of the writer that ``command`` runs."""
    words = shlex.split(command)
    assert words[0] == "python", command
    if words[1] == "-m":
        return importlib.import_module(MODULES[words[2]]).regenerate
    if words[1] in SCRIPTS:
        return importlib.import_module(SCRIPTS[words[1]]).regenerate
    return load_script(words[1]).regenerate


GENERATED = [p for p in PAGES if _command(p) and not _command(p).startswith(REBUILT_ELSEWHERE)]


@pytest.mark.parametrize("page", GENERATED, ids=lambda p: str(p.relative_to(RESULTS)))
def test_a_generated_page_regenerates_from_the_committed_files(page):
    assert _regenerate(_command(page))(str(page)) == page.read_text()


def test_pages_are_generated_or_written_and_say_which():
    """A page without the generated line is written by hand: it has no JSON
    twin that a script would have written beside it."""
    assert len(GENERATED) >= 40  # (the pages of analyses/, bench/ and evaluate.py)
    for page in PAGES:
        if _command(page):
            continue
        twin = page.with_suffix(".json")
        name = str(page.relative_to(RESULTS))
        assert not twin.exists() or name in WRITTEN_WITH_JSON, \
            f"{name} has no generated line but a JSON twin"
    assert files.generated_command(files.generated_line("python x.py --a 'b c'")) == \
        "python x.py --a 'b c'"
    assert files.generated_command("# Title\n") is None
