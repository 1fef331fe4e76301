"""The loop of ``svs-depth guide``: grab the newest pair, range it, warn, keep it; a camera that stops
answering in the middle of a walk is said to be lost, and opened again until it answers; and a guide that could
range no pair for ``--blind-s`` seconds says that it cannot see (:class:`~svs_torch.capture.guide.SightWatch`).

Why: the two boards talk over WiFi, and a walker moves through places where the link drops for seconds. Before,
a link that stayed down past the driver's own retries (``LinkConfig.max_retries`` / ``max_reconnects``, about
a second) ended ``guide`` with one line on the screen: the walker, who does not look at a screen, heard nothing
and was no longer warned. Now the loss is spoken at once ("Camera lost. No warnings until it is back."), the
camera is opened again every ``--reconnect-s`` seconds, and the first pair ranged after it is back is spoken too
("Camera back."), the warning state cleared so that an obstacle in the band is warned of at once. A camera that
never opened (a wrong address, a board switched off) still ends guide with its error, exit 1, as before; so does
one lost for ``--give-up-s`` seconds, if set. With ``--json`` each loss and return is a line of its own
(``{"event": "camera_lost", ...}``, ``{"event": "camera_back", "lost_s": ...}``); ``--record`` keeps pairs only.

Sight is judged on time, not only on the pairs that come: a link that froze while the driver retries brings no
pair for seconds, and the stream ticks (``IDLE_TICK_S``) so that "Cannot see ahead" comes after ``--blind-s``;
and a pair whose two frames came further apart than the camera's ``max_frame_gap_s`` after its regrabs is not
ranged (``{"event": "frames_apart"}``) and counts as not seen; so does a pair in which one camera's frame came again
(:class:`~svs_torch.capture.frozen.FrozenCameraWatch`, ``{"event": "camera_frozen", "camera": ...}``).
"""

from __future__ import annotations

import argparse
import contextlib
import time
import warnings
from typing import Callable

from ..capture.frozen import FrozenCameraWatch, one_image_twice
from ..capture.guide import CANNOT_SEE, CLEAR, UNSEEN, SightWatch
from ..capture.link_types import CaptureError
from ..capture.pattern_notice import PatternNotice
from ..depth.depth_types import ObstacleSide
from ..pipeline import PipelineStatus
from .capture import open_stereo_camera
from .guide import GUIDE_STOPPED  # (said there, before this module's imports are done)
from .guide_floor import DISTANCE_ALONG, FLOOR_MEMORY_S, FloorMemory
from .guide_log import GuideLog
from .guide_views import ViewsWatch

__all__ = ["CAMERA_BACK", "CAMERA_LOST", "CHECK_CAMERA", "CHECK_CAMERAS", "DISTANCE_ALONG", "FLOOR_MEMORY_S",
           "FloorMemory", "GUIDE_READY", "GUIDE_STOPPED", "GuideSession", "ONE_CAMERA_LOST"]

#: What a camera raises when it stops answering: the driver's error, or a serial port's own (pyserial's
#: SerialException is an OSError). A BrokenPipeError is stdout's reader gone, never the camera.
_CAMERA_ERRORS = (CaptureError, OSError)

