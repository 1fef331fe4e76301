"""What guide says of a repeated pattern it could not range (:class:`PatternNotice`): a fence, a railing or a grate
ahead whose distance the two views cannot tell.

Why: the pipeline leaves such an object without a distance rather than give it a wrong one (the alias check of
:mod:`svs_torch.depth.alias_choice`: its bars fit many shifts, each a distance). ``estimate`` lists it with the
distances its aliases give, and guide's status line showed "a repeated pattern seen, not ranged"; but a walker does
not read a screen. With no ranged obstacle near, the policy took the pair as a clear way and guide was silent, and
a pair with nothing else kept (``NO_DENSE_DEPTH``) was not seen, so after ``--blind-s`` the walker heard "Cannot see
ahead": neither says that a fence may be an arm's length away. Now :data:`REPEATED_PATTERN` is said.
"""

from __future__ import annotations

import collections
import math

from ..core.errors import InputError
from .sight import CONFIRM_FRAMES

__all__ = ["REPEATED_PATTERN", "PatternNotice"]

#: Said while an unranged repeated pattern that may lie within the warning band is in view. Short, for the reason
#: given at :data:`svs_torch.cli.guide_loop.CAMERAS_SWAPPED`: a newer message cuts off an older one.
REPEATED_PATTERN = "Repeated pattern ahead. Distance unknown."


class PatternNotice:
    """Decide, pair by pair, whether to say :data:`REPEATED_PATTERN`.

    A pattern counts on a pair where one of its unranged repeated objects may lie at ``far_m`` or nearer (the
    pair's :attr:`~svs_torch.pipeline.PipelineResult.nearest_unranged_alias_m`: a fence whose every alias is beyond
    the band is no warning). It is said once a majority of the last ``confirm_frames`` pairs count (as a warning is
    confirmed: one pair's noise says nothing), only where the walker would otherwise hear silence (no obstacle
    warning in effect and nothing else said on the pair, which it would cut off: a walker warned of an obstacle in
    the band takes care already, and a grate ranged on one part and not on another said both by turns), and then
    not again for ``repeat_s`` seconds while it stays in view; a pattern out of view for all of the last
    ``confirm_frames`` pairs is a new one when it comes back.

    Args:
        far_m: the warning band's far edge, metres (``guide --far-m``).
        repeat_s: least time between two notices, seconds (``guide --repeat-s``).
        confirm_frames: the pairs a pattern is confirmed over.
    """

    def __init__(self, far_m: float = 2.0, repeat_s: float = 3.0, confirm_frames: int = CONFIRM_FRAMES) -> None:
        if not (far_m > 0 and repeat_s >= 0 and math.isfinite(far_m)):  # (NaN fails too)
            raise InputError(f"far_m, repeat_s: expected far_m > 0 and repeat_s >= 0, got {far_m}, {repeat_s}")
        if isinstance(confirm_frames, bool) or not isinstance(confirm_frames, int) or confirm_frames < 1:
            raise InputError(f"confirm_frames: expected a whole number of frames >= 1, got {confirm_frames!r}")
        self.far_m, self.repeat_s = far_m, repeat_s
        self._recent: collections.deque[bool] = collections.deque(maxlen=confirm_frames)
        self._said_s: float | None = None  # when it was last said, while the pattern stayed in view
        self.nearest_m: float | None = None  # the nearest distance the last pair that counted allowed

    def counts(self, nearest_m: float | None) -> bool:
        """Whether a pair whose unranged pattern may be as near as ``nearest_m`` (None: none) counts."""
        return nearest_m is not None and nearest_m <= self.far_m

    def update(self, nearest_m: float | None, now_s: float, quiet: bool = True) -> str | None:
        """Take how near one pair's unranged pattern may be (metres, None: it has none) at ``now_s`` (seconds),
        and whether the walker hears silence on it (``quiet``: no warning in effect, nothing else said); the words
        to say, or None."""
        self._recent.append(self.counts(nearest_m))
        if self._recent[-1]:
            self.nearest_m = nearest_m
        if 2 * sum(self._recent) <= self._recent.maxlen:  # not confirmed
            if not any(self._recent):  # out of view for every recent pair: when it comes back, a new one
                self._said_s = None
            return None
        if not quiet or (self._said_s is not None and now_s - self._said_s < self.repeat_s):
            return None
        self._said_s = now_s
        return REPEATED_PATTERN

    def reset(self) -> None:
        """Forget the pairs seen and the last notice (the camera was lost)."""
        self._recent.clear()
        self._said_s = self.nearest_m = None
