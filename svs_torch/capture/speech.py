"""Saying guide's warnings: ``espeak-ng`` in a child process when it is installed, the text always.

Why a module of its own: the warning rule (:mod:`.guide`) needs no speech program, and a notice that the program
is missing belongs on stderr once per process, not among the warnings.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from typing import TextIO

__all__ = ["SPEECH_MISSING", "Speaker", "notice_once"]


#: How to get the speech program, in the one notice given when it is missing.
SPEECH_MISSING = ("speech: espeak-ng is not installed, so warnings are text only (to hear them: "
                  "sudo apt-get install espeak-ng; --no-speech silences this notice)")

#: The notices already given in this process. Deliberately process-wide: a missing program is missing for every
#: Speaker, and the user needs to read it once, not once per warning or per guide.
_NOTICES_GIVEN: set[str] = set()


def notice_once(text: str, stream: TextIO | None) -> bool:
    """Print ``text`` to ``stream`` unless this process already printed it; True if printed now."""
    if stream is None or text in _NOTICES_GIVEN:
        return False
    _NOTICES_GIVEN.add(text)
    print(text, file=stream, flush=True)
    return True


class Speaker:
    """Say messages with ``espeak-ng`` when it is installed, and print them as text.

    Args:
        executable: the speech program; ``"auto"`` finds ``espeak-ng`` with :func:`shutil.which`; None: text only.
        words_per_minute: speech rate passed as ``-s``.
        stream: where messages are printed (None: nowhere).
        notices: where the notice that ``espeak-ng`` is missing goes (None: stderr; not ``stream``, the warnings'
            stdout in text mode, where a program reading them took it for a warning).

    Speech runs in a child process so the loop never waits for it; a newer message interrupts an older one still
    being spoken (the newest warning matters most), but the same message again lets it finish (a ``--repeat-s``
    shorter than the sentence restarted it mid-word every time, and it was never heard whole). With ``"auto"`` and
    no ``espeak-ng``, one notice (:data:`SPEECH_MISSING`) says so and how to get it, once per process
    (:func:`notice_once`).
    """

    def __init__(self, executable: str | None = "auto", *, words_per_minute: int = 170,
                 stream: TextIO | None = sys.stderr, notices: TextIO | None = None) -> None:
        self.executable = shutil.which("espeak-ng") if executable == "auto" else executable
        self.words_per_minute = words_per_minute
        self.stream = stream
        self._process: subprocess.Popen | None = None
        self._spoken = ""  # the text of self._process
        if executable == "auto" and self.executable is None:
            notice_once(SPEECH_MISSING, notices if notices is not None else sys.stderr)

    @property
    def speaks(self) -> bool:
        """True when messages are spoken, not only printed."""
        return self.executable is not None

    def say(self, text: str) -> None:
        """If a speech program is available, speak ``text`` (interrupting the previous message); then print it.

        Spoken first: a print that fails (a terminal closed under guide, whose writes then fail with EIO; a closed
        pipe) raises after the words are on their way, not instead of them: "Guide stopped." went unsaid so."""
        failed = self._speak(text)
        if self.stream is not None:
            print(text, file=self.stream, flush=True)
        if failed is not None:  # (after the text: the notice is about it)
            notice_once(failed, self.stream)

    def _speak(self, text: str) -> str | None:
        """Speak ``text``; None, or the notice that speech stopped (the program could not be run)."""
        if self.executable is None:
            return None
        if text == self._spoken and self._process is not None and self._process.poll() is None:
            return None  # still being said
        self._stop_previous()
        try:
            self._process = subprocess.Popen([self.executable, "-s", str(self.words_per_minute), text],
                                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                             stderr=subprocess.DEVNULL)
            self._spoken = text
        except OSError as err:
            failed, self.executable = f"speech disabled: cannot run {self.executable}: {err}", None
            return failed
        return None

    def _stop_previous(self) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                self._process.kill()
        self._process = None

    def close(self) -> None:
        """Let the last message finish (at most 5 s), then stop it."""
        if self._process is not None:
            try:
                self._process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._stop_previous()
            self._process = None
