"""``svs-depth`` where standard output cannot encode every character (a C locale with Python's UTF-8 mode off,
``PYTHONIOENCODING=ascii``): the help texts' '–', '×', 'σ', '°' are written as escapes, never a traceback."""

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
