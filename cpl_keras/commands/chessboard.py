"""``python -m cpl_keras.real.chessboard`` (``cpl-chessboard``): print a
chessboard rig's OpenCV calibration as JSON (``cpl_keras.real.chessboard``)."""

from __future__ import annotations

import json

from cpl_keras import cli
from cpl_keras.real import RealDataError
from cpl_keras.real.chessboard import DATA_DIR, calibrate, calibration_report


def main(argv=None):
    prog = "python -m cpl_keras.real.chessboard"
    parser = cli.Parser(prog=prog, description="Print a chessboard rig's calibration.")
    parser.add_argument("--root", default=DATA_DIR, help="folder of left*/right* pairs")
    parser.add_argument("--pair", help="also the point and disparity of this pair (e.g. 01)")
    args = parser.parse_args(argv)
    try:
        cal = calibrate(args.root)
        print(json.dumps(calibration_report(cal, args.pair), indent=2))
    except (RealDataError, OSError) as error:
        return cli.fail(prog, error)
    return 0


if __name__ == "__main__":
    cli.run(main, "python -m cpl_keras.real.chessboard")
