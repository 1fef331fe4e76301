"""Whether one camera of the pair froze (:class:`FrozenCameraWatch`): its board keeps sending one frame while the other
board's frames go on, so a pair joins a stale view with a fresh one.

Why: the SVS is two SRV-1 boards, and a board whose sensor stalls can keep answering each grab with the same frame
buffer. Ranged, such a pair is two frames from different times (as a pair whose frames came apart, which ``guide``
refuses), and a walker is warned of where obstacles were, not where they are. A real sensor's noise makes two of
its frames of a scene differ somewhere (the argument of ``guide``'s test of one image sent for both views), so a
frame equal to that camera's previous one, pixel for pixel, is a sent-again buffer, unless it is flat (a covered
lens, the dark, a clipped sky: the pipeline's to find blank).
"""

from __future__ import annotations

import torch

from ..core.errors import InputError

__all__ = ["BOTH_FROZEN_S", "FROZEN_PAIRS", "ONE_FROZEN_S", "FrozenCameraWatch", "one_image_twice", "varies"]

#: Pairs in a row in which one camera's frame came again while the other's changed before that camera is judged
#: frozen. Not 1: where frames carry no noise (the emulator's default) a scene that steps (its keyframes, an image
#: folder's pairs) between the two boards' grabs of one pair makes one camera's frame look unchanged beside the
#: other's changed one, and the next pair then shows the other way round; a frozen camera stays unchanged. The one
#: pair ranged first joins frames one pair taken apart (0.1-0.2 s at guide's 5-10 pairs a second), about what guide
#: still ranges of a pair whose two frames came apart (``max_frame_gap_s``, 0.25 s).
FROZEN_PAIRS = 2
#: Seconds both cameras' frames must stay equal to their previous ones, pixel for pixel and not flat, before both are
#: judged frozen. Not a pair or two: frames without noise (the emulator's default) of a scene that holds still between
#: its steps (its keyframes 0.5 s apart, an image folder's pairs 1 s) repeat on both boards, where a real sensor's
#: noise never repeats. Found by an audit: both boards frozen (the emulator's --freeze, noise σ 4) left guide ranging
#: one old pair for good, "Obstacle ahead, 1.9 metres" every 3 s while the scene moved.
BOTH_FROZEN_S = 3.0
#: Seconds one camera's frames must stay equal to its previous ones, pixel for pixel and not flat, while the other's
#: changed in that time, before that camera is judged frozen even where :data:`FROZEN_PAIRS` pairs in a row never
#: showed it: frames without noise (the emulator's default) of a scene that steps every 0.5 s change on the other
#: board once a step, and the pairs between the steps repeat on both, so the count in a row started again at each
#: step. Found by an audit: the left board frozen from the start (``--freeze``, no noise) was never named, and guide
#: ranged its old frame beside the right's new ones, "Stop. Obstacle at 0.8 metres" with both boxes 1.6 m and
#: more away. As long as :data:`BOTH_FROZEN_S`: no real sensor's frame comes again for that long.
ONE_FROZEN_S = BOTH_FROZEN_S


def varies(image: torch.Tensor) -> bool:
    """Whether ``image`` is not flat: some pixel differs from another. Not differentiable (a comparison)."""
    return bool(image.amax() > image.amin())


def one_image_twice(left: torch.Tensor, right: torch.Tensor) -> bool:
    """Whether a pair's ``left`` and ``right`` frames are the same image, pixel for pixel, and not a flat one: two
    cameras' frames of a scene never are (each sensor has its own noise), one frame sent for both always is. Two flat
    frames (both lenses covered, black or clipped) may be equal and are the pipeline's to find blank. What guide
    refuses to range and capture warns of. Not differentiable (a comparison)."""
    return left.shape == right.shape and bool((left == right).all()) and varies(left)


