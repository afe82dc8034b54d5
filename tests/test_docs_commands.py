"""Every command the README and docs/ print is one the command lines accept:
its flags exist and its values pass their checks. Commands with a
placeholder (a CAPITALISED name such as RUN_DIR or DATA.h5, ``...``, an
optional ``[--flag]``, or ``$VARIABLE``) are templates, as README.md says;
they are checked too once the placeholders are filled in with examples. The
cheap ones also run, each in a fresh clone, and leave its `git status` clean."""

import argparse
import glob
import os
import re
import shlex
import shutil
import subprocess
import sys

import pytest

from helpers import REPO, main_functions

DOCUMENTS = ["README.md"] + sorted(
    os.path.relpath(p, REPO) for p in glob.glob(os.path.join(REPO, "docs", "*.md")))
#: A placeholder word: capitals, digits and _ (two or more letters), maybe with an extension.
PLACEHOLDER = re.compile(r"(?<![\w/.-])([A-Z][A-Z0-9_]{1,})(\.[a-z0-9]+)?(?![\w])")
#: How a template's placeholders are filled in for the check.
EXAMPLES = {"RUN_DIR": "runs/x", "RUN_A": "runs/a", "RUN_B": "runs/b", "DATA": "data/x",
            "DIR": "some/dir", "LEFT": "left", "RIGHT": "right", "N": "3", "OUT": "out"}
#: The command lines the docs use, by how they are invoked.
ENTRY = {"train.py": "train.py", "evaluate.py": "evaluate.py",
         "cpl_keras.reproduce": "reproduce", "cpl_keras.data.generate": "data.generate",
         "cpl_keras.data.mix": "data.mix", "cpl_keras.data.import_cvgl": "data.import_cvgl",
         "cpl_keras.calibrate": "calibrate", "cpl_keras.graph": "graph",
         "cpl_keras.real.build": "real.build", "cpl_keras.real.chessboard": "real.chessboard",
         "cpl_keras.learning_curves": "learning_curves"}


def shell_lines():
    """``(document, line)`` for every line of the docs' code blocks, the
    parts of ``a && b`` apart."""
    found = []
    for document in DOCUMENTS:
        with open(os.path.join(REPO, document)) as f:
            text = f.read()
        for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S):
            for line in block.replace("\\\n", " ").splitlines():
                found += [(document, part.strip()) for part in re.split(r"\s&&\s", line.strip())
                          if part.strip().split(" ")[0] in ("python", "mkdir", "cp", "tar")]
    return found


def documented_commands():
    """``(document, command text)`` for every ``python ...`` line of a code
    block (continuation lines joined, the shell comment dropped)."""
    return [(document, re.sub(r"\s+#.*$", "", line)) for document, line in shell_lines()
            if line.startswith("python ") and "<<" not in line]


def _fill(command):
    """The template with its placeholders filled in and its options chosen."""
    command = re.sub(r"\[([^\[\]]*)\]", lambda m: m.group(1).split("|")[0], command)
    command = command.replace("...", "").replace("$OUT", "out")
    return PLACEHOLDER.sub(lambda m: EXAMPLES.get(m.group(1), m.group(1).lower())
                           + (m.group(2) or ""), command)


def _argv(command):
    words = shlex.split(command)[1:]
    if words[0] == "-m":
        return words[1], words[2:]
    return os.path.basename(words[0]), words[1:]


class _Parsed(Exception):
    pass


COMMANDS = documented_commands()


def test_the_docs_have_commands_and_say_what_a_template_is():
    assert len(COMMANDS) > 40
    with open(os.path.join(REPO, "README.md")) as f:
        assert "CAPITALISED" in f.read()


@pytest.mark.parametrize("document, command", COMMANDS,
                         ids=[f"{d}:{c[:60]}" for d, c in COMMANDS])
def test_every_documented_command_parses(document, command, monkeypatch):
    entry, argv = _argv(_fill(command))
    if entry not in ENTRY:
        pytest.skip(f"{entry}: a benchmark or another tool")
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        raise _Parsed(original(self, args, namespace))

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    main = main_functions()[ENTRY[entry]]
    with pytest.raises(_Parsed):
        main(argv)


#: The cheap documented commands run for real, at tiny scale (the flags added
#: last override the printed ones), each in a fresh clone of the repository:
#: (entry, added flags).
CHEAP = {"cpl_keras.data.generate": ["--pairs", "6", "--image-size", "32", "--workers", "1",
                                     "--no-progress"],
         "cpl_keras.real.build": ["--image-size", "32", "--crops", "1"]}


