"""What ``guide`` tells of cameras mounted wrong, from what the pairs' matches show (:class:`ViewsWatch`): the two
boards in each other's place, or the rig on its side.

Why: the boards' roles (:meth:`~svs_torch.cli.guide_loop.GuideSession._check_roles`) tell only links that are swapped.
Boards remounted in each other's place answer in their right roles, yet every left view is the right camera's: the
matches lie to the right in the right view, and the pipeline ranged such pairs "OK", "verified", at 0.6-1.7 m (the
swapped shared pairs of ``estimate``'s audit), so a walker heard distances that were wrong. A rig worn on its side
matches along its columns, and the distances are wrong too. Each is what ``estimate``'s reasons say of one pair
(:func:`~svs_torch.cli.estimate_report.views_swapped`, :func:`~svs_torch.cli.estimate_report.rig_turned`).
"""

from __future__ import annotations

import collections

__all__ = ["VIEWS_FRAMES", "ViewsWatch"]

#: The ranged pairs a verdict is taken over; a majority of them must show it (one pair's noise shows nothing).
VIEWS_FRAMES = 5

#: What each verdict's printed line says (the spoken words are :data:`~svs_torch.cli.guide_loop.CAMERAS_SWAPPED`'s).
_LINES = {"swapped": "most pairs' matches lie to the right in the right view: the two boards mounted in each other's "
                     "place (the left camera's board on the right)? Every distance is wrong until they are swapped "
                     "back",
          "turned": "most pairs' matches move up or down, not along the rows: the rig worn on its side? Every "
                    "distance is wrong until the cameras stand side by side"}


class ViewsWatch:
    """Decide, pair by pair, whether the cameras look mounted wrong: once a majority of the last
    :data:`VIEWS_FRAMES` ranged pairs show views swapped, or turned (each test needs 8 RANSAC inliers or more),
    :meth:`update` returns that verdict, once a run."""

    def __init__(self, frames: int = VIEWS_FRAMES) -> None:
        self._recent: collections.deque[str | None] = collections.deque(maxlen=frames)
        self.said: str | None = None

    def update(self, result) -> str | None:
        """Take one ranged pair's pipeline result (a batch of one); the verdict to tell (``"swapped"`` or
        ``"turned"``), or None."""
        from .estimate_report import rig_turned, views_swapped

        if self.said is not None:
            return None
        verdict = "swapped" if views_swapped(result, 0) else "turned" if rig_turned(result, 0) else None
        self._recent.append(verdict)
        for kind in ("swapped", "turned"):
            if 2 * sum(seen == kind for seen in self._recent) > self._recent.maxlen:
                self.said = kind
                return kind
        return None

    @staticmethod
    def line(verdict: str) -> str:
        """The printed line of a verdict :meth:`update` returned."""
        return _LINES[verdict]
