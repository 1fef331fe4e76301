"""Progress of a long command (``eval``, ``sweep``, ``estimate --pairs``, ``capture``) on standard error.

On a terminal: a tqdm bar, redrawn in place. Into a file or a pipe (a log, ``2> run.log``, a CI job), or on a
``TERM=dumb`` terminal (an Emacs shell buffer): no carriage-return redraws, which a log shows as one unreadable
line; instead a plain line every few seconds (``eval: 120/512 pairs, 14.2 pairs/s, ETA 27 s``) and one summary
line at the end. ``SVS_TORCH_PROGRESS=plain`` gives a terminal those plain lines too (a screen reader, a braille
display), ``SVS_TORCH_PROGRESS=off`` none at all (:func:`~svs_torch.core.files.progress_setting`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TextIO, TypeVar

from ..core.files import STDERR_LOCK, progress_setting, redraws_in_place, stream_is_terminal

__all__ = ["Progress", "print_above_bar"]

T = TypeVar("T")

#: The bar drawn on the terminal now, if any (:func:`print_above_bar`).
_drawn: list[Progress] = []


def print_above_bar(line: str, file: TextIO) -> None:
    """Print ``line`` on ``file``, above the bar of a running :class:`Progress` if one is drawn: a warning printed
    on standard error while a bar was drawn there began on the bar's own line (``estimate:   0%|...| 0/6
    [00:00<?, ?pair/s]svs-depth estimate: warning: ...``, an audit of terminal output)."""
    with STDERR_LOCK:
        if _drawn:
            _drawn[-1].write(line, file)
        else:
            print(line, file=file, flush=True)


class Progress:
    """Progress over ``total`` items, a context manager.

    Args:
        total: how many items the command will run.
        desc: the command's name, the start of every line (``"eval"``).
        unit: what an item is (``"pair"``); lines say ``pairs``.
        stream: where progress goes (None: standard error).
        interval_s: seconds between plain lines when ``stream`` is not a terminal.
        tty: force terminal (True) or plain (False) mode; None: a terminal not ``TERM=dumb``
            (:func:`~svs_torch.core.files.redraws_in_place`).
        clock: seconds, monotonic (tests pass their own).
    """

    def __init__(self, total: int, desc: str, unit: str = "pair", stream: TextIO | None = None,
                 interval_s: float = 5.0, tty: bool | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.total, self.desc, self.unit = total, desc, unit
        self.stream = sys.stderr if stream is None else stream
        self.interval_s, self.clock = interval_s, clock
        self.done, self._closed, self._postfix = 0, False, ""
        self.started = self._last = clock()
        self._first: tuple[float, int] | None = None  # (time, count) of the first update
        self._silent = progress_setting() == "off"  # no progress lines; write() and warn() still print
        if tty is None:
            tty = redraws_in_place(self.stream)
        self._bar = None
        if tty:
            from tqdm import tqdm

            # The program's stderr unwrapped (cli.interrupts.StderrAfterDecoders): tqdm's monitor thread redraws a
            # bar idle for 10 s holding tqdm's lock, while update() takes STDERR_LOCK and then tqdm's: the wrapper
            # taking STDERR_LOCK under tqdm's lock inverted the order, a deadlock on a terminal.
            self._bar = tqdm(total=total, unit=unit, file=getattr(self.stream, "unlocked", self.stream),
                             desc=desc, dynamic_ncols=True, mininterval=0.5)
            _drawn.append(self)

    def _rate(self, elapsed_s: float) -> float | None:
        return self.done / elapsed_s if elapsed_s > 0 else None

    def _eta_rate(self, now: float) -> float | None:
        """The rate the ETA is told by: since the first update, once another came after it (no ETA before).
        Why: the start (a sweep's or estimate's worker processes importing torch, a first batch's kernels)
        counted in the rate, and a sweep's first line said 'ETA 78 s' of a run that ended 11.6 s after it (an
        audit of long runs)."""
        first_s, first_done = self._first
        if self.done > first_done and now > first_s:
            return (self.done - first_done) / (now - first_s)
        return None

    def update(self, count: int = 1) -> None:
        """``count`` more items are done."""
        self.done += count
        if self._bar is not None:
            with STDERR_LOCK:  # (see there: a line written while another thread decodes was lost)
                self._bar.update(count)
            return
        if self._silent:
            return
        now = self.clock()
        if self._first is None:
            self._first = (now, self.done)
        if now - self._last >= self.interval_s and self.done < self.total:
            self._last = now
            rate, eta_rate = self._rate(now - self.started), self._eta_rate(now)
            eta = f", ETA {(self.total - self.done) / eta_rate:.0f} s" if eta_rate else ""
            speed = f", {rate:.1f} {self.unit}s/s" if rate else ""
            postfix = f" ({self._postfix})" if self._postfix else ""
            with STDERR_LOCK:
                print(f"{self.desc}: {self.done}/{self.total} {self.unit}s{speed}{eta}{postfix}", file=self.stream,
                      flush=True)

    def over(self, iterable: Iterable[T]) -> Iterator[T]:
        """The items of ``iterable``, each counted done when the next is asked for; the summary after the last
        (``for item in progress.over(items)``, as ``for item in tqdm(items)``)."""
        for item in iterable:
            yield item
            self.update(1)
        self.close()

    def set_postfix(self, **values: object) -> None:
        """Numbers shown after the count (a loss, say): on the bar, or at the end of the next plain line."""
        self._postfix = ", ".join(f"{key} {value}" for key, value in values.items())
        if self._bar is not None:
            self._bar.set_postfix(values, refresh=False)

    def write(self, line: str, file: TextIO | None = None) -> None:
        """Print a result line to ``file`` (standard output) without breaking the bar: the bar is wiped and drawn
        again below the line where ``file`` is a terminal too; a line into a file or a pipe leaves it alone (it was
        wiped and redrawn for every row of ``eval > rows.txt``, 45 times for 45 pairs, each redraw a screen reader's
        to read again)."""
        file = sys.stdout if file is None else file
        with STDERR_LOCK:  # (the bar is redrawn on the progress stream)
            if self._bar is not None and stream_is_terminal(file):
                # Wiped by hand: tqdm.write wipes only a bar on the same file or on sys.stdout / sys.stderr, and the
                # bar draws on the program's stderr unwrapped (see __init__), so a row went onto the bar's line
                # ('| 3/10 [00:01<00:02,  2.83pair/s]eval3/Motorcycle  OK ...', an audit of eval on a terminal).
                self._bar.clear()
                print(line, file=file, flush=True)
                self._bar.refresh()
            else:
                print(line, file=file, flush=True)

    def warn(self, line: str) -> None:
        """Print a line on the progress stream (a warning) without breaking the bar."""
        self.write(line, self.stream)

    def close(self, summary: bool = True) -> None:
        """End the bar; in plain mode, the summary line (count, seconds, rate) unless ``summary`` is False (a
        command ending on an error whose one line is all it says). Once."""
        if self._closed:
            return
        self._closed = True
        with STDERR_LOCK:
            if self._bar is not None:
                if self in _drawn:
                    _drawn.remove(self)
                self._bar.close()
                return
            if self._silent or not summary:
                return
            elapsed = self.clock() - self.started
            rate = self._rate(elapsed)
            print(f"{self.desc}: {self.done}/{self.total} {self.unit}s in {elapsed:.1f} s"
                  + (f", {rate:.1f} {self.unit}s/s" if rate else ""), file=self.stream, flush=True)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
