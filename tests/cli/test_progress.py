"""Progress of long commands: a bar on a terminal, plain lines and a summary into a file or a pipe."""

from __future__ import annotations

import io
import re
import sys

from svs_torch.cli.progress import Progress


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_into_a_pipe_is_plain_lines_every_few_seconds_and_a_summary():
    clock, stream, out = _Clock(), io.StringIO(), io.StringIO()
    with Progress(10, "eval", stream=stream, interval_s=5.0, clock=clock) as progress:
        for number in range(10):
            clock.now += 2.0  # 2 s per pair: a line at 6, 12 and 18 s (3, 6 and 9 pairs), none per pair
            progress.write(f"row {number}", out)
            progress.update(1)
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue()
    assert lines == ["eval: 3/10 pairs, 0.5 pairs/s, ETA 14 s", "eval: 6/10 pairs, 0.5 pairs/s, ETA 8 s",
                     "eval: 9/10 pairs, 0.5 pairs/s, ETA 2 s", "eval: 10/10 pairs in 20.0 s, 0.5 pairs/s"]
    assert out.getvalue().splitlines() == [f"row {n}" for n in range(10)]


def test_progress_on_a_terminal_is_a_bar_and_keeps_result_lines_apart(monkeypatch):
    monkeypatch.setenv("TERM", "xterm")
    stream, out = _Terminal(), io.StringIO()
    with Progress(4, "sweep", stream=stream) as progress:
        for number in range(4):
            progress.write(f"row {number}", out)
            progress.update(1)
    drawn = stream.getvalue()
    assert "\r" in drawn and "sweep" in drawn and "4/4" in drawn  # tqdm's bar, redrawn in place
    assert not re.search(r"pairs in \d", drawn)  # no plain summary line on a terminal
    assert out.getvalue().splitlines() == [f"row {n}" for n in range(4)]


