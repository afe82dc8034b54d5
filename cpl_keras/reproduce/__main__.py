"""``python -m cpl_keras.reproduce``: the reproduction's command line."""

import sys

from cpl_keras.reproduce.cli import main

if __name__ == "__main__":
    sys.exit(main())