CAMERA_LOST = "Camera lost. No warnings until it is back."
#: :data:`CAMERA_LOST` where one board failed (``CaptureError.camera``): the walker, or whoever helps, knows which
#: board to look at, as a frozen one is named (:data:`CHECK_CAMERA`). Was: "Camera lost" for the right board's
#: silence or damaged frames alike, though the error named it (an audit of what a walker hears).
ONE_CAMERA_LOST = "{} camera lost. No warnings until it is back."
CAMERA_BACK = "Camera back."
#: Said once, when the camera first answers: the warm-up and the camera's opening take seconds, and with a clear way
#: nothing was said after them, so the walker could not tell a guide that sees nothing near from one still starting
#: (an audit of what a walker hears).
GUIDE_READY = "Guide ready."
#: Said once when the boards answer in the wrong stereo roles (the left URL reaches the slave): every disparity,
#: so every distance, is then wrong, and a printed warning is not read by a walker who cannot see the screen. Short:
#: the 15 words it had take about 5 s at 170 words a minute, and with the URLs swapped "Cannot see ahead" comes
#: 2 s after it and cuts it off (an audit); the printed warning says what to check.
CAMERAS_SWAPPED = "Check the cameras. Distances may be wrong."
#: Said after "Cannot see ahead" (one sentence: a newer message cuts off an older one) when the pairs were not ranged
#: because one camera keeps sending one frame (a stalled board), once a run for each camera, or with it said again
#: where guide was blind already (alone with --blind-s 0): the walker can do something about it (restart that board),
#: and short for the reason given at CAMERAS_SWAPPED.
CHECK_CAMERA = "Check the {} camera."
#: :data:`CHECK_CAMERA` where both boards keep sending one frame each (:data:`~svs_torch.capture.frozen.BOTH_FROZEN_S`).
CHECK_CAMERAS = "Check the cameras."
#: Seconds between the ticks of a stream that brings no pair (:meth:`SVSStereoCamera.stream_batches`'s ``idle_s``).
IDLE_TICK_S = 0.25


def _one_image_twice(batch) -> bool:
    """Whether a grabbed pair's two frames are one image (:func:`~svs_torch.capture.frozen.one_image_twice`)."""
    return batch is not None and one_image_twice(batch.left, batch.right)


