"""A Ctrl-C made to land, in turn, at each place a thread's lock can be left held, for the tests of
core/daemon_task.py and of the command line's interrupts.

Such a hang needs the signal to land in the few bytecodes between a lock's acquire and the ``with`` block that
releases it, so no number of real Ctrl-Cs makes it happen on demand (187 runs did not; CI met it once).
:func:`interrupt_each_place` makes it land there every time: a trace function raises KeyboardInterrupt as
``threading.Condition.__enter__`` returns with its lock taken (Python code around a lock's acquire, where
Python's own signal check can raise it too), at the 1st such return of a run, then the 2nd, and so on. Run it in
a child process with a timeout: a place that hangs never returns.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from types import FrameType

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent


def _interrupt_as_entered(place_to_interrupt: Callable[[FrameType], str | None]) -> None:
    """Trace this thread: as each ``threading.Condition.__enter__`` returns with its lock taken,
    ``place_to_interrupt(its caller's frame)`` names the place to raise KeyboardInterrupt at (printed, and the
    trace ends), or gives None to go on."""

    def tracer(frame, event, arg):
        return local if event == "call" and frame.f_code is threading.Condition.__enter__.__code__ else None

    def local(frame, event, arg):
        if event == "return":
            place = place_to_interrupt(frame.f_back)
            if place is not None:
                sys.settrace(None)
                print("interrupted in", place, flush=True)
                raise KeyboardInterrupt
        return local

    sys.settrace(tracer)


def interrupt_each_place(run: Callable[[], object], after: Callable[[], object] = lambda: None) -> list[str]:
    """Call ``run()`` with a KeyboardInterrupt raised at its k-th Condition ``__enter__`` in this thread, for
    k = 1, 2, ... until a run ends with none; ``after()`` follows each interrupted run (what a program does on
    Ctrl-C). Each place is printed as it is interrupted; returns them."""
    places = []
    for k in range(1, 200):
        entered = [0]

        def kth(caller: FrameType, k: int = k, entered: list[int] = entered) -> str | None:
            entered[0] += 1
            if entered[0] != k:
                return None
            places.append(f"{caller.f_code.co_name} <- {caller.f_back.f_code.co_name}")
            return places[-1]

        _interrupt_as_entered(kth)
        try:
            run()
        except KeyboardInterrupt:
            after()
            continue
        finally:
            sys.settrace(None)
        print("ended with no interrupt after", k - 1, flush=True)
        return places
    raise AssertionError("interrupt_each_place: more than 200 places")


def interrupt_where(callers: tuple[str, ...]) -> None:
    """From now on in this thread, raise KeyboardInterrupt as the first ``threading.Condition.__enter__`` whose
    callers' function names, innermost first, begin with ``callers`` returns with its lock taken (once)."""

    def matching(caller: FrameType) -> str | None:
        names = []
        while caller is not None and len(names) < len(callers):
            names.append(caller.f_code.co_name)
            caller = caller.f_back
        return " <- ".join(names) if tuple(names) == callers else None

    _interrupt_as_entered(matching)


def run_child(code: str, *args: str, timeout_s: float = 60) -> list[str]:
    """Run ``code`` (which calls :func:`interrupt_each_place`) in a child Python with the repository and ``tests/``
    importable; fail with what it printed when it does not end within ``timeout_s`` or does not end cleanly.
    Returns its lines of output."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO_ROOT), str(REPO_ROOT / "tests")]),
               PYTHONFAULTHANDLER="1")
    try:
        done = subprocess.run([sys.executable, "-c", code, *args], cwd=REPO_ROOT, env=env, capture_output=True,
                              text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired as hung:
        said = hung.stdout or b""
        pytest.fail("a Ctrl-C left the process waiting for good after:\n"
                    + (said.decode() if isinstance(said, bytes) else said)[-3000:])
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    assert lines and lines[-1].startswith("ended with no interrupt"), done.stdout
    return lines
