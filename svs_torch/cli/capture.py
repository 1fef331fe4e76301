"""``svs-depth capture``: grab stereo pairs from an SVS (or the built-in emulator) into a folder.

Output, in ``--out-dir`` (alias ``--out``):

* ``pair000000_left.jpg`` / ``pair000000_right.jpg`` …: each board's JPEG bytes exactly as received (colour,
  4:2:2, no re-encoding); each file is written under a temporary name and renamed, so none is ever half-written;
* ``index.jsonl``: one JSON object per pair, appended and flushed only after both of its images are in place, so
  after an error or Ctrl-C it lists exactly the complete pairs. Fields: ``index``, ``left``/``right`` (file
  names), ``width``, ``height``, ``left_bytes``/``right_bytes``, per camera ``*_request_monotonic_s``,
  ``*_header_monotonic_s`` (its frame header read), ``*_arrival_monotonic_s`` (its last byte), ``*_arrival_wall_s``
  (Unix seconds), ``*_attempts``, ``time_between_frames_s`` (right header − left header, seconds: when each board
  began its reply, its frame grabbed and encoded; not the last bytes, whose gap grows with the JPEGs' lengths on a
  slow link), ``quality`` (the ``--quality`` digit both boards were set to; null
  without it: the board's own setting, 4 at power-up, which no command reads back) and ``frozen_camera``
  (``"left"``/``"right"``: that camera's frame came again, pixel for pixel, while the other's changed; ``"both"``:
  both frames came again for 3 s; by ``guide``'s rule, :class:`~svs_torch.capture.frozen.FrozenCameraWatch`; else
  null; an older index has no such key), ``emulator`` (``--emulator``'s noise, loose rig, floor and heap,
  :func:`~svs_torch.cli.link_options.emulator_record`; null from boards; an older index has no such key),
  ``cameras_swapped`` (true: the left board answered ``V`` as other than the stereo master or the right as other
  than the slave, the URLs likely the other way round; null: a build that names no role;
  :attr:`~svs_torch.capture.stereo.SVSStereoCamera.roles_swapped`; an older index has no such key) and
  ``rig_calibration`` (``"calibration.json"`` with ``--calibration``, else null);
* ``calibration.json`` with ``--calibration``: a copy of the rig's calibration file (the frames stay as received;
  ``estimate --pairs OUT/index.jsonl --calibration OUT/calibration.json`` rectifies them). At the end capture prints
  the ``estimate`` command that ranges the pairs (as camera frames, with the calibration where one was given), after
  Ctrl-C, SIGTERM or an error too when it kept any, and a warning of each kind of pair guide would not range.

Exit codes: 0 done, 1 capture or file error, 2 bad arguments, 130 interrupted, 143 terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path
from typing import Any

from ..core.camera import parse_size
from ..core.errors import InputError
from ..core.files import error_text
from ..core.workers import signals_held
from .capture_checks import PairChecks
from .common import Terminated, add_retries_option, pair_count, quality_digit, timeout_seconds
from .link_options import add_emulator_frame_options, add_uart_options, emulator_record
from .pairs_folder import CALIBRATION_NAME, INDEX_NAME, drop_unused_pairs_folder, new_pairs_folder, open_pairs_index, \
    replay_command, save_pair
from .progress import Progress
from .rig import add_calibration_option, calibration_from_args

__all__ = ["CALIBRATION_NAME", "INDEX_NAME", "add_parser", "check_heap_in_view", "new_pairs_folder", "run", "save_pair"]

PROG = "svs-depth capture"
DEFAULT_TIMEOUT_S = 1.0  # LinkConfig.reply_timeout_s


EPILOG = """\
examples:
  svs-depth capture --emulator --count 20 --out-dir pairs/        try it without a device
  svs-depth capture --emulator --emulator-noise 4 --quality 4 --out-dir noisy/   the frames a real board sends
  svs-depth capture --left /dev/ttyUSB0 --right /dev/ttyUSB1 --out-dir pairs/
  svs-depth capture --left socket://192.168.0.15:10001 --right socket://192.168.0.15:10002 --size 640x480 --out-dir big/
  svs-depth capture --left /dev/ttyUSB0 --right /dev/ttyUSB1 --calibration rig.json --out-dir pairs/  (calibrate)
then range what was saved (the command capture prints at the end):
  svs-depth estimate --pairs pairs/index.jsonl --camera-frames --json
