"""Writing files atomically: the package's ground floor (it imports nothing
of the package, so every module can use it).

``atomic_path`` is the one way the package writes a file: under a temporary
name beside it, fsync'd, then renamed into place and the rename fsync'd
(its folder), so a kill at any moment leaves the old file or the new one,
never half of one. ``write_text``,
``write_json`` and ``save_figure`` go through it; ``read_json`` reads back.
A failed write is an ``OSError`` of one line naming the file
(``write_failed``), and ``new_folders`` makes an output's folders, removed
again if the write fails.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import sys
import tempfile
import warnings


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
    """Flush the finished temporary file ``tmp`` to disk, rename it to
    ``path`` and flush the rename (``sync_folder``)."""
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)
    sync_folder(os.path.dirname(os.path.abspath(path)))


def sync_folder(folder):
    """Flush ``folder``'s entries to disk (``fsync`` of the folder), so that
    a rename into it outlives a power cut or a crash of the system, not
    only of the process; nothing where the system or file system cannot
    (an ``OSError``: no such folder, or no fsync of folders)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


#: The temporary files of the atomic writes now in progress (``remove_unfinished``).
_unfinished = set()


def mark_unfinished(tmp):
    """Count ``tmp`` among the temporary files of unfinished writes, which
    ``remove_unfinished`` removes (a Ctrl-C's exit): for a writer that names
    its own temporary file (``data.writer.StereoWriter``)."""
    _unfinished.add(tmp)


def unmark_unfinished(tmp):
    """``tmp``'s write is over (committed or discarded): ``mark_unfinished`` undone."""
    _unfinished.discard(tmp)


def remove_unfinished():
    """Remove the temporary files of every atomic write still in progress (a
    process about to end at once, ``cli.run`` after a Ctrl-C)."""
    for tmp in list(_unfinished):
        try:
            os.remove(tmp)
        except OSError:
            pass


def write_failed(path, error):
    """The one line of a failed write of ``path`` (``error``: an ``OSError``,
    or the ``RuntimeError`` or ``OSError`` of a file library such as h5py,
    which carries the system's errno in its text): a full disk and a file
    over the system's size limit said in words. An error that says it
    already (``atomic_path``'s) is left as it is."""
    text = str(error)
    if text.startswith(f"cannot write {path}: "):
        return text
    number = getattr(error, "errno", None)
    if number == errno.ENOSPC or "No space left" in text or "errno = 28" in text:
        return f"cannot write {path}: no space left on the device"
    if number == errno.EFBIG or "File too large" in text or "errno = 27" in text:
        return f"cannot write {path}: the file is larger than this system allows"
    first = text.strip().splitlines()[0] if text.strip() else type(error).__name__
    return f"cannot write {path}: {first}"


@contextlib.contextmanager
def library_write(path):
    """A file library (h5py under Keras's ``save_weights``) writing ``path``:
    on a failure the process is marked to end without the interpreter's
    teardown, where the library, left in a failed state, can crash, and the
    exceptions that its handles print as they close are kept quiet from
    then on (``abandon``; the caller reports the failure in one line,
    ``write_failed``)."""
    previous = _quiet_h5py()
    try:
        yield
    except (OSError, RuntimeError):
        abandon()
        raise
    except BaseException:
        sys.excepthook, sys.unraisablehook = previous
        raise
    if not _abandoned:
        sys.excepthook, sys.unraisablehook = previous


def _from_h5py(tb):
    """Whether the traceback ``tb`` starts in h5py's compiled handles."""
    return tb is not None and "h5py" in tb.tb_frame.f_code.co_filename


def _quiet_h5py():
    """From now on, the exceptions that h5py's handles raise as they are
    released (each printed as a traceback, through ``sys.excepthook``, and
    an "Exception ignored" line, through ``sys.unraisablehook``) print
    nothing: after a failed write they are the same failure, already said.
    Returns the hooks it replaced."""
    excepthook, unraisablehook = sys.excepthook, sys.unraisablehook

    def quiet_excepthook(kind, value, tb):
        if not _from_h5py(tb):
            excepthook(kind, value, tb)

    def quiet_unraisablehook(report):
        if "h5py" not in repr(report.object) and not _from_h5py(report.exc_traceback):
            unraisablehook(report)

    sys.excepthook, sys.unraisablehook = quiet_excepthook, quiet_unraisablehook
    return excepthook, unraisablehook


#: Objects whose files could not be finished (``abandon``), kept alive.
_abandoned = []


def abandon(*handles):
    """Keep ``handles`` (a file library's objects whose file a failed write
    left unfinished: HDF5's after a full disk) alive until the process
    ends, and mark the process to end without the interpreter's teardown,
    where closing them would write again and crash (``teardown_unsafe``)."""
    if not _abandoned and sys.excepthook.__name__ != "quiet_excepthook":
        _quiet_h5py()
    _abandoned.append(handles or (None,))


def teardown_unsafe():
    """Whether this process holds abandoned handles (``abandon``): then a
    command ends with ``os._exit`` once its output is flushed (``cli.run``)."""
    return bool(_abandoned)


