"""The former name of ``cpl_keras.graph``: ``python -m cpl_keras.inspect``
keeps working (prefer ``python -m cpl_keras.graph``)."""

import sys

from cpl_keras.graph import camera_graph, draw_graph, format_table, main  # noqa: F401

if __name__ == "__main__":
    sys.exit(main(prog="python -m cpl_keras.inspect"))
