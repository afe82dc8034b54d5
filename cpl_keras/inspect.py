"""The former name of ``cpl_keras.graph``: ``python -m cpl_keras.inspect``
keeps working (prefer ``python -m cpl_keras.graph``)."""

from cpl_keras.graph import camera_graph, draw_graph, format_table, main  # noqa: F401

if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(lambda: main(prog="python -m cpl_keras.inspect"), "python -m cpl_keras.inspect")
