"""Interrupts of the command line (Ctrl-C, SIGTERM) at the moments an audit of interrupts found wanting."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _python(code: str, cwd: Path, timeout: float = 60) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_ctrl_c_while_the_interpreter_shuts_down_prints_no_traceback(tmp_path):
    """Was: a Ctrl-C just after a command had written everything, while the interpreter shut down (torch's exit
    handlers take a while), printed 'Exception ignored in atexit callback' and a KeyboardInterrupt traceback
    after the command's last line (svs-depth demo --figure, 1 try in 3 at its end). Now the program ends as the
    shell's Ctrl-C ends it: killed by SIGINT (130 to the shell), nothing printed. An exit handler that runs last
    sends the Ctrl-C here, as a terminal would in the middle of torch's."""
    code = ("import atexit, os, signal, sys, time\n"
            "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(5)))\n"
            "from svs_torch.cli import main\n"
            "sys.argv = ['svs-depth', 'results', 'missing.sqlite']\n"
            "sys.exit(main())\n")
    result = _python(code, tmp_path)
    assert "Traceback" not in result.stderr and "KeyboardInterrupt" not in result.stderr, result.stderr
    assert result.returncode == -signal.SIGINT, (result.returncode, result.stderr)
    assert result.stderr.startswith("svs-depth results: error:")  # the command's own line, said before


def test_main_called_with_arguments_leaves_the_ctrl_c_handler_alone(tmp_path):
    """A script or test that calls main(argv) keeps its own Ctrl-C handling."""
    from svs_torch.cli import main

    before = signal.getsignal(signal.SIGINT)
    assert main(["results", str(tmp_path / "missing.sqlite")]) == 2
    assert signal.getsignal(signal.SIGINT) is before
