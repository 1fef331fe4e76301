"""The emulator's command line (``python -m hw.emulator --help``): its options, each checked when parsed.

Why here and not where the values are used: a bad value there (a step of 0 s between image pairs, a length delta
of millions, a negative floor height) killed a board's thread in the middle of a run, its port closed while the
emulator looked alive.
"""

from __future__ import annotations

import argparse
import math

from .emulator_state import Faults
from .frames import MIN_IMAGE_STEP_S, WALKER_PITCH_DEG
from svs_torch.cli.capture import check_heap_in_view
from svs_torch.cli.common import MAX_SEED, finite_float, noise_levels, non_negative_float, non_negative_int, \
    positive_float, positive_int, seed_int
from svs_torch.cli.guide import MIN_EMULATOR_FLOOR_M
from svs_torch.cli.link_options import MIN_BAUD
from svs_torch.core.camera import SVS_CAMERA, SVS_RESOLUTIONS, parse_size
from svs_torch.data.rig_deviation import RigDeviation
from svs_torch.data.synthetic import CAMERA_PITCH_RANGE_DEG, WALL_DEPTH_M

__all__ = ["MAX_DELAY_S", "MIN_LINK_BYTES_PER_S", "faults_from_args", "parse_args", "right_deviation_from_args"]

#: The longest --grab-delay and --drip-delay, seconds (a day, as svs-depth's --timeout). Why: 1e300 was taken, and
#: a board's thread died at its first grab (OverflowError: past the platform's longest wait, threading.TIMEOUT_MAX),
#: its port closed while the emulator looked alive; the driver then said "Connection refused".
MAX_DELAY_S = 86400.0
#: The slowest --link-rate other than 0, bytes a second: 9600 baud, 8N1, the slowest --baud svs-depth takes. Why:
#: 1e-300 was taken, and the first reply's pacing wait killed the board's thread as a huge delay did.
MIN_LINK_BYTES_PER_S = MIN_BAUD // 10


def parse_args(argv: list[str] | None, description: str, link_bytes_per_s: float) -> argparse.Namespace:
    """The emulator's options (``description``: its help's first paragraph; ``link_bytes_per_s``: the default
    pace), with ``prepare_sizes``, the ``--prepare`` sizes parsed; a bad value is a usage error (exit 2)."""
    p = argparse.ArgumentParser(prog="python -m hw.emulator", description=description)
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default %(default)s)")
    p.add_argument("--left-port", type=_port, default=10001,
                   help="left/master TCP port, 0 = free (default %(default)s)")
    p.add_argument("--right-port", type=_port, default=10002,
                   help="right/slave TCP port, 0 = free (default %(default)s)")
    p.add_argument("--pty", action="store_true", help="also serve each board on a pseudo-terminal")
    p.add_argument("--images", metavar="DIR", help="left/right image folder (default: synthetic obstacles)")
    p.add_argument("--image-step", type=_image_step, default=1.0,
                   help=f"seconds per image pair, at least {MIN_IMAGE_STEP_S:g} (default %(default)s)")
    p.add_argument("--simple-frames", action="store_true", help="fast stand-in renderer instead of svs_torch's")
    p.add_argument("--prepare", metavar="WxH[,WxH]", default="",
                   help="render every synthetic keyframe at these sizes before serving (exact depths from the start)")
    p.add_argument("--holdoff-ms", type=_holdoff_ms, default=1.0, metavar="MS",
                   help=f"input discarded after each reply, ms, at most {MAX_DELAY_S * 1000:.0f} (default %(default)s)")
    p.add_argument("--link-rate", type=_link_rate, default=link_bytes_per_s, metavar="BYTES/S",
                   help="each board's replies paced to this many bytes a second, as the SVS's 2,304,000-baud "
                        f"UART sends them, at least {MIN_LINK_BYTES_PER_S} (default %(default)s); 0: as fast as the "
                        "socket takes them")
    p.add_argument("--json", action="store_true", help="print the URLs as one JSON line (for scripts)")
    # 0 to 255, as svs-depth's --emulator-noise: 1e9 was taken and every pixel came out 0 or 255, no scene left.
    p.add_argument("--noise-sigma", type=noise_levels, default=0.0, metavar="LEVELS",
                   help="independent Gaussian sensor noise in each camera, 8-bit levels, 0 to 255 (default "
                        "%(default)s)")
    # A seed torch takes: 2**64 was refused inside torch as "Overflow when unpacking long long", naming no option.
    p.add_argument("--noise-seed", type=seed_int, default=0, metavar="N",
                   help=f"seed of the left camera's noise, 0 to {MAX_SEED}; the right's is the next (default "
                        "%(default)s)")
    p.add_argument("--floor-height-m", type=positive_float, default=None, metavar="M",
                   help="synthetic frames: the cameras M metres over a textured floor, as a walker wears them, at "
                        "least 0.01 (default: no floor)")
    p.add_argument("--camera-pitch-deg", type=finite_float, default=WALKER_PITCH_DEG, metavar="DEG",
                   help="with --floor-height-m: the cameras pitched down DEG degrees, -30 to 60 (default %(default)s)")
    p.add_argument("--heap-ahead-m", type=positive_float, default=None, metavar="M",
                   help="with --floor-height-m: a heap of rocks on the floor M metres ahead, 0.9 m wide and 0.35 m "
                        "high (an obstacle; default: none)")
    p.add_argument("--boards-swapped", action="store_true",
                   help="the two boards mounted in each other's place: the left (master) board sends the right "
                        "view, the right (slave) board the left one, their roles and ports as wired")
    r = p.add_argument_group("a loosely mounted right camera (what it sees, before the noise)")
    for option, _, _, _, metavar, meaning in _DEVIATION_OPTIONS:
        r.add_argument(option, type=finite_float, default=0.0, metavar=metavar, help=f"{meaning}; default 0")
    _add_fault_options(p.add_argument_group("faults (replies to I)"))
    args = p.parse_args(argv)
    _check_values(p, args)
    return args