def _effect(argv):
    """What a command line does, but for where it writes (a flag given twice:
    its last value): two documented commands of the same effect run once
    (where each writes is checked for all of them:
    ``test_every_place_a_documented_command_writes_is_ignored_or_rewritten_the_same``)."""
    positional, flags, i = [], {}, 0
    while i < len(argv):
        if argv[i].startswith("--"):
            value = argv[i + 1] if i + 1 < len(argv) and not argv[i + 1].startswith("--") else None
            flags[argv[i]] = "PATH" if argv[i] in WRITES else value
            i += 2 if value is not None else 1
        else:
            positional.append(argv[i])
            i += 1
    return tuple(positional), tuple(sorted(flags.items(), key=lambda kv: kv[0]))


def _git(*args, cwd):
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=60, check=True).stdout


@pytest.mark.slow
def test_the_cheap_documented_commands_leave_a_clean_checkout(tmp_path):
    """Every README and docs command of the data generator and the real-set
    builder that is not a template runs as printed (at tiny scale) from the
    root of a fresh clone of the repository, exits 0, and leaves `git status
    --porcelain` there empty: what it writes goes under the git-ignored
    data/ and runs/, never over a tracked file nor beside them (two at a
    time, each in a clone of its own, removed once checked). The repository
    itself is left as it was."""
    if subprocess.run(["git", "rev-parse", "--is-inside-work-tree"], cwd=REPO,
                      capture_output=True, timeout=60).returncode != 0:
        pytest.skip("the repository is not a git checkout")
    ran, pending = [], []
    env = dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=REPO)
    before = _git("status", "--porcelain", cwd=REPO)
    for document, command in COMMANDS:
        entry, argv = _argv(command)
        if entry not in CHEAP or _fill(command) != command or \
                (entry, _effect(argv + CHEAP[entry])) in ran:
            continue
        ran.append((entry, _effect(argv + CHEAP[entry])))
        pending.append((document, command, [sys.executable, "-m", entry, *argv, *CHEAP[entry]]))
    # two at a time (the machine's two cores), each in a clone of its own
    for start in range(0, len(pending), 2):
        running = []
        for number, (document, command, args) in enumerate(pending[start:start + 2], start):
            clone = tmp_path / str(number)
            _git("clone", "--quiet", "--shared", REPO, str(clone), cwd=tmp_path)
            assert _git("status", "--porcelain", cwd=clone) == ""
            running.append((document, command, clone, subprocess.Popen(
                args, cwd=clone, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                text=True)))
        for document, command, clone, process in running:
            _, err = process.communicate(timeout=600)
            assert process.returncode == 0, (document, command, err[-2000:])
            status = _git("status", "--porcelain", cwd=clone)
            assert status == "", (document, command, status)
            assert any((clone / d).is_dir() for d in ("data", "runs")), command
            shutil.rmtree(clone)
    assert {entry for entry, _ in ran} == set(CHEAP), ran
    assert len(ran) >= 5
    assert _git("status", "--porcelain", cwd=REPO) == before   # nothing written into it


#: Flags whose value is a file or folder the command writes.
WRITES = ("--out", "--out-dir", "--preview", "--json-out", "--opencv-yaml", "--ros-yaml",
          "--run-dir", "--runs-dir", "--data-dir", "--dot", "--from-predictions")
#: Tracked places a documented command writes again, and the test that shows
#: its rerun leaves their bytes as they are (so `git status` stays empty).
REWRITTEN = {
    "paper_results/": "test_reproduce.py::test_rerunning_a_documented_preset_leaves_the_published"
                      "_record_untouched; test_paper_results.py (tables rebuilt from predictions)",
    "docs/camera_graph.": "test_graph.py::test_cli_prints_the_table_and_writes_the_diagram",
    "docs/": "test_data_cli.py::test_the_committed_contact_sheets_are_the_current_generators",
}


