"""``svs-depth guide``: a live loop — capture a pair, range the obstacles, warn when one is within the band."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import warnings

from ..core.files import PROGRESS_HELP
from .common import (Terminated, add_retries_option, finite_float, non_negative_float,
                     pair_count_or_zero, positive_float, positive_int, quality_digit, terminated_on_sigterm,
                     timeout_seconds)
from .hangup import HungUp, hung_up_on_sighup
from .link_options import add_emulator_frame_options, add_uart_options, emulator_record
from .rig import add_calibration_option, calibration_from_args
from .segment import FLOOR_CAMERA_HEIGHTS_M, add_floor_option

HELP = "live obstacle warnings from an SVS (or the built-in emulator)"

DESCRIPTION = """\
Grab pairs from the SVS continuously, run the whole pipeline on the most recent one, and warn when the nearest
obstacle's nearest visible surface (the 10th percentile of its distances) is within the distance band (default
1-2 m, the range the system was designed for), measured ahead along the floor where the floor was found (in the
pair, or in the last 2 s: a camera pitched down sees what lies on the floor 0.2-0.4 m farther along its axis than
it stands), else along a level floor under the camera as worn (--camera-pitch-deg) or along its axis: a spoken
message, with the side of the part of the obstacle that distance was measured on where it is not straight ahead
("Obstacle on the left, 1.5 metres"), when espeak-ng is installed, always a text line, rate-limited so it does not
chatter (a message repeats after --repeat-s seconds unless the distance class turns more urgent than the one last
said, a new obstacle follows a clear way of a second, or the nearest obstacle is now on another side and
--nearer-elsewhere-m nearer). Each pair's distance is confirmed by the pairs before it: the band is judged on the
median of the last --confirm-frames, so one noisy frame ranged wrong is not said. A status line shows frames per
second, that distance and the nearest obstacle's side. The floor (the road) ahead, which a walker's camera sees
as its nearest surface, is not an obstacle (--floor). The frames are a camera's (JPEG with sensor noise), so the
obstacles' disparity map is matched with its wider noise window at once, as estimate --camera-frames does.

Silence means nothing is near, never that nothing was measured (nor a guide still starting: "Guide ready" is said
once, when the camera first answers): when no pair could be ranged for --blind-s seconds (a covered lens, the dark,
a link that froze, pairs whose two frames came more than 0.25 s apart, which are not ranged: the walker moved
between them, one image sent for both cameras, or one camera's frame sent again while the other's changed, a stalled
board: not ranged either), "Cannot see ahead" is said, and "Seeing ahead again" when one is; after a stalled board's
pairs (or a late one's, apart), "Cannot see ahead" goes on "Check the left camera" (or right; a stalled one's with
--blind-s 0, said alone), once a run. A camera that stops answering in the middle of a walk (a WiFi drop) is said to
be lost, aloud (the board named where one failed), and opened again every --reconnect-s seconds; its return is said
too, and the warnings go on. One that never answered ends guide with its error (exit 1), as does one lost for
--give-up-s seconds if that is set. Whatever ends it (an error, --count, Ctrl-C, a service's stop, its terminal
closing), "Guide stopped. No more warnings." is said. Boards that answer in the wrong stereo roles (--left reaches
the slave: the URLs swapped) are said once, aloud ("Check the cameras"), as every distance is then wrong. SIGTERM
(a service's stop) ends it as Ctrl-C does, exit 143; so does the end of its terminal (SIGHUP: an ssh session
dropped, the window closed), exit 129, the words still said (the speaker needs no terminal; under nohup it goes on).