def _add_fault_options(f: argparse._ArgumentGroup) -> None:
    """The fault options (:func:`faults_from_args`), added to the group ``f``."""
    f.add_argument("--fault-camera", choices=("left", "right", "both"), default="both",
                   help="the board whose replies the faults below change (default: both)")
    f.add_argument("--silent", type=non_negative_int, default=0, metavar="N", help="no reply to the next N grabs")
    f.add_argument("--garbage", type=non_negative_int, default=0, metavar="N",
                   help="stray bytes before the next N frames")
    f.add_argument("--truncate", type=non_negative_int, default=0, metavar="N", help="cut the next N frames in half")
    f.add_argument("--damage", type=non_negative_int, default=0, metavar="N",
                   help="zero 2000 bytes inside the next N frames' JPEGs (they still decode, partly gray)")
    f.add_argument("--wrong-length", type=non_negative_int, default=0, metavar="N",
                   help="misannounce the next N lengths")
    f.add_argument("--wrong-length-delta", type=_length_delta, default=64, metavar="BYTES",
                   help="bytes added to the announced length, -65536..65536 (default %(default)s)")
    f.add_argument("--drip-chunk", type=non_negative_int, default=0, metavar="BYTES",
                   help="send replies in chunks of BYTES")
    f.add_argument("--drip-delay", type=_delay_seconds, default=0.0, metavar="S",
                   help=f"pause between chunks, seconds, at most {MAX_DELAY_S:g}")
    # At least 1: 0 was taken and the link dropped after the first frame, as with 1 (the count is of frames sent).
    f.add_argument("--drop-after", type=positive_int, default=None, metavar="N",
                   help="drop the TCP link after N frames, N >= 1")
    f.add_argument("--grab-delay", type=_delay_seconds, default=0.0, metavar="S",
                   help=f"grab + encode time, seconds, at most {MAX_DELAY_S:g}")
    f.add_argument("--freeze", type=non_negative_int, default=0, metavar="N",
                   help="answer the next N grabs with the last frame's JPEG bytes again (a stalled sensor)")


