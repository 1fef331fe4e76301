"""DaemonTask, and the Ctrl-C that once hung ``svs-depth eval`` in CI (core/daemon_task.py says how), made to land
at each place it can (tests/interrupt_places.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest
from conftest import REPO_ROOT
from interrupt_places import run_child

from svs_torch.core.daemon_task import DaemonTask

_EVAL_CHILD = '''
import sys
from interrupt_places import interrupt_each_place
from svs_torch.data import read_pair_sources
from svs_torch.evaluation import EvalSetup, evaluate_pairs

scenes = [sys.argv[1] + "/middlebury_eval3_Q/" + name for name in ("Teddy", "ArtL", "Motorcycle")]
sources, setup = read_pair_sources(scenes), EvalSetup(size_wh=(96, 72))
def run():
    rows = evaluate_pairs(sources, setup, batch_size=1)
    next(rows)  # the decode-ahead has started on the next block
    for _ in rows:
        pass
interrupt_each_place(run)
'''

_CAPTURE_CHILD = '''
from interrupt_places import interrupt_each_place
from hw.emulator import EmulatorServer
from svs_torch.capture import LinkConfig, SVSStereoCamera
import numpy as np

fast = LinkConfig(reply_timeout_s=0.25, transfer_margin_s=0.1, reconnect_delay_s=0.05, drain_quiet_s=0.02,
                  drain_max_s=0.2, poll_s=0.01)
noise = np.random.default_rng(0).integers(0, 200, (120, 160), dtype=np.uint8)
with EmulatorServer(left_port=0, right_port=0, source=lambda camera, w, h, t: noise[:h, :w]) as server:
    cameras = []
    def run():
        cameras.append(SVSStereoCamera(server.urls["left"], server.urls["right"], size_wh=(160, 120), config=fast,
                                       max_frame_gap_s=None))
        cameras[-1].grab_pair()
        for _ in cameras[-1].stream_batches(1, num_batches=2):  # its grabbing thread hands the pairs over
            pass
        cameras[-1].close()
    def after():  # what guide does on Ctrl-C: close the camera (it must not wait for the interrupted grab)
        if cameras:
            cameras[-1].close()
    interrupt_each_place(run, after)
'''


def test_a_task_gives_its_value_or_raises_its_error_in_the_caller():
    assert DaemonTask(sum, [1, 2, 3]).result() == 6
    failing = DaemonTask(int, "seven")
    with pytest.raises(ValueError, match="seven"):
        failing.result()
    assert isinstance(failing.exception(), ValueError) and failing.done()
    release = threading.Event()
    waiting = DaemonTask(release.wait, name="svs-test-wait")
    assert not waiting.done() and waiting._thread.daemon and waiting._thread.name == "svs-test-wait"
    release.set()
    assert waiting.result() is True


_EXIT_CHILD = """
import sys, threading, time
from svs_torch.core.daemon_task import DaemonTask

def slow_write(path):
    time.sleep(0.5)
    with open(path, "w") as done:
        done.write("the call ended")

if sys.argv[2] == "plain":
    DaemonTask(slow_write, sys.argv[1])
else:  # a Ctrl-C while start() waits for the thread to begin (as eval's did): as it ends its wait, or before it
    when = "return" if sys.argv[2] == "interrupted start" else "call"
    if when == "call":
        sys.setswitchinterval(100)  # the new thread gets the GIL only when this one waits: so at the exit
    def tracer(frame, event, arg):
        if event == when == "call" and frame.f_code is threading.Condition.wait.__code__:
            sys.settrace(None)
            raise KeyboardInterrupt
        return local if frame.f_code is threading.Condition.wait.__code__ else None
    def local(frame, event, arg):
        if event == "return":
            sys.settrace(None)
            raise KeyboardInterrupt
        return local
    sys.settrace(tracer)
    try:
        DaemonTask(slow_write, sys.argv[1])
    except KeyboardInterrupt:
        sys.settrace(None)
        sys.exit(3)  # (no output: writing it would let the new thread run before the exit)
"""


@pytest.mark.parametrize("how", ["plain", "interrupted start", "start cut short"])
def test_pythons_exit_lets_a_running_call_end(tmp_path, how):
    """Was: the exit went on while eval's decode-ahead was inside OpenCV, and Python's ending of that thread
    aborted the process (SIGABRT in 6 Ctrl-Cs of 6); with the call counted only after start() returned, a Ctrl-C
    in start() left it uncounted and so unwaited for; counted by its thread as it began, a thread that had not yet
    got the GIL when the exit looked was not waited for either (1 eval in 20 after Ctrl-C)."""
    done = subprocess.run([sys.executable, "-c", _EXIT_CHILD, str(tmp_path / "done.txt"), how], cwd=REPO_ROOT,
                          env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)), capture_output=True, text=True, timeout=60)
    assert done.returncode == (0 if how == "plain" else 3), done.stderr
    assert (tmp_path / "done.txt").read_text() == "the call ended"


def test_eval_ends_after_a_ctrl_c_wherever_it_lands_in_the_decode_ahead(data_dir):
    """The CI failure: Ctrl-C as ``submit`` took the executor's semaphore left its worker waiting on it, and
    the executor's exit waiting on the worker (the threads' stacks said so)."""
    lines = run_child(_EVAL_CHILD, str(data_dir))
    assert sum(line.startswith("interrupted in") for line in lines) >= 1, lines


def test_a_camera_closes_after_a_ctrl_c_wherever_it_lands_in_a_grab_or_a_stream():
    """The same pool was a stereo camera's two boards: Ctrl-C in a grab's ``submit`` left close() (which submitted
    the boards' closing) waiting on the semaphore its own thread held. A stream's Condition, taken by the consumer
    as the Ctrl-C came, left its grabbing thread waiting and the consumer's join waiting on that thread."""
    lines = run_child(_CAPTURE_CHILD)
    assert sum(line.startswith("interrupted in") for line in lines) >= 2, lines