--json prints a JSON line per pair ranged, for another program to act on; --record DIR keeps the pairs
ranged, and at the end prints the estimate command that ranges them again to the same distances, pair by pair
(a warning ranged along a floor remembered from an earlier pair, or along --camera-pitch-deg, is the walk's).
"""

EPILOG = """\
examples:
  svs-depth guide --emulator                                   try it without a device
  svs-depth guide --emulator --emulator-floor-m 1.3           a walker's view: the floor ahead is not warned of
  svs-depth guide --emulator --emulator-floor-m 1.3 --floor off   the same view, the floor kept and warned of
  svs-depth guide --emulator --emulator-floor-m 1.3 --emulator-heap-m 1.5   a heap of rocks on the floor, warned of
  svs-depth guide --left /dev/ttyUSB0 --right /dev/ttyUSB1 --camera-pitch-deg 20   a rig worn pitched 20° down
  svs-depth guide --left socket://192.168.0.15:10001 --right socket://192.168.0.15:10002
  svs-depth guide --left /dev/ttyUSB0 --right /dev/ttyUSB1 --near-m 0.8 --far-m 1.5 --no-speech
  svs-depth guide --emulator --count 50 --json --record walk/ > walk.jsonl   a walk kept, to range again
Stop with Ctrl-C.
""" + PROGRESS_HELP + "\n"


#: ``--second-passes``: what each choice does and costs (PipelineConfig.for_guide).
SECOND_PASSES_HELP = ("'on': a pair whose first pass measured too little of its obstacles is measured again on a "
                      "coarser grid, and one left unfinished whose cameras' exposures differ again with them "
                      "matched where that brings their matched features together; 'off': never, so no frame "
                      "waits for a second run (the shared real pairs as digit 4 frames on a 2-core AMD machine: "
                      "slowest 35.8 -> 18.4 ms; at digit 8 one frame of 45 took 98.0 ms, 46.0 without the exposure "
                      "retry) but noisy frames are ranged worse (held-out digit 4 frames: 97.95 -> 95.34 %% per "
                      "object): experiments/guide_second_passes.md, 'The map at the matched points' and 'Measured "
                      "again' (default: on)")

#: ``--json``: what its lines hold.
JSON_HELP = ("a JSON line per pair ranged on stdout for another program: estimate --json's fields (with the "
             "calibration its metres use), the capture's times, 'warning' (the pair's and the confirmed distance, the "
             "class clear / warn / stop, or unseen: nothing measured; the words said), 'dropped_pairs', 'latency_s', "
             "'quality' (--quality's digit), 'emulator' (--emulator's noise, loose rig, floor and heap; null from "
             "boards); a line {\"event\": ...} when the camera is lost or back (camera_lost, camera_back), guide "
             "cannot see or sees again (cannot_see, seeing_again, with the 'status' why), a pair is not ranged "
             "(frames_apart, identical_views, camera_frozen with its 'camera'), the boards answer in the wrong roles "
             "(cameras_swapped) or their matches show them mounted wrong (cameras_mounted_wrong: 'views' swapped or "
             "turned), or a repeated pattern not ranged is said (repeated_pattern, with the nearest distance it may "
             "be at); the warnings' text goes to stderr")


#: ``--confirm-frames``'s default: :data:`svs_torch.capture.guide.CONFIRM_FRAMES`, written out here because that
#: module imports torch, which ``--help`` must not wait for (a test holds the two equal).
CONFIRM_FRAMES = 3
#: ``--nearer-elsewhere-m``'s default: :data:`svs_torch.capture.guide.NEARER_ELSEWHERE_M` (as above).
NEARER_ELSEWHERE_M = 0.3
#: The most ``--confirm-frames``: a new obstacle is warned of N // 2 pairs later, here 10, half a second at 20 pairs/s
#: and over a second at the 8 pairs/s guide ranges at on 2 cores, while a walker at 1.4 m/s crosses the default
#: warning band (1 to 2 m) in 0.7 s. 10**9 was taken: after 1000 pairs of a clear way, a new obstacle went unwarned
#: for 1001 pairs (after a clear hour, another hour), and each pair sorted all the distances kept so far.
MAX_CONFIRM_FRAMES = 21
CONFIRM_FRAMES_HELP = ("warn on the median of the last N pairs' distances, so that one camera frame ranged wrong by "
                       "its noise neither raises a warning nor silences one; a new obstacle is warned of N // 2 pairs "
                       f"later (about 50 ms at 20 pairs/s); 1: each pair alone, at most {MAX_CONFIRM_FRAMES} (default: "
                       "3, experiments/guide_confirm.md)")
#: The highest ``--emulator-floor-m``: the emulator's wall stands 4 m ahead, and from 3 m up its cameras, pitched
#: 20° down, see no floor before it at 320x240 (none of 76,800 pixels; at 2.9 m 2,240). 1e9 was taken and guide
#: ran with no floor in view, unsaid.
MAX_EMULATOR_FLOOR_M = 3.0
#: The lowest ``--emulator-floor-m`` (and ``python -m hw.emulator --floor-height-m``): a lens 1 cm over the floor
#: lies on it. 1e-300 was taken, the renderer's float32 disparities of the floor overflowed, its thread died with a
#: traceback, and guide ranged the stand-in renderer's frames, which have no floor, unsaid (an audit).
MIN_EMULATOR_FLOOR_M = 0.01


def _confirm_frames(text: str) -> int:
    """argparse type of ``--confirm-frames``: 1 to :data:`MAX_CONFIRM_FRAMES` pairs."""
    value = positive_int(text)
    if value > MAX_CONFIRM_FRAMES:
        raise argparse.ArgumentTypeError(f"expected a number of pairs from 1 to {MAX_CONFIRM_FRAMES}, got {text!r}")
    return value


def _emulator_floor_m(text: str) -> float:
    """argparse type of ``--emulator-floor-m``: metres from :data:`MIN_EMULATOR_FLOOR_M` to under
    :data:`MAX_EMULATOR_FLOOR_M`."""
    value = positive_float(text)
    if value < MIN_EMULATOR_FLOOR_M:
        raise argparse.ArgumentTypeError(f"expected metres from {MIN_EMULATOR_FLOOR_M:g} (lower, the cameras lie on "
                                         f"the floor) to under {MAX_EMULATOR_FLOOR_M:g}, got {text!r}")
    if not value < MAX_EMULATOR_FLOOR_M:
        raise argparse.ArgumentTypeError(f"expected metres from {MIN_EMULATOR_FLOOR_M:g} to under "
                                         f"{MAX_EMULATOR_FLOOR_M:g} (higher, the emulator's cameras see no floor "
                                         f"before its wall 4 m ahead), got {text!r}")
    return value


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "guide", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--left", metavar="URL", help="left (master) board: serial device or socket://HOST:10001")
    parser.add_argument("--right", metavar="URL", help="right (slave) board: serial device or socket://HOST:10002")
    parser.add_argument("--emulator", action="store_true", help="use an in-process SVS emulator on loopback")
    add_emulator_frame_options(parser)
    parser.add_argument("--emulator-floor-m", type=_emulator_floor_m, metavar="M",
                        help="with --emulator: the cameras M metres over a textured floor, pitched down 20 degrees "
                             "(hw.frames.WALKER_PITCH_DEG) as a walker wears them, 0.01 to under 3; guide's floor "
                             f"rule finds a floor from {FLOOR_CAMERA_HEIGHTS_M[0]:g} m under the cameras, see --floor "
                             "(default: no floor)")
    parser.add_argument("--emulator-heap-m", type=positive_float, metavar="M",
                        help="with --emulator-floor-m: a heap of rocks on the floor M metres ahead, 0.9 m wide and "
                             "0.35 m high, which guide warns of (default: none)")
    _add_walker_options(parser)
    parser.add_argument("--size", default="320x240", metavar="WxH",
                        help="frame size: 160x120, 320x240, 640x480 or 1280x1024 (default: 320x240)")
    add_uart_options(parser)
    # capture's 1 s: at 2 s one grab the board left unanswered (SVS_PROTOCOL.md §3) kept the walker unwarned 2.2 s,
    # past --blind-s, and had "Cannot see ahead" and "Seeing ahead again" said for it (an audit of the device side)
    parser.add_argument("--timeout", type=timeout_seconds, default=1.0, metavar="S",
                        help="seconds to wait for a reply (a frame's header) before re-sending, at most --retries "
                             "times (default: 1, as capture's)")
    add_retries_option(parser)
    parser.add_argument("--quality", type=quality_digit, metavar="1-8",
                        help="JPEG quality 1 (best) to 8 (worst) (default: the board's own)")
    _add_warning_options(parser)
    add_calibration_option(parser, "the frames")
    _add_speech_options(parser)
    parser.add_argument("--count", type=pair_count_or_zero, default=0, metavar="N",
                        help="stop after N pairs (default: 0, run until Ctrl-C)")
    parser.add_argument("--json", action="store_true", help=JSON_HELP)
    parser.add_argument("--record", metavar="DIR",
                        help="keep every pair ranged in DIR, as capture does (each board's JPEG as received, "
                             "index.jsonl with --json's lines), so that estimate --pairs DIR/index.jsonl ranges "
                             "them again alike; DIR is created, and must not hold another run's index.jsonl, "
                             "calibration.json or pair images")
    parser.add_argument("--reconnect-s", type=timeout_seconds, default=2.0, metavar="S",
                        help="a camera that stops answering in the middle of a walk is said to be lost (spoken) "
                             "and opened again every S seconds until it answers (default: 2)")
    parser.add_argument("--blind-s", type=non_negative_float, default=2.0, metavar="S",
                        help="say 'Cannot see ahead' when no pair could be ranged for S seconds (a covered lens, "
                             "the dark: silence would mean the way is clear), and 'Seeing ahead again' when one is "
                             "(default: 2; 0: never)")
    parser.add_argument("--give-up-s", type=non_negative_float, default=0.0, metavar="S",
                        help="stop (exit 1) once the camera has been lost for S seconds, checked after each try to "
                             "open it again, so up to one try later (about --retries + 1 times --timeout; default: "
                             "0, never: a walker's guide keeps trying)")
    parser.set_defaults(func=run, out=".")


#: The speech rate's default and bounds, words a minute (espeak-ng's ``-s``: 80 to 450); the parser does not import
#: :mod:`svs_torch.capture.speech`, whose ``Speaker`` default this is.
SPEECH_WPM, MIN_WPM, MAX_WPM = 170, 80, 450


def _speech_rate(text: str) -> int:
    rate = positive_int(text)
    if not MIN_WPM <= rate <= MAX_WPM:
        raise argparse.ArgumentTypeError(f"expected words a minute from {MIN_WPM} to {MAX_WPM}, got {text!r}")
    return rate


def _add_speech_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-speech", action="store_true", help="text only, even if espeak-ng is installed")
    # A walker at 1.4 m/s covers 3.9 m while "Obstacle on the left, 1.5 metres" is said at 170 words a minute (an
    # audit of what a walker hears); users of screen readers often listen at twice that.
    parser.add_argument("--words-per-minute", type=_speech_rate, metavar="N",
                        help=f"speech rate, {MIN_WPM}-{MAX_WPM} (espeak-ng's range; default: {SPEECH_WPM}); "
                             "a faster one says a warning in less of the walk; not with --no-speech")


def _add_warning_options(parser: argparse.ArgumentParser) -> None:
    """The warning rule's options (``svs_torch.capture.guide.WarningPolicy``)."""
    parser.add_argument("--near-m", type=non_negative_float, default=1.0, metavar="M",
                        help="warning band start, metres; nearer is said urgently, \"Stop. Obstacle at 0.9 "
                             "metres\" (default: 1.0)")
    parser.add_argument("--far-m", type=positive_float, default=2.0, metavar="M",
                        help="warning band end, metres; farther is not said (default: 2.0)")
    parser.add_argument("--repeat-s", type=non_negative_float, default=3.0, metavar="S",
                        help="seconds before the same warning repeats; one still being spoken is let finish, "
                             "not restarted (default: 3)")
    parser.add_argument("--confirm-frames", type=_confirm_frames, default=CONFIRM_FRAMES, metavar="N",
                        help=CONFIRM_FRAMES_HELP)
    parser.add_argument("--nearer-elsewhere-m", type=_metres_or_off, default=NEARER_ELSEWHERE_M, metavar="M",
                        help="within --repeat-s, say a nearest obstacle on another side than the one last said at "
                             "once when it is at least M metres nearer (someone stepping in beside what was warned "
                             "of); off: wait for --repeat-s (default: 0.3, experiments/guide_nearer.md)")


def _metres_or_off(text: str) -> float:
    """argparse type of --nearer-elsewhere-m: metres >= 0, or ``off`` (infinity: never said before --repeat-s)."""
    if text.strip().lower() == "off":
        return math.inf
    try:
        return non_negative_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected metres >= 0 or 'off', got {text!r}") from None


#: Said when guide ends, whatever ends it: an error (a camera that never answered, one lost for --give-up-s), whose
#: line is on a screen the walker does not see, --count, Ctrl-C, a service's stop or the terminal's end (SIGHUP),
#: while it starts too. The silence after it read as a clear way (after "Camera lost. No warnings until it is
#: back.", a promise of more). Here, not in guide_loop (which re-exports it): said when Ctrl-C comes while that
#: module's imports (torch) are under way.
GUIDE_STOPPED = "Guide stopped. No more warnings."


def run(args: argparse.Namespace) -> int:
    from ..core.workers import imports_without_collection

    with imports_without_collection():  # see there: the imports' objects are frozen
        size = _checked_size(args)  # first: a missing board URL was said after torch's import (2.5 s)
        from ..capture.guide import LiveGuide, Speaker, StatusLine, WarningPolicy  # (no torch: the speaker at once)
        from .pairs_folder import new_pairs_folder

        record_dir = None if args.record is None else new_pairs_folder(args.record, "--record")
    policy = WarningPolicy(near_m=args.near_m, far_m=args.far_m, repeat_s=args.repeat_s,
                           confirm_frames=args.confirm_frames, nearer_elsewhere_m=args.nearer_elsewhere_m)
    status_line = StatusLine(sys.stderr)
    # Everything else that prints while the status line shows goes above it, on a line of its own, and the status
    # is drawn again below: the spoken warnings (stdout), the speaker's own notices, Python warnings (a board in
    # the wrong stereo role, a library's deprecation).
    # With --json, stdout holds the JSON lines alone, and the warnings' text goes above the status line on stderr.
    words = status_line.lines_above(sys.stderr if args.json else sys.stdout)
    rate = SPEECH_WPM if args.words_per_minute is None else args.words_per_minute
    guide = LiveGuide(policy, Speaker(None if args.no_speech else "auto", words_per_minute=rate, stream=words))
    # SIGHUP (the terminal closed) as SIGTERM, from here: the speaker is there to say the end
    with hung_up_on_sighup(), contextlib.closing(guide.speaker):
        try:
            session, log = _started(args, size, guide, status_line, record_dir)
        except (KeyboardInterrupt, Terminated) as stop:
            # Ctrl-C or a service's stop in the 1-3 s before the camera opens (torch's import, the warm-up): it
            # ended in "svs-depth guide: interrupted" with nothing said, though every other end says it (an audit).
            return _stopped(status_line, None, "guide stopped while starting, before the camera opened",
                            130 if isinstance(stop, KeyboardInterrupt) else stop.status, guide.speaker)
        return _walk(args, session, log, status_line, guide.speaker)


def _started(args: argparse.Namespace, size: tuple[int, int], guide, status_line, record_dir):
    """Everything a walk needs that takes seconds before the camera opens: the pipeline's imports (torch), its
    ranger and warm-up (:mod:`.guide_warm_up`). Returns the :class:`~.guide_loop.GuideSession` and its log."""
    from ..core.workers import imports_without_collection

    with imports_without_collection():
        from .guide_log import GuideLog
        from .guide_loop import GuideSession
        from .guide_warm_up import import_deferred_modules, pair_ranger, warm_up

        ranged = pair_ranger(args, size)  # it imports torch and the pipeline: here, with the other imports
        import_deferred_modules()
    # Before the camera opens: the first frames' warnings then come as fast as the later ones (guide_warm_up).
    warm_up(ranged, size)
    log = GuideLog(sys.stdout if args.json else None, record_dir, args.floor, args.calibration,
                   calibration_from_args(args), args.second_passes, args.quality, emulator_record(args))
    return GuideSession(args, size, ranged, guide, status_line, log), log


def _walk(args: argparse.Namespace, session, log, status_line, speaker) -> int:
    """Run ``session`` until it ends; the exit status, once :data:`GUIDE_STOPPED` is said (:func:`_stopped`)."""
    try:
        return _walked(args, session, log, status_line, speaker)
    except HungUp as stop:
        # The terminal closed, its SIGHUP taken while an end already under way was said: a write to the terminal
        # failed (EIO) just before, ending the walk as an error, and the SIGHUP cut that end short
        return _stopped(status_line, log, session.stopped_text(), stop.status, speaker)


def _walked(args: argparse.Namespace, session, log, status_line, speaker) -> int:
    """:func:`_walk`, but for a SIGHUP taken while one of its ends is said."""
    from ..capture.link_types import CaptureError

    try:
        with contextlib.ExitStack() as stack:
            stack.enter_context(warnings.catch_warnings())
            warnings.showwarning = status_line.show_warning
            stack.callback(log.close)  # the pairs recorded so far stay listed, whatever stops the loop
            stack.enter_context(terminated_on_sigterm())  # main's too: here the summary is said first
            session.run()
        return _stopped(status_line, log, session.stopped_text(), 0, speaker)  # (before the speaker closes)
    except Terminated as stop:  # a service stopped (systemctl stop), or the terminal closed: exit 143, 129
        return _stopped(status_line, log, session.stopped_text(), stop.status, speaker)
    except KeyboardInterrupt:
        return _stopped(status_line, log, session.stopped_text(), 130, speaker)
    except BrokenPipeError:  # --json's reader went away (| head -1): exit 141, as every command does
        # With --json the words go to stderr and the speaker, both whole: the walker still hears that it stopped
        _stopped(status_line, log, session.stopped_text(), 141, speaker if args.json else None)
        raise
    except (CaptureError, OSError) as error:
        return _stopped(status_line, log, f"svs-depth guide: error: {' '.join(str(error).split())}", 1, speaker)


def _add_walker_options(parser: argparse.ArgumentParser) -> None:
    """The options of the walker's view: the floor rule, the camera's pitch as worn, the second passes."""
    add_floor_option(parser, "on", "a walker's camera sees the floor ahead as the nearest surface; a heap seen "
                                   "from above can read as a floor too: experiments/walker_floor.md")
    parser.add_argument("--camera-pitch-deg", type=camera_pitch_deg, metavar="DEG",
                        help="the camera's pitch below the horizontal as worn, degrees (-45 to 60): where no floor "
                             "was found in the pair or the last 2 s (camera frames at digit 8, a view without "
                             "floor), distances run ahead along a level floor under a camera so pitched, not along "
                             "its axis (default: along its axis there)")
    parser.add_argument("--second-passes", choices=("on", "off"), default="on", help=SECOND_PASSES_HELP)


def camera_pitch_deg(text: str) -> float:
    """``--camera-pitch-deg``: degrees in [-45, 60] (a camera worn looking ahead, down to the feet)."""
    value = finite_float(text)
    if not -45 <= value <= 60:
        raise argparse.ArgumentTypeError(f"expected degrees from -45 to 60 (positive: pitched down), got {text!r}")
    return value


def _stopped(status_line, log, text: str, code: int, speaker=None) -> int:
    """End the status line, say :data:`GUIDE_STOPPED` with ``speaker``, then print ``text`` and what ``log`` (None:
    none yet) recorded on stderr; returns ``code``.

    Spoken at every end, not only an error's: the walker does not read the screen, and the silence after a guide
    that ended (``--count`` reached, Ctrl-C, a service's stop: a battery running low, a system update) read as a
    clear way, as after an error it did (an audit of what a walker hears). Not on a broken pipe of stdout without
    --json: the words' stream is what broke (with --json only the JSON lines' reader went away)."""
    try:
        status_line.close()  # (its last line before the words, in a log too)
    finally:  # said even where that line failed: a terminal gone (EIO) without a SIGHUP (setsid, disown -h)
        if speaker is not None:
            speaker.say(GUIDE_STOPPED)
    print(text, file=sys.stderr)
    if log is not None and (summary := log.summary()) is not None:
        print(summary, file=sys.stderr)
    return code


def _checked_size(args: argparse.Namespace) -> tuple[int, int]:
    """The SVS frame size of ``--size``, after checking it and the other options before the camera opens."""
    from ..capture.protocol import size_code_for
    from ..core.camera import parse_size
    from ..core.errors import InputError

    size = parse_size(args.size, "--size")
    try:
        size_code_for(size)
    except InputError:
        raise InputError(f"--size: expected 160x120, 320x240, 640x480 or 1280x1024, got {args.size!r}") from None
    if args.emulator and (args.left is not None or args.right is not None):  # '' too: it was run as not given
        raise InputError("--left, --right: the boards' URLs, or --emulator, not both")
    if not args.emulator and not (args.left and args.right):
        raise InputError("--left, --right: give both board URLs, or --emulator")
    from .capture import check_board_urls, check_emulator_options

    check_board_urls(args)
    check_emulator_options(args)
    if not 0 <= args.near_m < args.far_m:
        raise InputError(f"--near-m, --far-m: expected 0 <= near < far, got {args.near_m} and {args.far_m}")
    if args.quality is not None and not 1 <= args.quality <= 8:
        raise InputError(f"--quality: expected 1 (best) to 8 (worst), got {args.quality}")
    if args.no_speech and args.words_per_minute is not None:  # a rate asked for and never heard: said, not ignored
        raise InputError("--words-per-minute: a speech rate, and --no-speech says nothing aloud: give one of them")
    return size
