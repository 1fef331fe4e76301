"""``--baud`` of ``capture`` and ``guide``: the boards' UART speed, which sets how long a frame's bytes may take.

Only the standard library is imported (``--help`` must not wait for torch).
"""

from __future__ import annotations

import argparse

from .common import _number

__all__ = ["MAX_BAUD", "MIN_BAUD", "baud_rate"]

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