class FrozenCameraWatch:
    """Which camera of a stream of one-pair batches is frozen: :meth:`update` takes each pair grabbed, in order,
    and returns ``"left"`` or ``"right"`` when that camera's frame has been equal to its previous one, pixel for
    pixel and not flat, while the other camera's frame changed, on :data:`FROZEN_PAIRS` pairs in a row, or has not
    changed for :data:`ONE_FROZEN_S` seconds while the other's did (judged where :meth:`update` is given the time);
    ``"both"`` when both frames have stayed so for ``both_frozen_s`` seconds (:data:`BOTH_FROZEN_S`; judged where
    :meth:`update` is given the time); else None. It keeps the previous pair's two frames (references, not copies);
    :meth:`reset` forgets them (a camera opened again after a loss).
    """

    def __init__(self, frozen_pairs: int = FROZEN_PAIRS, both_frozen_s: float = BOTH_FROZEN_S) -> None:
        # Why: 0 (or -1) was taken, and every pair then named the left camera frozen, the first one too.
        if isinstance(frozen_pairs, bool) or not isinstance(frozen_pairs, int) or frozen_pairs < 1:
            raise InputError(f"frozen_pairs: expected a whole number of pairs >= 1, got {frozen_pairs!r}")
        if isinstance(both_frozen_s, bool) or not isinstance(both_frozen_s, (int, float)) or not both_frozen_s >= 0:
            raise InputError(f"both_frozen_s: expected seconds >= 0, got {both_frozen_s!r}")
        self.frozen_pairs, self.both_frozen_s = frozen_pairs, float(both_frozen_s)
        self.reset()

    def reset(self) -> None:
        """Forget the previous frames: the next pair is compared with nothing."""
        self._previous: dict[str, torch.Tensor] | None = None
        self._unchanged = {"left": 0, "right": 0}  # pairs in a row: this camera's frame came again, the other's not
        self._both_since_s: float | None = None  # since when both frames have come again, not flat
        self._still_since_s: dict[str, float | None] = {"left": None, "right": None}  # one camera's, likewise
        self._other_changed = {"left": False, "right": False}  # the other camera's frame changed since then

    def update(self, batch, now_s: float | None = None) -> str | None:
        """Take a grabbed pair (a :class:`~svs_torch.core.types.StereoBatch` of one, ``left``/``right``
        ``(1, 1, H, W)``; None: nothing to compare, the state kept) grabbed at ``now_s`` (seconds, monotonic; None:
        both cameras are not judged); the camera judged frozen (``"both"`` for both), or None."""
        if batch is None:
            return None
        frames = {"left": batch.left, "right": batch.right}
        previous, self._previous = self._previous, frames
        if previous is None or any(frames[name].shape != previous[name].shape for name in frames):
            self.reset()
            self._previous = frames
            return None
        same = {name: torch.equal(frames[name], previous[name]) for name in frames}  # (one pass, no copy)
        for name, other in (("left", "right"), ("right", "left")):
            frozen = same[name] and not same[other] and varies(frames[name])
            self._unchanged[name] = self._unchanged[name] + 1 if frozen else 0
        still = self._still_too_long(frames, same, now_s)  # (its clocks kept on every pair)
        both = now_s is not None and all(same.values()) and all(varies(frame) for frame in frames.values())
        if not both:
            self._both_since_s = None
        else:
            if self._both_since_s is None:
                self._both_since_s = now_s
            if now_s - self._both_since_s >= self.both_frozen_s:
                return "both"
        return next((name for name, count in self._unchanged.items() if count >= self.frozen_pairs), still)

    def _still_too_long(self, frames: dict[str, torch.Tensor], same: dict[str, bool],
                        now_s: float | None) -> str | None:
        """The camera whose frame has come again, not flat, for :data:`ONE_FROZEN_S` seconds while the other's
        changed in that time, or None; its clock and the other's changes are kept here. None without a time."""
        if now_s is None:
            return None
        for name, other in (("left", "right"), ("right", "left")):
            if not (same[name] and varies(frames[name])):
                self._still_since_s[name] = None
                continue
            if self._still_since_s[name] is None:
                self._still_since_s[name], self._other_changed[name] = now_s, False
            self._other_changed[name] = self._other_changed[name] or not same[other]
        return next((name for name, since_s in self._still_since_s.items() if since_s is not None
                     and self._other_changed[name] and now_s - since_s >= ONE_FROZEN_S), None)
