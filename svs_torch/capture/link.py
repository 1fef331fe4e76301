"""One SRV-1 camera link over pyserial: a UART (``/dev/ttyUSB0``) or the WiFi bridge (``socket://HOST:10001``).

The link sends one command and reads its whole reply before the next (``SVS_PROTOCOL.md`` §2: input that
arrives while a command is handled is discarded, so never pipeline). Every wait has a deadline:

* a command's reply must arrive within ``reply_timeout_s`` of sending it;
* a frame's JPEG must arrive within ``transfer_margin_s + transfer_slack · length / link_bytes_per_s`` of its
  header, the length being the one the header announces (bounded by :func:`~.protocol.max_jpeg_length`);
* a silent or broken reply is retried ``max_retries`` times (§3: ``I`` sometimes returns nothing), after
  discarding input until the link has been quiet for ``drain_quiet_s`` (at most ``drain_max_s``);
* a dropped link is reopened up to ``max_reconnects`` times per command, and the size, quality and flip are
  re-sent (to a board that sends a frame of another size, a reset one, too);
* a command that got nothing, sent within :data:`~.command_gap.HOLD_OFF_SUSPECT_S` of the last reply, widens the
  pause before each command, unless those sent as soon before it were answered (``command_gap_s``; :mod:`.command_gap`).

pyserial's ``read(n)`` returns short on timeout without raising, so reads use a short fixed timeout
(``poll_s``) in a loop that checks the deadline: a deadline is overshot by at most ``poll_s``. Opening a
``socket://`` link may take up to pyserial's fixed 5 s connect timeout, and closing one sleeps 0.3 s in pyserial.
"""

from __future__ import annotations

import time
from typing import Callable

import serial

from ..core.camera import SVS_RESOLUTIONS
from .command_gap import HOLD_OFF_SUSPECT_S, CommandGap
from .link_types import (CaptureError, LinkConfig, LinkStats, RawFrame, _Attempt, _Dropped, attempt_reasons,
                         check_link_url, frame_timeout_reason, got_words, open_hint, write_failure)
from .protocol import (BATTERY_PREFIX, CMD_BATTERY, CMD_GRAB, CMD_UPTIME, CMD_VERSION, QUALITY_PREFIX, UPTIME_PREFIX,
                       VERSION_PREFIX, BadFrame, FrameParser, ParsedFrame, ProtocolError, VersionInfo, describe_bytes,
                       find_line, find_token, parse_battery_reply, parse_quality_reply, parse_uptime_reply,
                       parse_version_line, quality_command, size_acks, size_command)

__all__ = ["CameraLink", "CaptureError", "LinkConfig", "LinkStats", "RawFrame", "check_link_url"]


Matcher = Callable[[bytes], "tuple[bytes, int] | None"]


