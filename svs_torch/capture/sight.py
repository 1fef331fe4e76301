"""Whether guide can see (:class:`SightWatch`): silence must mean "nothing near", never "nothing measured".

Its words, :data:`CANNOT_SEE` and :data:`SEEING_AGAIN`, are spoken by :mod:`svs_torch.capture.guide`'s speaker;
:mod:`svs_torch.capture.guide` re-exports all three (their home before this module).
"""

from __future__ import annotations

import collections
import math
import time

from ..core.errors import InputError

__all__ = ["CANNOT_SEE", "CONFIRM_FRAMES", "SEEING_AGAIN", "SightWatch"]

#: The frames a distance is confirmed over (the median of the last 3): rendered walks toward a box as the board's
#: camera frames at 20 frames/s, digits 4-8, and the shared scenes' frames held still (experiments/guide_confirm.md).
CONFIRM_FRAMES = 3

CANNOT_SEE = "Cannot see ahead. No warnings until it can."
SEEING_AGAIN = "Seeing ahead again."


class SightWatch:
    """Whether the guide can see: silence must mean "nothing near", not "nothing measured".

    A pair the pipeline could not see (a covered lens or the dark leave blank frames; noise that nothing verifies,
    ``NO_DENSE_DEPTH``) gives no distance, which the :class:`WarningPolicy` takes as clear. When no pair has been
    seen for ``blind_s`` seconds (from the start too), :meth:`update` returns :data:`CANNOT_SEE` once; once a
    majority of the last ``confirm_frames`` pairs are seen again, :data:`SEEING_AGAIN` (as a warning needs a
    majority: an audit found a covered lens's noise ranged now and then, each such pair saying "Seeing ahead
    again" while the lens stayed covered). A single pair not seen among seen ones says nothing. ``blind_s`` 0:
    never. The caller says what was seen (``guide``: ranged, or a view whose disparity map found only floor).
    """

    def __init__(self, blind_s: float = 2.0, start_s: float | None = None,
                 confirm_frames: int = CONFIRM_FRAMES) -> None:
        if not (blind_s >= 0 and math.isfinite(blind_s)):
            raise InputError(f"blind_s: expected a finite number of seconds >= 0, got {blind_s}")
        self.blind_s = blind_s
        self.last_seen_s = time.monotonic() if start_s is None else start_s
        self.blind = False
        self._while_blind: collections.deque[bool] = collections.deque(maxlen=max(1, int(confirm_frames)))

    def update(self, seen: bool, now_s: float) -> str | None:
        """Take whether the pair at ``now_s`` was seen; the words to say, or None."""
        if self.blind:
            self._while_blind.append(bool(seen))
            if 2 * sum(self._while_blind) > self._while_blind.maxlen:
                self.blind, self.last_seen_s = False, now_s
                return SEEING_AGAIN
            return None
        if seen:
            self.last_seen_s = now_s
            return None
        if self.blind_s and now_s - self.last_seen_s >= self.blind_s:
            self.blind = True
            self._while_blind.clear()
            return CANNOT_SEE
        return None
