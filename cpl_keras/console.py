"""The installed command lines (pyproject.toml's ``[project.scripts]``).

Each leaves through ``cli.run`` as the modules' ``__main__`` blocks do, and
imports its command's module inside ``cli.run``'s Ctrl-C guard (the guard
is in place at once; the module's imports take a moment):

    cpl-train        train.py                          (cpl_keras.commands.train)
    cpl-evaluate     evaluate.py                       (cpl_keras.commands.evaluate)
    cpl-reproduce    python -m cpl_keras.reproduce         (cpl_keras.commands.reproduce)
    cpl-calibrate    python -m cpl_keras.calibrate         (cpl_keras.commands.calibrate)
    cpl-graph        python -m cpl_keras.graph             (cpl_keras.commands.graph)
    cpl-generate     python -m cpl_keras.data.generate     (cpl_keras.commands.generate)
    cpl-real-build   python -m cpl_keras.real.build        (cpl_keras.commands.real_build)
    cpl-chessboard   python -m cpl_keras.real.chessboard   (cpl_keras.commands.chessboard)
    cpl-mix          python -m cpl_keras.data.mix          (cpl_keras.commands.mix)
    cpl-import-cvgl  python -m cpl_keras.data.import_cvgl  (cpl_keras.commands.import_cvgl)
    cpl-learning-curves  python -m cpl_keras.learning_curves  (cpl_keras.commands.learning_curves)

``cpl-train`` and ``cpl-evaluate`` go by those names in their lines and in
the commands they record; the others by their ``python -m`` form, which
runs wherever the package is installed.
"""

from __future__ import annotations

import importlib

from cpl_keras import cli


def _main(module, **options):
    """``main`` of ``module``, imported when called."""
    return lambda: importlib.import_module(module).main(**options)


def train():
    cli.run(_main("cpl_keras.commands.train", prog="cpl-train"), "cpl-train")


def evaluate():
    def main():
        try:
            return _main("cpl_keras.commands.evaluate", prog="cpl-evaluate")()
        except KeyboardInterrupt:  # (during the import; evaluate's main says the same)
            return cli.interrupted("cpl-evaluate", note="nothing was written")

    cli.run(main, "cpl-evaluate", note="nothing was written")


def _command(name, prog):
    """The console command that runs ``cpl_keras.commands.<name>``'s main
    as ``prog`` (its ``python -m`` form)."""
    def command():
        cli.run(_main(f"cpl_keras.commands.{name}"), prog)

    command.__name__ = command.__qualname__ = name
    command.__doc__ = f"``{prog}``"
    return command


reproduce = _command("reproduce", "python -m cpl_keras.reproduce")
calibrate = _command("calibrate", "python -m cpl_keras.calibrate")
graph = _command("graph", "python -m cpl_keras.graph")
generate = _command("generate", "python -m cpl_keras.data.generate")
real_build = _command("real_build", "python -m cpl_keras.real.build")
chessboard = _command("chessboard", "python -m cpl_keras.real.chessboard")
mix = _command("mix", "python -m cpl_keras.data.mix")
import_cvgl = _command("import_cvgl", "python -m cpl_keras.data.import_cvgl")
learning_curves = _command("learning_curves", "python -m cpl_keras.learning_curves")