class GuideSession:
    """One ``guide`` run: ``ranged`` (the pipeline on a one-pair batch), ``guide`` (a
    :class:`~svs_torch.capture.guide.LiveGuide`), the ``status_line`` and the ``log`` (:class:`GuideLog`), over the
    camera of ``args`` at ``size``. ``processed`` counts the pairs taken (``--count``'s), ``torn`` those of them not
    ranged because their two frames came too far apart."""

    def __init__(self, args: argparse.Namespace, size: tuple[int, int], ranged: Callable, guide, status_line,
                 log: GuideLog) -> None:
        self.args, self.size, self.ranged = args, size, ranged
        self.guide, self.status_line, self.log = guide, status_line, log
        self.processed = self.torn = self.one_image = self.frozen_pairs = self.both_frozen_pairs = 0
        self.frozen_watch = FrozenCameraWatch()  # compares each pair's frames with the previous pair's
        self.cameras_checked: set[str] = set()  # the cameras CHECK_CAMERA was said of
        self.opened = False  # the camera answered once: a later failure is a loss, not a wrong address
        self.roles_said = False  # CAMERAS_SWAPPED said (the boards' roles, or the views: self.views)
        self.views = ViewsWatch()
        self.lost_at_s: float | None = None
        self.sight = None  # a SightWatch, from when the camera first answers
        self.next_pair_index = 0  # the index of the next pair grabbed, over every time the camera is opened
        self.floor = FloorMemory(worn_pitch_deg=getattr(args, "camera_pitch_deg", None))
        policy = guide.policy
        self.pattern = PatternNotice(policy.far_m, policy.repeat_s, policy.confirm_frames)  # a fence not ranged

    def run(self) -> None:
        """Range pairs until ``--count`` (0: until interrupted), opening the camera again while it is lost.

        Raises:
            CaptureError: the camera never opened, or stayed lost for ``--give-up-s`` seconds (if set).
        """
        while True:
            with contextlib.ExitStack() as stack:  # the camera closed before waiting to open it again
                try:
                    # Numbered on from the camera before a loss: --record's pair files are never overwritten.
                    camera = open_stereo_camera(self.args, self.size, stack, first_index=self.next_pair_index)
                except BrokenPipeError:  # stdout's reader gone, never the camera
                    raise
                except _CAMERA_ERRORS as error:
                    if not self.opened:
                        raise
                    lost = error
                else:
                    if not self.opened:  # silence from here means a clear way, not a guide still starting
                        self.guide.speaker.say(GUIDE_READY)
                    self.opened = True
                    self.log.open()  # only once a camera answered: a refused one leaves no folder
                    self._check_roles(camera)
                    if self.sight is None:
                        self.sight = SightWatch(self.args.blind_s, confirm_frames=self.guide.policy.confirm_frames)
                    self.frozen_watch.reset()  # a frame from before a loss is no frame to compare with
                    try:
                        lost = self._range_stream(camera)
                    finally:
                        self.next_pair_index = camera.next_index
            if lost is None:
                return
            self._lost(lost)

    def _check_roles(self, camera) -> None:
        """Say :data:`CAMERAS_SWAPPED` (once a run) when the left board answers as the slave or the right as the
        master; the driver's warning is printed too. Boards of a build that names no role are not said."""
        versions = getattr(camera, "versions", None)  # (a camera of another kind has no boards' version lines)
        # Each recorded pair is marked as capture marks its index (--record's pairs were unmarked: an audit)
        self.log.cameras_swapped = camera.roles_swapped if versions else None
        if self.roles_said or not self.log.cameras_swapped:
            return
        self.roles_said = True
        self.guide.speaker.say(CAMERAS_SWAPPED)
        self.log.event("cameras_swapped", left_role=versions["left"].role, right_role=versions["right"].role)

    def _range_stream(self, camera) -> Exception | None:
        """Range the pairs ``camera`` streams until ``--count`` (None) or until it is lost (its error). Only the
        camera's errors are a loss: one writing the record or the JSON lines is raised."""
        remaining = self.args.count - self.processed if self.args.count else None
        gap_limit_s = camera.max_frame_gap_s  # the camera's own test of a torn pair, after its regrabs
        # A tick while no pair comes (the link froze and the driver retries): sight is judged on time, not only on
        # pairs, so the walker hears "Cannot see ahead" after --blind-s, not seconds of silence until the loss.
        stream = camera.stream_batches(1, num_batches=remaining, idle_s=IDLE_TICK_S)
        with contextlib.closing(stream):  # its grabbing thread stops whatever ends the loop
            while True:
                try:
                    item = next(stream)
                except StopIteration:
                    return None
                except BrokenPipeError:
                    raise
                except _CAMERA_ERRORS as error:
                    return error
                if item is None:
                    self._waiting(time.monotonic())
                    continue
                # Every pair: a camera's previous frame is its last.
                frozen = self.frozen_watch.update(item.batch, time.monotonic())
                if gap_limit_s is not None and abs(item.pairs[0].time_between_frames_s) > gap_limit_s:
                    self._torn(item)
                elif _one_image_twice(item.batch):
                    self._one_image(item)
                elif frozen is not None:
                    self._frozen_camera(item, frozen)
                else:
                    self._range(item)

    def _lost(self, error: Exception) -> None:
        """Say the camera is lost (once a loss), give up after ``--give-up-s``, and wait ``--reconnect-s`` (at most
        until ``--give-up-s``)."""
        now = time.monotonic()
        if self.lost_at_s is None:
            self.lost_at_s = now
            camera = getattr(error, "camera", None)  # (a serial port's own OSError names none)
            self.guide.speaker.say(CAMERA_LOST if camera is None else ONE_CAMERA_LOST.format(camera.capitalize()))
            self.guide.policy.reset()  # an obstacle seen when it is back is warned of at once
            self.pattern.reset()
            self.log.event("camera_lost", camera=camera, error=" ".join(str(error).split()))
        lost_s = now - self.lost_at_s
        if self.args.give_up_s and lost_s >= self.args.give_up_s:
            raise CaptureError(f"camera lost for {lost_s:.0f} s (--give-up-s {self.args.give_up_s:g}): "
                               f"{' '.join(str(error).split())}")
        self.status_line.show(f"camera lost {lost_s:.0f} s ago: opening it again")
        # The last wait ends at --give-up-s (one more try, then give up): a whole --reconnect-s 8 after --give-up-s 1
        # ended guide 9 s after the loss (an audit)
        time.sleep(min(self.args.reconnect_s, self.args.give_up_s - lost_s) if self.args.give_up_s
                   else self.args.reconnect_s)

    @staticmethod
    def _seen(result) -> bool:
        """Whether a ranged pair saw: ranged, or no obstacle kept from a disparity map that measured the view (a
        view of floor only, a walker's camera pitched down in an empty corridor). Blank frames measure too little
        to be segmented by their map (from_disparity False), and a pair whose kept regions could not be ranged is
        not seen either."""
        status = PipelineStatus(int(result.status[0]))
        from_map = result.segmentation.from_disparity
        return status == PipelineStatus.OK or (status == PipelineStatus.NO_OBJECTS and from_map is not None
                                               and bool(from_map[0]))

    def _watch_sight(self, seen: bool, status: str, now_s: float, then: str | None = None) -> str | None:
        """Say when nothing has been seen for ``--blind-s`` seconds, and when something is again
        (:class:`~svs_torch.capture.guide.SightWatch`): silence would otherwise tell the walker the way is clear.
        ``status``: why, in the JSON event (the pipeline's status, or what kept the pair from being ranged);
        ``then``: words said after :data:`CANNOT_SEE`, in the same breath. Returns the sight's words, or None."""
        said = self.sight.update(seen, now_s)
        if said is not None:
            self.guide.speaker.say(f"{said} {then}" if then and said == CANNOT_SEE else said)
            if said == CANNOT_SEE:
                self.guide.policy.reset()  # an obstacle seen again is warned of at once
            self.log.event("cannot_see" if said == CANNOT_SEE else "seeing_again", status=status)
        return said

    def _show_not_seen(self, detail: str) -> None:
        """The status line of a moment nothing was seen, with ``detail`` (why)."""
        self.status_line.show(f"{self.guide.status(self.guide.policy.confirmed_m, self._shown(False))}  {detail}")

    def _waiting(self, now: float) -> None:
        """A tick of a stream that brings no pair: sight judged on time (not while the camera is already said
        lost: it is not also said blind)."""
        if self.lost_at_s is None and self._watch_sight(False, "WAITING_FOR_FRAMES", now) is None:
            self._show_not_seen(f"waiting for frames, nothing seen for {now - self.sight.last_seen_s:.1f} s")

    def _shown(self, seen: bool) -> str:
        """The class shown and logged: "unseen" where the policy's would read "clear" on a pair that saw nothing
        (a belt or a logger acting on the class would otherwise tell the walker the way is clear)."""
        return UNSEEN if not seen and self.guide.policy.current == CLEAR else self.guide.policy.current

    def _torn(self, item) -> None:
        """A pair whose two frames came further apart than the camera's ``max_frame_gap_s`` after its own regrabs
        (one board kept missing its grab): not ranged, not seen. Why: the walker and the scene move between the
        frames, and such pairs were ranged (a 0.8 m obstacle said "clear" at 2-3 m, a 2 m one "Stop" at 0.5 m).
        "Cannot see ahead" said for them goes on :data:`CHECK_CAMERA` of the later board, once a run for each: a right
        board 0.4 s late on every grab had the walker hear "Cannot see ahead" alone, unlike a frozen one (an audit)."""
        gap_s = item.pairs[0].time_between_frames_s
        late = "right" if gap_s > 0 else "left"  # (right's header minus left's: stereo_frames.time_between_frames_s)
        check = None if late in self.cameras_checked else CHECK_CAMERA.format(late)
        said = self._not_ranged(item, "FRAMES_APART", f"frames {abs(gap_s):.2f} s apart: not ranged", "frames_apart",
                                then=check, time_between_frames_s=round(gap_s, 3), num_dropped=item.num_dropped)
        if said is None and check and self.sight.blind:  # blind already: the ticks while its regrabs took seconds
            self.guide.speaker.say(f"{CANNOT_SEE} {check}")
            said = CANNOT_SEE
        if said == CANNOT_SEE and check:
            self.cameras_checked.add(late)
        self.torn += 1

    def _one_image(self, item) -> None:
        """A pair whose two frames are one image, pixel for pixel (a driver or a relay that sent one board's frame
        for both): not ranged, not seen. Ranged, it measured a view with nothing near (every disparity 0), "seen",
        so guide stayed silent, which the walker hears as a clear way (an audit of estimate's numbers)."""
        self._not_ranged(item, "IDENTICAL_VIEWS", "the two cameras sent one image: not ranged", "identical_views")
        self.one_image += 1

    def _frozen_camera(self, item, camera: str) -> None:
        """A pair whose ``camera`` frame came again, pixel for pixel, while the other camera's frames changed
        (:class:`~svs_torch.capture.frozen.FrozenCameraWatch`): not ranged, not seen. Ranged, a stalled board's old
        frame beside the other's new one gave distances of where obstacles were (the emulator's --freeze: 2.1 m
        then 4.1 m while both boxes moved), and a walker was warned of that. When it leaves guide blind,
        :data:`CHECK_CAMERA` is said with "Cannot see ahead", once a run for each camera; where guide was blind
        already (its link froze first, then the board sent its last frame again), "Cannot see ahead" had been said
        without it, and the walker never heard which camera to check (an audit): both are said again then. With
        --blind-s 0, which asks for no word of being blind, the check alone, at once: a stalled board then left
        guide silent, every pair unranged, which the walker hears as a clear way (an audit)."""
        both = camera == "both"  # both boards stalled (FrozenCameraWatch's "both"): "Check the cameras."
        check = None if camera in self.cameras_checked else CHECK_CAMERAS if both else CHECK_CAMERA.format(camera)
        detail = "both cameras send one frame again" if both else f"the {camera} camera sends one frame again"
        said = self._not_ranged(item, "CAMERA_FROZEN", f"{detail}: not ranged", "camera_frozen", then=check,
                                camera=camera)
        if said is None and check and (self.sight.blind or not self.sight.blind_s):
            # Whole, not the check alone: it may cut off "Cannot see ahead" said moments ago, which it then repeats.
            self.guide.speaker.say(f"{CANNOT_SEE} {check}" if self.sight.blind else check)
            said = CANNOT_SEE
        if said == CANNOT_SEE:
            self.cameras_checked.add(camera)
        if both:  # (the summary said "one camera sent its last frame again" of both boards' pairs: an audit)
            self.both_frozen_pairs += 1
        else:
            self.frozen_pairs += 1

    def _not_ranged(self, item, status: str, detail: str, event: str, then: str | None = None,
                    **fields) -> str | None:
        """A grabbed pair left unranged (``status`` in the sight's JSON event, ``detail`` on the status line): not
        seen, its own ``event`` logged with ``fields``, and taken (``--count``'s). ``then``: words said after
        "Cannot see ahead" if it is said now. Returns the sight's words, or None."""
        now = time.monotonic()
        self._come_back(now)
        said = self._watch_sight(False, status, now, then)
        self._show_not_seen(detail)
        self.log.event(event, pair=item.pairs[0].index, **fields)
        self.processed += 1
        return said

    def stopped_text(self) -> str:
        """What guide says when it stops: the pairs taken, and how many were not ranged (a right board 0.5 s late
        on every frame ended "guide stopped after 5 pairs" with not one ranged, and nothing said of it)."""
        text = f"guide stopped after {self.processed} pair{'' if self.processed == 1 else 's'}"  # (not "1 pairs")
        why = [f"{count} not: {reason}" for count, reason in (
            (self.torn, "their two frames came too far apart"), (self.one_image, "their two frames were one image"),
            (self.frozen_pairs, "one camera sent its last frame again"),
            (self.both_frozen_pairs, "both cameras sent their last frames again")) if count]
        if why:
            ranged = self.processed - self.torn - self.one_image - self.frozen_pairs - self.both_frozen_pairs
            text += f" ({ranged} ranged; {'; '.join(why)})"
        return text

    def _come_back(self, now: float) -> None:
        """Say the camera is back at the first pair after a loss (not when the link merely opened)."""
        if self.lost_at_s is not None:
            self.guide.speaker.say(CAMERA_BACK)
            self.log.event("camera_back", lost_s=round(now - self.lost_at_s, 3))
            self.lost_at_s = None
            # The time lost was said already; sight is judged from here, and a view still blind is said again
            # after --blind-s (silence after "Camera back." would read as a clear way).
            self.sight.last_seen_s, self.sight.blind = now, False

    def _range(self, item) -> None:
        """Range one grabbed pair (a :class:`~svs_torch.capture.stereo.PairBatch` of one), warn, keep it."""
        started = time.perf_counter()
        result = self.ranged(item.batch)
        elapsed_s = time.perf_counter() - started
        now = time.monotonic()
        self._come_back(now)
        nearest_alias = result.nearest_unranged_alias_m  # an unranged fence may be this near: seen, and said
        pattern_m = None if nearest_alias is None or bool(nearest_alias[0].isnan()) else float(nearest_alias[0])
        seen = self._seen(result) or self.pattern.counts(pattern_m)
        sight_said = self._watch_sight(seen, PipelineStatus(int(result.status[0])).name, now)
        nearest, along, floor_age_s = self.floor.nearest(result, now)
        # Warn on the nearest obstacle's nearest visible surface (its low depth percentile): the part a walker
        # reaches first, not the median of an object that may recede.
        distance = float(nearest.surface_m[0]) if bool(nearest.valid[0]) else None
        side = ObstacleSide(int(nearest.side[0])).name.lower()
        message = self.guide.update(distance, now, side)  # the side said too: a walker hears where to step aside
        confirmed = self.guide.policy.confirmed_m  # the median of the last frames' distances, which was judged
        confirmed_side = self.guide.policy.confirmed_side  # the side of the frame that median came from
        quiet = message is None and sight_said is None and self.guide.policy.current == CLEAR  # silence otherwise
        notice = self.pattern.update(pattern_m, now, quiet)
        if notice is not None:
            self.guide.speaker.say(notice)
            self.log.event("repeated_pattern", pair=item.pairs[0].index,
                           nearest_alias_m=round(self.pattern.nearest_m, 3))
        shown = self._shown(seen)
        self.status_line.show(f"{self.guide.status(confirmed, shown)}  {confirmed_side or side}"
                              + ("  a repeated pattern seen, not ranged" if pattern_m is not None else ""))
        warned = {"distance_m": None if distance is None else round(distance, 4), "side": side,
                  "confirmed_m": None if confirmed is None else round(confirmed, 4), "confirmed_side": confirmed_side,
                  "distance_along": along, "floor_age_s": None if floor_age_s is None else round(floor_age_s, 3),
                  "class": shown, "message": message or notice}  # the words said on this pair (at most one)
        self._check_views(result, item)  # last: its words may cut off this pair's, which it says are wrong
        self.processed += 1  # taken (ranged, warned of) before it is kept: a --json line that broke is still counted
        self.log.write(item.pairs[0], result, elapsed_s, warned, item.num_dropped)

    def _check_views(self, result, item) -> None:
        """Say :data:`CAMERAS_SWAPPED` (once a run, as for the roles) when the pairs' matches show the boards in each
        other's place or the rig on its side (:class:`~svs_torch.cli.guide_views.ViewsWatch`), printed and logged."""
        verdict = self.views.update(result)
        if verdict is not None:
            warnings.warn(ViewsWatch.line(verdict), stacklevel=1)
            self.log.event("cameras_mounted_wrong", pair=item.pairs[0].index, views=verdict)
            if not self.roles_said:
                self.roles_said = True
                self.guide.speaker.say(CAMERAS_SWAPPED)