class CameraLink:
    """A link to one SRV-1 board; see the module docstring for the timeout rules.

    Args:
        url: ``/dev/ttyUSB0``-style device path or ``socket://HOST:PORT`` (10001 left/master, 10002 right/slave).
        name: the camera's name in messages, ``"left"`` or ``"right"``.
        config: timeouts, retries and UART settings.
    """

    def __init__(self, url: str = "/dev/ttyUSB0", name: str = "left", config: LinkConfig | None = None) -> None:
        self.url = url
        self.name = name
        self.config = config or LinkConfig()
        self.stats = LinkStats()
        self.size_code: str | None = None  # size set on the board; frames of another size are rejected
        self.quality: int | None = None  # JPEG quality digit set on the board, if any
        self.flip: bool | None = None  # the image flip set on the board (y / Y), if any
        self._serial: serial.SerialBase | None = None
        self._last_reply_s = self._request_s = 0.0
        self._gap = CommandGap(self.config.command_gap_s)  # (widened by a board's hold-off: _after_silence)
        self._prompt = False  # the last command was sent within HOLD_OFF_SUSPECT_S of the reply before it
        self._pending_drop: str | None = None

    @property
    def where(self) -> str:
        """``left camera (socket://...)``: how messages name this link."""
        return f"{self.name} camera ({self.url})"

    def open(self) -> None:
        """Open the link and discard anything already waiting (the master's power-up banner, §2)."""
        cfg = self.config
        try:
            # exclusive: a serial device another program (or this one's other camera, by another path) holds is
            # refused ("Could not exclusively lock port"). Why: without the lock both read parts of each other's
            # replies and failed on frames "cut short" (an audit). Ignored by socket:// (one client at a time).
            self._serial = serial.serial_for_url(
                self.url, baudrate=cfg.baudrate, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE, rtscts=cfg.rtscts, timeout=cfg.poll_s,
                write_timeout=cfg.write_timeout_s, exclusive=True)
        except (serial.SerialException, ValueError, OSError) as err:
            raise CaptureError(f"{self.where}: could not open the link: {err}{open_hint(self.url, err)}") from err
        self._pending_drop = None
        try:
            self.drain()
        except _Dropped as err:
            self.close()
            raise CaptureError(f"{self.where}: the link closed right after opening: {err}") from err

    def close(self) -> None:
        """Close the link (pyserial's socket close sleeps 0.3 s); safe to call twice."""
        link, self._serial = self._serial, None
        if link is not None:
            try:
                link.close()
            except (serial.SerialException, OSError):
                pass

    def drain(self) -> int:
        """Discard input until the link is quiet for ``drain_quiet_s`` (at most ``drain_max_s``); bytes dropped."""
        cfg = self.config
        start = last = time.monotonic()
        dropped = 0
        while True:
            data = self._read(4096)
            now = time.monotonic()
            if data:
                dropped += len(data)
                last = now
            if now - last >= cfg.drain_quiet_s or now - start >= cfg.drain_max_s:
                break
        self.stats.stray_bytes += dropped
        return dropped

    # ----------------------------------------------------------------------------------------- short commands

    def command(self, command: bytes, match: Matcher, expected: str, *, allow_reconnect: bool = True) -> bytes:
        """Send ``command``, read until ``match`` finds its reply (stray bytes before it are skipped); retried.

        Raises:
            CaptureError: no matching reply after ``max_retries + 1`` attempts or ``max_reconnects`` reopenings.
        """
        attempts, reconnects, attempt = self.config.max_retries + 1, 0, 0
        received = b""
        while attempt < attempts:
            try:
                self._require_open()
                self._send(command)
                reply, received = self._read_reply(match)
            except _Dropped as err:
                if not allow_reconnect or reconnects >= self.config.max_reconnects:
                    raise CaptureError(f"{self.where}: link dropped while sending {command!r} (expected {expected}): "
                                       f"{err}") from None
                reconnects += 1
                self._reconnect(str(err))
                continue
            attempt += 1
            if reply is not None:
                return reply
            self._after_silence(not received)
            self._note_failure(f"sent {command!r}, expected {expected}, got {describe_bytes(received)}")
            if attempt < attempts:
                self.stats.retries += 1
                self._drain_quietly()
        raise CaptureError(f"{self.where}: sent {command!r} {attempts} times, expected {expected} within "
                           f"{self.config.reply_timeout_s:g} s each, last got {got_words(self, received)}")

    def command_ack(self, command: bytes, acks: tuple[bytes, ...], **kwargs: bool) -> bytes:
        """Send a command whose reply is one of the two-byte ``acks`` (e.g. ``b"b"`` → ``#b``)."""
        expected = " or ".join(repr(a) for a in acks)
        return self.command(command, lambda buf: find_token(buf, acks), expected, **kwargs)

    def command_line(self, command: bytes, prefix: bytes, **kwargs: bool) -> bytes:
        """Send a command whose reply is one ``\\r\\n``-terminated line starting with ``prefix``; the line."""
        expected = f"a line starting {prefix!r}"
        return self.command(command, lambda buf: find_line(buf, prefix), expected, **kwargs)

    def set_flip(self, flip: bool, *, allow_reconnect: bool = True) -> None:
        """Flip the image (``y``: a camera mounted upside down) or not (``Y``), and remember it to restore."""
        self.command_ack(b"y" if flip else b"Y", (b"#y",) if flip else (b"#Y",), allow_reconnect=allow_reconnect)
        self.flip = flip

    def restore_settings(self, *, allow_reconnect: bool = True) -> None:
        """Send again the size, quality and flip this link set: after a reconnect, or to a board that sent a frame
        of another size (it was reset to its power-on settings, all of them)."""
        if self.size_code is not None:
            self.set_size(self.size_code, allow_reconnect=allow_reconnect)
        if self.quality is not None:
            self.set_quality(self.quality, allow_reconnect=allow_reconnect)
        if self.flip is not None:
            self.set_flip(self.flip, allow_reconnect=allow_reconnect)

    def configure(self, size_code: str, quality: int | None = None, flip: bool | None = None) -> None:
        """Set the size, the caption overlay off (``O``: a board keeps one an earlier session turned on, across
        reconnects, burnt into its frames' top rows; an audit), and the quality and flip where given."""
        self.set_size(size_code)
        self.command_ack(b"O", (b"#O", b"#?"))  # (#?: a build without the overlay has none to turn off)
        for value, setter in ((quality, self.set_quality), (flip, self.set_flip)):
            if value is not None:
                setter(value)

    def set_size(self, size_code: str, *, allow_reconnect: bool = True) -> None:
        """Select a frame size by its code (``'5'`` = 320×240) and remember it for checking frames."""
        self.command_ack(size_command(size_code), size_acks(size_code), allow_reconnect=allow_reconnect)
        self.size_code = size_code

    def set_quality(self, quality: int, *, allow_reconnect: bool = True) -> None:
        """Set the JPEG quality digit, 1 (best) … 8 (worst); checks the board's ``##quality`` echo."""
        line = self.command_line(quality_command(quality), QUALITY_PREFIX, allow_reconnect=allow_reconnect)
        try:
            echoed = parse_quality_reply(line)
        except ProtocolError:  # a garbled digit (no checksums, §2): the board's failure, not an internal error
            echoed = None
        if echoed != quality:
            raise CaptureError(f"{self.where}: sent quality {quality}, the board replied {line!r}")
        self.quality = quality

    def identify(self) -> VersionInfo:
        """Send ``V``; the version line and the board's role (``master`` = left, ``slave`` = right)."""
        return parse_version_line(self.command_line(CMD_VERSION, VERSION_PREFIX))

    def uptime_ms(self) -> int:
        """Send ``t``; milliseconds since the board powered up."""
        return parse_uptime_reply(self.command_line(CMD_UPTIME, UPTIME_PREFIX))

    def battery_ok(self) -> bool:
        """Send ``D``; False when the board reports a low battery."""
        return parse_battery_reply(self.command_line(CMD_BATTERY, BATTERY_PREFIX))

    # ---------------------------------------------------------------------------------------------- frames

    def request_frame(self) -> None:
        """Send ``I`` without reading; a write on a dropped link is remembered and handled by :meth:`read_frame`.
        Bytes already waiting are dropped first (:meth:`_discard_stale_input`)."""
        try:
            self._require_open()
            self._discard_stale_input()
            self._send(CMD_GRAB)
        except _Dropped as err:
            self._pending_drop = str(err)

    def _discard_stale_input(self) -> None:
        """Drop whatever the board sent before this grab was asked for. Why: a reply that came late (to an ``I``
        re-sent after its timeout, or a board answering twice) was read as the next grab's frame, one grab old, and
        on a board with no hold-off every later frame stayed one behind; the pair's two frames then showed two
        moments while its record said they came together (an audit of the device side: 13 px of skew on a moving
        bar, a false disparity while the walker turns)."""
        try:
            if self._serial.in_waiting:
                self.stats.stale_inputs += 1
                self._serial.reset_input_buffer()
        except (serial.SerialException, OSError) as err:
            raise _Dropped(f"read: {err}") from None

    def read_frame(self) -> RawFrame:
        """Read the frame asked for by :meth:`request_frame`, re-sending ``I`` after a silent or broken reply.

        Raises:
            CaptureError: no valid frame after ``max_retries + 1`` attempts (each bounded by
                :meth:`LinkConfig.frame_attempt_timeout_s`) or ``max_reconnects`` reopenings.
        """
        attempts, attempt, reconnects = self.config.max_retries + 1, 0, 0
        first_reason = ""
        start = time.monotonic()
        while True:
            try:
                if self._pending_drop is not None:
                    raise _Dropped(self._pending_drop)
                outcome = self._read_frame_once(attempt + 1)
            except _Dropped as err:
                self._pending_drop = None
                if reconnects >= self.config.max_reconnects:
                    raise CaptureError(f"{self.where}: link dropped while waiting for a frame and "
                                       f"{reconnects} reconnects did not help: {err}") from None
                reconnects += 1
                self._reconnect(str(err))
                self.request_frame()
                continue
            attempt += 1
            if isinstance(outcome, RawFrame):
                self.stats.frames += 1
                return outcome
            self._after_silence(outcome.silent)
            self._note_failure(outcome.reason)
            first_reason = first_reason or outcome.reason
            if attempt >= attempts:
                raise CaptureError(f"{self.where}: no valid frame after {attempts} attempt"
                                   f"{'s' if attempts > 1 else ''} of {CMD_GRAB!r} in {time.monotonic() - start:.2f} s;"
                                   f" {attempt_reasons(first_reason, outcome.reason)}")
            self.stats.retries += 1
            self._drain_quietly()
            if outcome.wrong_size:  # a board reset to its power-on settings: every one this link set
                self.restore_settings()
            self.request_frame()

    def grab(self) -> RawFrame:
        """Send ``I`` and read its frame (with retries and reconnects)."""
        self.request_frame()
        return self.read_frame()

    def _read_frame_once(self, attempt: int) -> RawFrame | _Attempt:
        cfg = self.config
        parser = FrameParser()
        deadline = self._request_s + cfg.reply_timeout_s
        received = bytearray()
        last_data_s = header_s = time.monotonic()
        while time.monotonic() < deadline:
            had_header = parser.header is not None
            data = self._read(parser.bytes_needed)
            if not data:
                continue
            last_data_s = time.monotonic()
            header_s = header_s if had_header else last_data_s  # the read that completed the header (RawFrame)
            received += data[:64 - len(received)] if len(received) < 64 else b""
            for event in parser.feed(data):
                return self._finish_frame(event, attempt, header_s)
            if parser.header is not None and not had_header:
                deadline = time.monotonic() + cfg.transfer_timeout_s(parser.header.length)
        self.stats.stray_bytes += parser.skipped_bytes
        return _Attempt(frame_timeout_reason(cfg, self.size_code, parser, bytes(received),
                                             time.monotonic() - last_data_s), silent=not received)

    def _finish_frame(self, event: ParsedFrame | BadFrame, attempt: int, header_s: float) -> RawFrame | _Attempt:
        now, wall = time.monotonic(), time.time()
        self._replied(now)
        self.stats.stray_bytes += event.skipped_bytes
        header = event.header
        if isinstance(event, BadFrame):
            return _Attempt(f"frame of {header.length} bytes at {header.width}x{header.height}: {event.reason}")
        if self.size_code is not None and header.size_code != self.size_code:
            want = SVS_RESOLUTIONS[self.size_code]
            return _Attempt(f"expected size code {self.size_code!r} ({want[0]}x{want[1]}), got "
                            f"{header.size_code!r} ({header.width}x{header.height})", wrong_size=True)
        if event.after_banner:  # reset at its power-on size: its quality and flip were lost without a word (an audit)
            return _Attempt("the board sent its power-on banner before the frame: it was reset, so its settings are "
                            "sent again", wrong_size=True)
        return RawFrame(header=header, jpeg=event.jpeg, request_monotonic_s=self._request_s,
                        arrival_monotonic_s=now, arrival_wall_s=wall, attempts=attempt,
                        skipped_bytes=event.skipped_bytes, header_monotonic_s=header_s)

    # ----------------------------------------------------------------------------------------- low level

    def _require_open(self) -> None:
        if self._serial is None:
            raise _Dropped("the link is not open")

    def _replied(self, now_s: float) -> None:  # the next command's pause runs from a reply
        self._last_reply_s = now_s
        self._gap.answered(self._prompt)

    def _after_silence(self, silent: bool) -> None:
        """Widen the pause before each command where the board likely discarded one sent right after its last reply
        (§2; :class:`~.command_gap.CommandGap`). Why: a board ignoring input for 30 ms lost the first try of every
        command, ``reply_timeout_s`` each (an audit: opening took 3.3 s for 0.09, three pairs 3.6 s for 0.39)."""
        if self._gap.silent(silent and self._prompt):
            self.stats.command_gap_s = self._gap.gap_s

    def _send(self, command: bytes) -> None:
        wait = self._last_reply_s + self._gap.gap_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        try:
            self._serial.write(command)
        except (serial.SerialException, OSError) as err:
            raise _Dropped(write_failure(self.url, err)) from None
        self._request_s = time.monotonic()
        self._prompt = self._request_s - self._last_reply_s < HOLD_OFF_SUSPECT_S

    def _read(self, count: int | None) -> bytes:
        """Read up to ``count`` bytes (None: what is waiting, at least 1) within ``poll_s``."""
        if self._serial is None:
            raise _Dropped("the link is not open")
        try:
            if count is None:
                count = max(1, self._serial.in_waiting)
            return self._serial.read(count)
        except (serial.SerialException, OSError) as err:
            raise _Dropped(f"read: {err}") from None

    def _read_reply(self, match: Matcher) -> tuple[bytes | None, bytes]:
        """Read until ``match`` finds the reply or ``reply_timeout_s`` passes; (reply or None, bytes read)."""
        deadline = self._request_s + self.config.reply_timeout_s
        buffer = bytearray()
        while time.monotonic() < deadline:
            data = self._read(None)
            if not data:
                continue
            buffer += data
            found = match(bytes(buffer))
            if found is not None:
                reply, end = found
                self.stats.stray_bytes += end - len(reply)
                self._replied(time.monotonic())
                return reply, bytes(buffer)
        return None, bytes(buffer)

    def _drain_quietly(self) -> None:
        try:
            self.drain()
        except _Dropped as err:
            self._pending_drop = str(err)

    def _reconnect(self, reason: str) -> None:
        """Reopen the link and restore the size, quality and flip; raises CaptureError if it cannot."""
        self.stats.reconnects += 1
        self._note_failure(f"link dropped: {reason}")
        self.close()
        for attempt in range(self.config.max_reconnects + 1):
            time.sleep(self.config.reconnect_delay_s)
            try:
                self.open()
                break
            except CaptureError as err:  # (said with the drop: "could not open" alone, after pairs, puzzled)
                if attempt == self.config.max_reconnects:
                    raise CaptureError(f"{err} (after the link dropped: {reason})") from None
        self.restore_settings(allow_reconnect=False)

    def _note_failure(self, reason: str) -> None:
        self.stats.failures = (self.stats.failures + [reason])[-8:]
