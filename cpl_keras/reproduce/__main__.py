"""``python -m cpl_keras.reproduce``: the reproduction's command line."""

from cpl_keras.reproduce.cli import PROG, main

if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, PROG)
