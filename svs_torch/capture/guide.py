"""Reusable pieces of a live guide loop: when to warn, how to say it, whether it can see, and how fast the loop
runs.

The warning rule follows the paper's use case (a walker warned of obstacles 1–2 m ahead): a distance inside
the band ``[near_m, far_m]`` gives a warning, a distance below it an urgent one, anything farther (or no
obstacle) silence. A message is not repeated more often than every ``repeat_s`` seconds unless the distance
moved to a more urgent class than the one last spoken (a return to it after a frame of silence is not a new
class; after a confirmed clear spell of ``CLEAR_SPELL_S`` it is), or the nearest obstacle is now on another side
and at once at least ``nearer_elsewhere_m`` nearer than the one last said (a person stepping in beside the obstacle
warned of: it is the nearer one, and the walker hears where it is). A more urgent class is taken at once; a less
urgent one only when the distance is past the edge by ``hysteresis_m``, so a distance hovering on an edge does
not flap. Each frame's distance is first confirmed by the frames before it: the rule takes the median of the last
``confirm_frames`` (a frame with no obstacle counts as farther than any), so one camera frame ranged wrong by its
noise neither raises a warning nor drops one, at the cost of a new obstacle being warned of ``confirm_frames // 2``
frames later (:data:`CONFIRM_FRAMES`). Nothing here needs a camera: the loop feeds distances in metres and clock
readings in seconds.
"""

from __future__ import annotations

import collections
import math
import sys
import time
from typing import TextIO

from ..core.errors import InputError
from ..core.files import progress_setting, redraws_in_place
from .sight import CANNOT_SEE, CONFIRM_FRAMES, SEEING_AGAIN, SightWatch
from .speech import SPEECH_MISSING, Speaker, notice_once  # (moved there; still importable from here)

__all__ = ["CLEAR_SPELL_S", "CONFIRM_FRAMES", "SPEECH_MISSING", "WarningPolicy", "Speaker", "notice_once",
           "said_metres", "FpsMeter", "LiveGuide", "StatusLine", "LinesAbove", "SightWatch", "CANNOT_SEE",
           "SEEING_AGAIN", "CLEAR", "WARN", "STOP", "UNSEEN", "NEARER_ELSEWHERE_M"]

CLEAR, WARN, STOP = "clear", "warn", "stop"  # distance classes: beyond the band, inside it, below it
#: What guide reports instead of ``clear`` for a pair it could not measure (no obstacle kept and no map of the
#: view): nothing is known to be near, which is not a clear way.
UNSEEN = "unseen"
_SEVERITY = {CLEAR: 0, WARN: 1, STOP: 2}

#: A confirmed clear way this long (or ``repeat_s``, if shorter), seconds, makes the next warning a new obstacle,
#: said at once: one warned of 2 s before a 6 s clear spell went unsaid until --repeat-s ran out (an audit).
CLEAR_SPELL_S = 1.0

#: A nearest obstacle on another side than the one last said, and at least this much nearer, metres, is said at
#: once, within ``repeat_s``: one stepping in 0.5 m nearer beside an obstacle warned of was said only when
#: ``repeat_s`` ran out (an audit). Chosen in ``experiments/guide_nearer.md``.
NEARER_ELSEWHERE_M = 0.3


