"""Options ``capture`` and ``guide`` share: ``--baud``, the boards' UART speed, which sets how long a frame's bytes
may take, and what the in-process emulator's frames are like (``--emulator-noise``, ``--emulator-loose-rig``).

Only the standard library is imported (``--help`` must not wait for torch).
"""

from __future__ import annotations

import argparse

from .common import _number, noise_levels

__all__ = ["DEFAULT_BAUD", "MAX_BAUD", "MIN_BAUD", "add_emulator_frame_options", "add_uart_options", "baud_rate",
           "emulator_record"]

DEFAULT_BAUD = 2_304_000  # LinkConfig.baudrate (SVS_PROTOCOL.md §1); a literal so --help needs no capture import

#: The slowest ``--baud`` taken: 9600, the slowest standard rate a serial camera is run at, already allows a
#: 320x240 frame up to 6 minutes (LinkConfig.frame_attempt_timeout_s). ``--baud 1`` was taken, and allowed each
#: attempt 40 days: a board that stopped half-way through a frame held capture or guide, silent, for that long.
MIN_BAUD = 9_600
#: The fastest ``--baud`` taken: the fastest USB serial adapters (12 Mbaud; the SVS's own UART runs at 2,304,000).
#: Above it the frames' timeouts no longer follow the link (``--baud 10**12`` allowed every frame 2 s, whatever its
#: size), so a slower link's frames were cut as broken.
MAX_BAUD = 12_000_000


def baud_rate(text: str) -> int:
    """argparse type of ``--baud``: :data:`MIN_BAUD` to :data:`MAX_BAUD`."""
    value = _number(text, int)
    if not MIN_BAUD <= value <= MAX_BAUD:
        raise argparse.ArgumentTypeError(f"expected a UART speed from {MIN_BAUD} to {MAX_BAUD} baud, got {text!r}")
    return value


def add_uart_options(parser: argparse.ArgumentParser) -> None:
    """``--baud`` and ``--no-flow-control``, the boards' UART as ``capture`` and ``guide`` reach it."""
    parser.add_argument("--baud", type=baud_rate, default=DEFAULT_BAUD,
                        help=f"the boards' UART speed, serial devices and WiFi (socket://) alike: it sets how long "
                             f"a frame's bytes may take, {MIN_BAUD} to {MAX_BAUD} (default: {DEFAULT_BAUD}; 115200 "
                             "for a board built so)")
    # Why: the SVS's UART wants RTS/CTS (§1), but many USB serial adapters wire TX, RX and ground only; with flow
    # control on, such a cable's CTS never rises and every command's write timed out, with no way to turn it off.
    parser.add_argument("--no-flow-control", action="store_true",
                        help="serial devices: no RTS/CTS hardware flow control, for a 3-wire cable (TX, RX, "
                             "ground); the SVS's UART expects it, so use a lower --baud if frames arrive damaged")


def add_emulator_frame_options(parser: argparse.ArgumentParser) -> None:
    """``--emulator-noise`` and ``--emulator-loose-rig``: the frames of ``--emulator``'s boards, as a real rig's."""
    parser.add_argument("--emulator-noise", type=noise_levels, default=0.0, metavar="LEVELS",
                        help="with --emulator: independent Gaussian sensor noise in each camera, 8-bit levels "
                             "(default 0)")
    parser.add_argument("--emulator-loose-rig", action="store_true",
                        help="with --emulator: its right camera mounted loosely, as experiments/real_rig.py's "
                             "'combined': rolled 1 degree, tilted 0.5 about x and -0.5 about y, 2 %% of the height "
                             "lower, 1 %% larger, 20 %% darker; python -m hw.emulator sets each on its own")


def emulator_record(args: argparse.Namespace) -> dict | None:
    """What ``capture``'s and ``guide --record``'s index lines (and guide's ``--json`` ones) say of the in-process
    emulator that sent their frames (``--emulator``): its ``noise_sigma`` (8-bit levels), ``loose_rig``,
    ``floor_m`` and ``heap_m`` (null: none); None for the boards at ``--left``/``--right`` (an emulator run on its
    own is a board to them). Why: a folder of ``capture --emulator --emulator-noise 4`` frames, read later, could
    not be told from a real board's, nor its noise from another run's (an audit of recordings)."""
    if not getattr(args, "emulator", False):
        return None
    return {"noise_sigma": getattr(args, "emulator_noise", 0.0),
            "loose_rig": getattr(args, "emulator_loose_rig", False),
            "floor_m": getattr(args, "emulator_floor_m", None), "heap_m": getattr(args, "emulator_heap_m", None)}