def written_paths(command):
    """The files and folders a documented shell line writes: the path flags'
    values, a reproduction's default folders, train.py's default run
    directory, and what ``python -m venv``, ``mkdir``, ``cp`` and ``tar -C``
    make."""
    from cpl_keras.reproduce.presets import default_folders

    words = shlex.split(command.split(" #")[0])
    if words[:3] == ["python", "-m", "venv"]:
        return [w + "/" for w in words[3:]]
    if words[:1] == ["mkdir"]:
        return [w + "/" for w in words[1:] if not w.startswith("-")]
    if words[:1] == ["cp"]:
        return words[-1:]
    if words[:1] == ["tar"]:
        return [words[words.index("-C") + 1]] if "-C" in words else []
    if words[:1] != ["python"]:
        return []
    entry, argv = _argv(" ".join(shlex.quote(w) for w in words))
    paths = [argv[i + 1] + ("/" if word.endswith("dir") else "")
             for i, word in enumerate(argv[:-1]) if word in WRITES]
    if entry == "cpl_keras.reproduce" and "--from-predictions" not in argv:
        preset = "quick" if "--quick" in argv else (
            argv[argv.index("--preset") + 1] if "--preset" in argv else None)
        out, data_dir, runs_dir = default_folders(preset)
        given = dict(zip(argv, argv[1:]))
        paths += [given.get("--out", out), given.get("--data-dir", data_dir),
                  given.get("--runs-dir", runs_dir)]
    if entry == "train.py" and "--run-dir" not in argv:
        paths.append("runs/")
    return paths


def test_every_place_a_documented_command_writes_is_ignored_or_rewritten_the_same():
    """What the documented commands make (datasets, runs, a venv, folders)
    goes where git ignores it; the tracked places they write (the published
    record, the docs' figures) are rewritten byte for byte, each with the
    test that shows it: so a documented command, run as printed, leaves
    `git status` empty. (``python -m venv bench-venv`` left an untracked
    folder.)"""
    checked, outside = 0, []
    for document, line in shell_lines():
        if _fill(line) != line:
            continue  # (a template: the user names its places)
        for path in written_paths(line):
            path = os.path.relpath(path, REPO) if os.path.isabs(path) else path
            path = os.path.normpath(path) + ("/" if path.endswith("/") else "")
            checked += 1
            ignored = subprocess.run(["git", "check-ignore", "-q", "--no-index", path], cwd=REPO,
                                     timeout=60).returncode == 0
            if not ignored and not any(path.startswith(place) for place in REWRITTEN):
                outside.append((document, line, path))
    assert checked > 60
    assert outside == [], "\n".join(map(str, outside))


def test_no_script_writes_gits_own_files():
    """No command, script or benchmark of the repository edits .git/ (the
    wheels bench/paper_gpu.sh fetches go to .whl/, which .gitignore
    ignores)."""
    sources = [os.path.join(REPO, name) for name in ("train.py", "evaluate.py")]
    for folder in ("bench", "analyses", "cpl_keras"):
        for root, _, files in os.walk(os.path.join(REPO, folder)):
            sources += [os.path.join(root, f) for f in files if f.endswith((".py", ".sh"))]
    assert len(sources) > 50
    for path in sources:
        with open(path) as f:
            assert ".git/" not in f.read(), path
    with open(os.path.join(REPO, ".gitignore")) as f:
        assert "/.whl/" in f.read().split()


def _generated(argv):
    """``(out, settings)`` of a generator command line (its parsed arguments)."""
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        raise _Parsed(original(self, args, namespace))

    argparse.ArgumentParser.parse_args = parse_then_stop
    try:
        main_functions()["data.generate"](argv)
    except _Parsed as parsed:
        args = parsed.args[0]
    finally:
        argparse.ArgumentParser.parse_args = original
    return args.out, (args.protocol, args.pairs, args.seed, args.image_size)


def test_no_two_documented_datasets_of_other_settings_share_a_name(monkeypatch):
    """docs/training.md's `generate --pairs 123017 --out data/cvgl.h5` was
    refused (rightly) after docs/data.md had made a 10,000-pair
    data/cvgl.h5: two generator commands of README.md and docs/ (and the
    full-scale one the demonstration prints) with other settings never
    write the same --out."""
    from cpl_keras.commands import train

    lines = [(document, command) for document, command in COMMANDS
             if _argv(command)[0] == "cpl_keras.data.generate" and _fill(command) == command]
    monkeypatch.setattr(train, "estimate_cost", lambda *a, **k: (_ for _ in ()).throw(OSError))
    demo = [line.strip() for line in train.next_step("cpl-a", "demo.h5").splitlines()
            if "cpl_keras.data.generate" in line]
    assert len(demo) == 1
    lines.append(("the demonstration's next step", demo[0]))
    made = {}
    for document, command in lines:
        out, settings = _generated(_argv(command)[1])
        if out is not None:
            made.setdefault(os.path.normpath(out), {}).setdefault(settings, document)
    assert len(made) >= 6
    shared = {out: found for out, found in made.items() if len(found) > 1}
    assert not shared, shared
