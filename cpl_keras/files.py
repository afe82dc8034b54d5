"""Writing files atomically: the package's ground floor (it imports nothing
of the package, so every module can use it).

``atomic_path`` is the one way the package writes a file: under a temporary
name beside it, fsync'd, then renamed into place, so a kill at any moment
leaves the old file or the new one, never half of one. ``write_text``,
``write_json`` and ``save_figure`` go through it; ``read_json`` reads back.
"""

from __future__ import annotations

import contextlib
import json
import os


def _partial(path):
    """``path``'s temporary name, keeping its extension (savers pick the
    format from it; Keras's weights files must end in ``.weights.h5``)."""
    directory, name = os.path.split(path)
    for ext in (".weights.h5", ".partial"):
        if name.endswith(ext):
            break
    else:
        ext = os.path.splitext(name)[1]
    stem = name[: len(name) - len(ext)] if ext else name
    return os.path.join(directory, f".{stem}.partial{ext}")


def commit(tmp, path):
    """Flush the finished temporary file ``tmp`` to disk and rename it to ``path``."""
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


#: The temporary files of the atomic writes now in progress (``remove_unfinished``).
_unfinished = set()


def remove_unfinished():
    """Remove the temporary files of every atomic write still in progress (a
    process about to end at once, ``cli.run`` after a Ctrl-C)."""
    for tmp in list(_unfinished):
        try:
            os.remove(tmp)
        except OSError:
            pass


@contextlib.contextmanager
def atomic_path(*paths):
    """Yield temporary paths (one per ``path``, the same extension) to write
    to; when the block ends without an error, each file is fsync'd and
    renamed into place, all of them or (on an error) none: the temporary
    files are removed and the final files left as they were. With one path,
    yields one temporary path; with several, a list."""
    tmps = [_partial(os.fspath(p)) for p in paths]
    _unfinished.update(tmps)
    try:
        yield tmps[0] if len(tmps) == 1 else tmps
        for tmp, path in zip(tmps, paths):
            commit(tmp, path)
    finally:
        for tmp in tmps:
            if os.path.exists(tmp):
                os.remove(tmp)
        _unfinished.difference_update(tmps)


def write_text(path, text):
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(text)


def write_json(path, payload, indent=2):
    """Write ``payload`` as JSON to ``path`` atomically (strict JSON: no NaN)."""
    write_text(path, json.dumps(payload, indent=indent) + "\n")


def save_figure(fig, path, **savefig_args):
    """Save the matplotlib figure ``fig`` to ``path`` atomically, then close it."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, **savefig_args)
    finally:
        plt.close(fig)


def read_json(path, default=None):
    """The JSON in ``path``, or ``default`` when there is no such file."""
    if not os.path.exists(path):
        return default
    with open(path) as f:
        return json.load(f)