def _check_values(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Check the parsed values together, and add ``right_deviation`` and ``prepare_sizes``; ``p.error`` on a bad
    one."""
    # Checked here, not in the threads that use them: a bad value there killed a board's thread mid-run.
    # One port given twice was said as "Address already in use" (exit 1), though no other program held it.
    if args.left_port == args.right_port != 0:
        p.error(f"--left-port, --right-port: expected two ports (one per board), got {args.left_port} for both")
    # The synthetic renderer's range: outside it the render thread died and every frame was the stand-in's, no floor.
    low, high = CAMERA_PITCH_RANGE_DEG
    if not low <= args.camera_pitch_deg <= high:
        p.error(f"--camera-pitch-deg: expected degrees in [{low:g}, {high:g}], got {args.camera_pitch_deg:g}")
    _check_floor_in_view(p, args)
    if args.heap_ahead_m is not None and args.floor_height_m is None:
        p.error("--heap-ahead-m: expected --floor-height-m too (a heap stands on the floor)")
    if args.heap_ahead_m is not None:
        # svs-depth's --emulator-heap-m bounds, at this pitch: 100 m was taken and no frame showed a pixel of heap
        # (behind the wall), unsaid. At 1280x1024, the tallest and sharpest view a board sends: the loosest bounds.
        try:
            check_heap_in_view(args.heap_ahead_m, args.floor_height_m, (1280, 1024), args.camera_pitch_deg,
                               "--heap-ahead-m")
        except ValueError as err:  # svs_torch's InputError is a ValueError
            p.error(str(err))
    if args.images is not None and not args.images.strip():
        # An empty value (an unset shell variable) served the synthetic obstacles instead, unsaid.
        p.error(f"--images: expected a folder of left/right image pairs, got {args.images!r}")
    if args.floor_height_m is not None and (args.images or args.simple_frames):
        # The floor was ignored: the frames showed none, and nothing said so.
        p.error("--floor-height-m: only the synthetic frames of svs_torch's renderer have a floor, not "
                f"{'--images' if args.images else '--simple-frames'}")
    try:
        args.right_deviation = right_deviation_from_args(args)
    except ValueError as err:  # RigDeviation's field, named as its option
        p.error(str(err))
    try:
        args.prepare_sizes = [parse_size(size, "--prepare") for size in filter(None, args.prepare.split(","))]
    except ValueError as err:  # svs_torch's InputError is a ValueError
        p.error(str(err))
    # Only the sizes a board sends (§3): 321x240 was taken and its keyframes rendered, a size nothing asks for,
    # while the 320x240 meant was served by the stand-in renderer until its own keyframes were ready.
    odd = next((size for size in args.prepare_sizes if size not in SVS_RESOLUTIONS.values()), None)
    if odd is not None:
        sizes = ", ".join(f"{w}x{h}" for w, h in SVS_RESOLUTIONS.values())
        p.error(f"--prepare: expected {sizes.replace(', 1280', ' or 1280')} (the sizes a board sends), got "
                f"{odd[0]}x{odd[1]}")


def _highest_floor_seen_m(pitch_deg: float) -> float:
    """The height over the floor from which cameras pitched ``pitch_deg`` down see none of it before the wall, at
    the tallest view of the sizes a board sends (the view's bottom ray meets the floor at the wall's depth). Why:
    ``--floor-height-m 1e9`` was taken and every frame showed no floor, unsaid (at 20 degrees 320x240 sees none
    from 3.00 m up, 1280x1024 from 3.11 m; at -30 degrees no height shows any)."""
    half_rad = max(math.atan(h / 2 / SVS_CAMERA.focal_px(w)) for w, h in SVS_RESOLUTIONS.values())
    return WALL_DEPTH_M * math.sin(math.radians(pitch_deg) + half_rad) / math.cos(half_rad)


def _check_floor_in_view(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--floor-height-m`` low enough for the cameras, pitched ``--camera-pitch-deg``, to see the floor."""
    if args.floor_height_m is None:
        return
    if args.floor_height_m < MIN_EMULATOR_FLOOR_M:  # (1e-300 killed the render thread: svs-depth guide's bound)
        p.error(f"--floor-height-m: expected at least {MIN_EMULATOR_FLOOR_M:g} m (lower, the cameras lie on the "
                f"floor), got {args.floor_height_m:g}")
    highest_m, pitch = _highest_floor_seen_m(args.camera_pitch_deg), f"--camera-pitch-deg {args.camera_pitch_deg:g}"
    if highest_m <= 0:
        p.error(f"--floor-height-m: cameras at {pitch} see no floor at any height before the wall {WALL_DEPTH_M:g} m "
                "ahead; pitch them further down")
    if not args.floor_height_m < highest_m:
        p.error(f"--floor-height-m: expected under {highest_m:.2f} m with {pitch} (higher, no size a board sends "
                f"shows any floor before the wall {WALL_DEPTH_M:g} m ahead), got {args.floor_height_m:g}")


def _port(text: str) -> int:
    """argparse type: a TCP port, 0 (a free one) to 65535."""
    port = non_negative_int(text)
    if port > 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port 0..65535, got {text!r}")
    return port


def _image_step(text: str) -> float:
    """argparse type of ``--image-step``: at least :data:`~hw.frames.MIN_IMAGE_STEP_S` seconds."""
    value = positive_float(text)
    if value < MIN_IMAGE_STEP_S:
        raise argparse.ArgumentTypeError(f"expected seconds from {MIN_IMAGE_STEP_S:g}, got {text!r}")
    return value


def _delay_seconds(text: str) -> float:
    """argparse type of a fault's delay: 0 to :data:`MAX_DELAY_S` seconds."""
    value = non_negative_float(text)
    if value > MAX_DELAY_S:
        raise argparse.ArgumentTypeError(f"expected seconds from 0 to {MAX_DELAY_S:g} (a day), got {text!r}")
    return value


def _holdoff_ms(text: str) -> float:
    """argparse type of ``--holdoff-ms``: 0 to :data:`MAX_DELAY_S` in ms. Why: 1e300 was taken, and each board
    answered its first command and discarded every later one, the emulator looking alive."""
    value = non_negative_float(text)
    if value > MAX_DELAY_S * 1000:
        raise argparse.ArgumentTypeError(f"expected ms from 0 to {MAX_DELAY_S * 1000:.0f} (a day), got {text!r}")
    return value


def _link_rate(text: str) -> float:
    """argparse type of ``--link-rate``: 0 (unpaced) or :data:`MIN_LINK_BYTES_PER_S` bytes a second or more."""
    value = non_negative_float(text)
    if 0 < value < MIN_LINK_BYTES_PER_S:
        raise argparse.ArgumentTypeError(f"expected 0 (unpaced) or at least {MIN_LINK_BYTES_PER_S} bytes a second "
                                         f"(9600 baud), got {text!r}")
    return value


def _length_delta(text: str) -> int:
    """argparse type: bytes added to a frame's announced length (a frame's length field is 32 bits; a delta of
    millions made the frame encoder raise in the board's thread)."""
    try:
        delta = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of bytes, got {text!r}") from None
    if abs(delta) > 65536:
        raise argparse.ArgumentTypeError(f"expected -65536..65536 bytes, got {text!r}")
    return delta


def faults_from_args(args: argparse.Namespace) -> Faults:
    """The faults the options ask for (``Faults``' fields)."""
    return Faults(silent_grabs=args.silent, garbage_frames=args.garbage, truncated_frames=args.truncate,
                  damaged_frames=args.damage, wrong_length_frames=args.wrong_length,
                  wrong_length_delta=args.wrong_length_delta,
                  drip_chunk_bytes=args.drip_chunk, drip_delay_s=args.drip_delay,
                  drop_after_frames=args.drop_after, grab_delay_s=args.grab_delay, frozen_grabs=args.freeze)


#: The right camera's options: the :class:`RigDeviation` field each sets, its factor (a percentage is a share), its
#: range in the option's own unit (the field's, scaled: each end open where the field's is), metavar and help.
_DEVIATION_OPTIONS = (
    ("--right-roll-deg", "roll_deg", 1.0, "(-90, 90) degrees", "DEG", "turned DEG degrees about its optical axis"),
    ("--right-tilt-x-deg", "tilt_x_deg", 1.0, "(-90, 90) degrees", "DEG",
     "turned DEG degrees about its x axis, up or down, a keystone"),
    ("--right-tilt-y-deg", "tilt_y_deg", 1.0, "(-90, 90) degrees", "DEG",
     "turned DEG degrees about its y axis, inwards or outwards, a keystone"),
    ("--right-shift-percent", "shift_y_fraction", 0.01, "[-100, 100] % of the height", "P",
     "moved P %% of the image height down, negative: up"),
    ("--right-scale-percent", "scale", 0.01, "(-100, 10000] %", "P",
     "its view P %% larger, another lens; negative: smaller"),
    ("--right-gain-percent", "gain", 0.01, "(-100, 10000] %", "P",
     "its frames P %% brighter, another exposure; negative: darker"),
)


def right_deviation_from_args(args: argparse.Namespace) -> RigDeviation | None:
    """The right camera's deviation the ``--right-*`` options ask for; None for the ideal rig. A value out of its
    range is an error naming the option (a roll of 90° or more, a shift past the whole height, a scale or gain of
    -100 % or less)."""
    fields = {}
    for option, field, factor, interval, _, _ in _DEVIATION_OPTIONS:
        value = getattr(args, option[2:].replace("-", "_"))
        fields[field] = value * factor
        try:
            RigDeviation(**{field: fields[field]})
        except ValueError:  # svs_torch's InputError, naming the field
            raise ValueError(f"{option}: expected {interval}, got {value:g}") from None
    deviation = RigDeviation(**fields)
    return None if deviation.is_identity else deviation