@contextlib.contextmanager
def atomic_path(*paths):
    """Yield temporary paths (one per ``path``, the same extension) to write
    to; when the block ends without an error, each file is fsync'd and
    renamed into place, all of them or (on an error) none: the temporary
    files are removed and the final files left as they were. With one path,
    yields one temporary path; with several, a list. An ``OSError`` in the
    block or the renames (a full disk's ENOSPC names no file) is raised
    again as one naming the file, in one line (``_failed_write``)."""
    tmps = [_partial(os.fspath(p)) for p in paths]
    _unfinished.update(tmps)
    try:
        try:
            yield tmps[0] if len(tmps) == 1 else tmps
            for tmp, path in zip(tmps, paths):
                commit(tmp, path)
        except OSError as error:
            raise _failed_write(tmps, paths, error) from None
    finally:
        for tmp in tmps:
            if os.path.exists(tmp):
                os.remove(tmp)
        _unfinished.difference_update(tmps)


def _failed_write(tmps, paths, error):
    """An ``OSError`` (``write_failed``'s line, ``error``'s errno) for the
    ``OSError`` ``error`` of ``atomic_path`` that wrote ``tmps`` for
    ``paths``: it names the file that ``error`` names, else the last one
    whose temporary file was begun (the files are written in turn)."""
    named = {os.path.abspath(t): os.fspath(p) for t, p in zip(tmps, paths)}
    names = [getattr(error, name, None) for name in ("filename", "filename2")]
    path = next((named[os.path.abspath(n)] for n in names
                 if isinstance(n, str) and os.path.abspath(n) in named), None)
    if path is None:
        begun = [os.fspath(p) for t, p in zip(tmps, paths) if os.path.exists(t)]
        path = begun[-1] if begun else os.fspath(paths[0])
    failure = OSError(write_failed(path, error))
    failure.errno = error.errno  # (its text stays the line: no strerror)
    return failure


def cannot_write(folder):
    """Why no file can be made in ``folder`` (while it is missing, in the
    nearest folder above it, where it would be made), in the OSError's
    words, or None when one can: a nameless file made there and gone at
    once, since ``os.access`` says yes to root on /proc. Nothing is left."""
    folder = os.path.abspath(os.fspath(folder))
    while not os.path.isdir(folder):
        if os.path.lexists(folder):
            return f"{folder} is not a folder"
        folder = os.path.dirname(folder)
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        return error.strerror or " ".join(str(error).split())
    return None


@contextlib.contextmanager
def new_folders(*paths):
    """Create the missing folders above the files ``paths``, once every one
    is known to be possible (``OSError`` in one line, and nothing made, when
    a file stands where a folder must be); when the block ends with an
    exception, remove those made again (each if still empty), so that a
    failed command leaves no empty folder. Yields the folders made,
    outermost first."""
    missing = []
    for path in paths:
        folder = os.path.dirname(os.path.abspath(os.fspath(path)))
        while not os.path.isdir(folder):
            if os.path.exists(folder):
                raise OSError(f"cannot write {os.fspath(path)}: {folder} is a file, "
                              "not a folder")
            missing.append(folder)
            folder = os.path.dirname(folder)
    made = []
    try:
        for folder in sorted(set(missing), key=len):
            if not os.path.isdir(folder):
                os.mkdir(folder)
                made.append(folder)
        yield made
    except BaseException:
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                os.rmdir(folder)  # (only if it is still empty)
        raise


def write_text(path, text):
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(text)


def write_json(path, payload, indent=2):
    """Write ``payload`` as JSON to ``path`` atomically (strict JSON: no NaN)."""
    write_text(path, json.dumps(payload, indent=indent) + "\n")


#: The first line of every page a script writes: which command, and not by hand.
GENERATED = "<!-- generated by `{command}`; do not edit by hand -->"


def generated_line(command):
    """The first line of a generated Markdown page: the command that wrote
    it, and that it is not to be edited by hand (a test regenerates it)."""
    return GENERATED.format(command=command)


def generated_command(text):
    """The command named by a page's first line, or None for a written page."""
    first = text.split("\n", 1)[0]
    prefix, suffix = GENERATED.split("{command}")
    if first.startswith(prefix) and first.endswith(suffix):
        return first[len(prefix):len(first) - len(suffix)]
    return None


def page_source(page_path):
    """``(command, payload)`` of a generated page: the command on its first
    line and the JSON beside it (the same name, ``.json``), what a writer's
    ``regenerate`` renders the page again from."""
    with open(page_path) as f:
        command = generated_command(f.read())
    return command, read_json(os.path.splitext(page_path)[0] + ".json")


def write_page(path, text, payload):
    """A Markdown page ``path`` (``.md``) and its figures as JSON beside it
    (the same name, ``.json``), each atomically; returns the JSON's path."""
    json_path = os.path.splitext(path)[0] + ".json"
    write_text(path, text)
    write_json(json_path, payload)
    return json_path


#: matplotlib's warning for a character no font of its has (a file name in
#: Japanese in a figure's title): one line per character, and the box drawn
#: in its place says as much.
MISSING_GLYPH = r"Glyph \d+ .*missing from font"


@contextlib.contextmanager
def glyphs_quiet():
    """matplotlib's missing-glyph warnings off within the block (a figure's
    layout and its saving: where text is drawn)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=MISSING_GLYPH, category=UserWarning)
        yield


def save_figure(fig, path, **savefig_args):
    """Save the matplotlib figure ``fig`` to ``path`` atomically, then close
    it (``glyphs_quiet``)."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path) as tmp, glyphs_quiet():
            fig.savefig(tmp, **savefig_args)
    finally:
        plt.close(fig)


def read_json(path, default=None):
    """The JSON in ``path``, or ``default`` when there is no such file."""
    if not os.path.exists(path):
        return default
    with open(path) as f:
        return json.load(f)