class WarningPolicy:
    """Decide, distance by distance, whether to speak a warning.

    Args:
        near_m: lower edge of the warning band, metres (below it: urgent ``stop`` warnings).
        far_m: upper edge of the warning band, metres (beyond it: silence).
        repeat_s: least time between two messages of the same class, seconds.
        hysteresis_m: to move to a less urgent class a distance must pass the edge by this much, metres.
        warn_below_band: also warn (urgently) below ``near_m``; if False such distances are silent.
        confirm_frames: the rule takes the median of the last this many frames' distances (module docstring;
            for an even count the farther of the two middle ones); 1: each frame's own.
        nearer_elsewhere_m: within ``repeat_s``, a warning of the same class is said again when its side differs
            from the one last said and its distance is at least this many metres nearer than the one said and
            than the pair before's (``math.inf``: never).
    """

    def __init__(self, near_m: float = 1.0, far_m: float = 2.0, repeat_s: float = 3.0, hysteresis_m: float = 0.1,
                 warn_below_band: bool = True, confirm_frames: int = CONFIRM_FRAMES,
                 nearer_elsewhere_m: float = NEARER_ELSEWHERE_M) -> None:
        if not 0 <= near_m < far_m:
            raise InputError(f"near_m, far_m: expected 0 <= near_m < far_m, got {near_m}, {far_m}")
        if not (repeat_s >= 0 and hysteresis_m >= 0 and nearer_elsewhere_m >= 0):  # (NaN fails too)
            raise InputError("repeat_s, hysteresis_m, nearer_elsewhere_m: expected non-negative values, got "
                             f"{repeat_s}, {hysteresis_m}, {nearer_elsewhere_m}")
        if isinstance(confirm_frames, bool) or not isinstance(confirm_frames, int) or confirm_frames < 1:
            raise InputError(f"confirm_frames: expected a whole number of frames >= 1, got {confirm_frames!r}")
        self.near_m, self.far_m = near_m, far_m
        self.repeat_s, self.hysteresis_m = repeat_s, hysteresis_m
        self.warn_below_band, self.nearer_elsewhere_m = warn_below_band, nearer_elsewhere_m
        self.current = CLEAR  # class of the last distance
        self.confirmed_m: float | None = None  # the distance the rule took last (the median), None: no obstacle
        self.confirmed_side: str | None = None  # the side of the frame whose distance is confirmed_m
        # (distance, side) of the last frames: the side said is that of the obstacle whose distance is said
        self._recent: collections.deque[tuple[float, str | None]] = collections.deque(maxlen=confirm_frames)
        self._last_spoken_s = -math.inf
        self._last_spoken_class: str | None = None
        self._last_spoken_m, self._last_spoken_side = math.inf, None  # the distance and side last said
        self._clear_since_s: float | None = None  # when the confirmed class last turned clear (None: not clear)

    @property
    def confirm_frames(self) -> int:
        """The frames a distance is confirmed over (the constructor's ``confirm_frames``)."""
        return int(self._recent.maxlen)

    def classify(self, distance_m: float | None) -> str:
        """Class of a distance without hysteresis: ``stop`` (below the band), ``warn`` (in it) or ``clear``."""
        if distance_m is None or not math.isfinite(distance_m) or distance_m > self.far_m:
            return CLEAR
        if distance_m < self.near_m:
            return STOP if self.warn_below_band else CLEAR
        return WARN

    def confirm(self, distance_m: float | None, side: str | None = None) -> float | None:
        """Add one frame's distance (metres, None = no obstacle) and its obstacle's ``side``; the median of the last
        ``confirm_frames`` (fewer at the start), None where that is no obstacle. ``confirmed_side`` is then the
        side of the frame that median came from: said with the current frame's side, a distance confirmed from an
        earlier frame's obstacle on the left was said "on the right" of the one now nearest (an audit)."""
        finite = distance_m is not None and math.isfinite(distance_m)
        self._recent.append((distance_m if finite else math.inf, side if finite else None))
        ordered = sorted(self._recent, key=lambda entry: entry[0])  # stable: of equal distances, the older first
        # The farther middle one of an even count: a warning needs a majority.
        median, self.confirmed_side = ordered[len(ordered) // 2]
        return median if math.isfinite(median) else None

    def update(self, distance_m: float | None, now_s: float, side: str | None = None) -> str | None:
        """Take one frame's nearest obstacle distance (metres, None = none) at ``now_s``, and its ``side`` (``left``,
        ``centre``, ``right``; None: unsaid); the message to say, or None. The rule reads the confirmed distance
        (:meth:`confirm`, kept as ``confirmed_m``), which the message speaks, with the side (a side alone never
        makes a message)."""
        previous_m = math.inf if self.confirmed_m is None else self.confirmed_m
        distance_m = self.confirmed_m = self.confirm(distance_m, side)
        side = self.confirmed_side
        new = self.classify(distance_m)
        if _SEVERITY[new] < _SEVERITY[self.current] and distance_m is not None and math.isfinite(distance_m):
            # Escalate at once, relax only once the distance is past the edge by the hysteresis margin.
            relaxed = self.classify(distance_m - self.hysteresis_m)
            new = relaxed if _SEVERITY[relaxed] < _SEVERITY[self.current] else self.current
        self.current = new
        if new == CLEAR:
            self._clear_since_s = now_s if self._clear_since_s is None else self._clear_since_s
            if now_s - self._clear_since_s >= min(self.repeat_s, CLEAR_SPELL_S):
                self._last_spoken_class = None  # a clear way, then an obstacle: a new one, said at once
            return None
        self._clear_since_s = None
        # Within repeat_s only a more urgent class than the one last spoken is said: an obstacle seen every other
        # frame (warn, clear, warn, ...) is said once, not at each return to the band, which cut the speech into
        # pieces; and a walker swaying on the near edge heard "Stop" and "Obstacle ahead" by turns every 0.6 s (an
        # audit), the second a relief it should not get. Escalation is said at once.
        last = self._last_spoken_class
        if (last is not None and _SEVERITY[new] <= _SEVERITY[last] and now_s - self._last_spoken_s < self.repeat_s
                and not self._nearer_elsewhere(distance_m, side, previous_m)):
            return None
        own = self.classify(distance_m)
        if own != new and (last == new or own == CLEAR):
            # Held by the hysteresis only, past the band's edge: not said again ("Obstacle ahead, 2.1 metres" with
            # a 1-2 m band, every --repeat-s, an audit); said again once back inside, or a new class at once. Beyond
            # the band it is never said, whatever was said last: after a "Stop" the way receding to 2.08 m was said
            # "Obstacle ahead, 2.1 metres" once --repeat-s ran out (an audit).
            return None
        self._last_spoken_s, self._last_spoken_class = now_s, new
        self._last_spoken_m, self._last_spoken_side = distance_m, side
        return self.message(new, distance_m, side)

    def _nearer_elsewhere(self, distance_m: float, side: str | None, previous_m: float) -> bool:
        """Whether the confirmed obstacle is another one, nearer, said at once: on another side than the one last
        said, and ``nearer_elsewhere_m`` nearer than both it and the pair before's confirmed distance. The jump
        from the pair before tells another obstacle from the same one drifting across a third's edge as the walker
        nears it (said again with its new side 5 times in 24 walks otherwise, once just before its "Stop":
        experiments/guide_nearer.md)."""
        nearer_by = min(self._last_spoken_m, previous_m) - distance_m
        return (side is not None and self._last_spoken_side is not None and side != self._last_spoken_side
                and nearer_by >= self.nearer_elsewhere_m)

    def reset(self) -> None:
        """Forget the last class, message and distances (the camera was lost): the next distance in or below the
        band is warned of at once, confirmed by the frames from then on only."""
        self.current = CLEAR
        self.confirmed_m = self.confirmed_side = None
        self._recent.clear()
        self._last_spoken_s = -math.inf
        self._last_spoken_class = None
        self._last_spoken_m, self._last_spoken_side = math.inf, None
        self._clear_since_s = None

    @staticmethod
    def message(distance_class: str, distance_m: float, side: str | None = None) -> str:
        """The words for a class, distance and side, e.g. ``Obstacle ahead, 1.5 metres``, ``Obstacle on the left,
        1.5 metres``, ``Stop. Obstacle at 0.9 metres`` (``side``: ``left`` / ``right`` said, ``centre`` or None
        "ahead"). "Stop"'s distance is rounded down to the decimetre: 0.97 m said "1.0 metres" read as the band's
        edge, not under it."""
        aside = side in ("left", "right")
        if distance_class == STOP:
            return f"Stop. Obstacle {f'on the {side} ' if aside else ''}at {said_metres(STOP, distance_m)} metres"
        return f"Obstacle {f'on the {side}' if aside else 'ahead'}, {said_metres(WARN, distance_m)} metres"


def said_metres(distance_class: str, distance_m: float) -> str:
    """A distance as said and shown, to the decimetre: rounded, and for ``stop`` rounded down (0.97 m said
    "1.0" read as the band's edge, not under it)."""
    if distance_class == STOP:
        return f"{math.floor(distance_m * 10 + 1e-9) / 10:.1f}"  # (0.7 * 10 is 6.999…: not 0.6)
    return f"{distance_m:.1f}"


class FpsMeter:
    """Frames per second over the last ``window_s`` seconds of ticks."""

    def __init__(self, window_s: float = 2.0) -> None:
        # Finite too: NaN or inf was taken and no tick ever left the window, which grew a tick a frame for the whole
        # walk (and the rate was over all of it).
        if not (window_s > 0 and math.isfinite(window_s)):
            raise InputError(f"window_s: expected a positive finite window in seconds, got {window_s}")
        self.window_s = window_s
        self._ticks: collections.deque[float] = collections.deque()

    def tick(self, now_s: float | None = None) -> float:
        """Record one frame at ``now_s`` (default ``time.monotonic()``); the current rate in frames/s."""
        now_s = time.monotonic() if now_s is None else now_s
        self._ticks.append(now_s)
        while self._ticks and self._ticks[0] < now_s - self.window_s:
            self._ticks.popleft()
        return self.fps

    @property
    def measured(self) -> bool:
        """Whether the window holds a rate: two ticks at different times (one frame has no rate yet)."""
        return len(self._ticks) >= 2 and self._ticks[-1] > self._ticks[0]

    @property
    def fps(self) -> float:
        """Frames/s: ticks in the window minus one over the time they span; 0 with fewer than two ticks."""
        if not self.measured:
            return 0.0
        return (len(self._ticks) - 1) / (self._ticks[-1] - self._ticks[0])


class LiveGuide:
    """One step of a guide loop: count the frame, decide on a warning, say it.

    ``update(nearest_m, side=...)`` is called once per processed pair with the nearest obstacle distance in metres
    (None when nothing was found) and its side; it returns the message said, or None.
    """

    def __init__(self, policy: WarningPolicy | None = None, speaker: Speaker | None = None,
                 meter: FpsMeter | None = None) -> None:
        self.policy = policy or WarningPolicy()
        self.speaker = speaker or Speaker()
        self.meter = meter or FpsMeter()

    def update(self, nearest_m: float | None, now_s: float | None = None, side: str | None = None) -> str | None:
        now_s = time.monotonic() if now_s is None else now_s
        self.meter.tick(now_s)
        message = self.policy.update(nearest_m, now_s, side)
        if message is not None:
            self.speaker.say(message)
        return message

    def status(self, nearest_m: float | None, shown_class: str | None = None) -> str:
        """A one-line status, e.g. ``12.5 fps  nearest 1.4 m  warn`` (``shown_class``: the class to show instead of
        the policy's, e.g. :data:`UNSEEN`)."""
        shown = shown_class or self.policy.current
        distance = "none" if nearest_m is None else f"{said_metres(shown, nearest_m)} m"  # as the message says it
        # Before a second frame there is no rate: "--", not a rate of 0 (guide --count 1 ended on "0.0 fps").
        rate = f"{self.meter.fps:5.1f}" if self.meter.measured else "   --"
        return f"{rate} fps  nearest {distance}  {shown}"


class StatusLine:
    """A status line rewritten in place on ``stream`` (``\\r``), with messages printed above it.

    A message (a warning) gets a line of its own: the status line is wiped first, the message printed on
    ``message_stream`` with a newline, then the status drawn again below it, so neither overwrites the other
    when both streams reach the same terminal. Into a file or a pipe (``guide 2> walk.log``, a service's journal)
    there is no redrawing, which a log shows as one line growing for the whole walk: the status is a plain line
    every ``interval_s`` seconds, and the last one shown is printed at :meth:`close` (as
    :class:`svs_torch.cli.progress.Progress` does for the long commands). ``SVS_TORCH_PROGRESS=plain`` makes it
    those plain lines on a terminal too, ``SVS_TORCH_PROGRESS=off`` silences it
    (:func:`~svs_torch.core.files.progress_setting`).

    Args:
        stream: where the status goes (None: nowhere).
        interval_s: seconds between plain status lines when ``stream`` is not a terminal.
        tty: force terminal (True) or plain (False) mode; None: a terminal not ``TERM=dumb`` (an Emacs shell
            buffer: see :func:`~svs_torch.core.files.redraws_in_place`).
        clock: seconds, monotonic (tests pass their own).
    """

    def __init__(self, stream: TextIO | None = sys.stderr, interval_s: float = 5.0, tty: bool | None = None,
                 clock=time.monotonic) -> None:
        self.stream, self.interval_s, self.clock = stream, interval_s, clock
        self.tty = redraws_in_place(stream) if tty is None else bool(tty)
        self.silent = progress_setting() == "off"  # SVS_TORCH_PROGRESS=off: no status; messages still print
        self._shown = ""
        # Plain mode: when the last status line was printed. The first waits an interval too, so it reports a rate
        # measured over some frames, not the 0 fps of the first.
        self._printed_at = clock()
        self._pending = ""  # plain mode: the status shown since then, printed at the next interval or at close

    def show(self, text: str) -> None:
        """Replace the status line with ``text`` (padded so no tail of a longer old status is left); in plain
        mode, print it as a line when ``interval_s`` has passed since the last one."""
        if self.stream is None or self.silent:
            return
        if not self.tty:
            now = self.clock()
            if now - self._printed_at >= self.interval_s:
                print(text, file=self.stream, flush=True)
                self._printed_at, self._pending = now, ""
            else:
                self._pending = text
            return
        padding = " " * max(len(self._shown) - len(text), 0)
        print(f"\r{text}{padding}", end="", file=self.stream, flush=True)
        self._shown = text

    def clear(self) -> None:
        """Wipe the status line, leaving the cursor at its start."""
        if self.stream is not None and self._shown:
            print("\r" + " " * len(self._shown) + "\r", end="", file=self.stream, flush=True)

    def message(self, text: str, message_stream: TextIO | None = None) -> None:
        """Print ``text`` on a line of its own above the status line, then draw the status again."""
        shown = self._shown
        self.clear()
        print(text, file=message_stream or self.stream, flush=True)
        self._shown = ""
        if shown:
            self.show(shown)

    def close(self) -> None:
        """End the status line with a newline (the next output starts on a fresh line); in plain mode, print the
        last status not printed yet."""
        if self.stream is not None and self._shown:
            print(file=self.stream, flush=True)
        if self.stream is not None and self._pending:
            print(self._pending, file=self.stream, flush=True)
        self._shown = self._pending = ""

    def lines_above(self, message_stream: TextIO | None = None) -> LinesAbove:
        """A text stream whose every line is a :meth:`message`: hand it to what prints on its own (a
        :class:`Speaker`, ``warnings``), and its lines land above the status line instead of on it."""
        return LinesAbove(self, message_stream)

    def show_warning(self, message, category, filename, lineno, file=None, line=None) -> None:
        """A ``warnings.showwarning``: one line, ``warning: ...``, above the status line."""
        self.message(f"warning: {' '.join(str(message).split())}")


class LinesAbove:
    """Write-only text stream of :meth:`StatusLine.lines_above`: complete lines become status-line messages."""

    def __init__(self, status_line: StatusLine, message_stream: TextIO | None) -> None:
        self.status_line, self.message_stream = status_line, message_stream
        self._pending = ""

    def write(self, text: str) -> int:
        *lines, self._pending = (self._pending + text).split("\n")
        for line in lines:
            self.status_line.message(line, self.message_stream)
        return len(text)

    def flush(self) -> None:
        if self.message_stream is not None:
            self.message_stream.flush()