def test_rows_into_a_file_leave_the_bar_on_the_terminal_alone(monkeypatch):
    """Was (an audit of terminal output): with ``eval > rows.txt`` every row wiped the bar on the terminal and drew
    it again (52 bar drawings, 12.5 kB for 45 pairs), each a screen reader's to read again. Rows into a file now
    leave it alone (7 drawings, 1.4 kB)."""
    monkeypatch.setenv("TERM", "xterm")
    monkeypatch.delenv("SVS_TORCH_PROGRESS", raising=False)
    terminal, rows = _Terminal(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", terminal)
    monkeypatch.setattr(sys, "stdout", rows)
    with Progress(20, "eval") as progress:
        for number in range(20):
            progress.write(f"row {number}")
            progress.update(1)
    assert rows.getvalue().splitlines() == [f"row {n}" for n in range(20)]
    assert terminal.getvalue().count("eval:") <= 3  # the first drawing, maybe one more, the last (was one a row: 22)


def test_a_warning_during_a_bar_gets_a_line_of_its_own(monkeypatch):
    """Was (an audit of terminal output): a warning raised while the bar was drawn (estimate --pairs --size that
    enlarges) was printed onto the bar's line, ``| 0/6 [00:00<?, ?pair/s]svs-depth estimate: warning: ...``, and
    read aloud as one with it. The bar is now wiped first, the warning printed on its own line, the bar drawn below."""
    import warnings

    from svs_torch.cli import _warning_printer

    monkeypatch.setenv("TERM", "xterm")
    monkeypatch.delenv("SVS_TORCH_PROGRESS", raising=False)
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    with Progress(6, "estimate") as progress, warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = _warning_printer("svs-depth estimate")
        warnings.warn("--size 960x720 enlarges the 463x370 pair 2.1 times")
        progress.update(6)
    drawn = terminal.getvalue()
    assert "\rsvs-depth estimate: warning: --size 960x720 enlarges the 463x370 pair 2.1 times\n" in drawn
    assert "]svs-depth" not in drawn


def test_rows_on_the_terminal_of_the_bar_get_lines_of_their_own(monkeypatch):
    """Found by an audit of eval on a terminal: the program's stderr is wrapped (cli.interrupts.StderrAfterDecoders)
    and the bar draws on the stream unwrapped, which tqdm.write did not take for sys.stderr, so it never wiped the bar
    before a row: each row printed after a drawing began on the bar's line, '| 3/10 [00:01<00:02,  2.83pair/s]{"left":
    ...' (and the table's rows so too). Both streams here write to one terminal, as they do on a real one."""
    from svs_torch.cli.interrupts import StderrAfterDecoders

    monkeypatch.setenv("TERM", "xterm")
    monkeypatch.delenv("SVS_TORCH_PROGRESS", raising=False)
    terminal = _Terminal()

    class Descriptor(_Terminal):  # stdout and stderr: two files, one terminal
        def write(self, text: str) -> int:
            return terminal.write(text)

    monkeypatch.setattr(sys, "stderr", StderrAfterDecoders(Descriptor()))
    monkeypatch.setattr(sys, "stdout", Descriptor())
    with Progress(3, "eval") as progress:
        for number in range(3):
            progress.write(f"row {number}")
            progress.update(1)
    drawn = terminal.getvalue()
    assert "eval:" in drawn and "]row" not in drawn, drawn
    shown = [line.split("\r")[-1].strip() for line in drawn.split("\n")]  # what a line shows once redrawn
    assert shown[:3] == [f"row {n}" for n in range(3)], drawn


def test_progress_on_a_dumb_terminal_is_plain_lines(monkeypatch):
    """Was (an audit of terminal output): in an Emacs shell buffer (TERM=dumb, a terminal to the program) the bar's
    carriage-return redraws piled up on one line, each read aloud by emacspeak. Now such a terminal gets the plain
    lines a log gets."""
    monkeypatch.setenv("TERM", "dumb")
    clock, stream = _Clock(), _Terminal()
    with Progress(4, "eval", stream=stream, interval_s=5.0, clock=clock) as progress:
        for _ in range(4):
            clock.now += 3.0
            progress.update(1)
    assert "\r" not in stream.getvalue() and "\x1b" not in stream.getvalue()
    assert stream.getvalue().splitlines() == ["eval: 2/4 pairs, 0.3 pairs/s, ETA 6 s",
                                              "eval: 4/4 pairs in 12.0 s, 0.3 pairs/s"]


def test_svs_torch_progress_plain_or_off_for_a_screen_reader(monkeypatch):
    """Was (an audit of terminal output): a screen-reader or braille user had no way to stop the bar redrawn on
    their terminal (read again at every redraw), nor to silence progress. SVS_TORCH_PROGRESS=plain gives a
    terminal the plain lines of a log; =off prints no progress, but the results and warnings still."""
    monkeypatch.setenv("TERM", "xterm")
    for setting, expected in (("plain", ["eval: 2/4 pairs, 0.3 pairs/s, ETA 6 s",
                                         "eval: 4/4 pairs in 12.0 s, 0.3 pairs/s"]), ("off", [])):
        monkeypatch.setenv("SVS_TORCH_PROGRESS", setting)
        clock, stream, out = _Clock(), _Terminal(), io.StringIO()
        with Progress(4, "eval", stream=stream, interval_s=5.0, clock=clock) as progress:
            for number in range(4):
                clock.now += 3.0
                progress.write(f"row {number}", out)
                progress.update(1)
            progress.warn("eval: warning: a pair was skipped")
        assert "\r" not in stream.getvalue()
        assert [line for line in stream.getvalue().splitlines() if "warning" not in line] == expected
        assert "eval: warning: a pair was skipped" in stream.getvalue().splitlines()
        assert out.getvalue().splitlines() == [f"row {n}" for n in range(4)]


def test_the_help_names_svs_torch_progress():
    from svs_torch.cli import build_parser

    assert "SVS_TORCH_PROGRESS=off" in build_parser().format_help()
    assert "SVS_TORCH_PROGRESS=off" in build_parser().commands()["guide"].format_help()


def test_an_unknown_svs_torch_progress_is_warned_of_once(data_dir, capsys, monkeypatch):
    """A mistyped SVS_TORCH_PROGRESS (quiet) was taken as unset without a word: the user who asked for silence got
    the bar and no reason. Now one warning says what it expects. In this process (no child's 2.5 s of imports):
    the values warned of are emptied as in a fresh process, and the command's stderr is a pipe's (no terminal)."""
    import svs_torch.core.files
    from svs_torch.cli import main

    monkeypatch.setattr(svs_torch.core.files, "_PROGRESS_WARNED", set())
    monkeypatch.setenv("SVS_TORCH_PROGRESS", "Quiet")
    scene = data_dir / "middlebury_2001" / "Tsukuba"
    code = main(["eval", str(scene), str(scene), "--size", "160x120"])
    stderr = capsys.readouterr().err
    assert code == 0, stderr
    warned = [line for line in stderr.splitlines() if "SVS_TORCH_PROGRESS" in line]
    assert warned == ["svs-depth eval: warning: SVS_TORCH_PROGRESS='quiet': expected plain or off (or auto, the "
                      "default); progress is shown as without it"], stderr


def test_eval_into_a_pipe_has_no_carriage_returns(data_dir, capsys, monkeypatch):
    """In this process (no child's 2.5 s of imports): capsys's stderr is, as a pipe, no terminal."""
    from svs_torch.cli import main

    monkeypatch.delenv("SVS_TORCH_PROGRESS", raising=False)
    scene = data_dir / "middlebury_2001" / "Tsukuba"
    code = main(["eval", str(scene), "--size", "160x120"])
    stderr = capsys.readouterr().err
    assert code == 0 and "\r" not in stderr
    assert re.fullmatch(r"eval: 1/1 pairs in \d+\.\d s, \d+\.\d pairs/s", stderr.strip().splitlines()[-1])


def test_progress_over_an_iterable_counts_each_item_and_shows_a_postfix():
    clock, stream = _Clock(), io.StringIO()
    progress = Progress(4, "train", unit="step", stream=stream, interval_s=5.0, clock=clock)
    seen = []
    for step in progress.over(range(4)):
        seen.append(step)
        clock.now += 3.0
        progress.set_postfix(loss=f"{0.5 / (step + 1):.3f}")
    assert seen == [0, 1, 2, 3]
    assert stream.getvalue().splitlines() == ["train: 2/4 steps, 0.3 steps/s, ETA 6 s (loss 0.250)",
                                              "train: 4/4 steps in 12.0 s, 0.3 steps/s"]


def test_the_eta_leaves_out_the_start_up():
    """Was (an audit of long runs): the ETA divided by the rate since the command began, worker start-up
    included, so a sweep's first line said 'ETA 78 s' of a run that ended 11.6 s after it. Now the ETA's rate is
    counted from the first finished item, and none is shown before a second; the pairs/s is still the whole
    run's."""
    clock, stream = _Clock(), io.StringIO()
    with Progress(20, "sweep", stream=stream, interval_s=5.0, clock=clock) as progress:
        clock.now += 10.0  # the workers start
        for _ in range(20):
            clock.now += 1.0
            progress.update(1)
    lines = stream.getvalue().splitlines()
    assert lines[:2] == ["sweep: 1/20 pairs, 0.1 pairs/s",  # one item: no rate of the running yet (was ETA 209 s)
                         "sweep: 6/20 pairs, 0.4 pairs/s, ETA 14 s"]  # 1 pair/s once running (was ETA 33 s)


def test_a_progress_line_waits_for_another_threads_decoder_window(capfd):
    """While a thread lends descriptor 2 to a C decoder to collect its complaints (eval decodes its next block in a
    thread), a progress line printed meanwhile went into that window and was lost: a log of a 1000-pair eval kept
    2 of its 10-odd lines (an audit). It now waits the window out (milliseconds) and reaches standard error."""
    import threading
    import time

    from svs_torch.core.image_files import _native_stderr_collected

    collected: list[str] = []
    opened, release = threading.Event(), threading.Event()

    def decode() -> None:
        with _native_stderr_collected(collected):
            opened.set()
            release.wait(5)

    decoder = threading.Thread(target=decode)
    decoder.start()
    assert opened.wait(5)
    with open(2, "w", closefd=False) as descriptor_2:  # sys.stderr, as the command line has it (not pytest's)
        progress = Progress(4, "eval", stream=descriptor_2, tty=False, interval_s=0.0)
        writer = threading.Thread(target=progress.update, args=(2,))
        writer.start()
        time.sleep(0.05)
        release.set()
        decoder.join()
        writer.join()
    assert collected == [] and "eval: 2/4 pairs" in capfd.readouterr().err


_MONITOR_CHILD = """
import io, threading, time
from tqdm import tqdm
from svs_torch.cli.interrupts import StderrAfterDecoders
from svs_torch.cli.progress import Progress
from svs_torch.core.files import STDERR_LOCK

class Terminal(io.StringIO):
    def isatty(self):
        return True

progress = Progress(10, "eval", stream=StderrAfterDecoders(Terminal()), tty=True)
holding, monitor_has_its_lock = threading.Event(), threading.Event()

def main_thread():  # Progress.update: STDERR_LOCK, then tqdm's lock (to redraw the bar)
    with STDERR_LOCK:
        holding.set()
        monitor_has_its_lock.wait()
        time.sleep(0.6)  # past the bar's mininterval, so that update() redraws
        progress.update(1)

def monitor():  # as tqdm's TMonitor redraws a bar idle for 10 s: under tqdm's lock
    holding.wait()
    with tqdm.get_lock():
        monitor_has_its_lock.set()
        progress._bar.refresh(nolock=True)

threads = [threading.Thread(target=main_thread, daemon=True), threading.Thread(target=monitor, daemon=True)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join(10)
print("deadlocked" if any(thread.is_alive() for thread in threads) else "both ended", flush=True)
"""


def test_a_bar_redrawn_by_tqdms_monitor_while_the_program_updates_it_does_not_deadlock():
    """Was: the program's stderr took STDERR_LOCK for every write, tqdm's monitor thread writes holding tqdm's
    lock, and Progress.update takes STDERR_LOCK and then tqdm's: a bar idle for 10 s on a terminal (a long batch)
    redrawn as the batch ended deadlocked the command. The bar writes to the stream unwrapped."""
    import os
    import subprocess

    from conftest import REPO_ROOT

    done = subprocess.run([sys.executable, "-c", _MONITOR_CHILD], cwd=REPO_ROOT, capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)), timeout=60)
    assert done.stdout == "both ended\n", done.stderr
