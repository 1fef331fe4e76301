"""``svs-depth guide`` run for hours as an assistive device runs it: what fills up (a disk under its --json lines)
must not end the warnings."""

from __future__ import annotations

import json
import sys

from svs_torch.cli import main


class _DiskFullAfter:
    """A text stream on a regular file whose disk fills at line ``full_at`` (1-based): that line's first half is
    written, then ``write`` fails with ENOSPC as a file on a full disk does."""

    def __init__(self, path, full_at: int) -> None:
        self.file = open(path, "w", encoding="ascii")
        self.full_at, self.lines = full_at, 0

    def write(self, text: str) -> int:
        self.lines += text.count("\n")
        if self.lines >= self.full_at:
            self.file.write(text[:len(text) // 2])
            self.file.flush()
            raise OSError(28, "No space left on device")
        return self.file.write(text)

    def flush(self) -> None:
        self.file.flush()

    def fileno(self) -> int:
        return self.file.fileno()


def test_guide_a_full_disk_under_its_json_lines_stops_the_lines_not_the_warnings(monkeypatch, capsys, tmp_path):
    """Was (an audit of long walks): the help's own ``guide --json --record walk/ > walk.jsonl`` on a disk that
    filled said "recording stopped ..., the warnings go on", and at the next --json line ended guide (exit 1, "No
    space left on device: 'standard output'"): the walker heard "Guide stopped" and nothing more. Now the lines stop,
    said once, the file keeps its whole lines only (the one cut short is cut off), and every pair is ranged."""
    walk = tmp_path / "walk.jsonl"
    stdout = _DiskFullAfter(walk, full_at=3)
    monkeypatch.setattr(sys, "stdout", stdout)
    # (--size: what a full disk stops, not what is ranged; 0.2 s a pair less than the default's 320x240)
    code = main(["guide", "--emulator", "--count", "5", "--no-speech", "--json", "--size", "160x120"])
    stdout.file.close()
    err = capsys.readouterr().err
    assert code == 0, err
    assert err.count("the --json lines stopped") == 1
    # worded as the record's stop and the error handler word it (error_text): was "[Errno 28] No space left on
    # device: 'standard output'; the --json lines stopped ..." (an audit)
    assert "svs-depth guide: No space left on device: standard output; the --json lines stopped" in err, err
    assert "guide stopped after 5 pairs" in err and "error" not in err
    text = walk.read_text()
    assert text.endswith("\n") and [json.loads(line)["index"] >= 0 for line in text.splitlines()] == [True, True]
