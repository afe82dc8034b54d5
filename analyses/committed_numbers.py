"""The one way the figure scripts of analyses/ write, or check, the numbers
they draw: ``--check`` recomputes them from the committed files and compares
them with the committed JSON (exit 1 on a difference); otherwise the JSON is
written and then whatever is drawn from it (a figure, a page).

    from committed_numbers import check_or_write
    return check_or_write("forest_plot", OUT, result, check=args.check,
                          draw=lambda: plot(result, OUT + ".png"))
"""

from __future__ import annotations

import json
import os
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def check_or_write(script, out, result, *, check, draw, pages=None):
    """``out``.json against ``result`` (and each ``{path: text}`` of
    ``pages`` against its committed file) with ``check``; else write them
    and call ``draw()``. Returns the exit status."""
    result = json.loads(json.dumps(result))
    name = os.path.relpath(out, REPO) + ".json"
    pages = pages or {}
    if check:
        with open(out + ".json") as f:
            same = json.load(f) == result
        for path, text in pages.items():
            with open(path) as f:
                same = same and f.read() == text
        if not same:
            print(f"{script}: the committed {name} (or its page) differs from what the "
                  "committed files give", file=sys.stderr)
            return 1
        print(f"{script}: {name} is what the committed files give")
        return 0
    from cpl_keras import files

    files.write_json(out + ".json", result)
    for path, text in pages.items():
        files.write_text(path, text)
    draw()
    print(out + ".json")
    return 0


def parser(doc, what="JSON"):
    """A figure script's command line: its ``--check``."""
    import argparse

    made = argparse.ArgumentParser(description=doc.splitlines()[0])
    made.add_argument("--check", action="store_true",
                      help=f"recompute and compare with the committed {what} (exit 1 if not)")
    return made


def save(fig, path):
    """Lay ``fig`` out and save it at ``path`` (atomically; no software tag,
    so the same numbers give the same bytes)."""
    from cpl_keras import files

    fig.tight_layout()
    files.save_figure(fig, path, dpi=120, metadata={"Software": None})