"""


def add_parser(subparsers: Any) -> None:
    """Register the ``capture`` subcommand on an argparse subparsers object (sets ``func=run``)."""
    parser = subparsers.add_parser(
        "capture", help="grab stereo pairs from an SVS camera into a folder",
        description="Grab stereo pairs from a Surveyor SVS (two SRV-1 boards) and save each board's JPEG plus an\n"
                    "index.jsonl of timestamps. --emulator tries it without a device. Every pair is kept; the index\n"
                    "marks, and the end warns of, pairs guide would not range (a frozen camera, frames far apart)\n"
                    "and boards answering in each other's roles, --left not the stereo master (cameras_swapped: the\n"
                    "URLs likely the other way round; cover the left lens, and its image must be the dark one).\n"
                    "Exit status: 0 done, 1 capture or file error, 2 bad arguments, 130 interrupted, 143 terminated\n"
                    "(SIGTERM).",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--left", metavar="URL",
                        help="left/master board: socket://HOST:10001 or a serial device such as /dev/ttyUSB0")
    parser.add_argument("--right", metavar="URL",
                        help="right/slave board: socket://HOST:10002 or a serial device such as /dev/ttyUSB1")
    parser.add_argument("--size", default="320x240", metavar="WxH",
                        help="frame size: 160x120, 320x240, 640x480 or 1280x1024 (default: 320x240)")
    parser.add_argument("--count", type=pair_count, default=10, help="number of pairs to grab (default: 10)")
    parser.add_argument("--out-dir", "--out", dest="out", required=True, metavar="DIR",
                        help="output folder, created if missing; it must not hold another run's index.jsonl, "
                             "calibration.json or pair images (also --out)")
    parser.add_argument("--quality", type=quality_digit, default=None, metavar="1-8",
                        help="JPEG quality digit, 1 best … 8 worst (default: leave the board's, 4 at power-up)")
    add_uart_options(parser)
    parser.add_argument("--timeout", type=timeout_seconds, default=DEFAULT_TIMEOUT_S, metavar="S",
                        help="seconds to wait for a reply (a frame's header) before re-sending, at most --retries "
                             f"times (default: {DEFAULT_TIMEOUT_S:g})")
    add_retries_option(parser)
    add_calibration_option(parser, "the saved pairs (estimate/eval --calibration OUT/calibration.json)")
    parser.add_argument("--emulator", action="store_true",
                        help="start an in-process emulator on free loopback ports and capture from it")
    add_emulator_frame_options(parser)
    parser.set_defaults(func=run)


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: error: {' '.join(str(message).split())}", file=sys.stderr)
    return code


def _check_args(args: argparse.Namespace) -> tuple[tuple[int, int], Path]:
    from ..capture.protocol import size_code_for

    size = parse_size(args.size, "--size")
    try:
        size_code_for(size)
    except InputError:
        raise InputError(f"--size: expected 160x120, 320x240, 640x480 or 1280x1024, got {args.size!r}") from None
    if args.count < 1:
        raise InputError(f"--count: expected a positive number of pairs, got {args.count}")
    if args.quality is not None and not 1 <= args.quality <= 8:
        raise InputError(f"--quality: expected 1 (best) to 8 (worst), got {args.quality}")
    if args.emulator and (args.left is not None or args.right is not None):  # '' too: it was run as not given
        raise InputError("--left, --right: not used with --emulator (it picks its own loopback ports)")
    if not args.emulator and not (args.left and args.right):
        raise InputError("--left, --right: both board URLs are needed (or --emulator)")
    check_board_urls(args)
    return size, new_pairs_folder(args.out, "--out-dir")


def check_heap_in_view(heap_m: float, floor_m: float, size_wh: tuple[int, int], pitch_deg: float | None = None,
                       option: str = "--emulator-heap-m") -> None:
    """``--emulator-heap-m`` where the emulator's cameras see the heap: not wholly below their view (``floor_m`` high,
    pitched ``pitch_deg``, default ``hw.frames.WALKER_PITCH_DEG``), nor so far that it is under 2 pixels high or
    behind the emulator's wall. Each was accepted, and guide then ran with no heap to warn of (behind the wall: 4.5
    to 48 m at 1.3 m high, not a pixel of it rendered, the error's own range said 48, an audit). The bounds said are
    those applied: 0.78 was refused as outside "0.78 to 48", the bound rounded for the message. ``option``: the name
    the error gives the heap (the standalone emulator's ``--heap-ahead-m`` means the same)."""
    from hw.frames import WALKER_PITCH_DEG
    from ..core.camera import SVS_CAMERA
    from ..data.heap_rendering import WALKER_HEAP_HEIGHT_M, WALKER_HEAP_RADIUS_M
    from ..data.synthetic import WALL_DEPTH_M

    roughness_m = 0.05  # render_obstacle_scenes's heap_roughness_m, which the emulator keeps
    focal_px = SVS_CAMERA.focal_px(size_wh[0])
    pitch_deg = WALKER_PITCH_DEG if pitch_deg is None else pitch_deg
    pitch = math.radians(pitch_deg)
    lowest_ray = pitch + math.atan(size_wh[1] / 2 / focal_px)  # the view's bottom edge

    def rise_m(x_m: float) -> float:  # its dome (heap_rendering.make_heap_field) with the rocks' greatest rise on it
        return WALKER_HEAP_HEIGHT_M * (1 - (x_m / WALKER_HEAP_RADIUS_M) ** 2) ** 0.75 + roughness_m

    # Seen once some point of its far side, x beyond its centre, rises above the view's bottom edge
    def reach_needed_m(x_m: float) -> float:
        return max(floor_m - rise_m(x_m), 0.0) / math.tan(lowest_ray) - x_m

    # and while some point of its near side, x before its centre, lies nearer along the cameras' axis than the
    # wall, a plane WALL_DEPTH_M along it (the pitch moves only the floor): (ahead + x)·cos p + (floor − rise)·sin p.
    # Its dome alone: the rocks' greatest rise, at its rim, put the bound 2-4 cm past its last rendered pixel.
    def hidden_from_m(x_m: float) -> float:
        return (WALL_DEPTH_M - (floor_m - rise_m(x_m) + roughness_m) * math.sin(pitch)) / math.cos(pitch) - x_m

    # Pitched further down than half the view (the standalone emulator's --camera-pitch-deg 60), its top edge
    # meets the floor too: a heap whose near rim lies past it is above the view (3 m ahead at 60° down, 1.3 m high,
    # had no pixel). Its dome without the rocks: a ray under the top edge meets the first rise of its near rim.
    top_ray = pitch - math.atan(size_wh[1] / 2 / focal_px)
    offsets_m = [WALKER_HEAP_RADIUS_M * i / 100 for i in range(100)]  # from its centre towards its rim
    above_from_m = max((floor_m - rise_m(-x_m) + roughness_m) / math.tan(top_ray) + x_m for x_m in offsets_m) \
        if top_ray > 0 else math.inf
    nearest_m = max(min(reach_needed_m(x_m) for x_m in offsets_m), 0.0)
    farthest = {"it is under 2 pixels high": WALKER_HEAP_HEIGHT_M * focal_px / 2, "it lies above their view":
                above_from_m, f"it stands behind the emulator's wall, {WALL_DEPTH_M:g} m along their axis":
                max(hidden_from_m(-x_m) for x_m in offsets_m)}
    far_why = min(farthest, key=farthest.get)
    nearest_m, farthest_m = math.ceil(nearest_m * 100) / 100, math.floor(farthest[far_why] * 100) / 100  # (as said)
    if not nearest_m <= heap_m <= farthest_m:
        # The side and the bound it missed ("behind the wall" was said of a heap too near, or too small to see, as
        # well). A bound of 0 is said as "more than 0": the option takes positive distances only.
        why = "nearer, it lies below their view" if heap_m < nearest_m else f"farther, {far_why}"
        lowest = f"{nearest_m:.2f}" if nearest_m > 0 else "more than 0"
        raise InputError(f"{option}: expected {lowest} to {farthest_m:.2f} metres, where cameras "
                         f"{floor_m:g} m over the floor, pitched {pitch_deg:g}° down, see the heap at "
                         f"{size_wh[0]}x{size_wh[1]}; got {heap_m:g} ({why})")


def check_board_urls(args: argparse.Namespace) -> None:
    """``--left`` and ``--right`` as links pyserial can open, and two of them, before the camera is opened, with no
    ``--emulator-*`` option beside them. Why:
    ``socket://HOST`` without its port failed inside pyserial ("'<=' not supported between 'int' and
    'NoneType'"), ``http://...`` as a capture error (exit 1, not a bad argument), and one URL given twice as the
    link closing right after it opened."""
    from ..capture.link_types import check_link_url

    if args.emulator:
        floor, heap = getattr(args, "emulator_floor_m", None), getattr(args, "emulator_heap_m", None)
        if floor is not None and heap is not None:
            check_heap_in_view(heap, floor, parse_size(args.size, "--size"))
        return
    # The emulator's options describe its scene; beside real boards they were accepted and did nothing.
    given = [option for option, name, unset in (("--emulator-noise", "emulator_noise", 0.0),
                                                 ("--emulator-loose-rig", "emulator_loose_rig", False),
                                                 ("--emulator-floor-m", "emulator_floor_m", None),
                                                 ("--emulator-heap-m", "emulator_heap_m", None))
             if getattr(args, name, unset) != unset]
    if given:
        raise InputError(f"{', '.join(given)}: only with --emulator (the boards at --left/--right send what they see)")
    for option, url in (("--left", args.left), ("--right", args.right)):
        check_link_url(url, option)
    if args.left == args.right:
        raise InputError(f"--left, --right: expected the two boards' links, got {args.left!r} for both")


def _kept(done: int, out: Path) -> str:
    """What an interrupted capture kept: its pairs and where they are listed, or that nothing was saved (stopped
    before the boards answered, no folder was made: an audit found "after 0 pairs (index.jsonl lists them)")."""
    if not (out / "index.jsonl").is_file():
        return "0 pairs: nothing saved"
    return f"{done} pair{'' if done == 1 else 's'} (index.jsonl lists them)"


def run(args: argparse.Namespace) -> int:
    """Run ``capture``; returns the exit code (errors are one line on stderr)."""
    from ..capture.link_types import CaptureError

    try:
        size, out = _check_args(args)
        calibration = calibration_from_args(args)
        if calibration is not None:
            calibration.scaled_to(size, "--calibration")  # the rig's aspect ratio must be the frames'
    except InputError as err:
        return _fail(str(err), 2)
    # The command that ranges them, as guide --record's summary gives it: camera frames, rectified by the rig's file.
    replay = replay_command(out, calibration=None if calibration is None else str(out / CALIBRATION_NAME))
    done, checks = 0, None
    try:
        with contextlib.ExitStack() as stack:
            camera = open_stereo_camera(args, size, stack)
            # The index first: made anew, it is this run's folder (another capture into it is refused there, and
            # its clean-up removed this one's index and folder, an audit), then the calibration beside it.
            index, made = open_pairs_index(out, "--out-dir")
            # However the capture ends, one that saved no pair removes what it wrote (its index closed first).
            stack.callback(lambda: None if done else drop_unused_pairs_folder(out, made))
            stack.enter_context(index)
            if calibration is not None:  # the frames stay as received; their rig's calibration goes beside them
                from ..geometry.calibration import write_calibration

                write_calibration(out / CALIBRATION_NAME, calibration, "--out-dir")
            progress = stack.enter_context(Progress(args.count, "capture"))
            checks = PairChecks(camera)
            for _ in range(args.count):  # a pair kept whole or not at all (pairs_folder's docstring)
                pair = camera.grab_pair()
                frozen = checks.frozen_camera(pair)
                with signals_held():  # its images and its index line, both or neither (pairs_folder's docstring)
                    record = save_pair(out, pair, "--out-dir")
                    # Which JPEG quality the frames were sent at: a folder did not say, and a board keeps a digit set
                    # by an earlier run. None: --quality not given (the protocol has no command that reads it back).
                    record.update(quality=args.quality, emulator=emulator_record(args), frozen_camera=frozen,
                                  cameras_swapped=checks.swapped,
                                  rig_calibration=None if calibration is None else CALIBRATION_NAME)
                    index.append(record)
                    done += 1
                    checks.count(pair, frozen)  # kept (capture keeps what the boards sent), but counted
                progress.update()
    # However the capture ended, the pairs kept are warned of, and one that ended early says how to range them (as
    # guide --record does at every end): a long capture is ended with Ctrl-C, and it said neither (an audit).
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted after {_kept(done, out)}", file=sys.stderr)
        return _ended(130, checks, done, replay)
    except Terminated:  # SIGTERM (svs_torch.cli.common.terminated_on_sigterm), said as Ctrl-C is
        print(f"{PROG}: terminated after {_kept(done, out)}", file=sys.stderr)
        return _ended(143, checks, done, replay)
    except (CaptureError, OSError, InputError) as err:
        # A camera that never opened left no folder to name (an audit: "0 of 2 pairs saved in cap7", never made).
        saved = f"{done} of {args.count} pairs saved in {out}" if out.is_dir() else "nothing saved"
        return _ended(_fail(f"{error_text(err)} ({saved})", 1), checks, done, replay)
    print(f"{PROG}: saved {done} pair{'' if done == 1 else 's'} to {out}; range them with: {replay}", file=sys.stderr)
    return _ended(0, checks, done)


def _ended(code: int, checks: PairChecks | None, done: int, replay: str | None = None) -> int:
    """Print the command that ranges the ``done`` pairs kept (``replay``, of a capture that ended early; None:
    said already) and their warnings (:meth:`~svs_torch.cli.capture_checks.PairChecks.warnings`; None: no pair was
    grabbed); returns ``code``."""
    if replay is not None and done:
        print(f"{PROG}: range the pairs kept with: {replay}", file=sys.stderr)
    for warning in checks.warnings(done) if checks is not None else ():
        print(f"{PROG}: warning: {warning}", file=sys.stderr)
    return code


def open_stereo_camera(args: argparse.Namespace, size: tuple[int, int], stack: contextlib.ExitStack,
                       first_index: int = 0):
    """The stereo camera of ``--left``/``--right`` (or ``--emulator``), with the link options, closed by ``stack``;
    its first pair has index ``first_index``."""
    from ..capture.link_types import LinkConfig
    from ..capture.stereo import SVSStereoCamera

    left, right = board_urls(args, size, stack)
    config = LinkConfig(baudrate=args.baud, reply_timeout_s=args.timeout, max_retries=args.retries,
                        rtscts=not args.no_flow_control)
    return stack.enter_context(SVSStereoCamera(left, right, size, quality=args.quality, config=config,
                                               first_index=first_index))


def check_emulator_options(args: argparse.Namespace) -> None:
    """The ``--emulator-*`` options, checked before anything starts (guide's speech notice came before their error,
    an audit)."""
    noise = getattr(args, "emulator_noise", 0.0)
    if not (math.isfinite(noise) and noise >= 0):
        raise InputError(f"--emulator-noise: expected a σ >= 0 in 8-bit levels, got {noise!r}")
    floor, heap = getattr(args, "emulator_floor_m", None), getattr(args, "emulator_heap_m", None)
    if heap is not None and floor is None:
        raise InputError(f"--emulator-heap-m: expected --emulator-floor-m too (a heap stands on the floor), got "
                         f"{heap!r} without it")


def board_urls(args: argparse.Namespace, size: tuple[int, int], stack: contextlib.ExitStack) -> tuple[str, str]:
    """The board URLs: from the arguments, or from an in-process emulator started on free loopback ports."""
    if not args.emulator:
        return args.left, args.right
    from hw.emulator import SVS_LINK_BYTES_PER_S, EmulatorServer
    from hw.frames import WALKER_PITCH_DEG, ObstacleTrack, SyntheticSource
    from ..data.rig_deviation import LOOSE_RIG

    check_emulator_options(args)
    noise = getattr(args, "emulator_noise", 0.0)
    floor, heap = getattr(args, "emulator_floor_m", None), getattr(args, "emulator_heap_m", None)
    source = SyntheticSource(ObstacleTrack(floor_height_m=floor, camera_pitch_deg=WALKER_PITCH_DEG,
                                           heap_ahead_m=heap) if floor else None)
    # At the SVS's link rate: served faster, the in-process emulator renders and encodes pairs the grabber then
    # drops, on the cores the pipeline runs on (guide at 320x240: 158 ms a pair ranged, against 70 ms paced).
    loose = LOOSE_RIG if getattr(args, "emulator_loose_rig", False) else None
    server = stack.enter_context(EmulatorServer(left_port=0, right_port=0, source=source, noise_sigma=noise,
                                                link_bytes_per_s=SVS_LINK_BYTES_PER_S, right_deviation=loose))
    source.prepare(size, timeout_s=30.0, complete=False)  # the first rendered keyframe, not the stand-in
    print(f"svs-depth: emulator on {server.urls['left']} (left) and {server.urls['right']} (right)", file=sys.stderr)
    return server.urls["left"], server.urls["right"]


