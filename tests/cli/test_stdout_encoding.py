"""``svs-depth``'s standard streams: where standard output cannot encode every character (a C locale with
Python's UTF-8 mode off, ``PYTHONIOENCODING=ascii``) the help texts' '–', '×', 'σ', '°' are written as escapes,
never a traceback; where the shell closed one (``>&-``, ``2>&-``) the command runs as if it were the null
device."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


@pytest.mark.parametrize("setting", [{"PYTHONIOENCODING": "ascii"},
                                     {"LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}])
def test_help_prints_on_an_ascii_stdout(setting):
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONIOENCODING", "PYTHONUTF8")}
    done = subprocess.run([sys.executable, "-m", "svs_torch.cli", "--help"], env={**env, **setting},
                          capture_output=True, timeout=60)
    assert done.returncode == 0 and done.stderr == b"", done.stderr.decode(errors="replace")[-300:]
    assert b"1\\u20132 m ahead" in done.stdout


def test_undecodable_bytes_of_a_file_name_are_written_as_they_were():
    """Under the C locale, stdout's ``surrogateescape`` wrote a file name's raw bytes: they still are."""
    code = ("import sys\nfrom svs_torch.cli import _unencodable_escaped\n_unencodable_escaped()\n"
            "print('a\\udcc3\\udcb6b \\u03c3')")
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONIOENCODING", "PYTHONUTF8")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60,
                          env={**env, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"})
    assert done.stdout == b"a\xc3\xb6b \\u03c3\n", done


def _pair(tmp_path) -> list[str]:
    """A pair too small to range: estimate prints its report (TOO_SMALL) without running the pipeline."""
    import cv2
    import numpy as np

    paths = [str(tmp_path / "left.png"), str(tmp_path / "right.png")]
    for path in paths:
        cv2.imwrite(path, np.full((12, 16), 128, dtype=np.uint8))
    return paths


@pytest.mark.parametrize("closed", [1, 2])
def test_a_command_runs_with_a_standard_stream_closed(tmp_path, closed):
    """``svs-depth estimate L R >&-`` (a service started with its output closed) ended in "internal error:
    AttributeError: 'NoneType' object has no attribute 'write'" and exit 1 (an audit of guide): Python has no
    ``sys.stdout`` then. It now runs as if the stream were the null device. With stderr closed, a bad argument still
    exits 2, and its error line is not written into the results (print's ``file=None`` is standard output)."""
    left, right = _pair(tmp_path)
    # (stderr closed: an option estimate refuses before it loads torch, 0.4 s; a missing image was refused after it)
    argv, code = ([left, right, "--json"], 0) if closed == 1 else ([left, right, "--workers", "2"], 2)
    kept = 2 if closed == 1 else 1
    done = subprocess.run([sys.executable, "-m", "svs_torch.cli", "estimate", *argv], timeout=120,
                          stdout=subprocess.PIPE if kept == 1 else None, stderr=subprocess.PIPE if kept == 2 else None,
                          preexec_fn=lambda: os.close(closed))
    said = (done.stdout if kept == 1 else done.stderr).decode(errors="replace")
    assert done.returncode == code and "internal error" not in said, said[-300:]
    assert kept == 2 or said == "", said  # the error line is not written into the results instead
