"""The ``svs-depth`` command line.

Each subcommand lives in its own module with ``add_parser(subparsers)`` and a ``run(args) -> int``; heavy
imports (torch, OpenCV) happen inside ``run`` so that ``svs-depth --help`` answers at once.
"""

from __future__ import annotations

import argparse
import sys

from . import capture, demo, estimate, features, fundamental, guide, segment

__all__ = ["main", "build_parser", "CliError"]

DESCRIPTION = """\
Range obstacles 1–2 m ahead with a Surveyor SVS stereo camera, batched in PyTorch.

The pipeline of the paper, stage by stage: segment the obstacles (Otsu threshold, erosion + dilation, the
largest connected regions), find SURF features on the masked images, match them by SAD, estimate the
fundamental matrix by RANSAC, rectify, and range the obstacles from disparity (R = f·B/d).
"""

EPILOG = """\
examples:
  svs-depth demo                          render a synthetic SVS scene, range its obstacles (no camera needed)
  svs-depth estimate left.png right.png   distance to the obstacles of a stereo pair
  svs-depth segment left.png right.png    segment a stereo pair, print the obstacles found
  svs-depth segment L.png R.png --json    the same as JSON, for scripts
  svs-depth segment L.png R.png --out seg.png --kernel-size 7 --keep 3
  svs-depth features L.png R.png --size 320x240 --plot matches.png    SURF keypoints and SAD matches
  svs-depth fundamental L.png R.png --json                           F by batched 7-point RANSAC
  svs-depth capture --emulator --count 5 --out pairs/    grab pairs from a built-in SVS emulator
  svs-depth guide --emulator              live warnings when an obstacle is 1-2 m ahead

Real data: any left/right image files work (gray or color; 8 or 16 bit). Without calibration the SVS
model is assumed: 3.6 mm lens, 4.17 mm sensor, 10.75 cm baseline (focal 276 px at 320x240).
Run 'svs-depth COMMAND --help' for each command's options.
"""


class CliError(Exception):
    """A user-facing failure: printed as one line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="svs-depth",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in (demo, estimate, segment, features, fundamental, capture, guide):
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``svs-depth`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from ..checks import InputError

    try:
        return int(args.func(args) or 0)
    except (InputError, CliError, FileNotFoundError, PermissionError, IsADirectoryError) as error:
        print(f"svs-depth {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"svs-depth {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
