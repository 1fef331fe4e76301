"""``svs-depth guide``: a live loop — capture a pair, range the obstacles, warn when one is within the band."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time

HELP = "live obstacle warnings from an SVS (or the built-in emulator)"

DESCRIPTION = """\
Grab pairs from the SVS continuously, run the whole pipeline on the most recent one, and warn when the
nearest obstacle's nearest visible surface (the 10th depth percentile of its dense disparities) is within
the distance band (default 1-2 m, the range the system was designed for): a
spoken message when espeak-ng is installed, always a text line, rate-limited so it does not chatter (a
message repeats after --repeat-s seconds unless the distance class changes). A status line shows frames
per second, the nearest distance and its side.
"""

EPILOG = """\
examples:
  svs-depth guide --emulator                                   try it without a device
  svs-depth guide --left socket://192.168.0.15:10001 --right socket://192.168.0.15:10002
  svs-depth guide --left /dev/ttyUSB0 --right /dev/ttyUSB1 --near-m 0.8 --far-m 1.5 --no-speech
Stop with Ctrl-C.
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "guide", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--left", metavar="URL", help="left (master) board: serial device or socket://HOST:10001")
    parser.add_argument("--right", metavar="URL", help="right (slave) board: serial device or socket://HOST:10002")
    parser.add_argument("--emulator", action="store_true", help="use an in-process SVS emulator on loopback")
    parser.add_argument("--size", default="320x240", help="frame size (default: 320x240)")
    parser.add_argument("--baud", type=int, default=2_304_000, help="UART speed for serial links")
    parser.add_argument("--timeout", type=float, default=2.0, help="reply timeout per command, seconds")
    parser.add_argument("--quality", type=int, help="JPEG quality 1 (best) to 8 (worst)")
    parser.add_argument("--near-m", type=float, default=1.0, help="warning band start, metres (default 1.0)")
    parser.add_argument("--far-m", type=float, default=2.0, help="warning band end, metres (default 2.0)")
    parser.add_argument("--repeat-s", type=float, default=3.0, help="seconds before the same warning repeats")
    parser.add_argument("--no-speech", action="store_true", help="text only, even if espeak-ng is installed")
    parser.add_argument("--count", type=int, default=0, help="stop after N pairs (default: run until Ctrl-C)")
    parser.set_defaults(func=run, out=".", json=False)


def run(args: argparse.Namespace) -> int:
    from ..camera import parse_size
    from ..capture.guide import LiveGuide, Speaker, WarningPolicy
    from ..capture.link import CaptureError
    from ..checks import InputError
    from ..depth import ObstacleSide
    from ..pipeline import estimate_obstacle_depth
    from .capture import open_stereo_camera

    size = parse_size(args.size, "size")
    if args.emulator == bool(args.left or args.right) or (not args.emulator and not (args.left and args.right)):
        raise InputError("left, right: give both --left and --right board URLs, or --emulator")
    if not 0 <= args.near_m < args.far_m:
        raise InputError(f"near-m, far-m: expected 0 <= near < far, got {args.near_m} and {args.far_m}")
    policy = WarningPolicy(near_m=args.near_m, far_m=args.far_m, repeat_s=args.repeat_s)
    guide = LiveGuide(policy, Speaker(None if args.no_speech else "auto", stream=sys.stdout))
    processed = 0
    try:
        with contextlib.ExitStack() as stack:
            camera = open_stereo_camera(args, size, stack)
            for item in camera.stream_batches(1, num_batches=args.count or None):
                result = estimate_obstacle_depth(item.batch)
                nearest = result.depth.nearest
                # Warn on the nearest obstacle's nearest visible surface (its low depth percentile): the part
                # a walker reaches first, not the median of an object that may recede.
                distance = float(nearest.surface_m[0]) if bool(nearest.valid[0]) else None
                guide.update(distance, time.monotonic())
                side = ObstacleSide(int(nearest.side[0])).name.lower()
                print(f"\r{guide.status(distance)}  {side:6s}", end="", file=sys.stderr, flush=True)
                processed += 1
    except KeyboardInterrupt:
        print(f"\nguide stopped after {processed} pairs", file=sys.stderr)
        return 130
    except CaptureError as error:
        print(f"\nsvs-depth guide: error: {error}", file=sys.stderr)
        return 1
    print(f"\nguide stopped after {processed} pairs", file=sys.stderr)
    return 0
