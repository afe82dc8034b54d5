"""A folder's calibration warnings grouped by kind: one line for each kind of
warning, with how many of the folder's pairs it concerns and their names
(abbreviated), not one line a pair (500 pairs once gave 2,840 lines).

A kind is a warning's text whatever its pair: its numbers and the pair's
file paths left out, and the training-range warning one kind whatever
parameters it lists. A grouped line quotes its first pair's warning as
given, values and all (each pair's values are in the JSON)."""

from __future__ import annotations

import re

#: The training-range warning's words before its list of values.
OUTSIDE_RANGE = "predictions outside the training labels' range, in the model's input units"
#: The pairs a grouped line names before "and N others".
NAMED = 3
_NUMBER = re.compile(r"[-+]?(?:\d[\d,]*(?:\.\d*)?|\.\d+)(?:e[-+]?\d+)?", re.IGNORECASE)


def warning_kind(line, paths=()):
    """What ``line`` warns of, whatever its pair: its numbers, and ``paths``
    (the pair's files) where it names them, left out."""
    text = line.removeprefix("warning: ")
    if text.startswith(OUTSIDE_RANGE):
        return OUTSIDE_RANGE
    for path in paths:
        text = text.replace(str(path), "<file>")
    return _NUMBER.sub("#", text)


def abbreviate(names, named=NAMED):
    """``names`` joined, the first ``named`` then how many others (none left
    out for one more than ``named``)."""
    if len(names) <= named + 1:
        return ", ".join(names)
    return f"{', '.join(names[:named])} and {len(names) - named} others"


class WarningGroups:
    """The warnings of a folder's pairs by kind, in the order first given:
    ``add`` each (``name`` None: a warning about the run, not its pair,
    given once as it is), then ``lines``."""

    def __init__(self):
        self._groups = {}   # kind -> (its first line, the names of its pairs)

    def add(self, name, line, paths=()):
        key = (name is None, line if name is None else warning_kind(line, paths))
        first, names = self._groups.setdefault(key, (line, []))
        if name is not None and name not in names:
            names.append(name)

    def lines(self, total):
        """One line for each kind: ``warning: K of N pairs (NAMES), as on
        FIRST: ...`` (``as on`` for more than one)."""
        said = []
        for first, names in self._groups.values():
            if not names:
                said.append(first)
                continue
            where = f", as on {names[0]}" if len(names) > 1 else ""
            said.append(f"warning: {len(names)} of {total} pair{'s' if total > 1 else ''} "
                        f"({abbreviate(names)}){where}: {first.removeprefix('warning: ')}")
        return said
