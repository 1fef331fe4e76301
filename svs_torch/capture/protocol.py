"""The SRV-1 Blackfin byte protocol, as pure functions on bytes (no I/O).

Written from ``../shared/SVS_PROTOCOL.md`` (sections cited as §n). A command is one leading byte, sometimes
followed by parameter bytes (§2); replies are short ASCII acks, ``\\r\\n``-terminated lines, or an image frame:
``##IMJ`` + one ASCII size code + a 4-byte little-endian JPEG length whose fourth byte is 0 + the JPEG (§3).

Everything here is pure so the link, the emulator and the tests share one reading of the protocol. Parse errors
raise :class:`ProtocolError` whose message says what was expected and what was received.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..core.camera import SVS_RESOLUTIONS
from ..core.errors import InputError

__all__ = [
    "ProtocolError",
    "VersionInfo",
    "FrameHeader",
    "ParsedFrame",
    "BadFrame",
    "FrameParser",
    "CMD_VERSION",
    "CMD_GRAB",
    "CMD_UPTIME",
    "CMD_BATTERY",
    "VERSION_PREFIX",
    "QUALITY_PREFIX",
    "UPTIME_PREFIX",
    "BATTERY_PREFIX",
    "FRAME_MAGIC",
    "FRAME_HEADER_LEN",
    "size_code_for",
    "size_command",
    "size_acks",
    "quality_command",
    "parse_version_line",
    "parse_quality_reply",
    "parse_uptime_reply",
    "parse_battery_reply",
    "parse_frame_header",
    "check_jpeg",
    "encode_frame",
    "max_jpeg_length",
    "find_token",
    "find_line",
    "describe_bytes",
]

CMD_VERSION = b"V"  # §3: identify, replies one ``##Version`` line
CMD_GRAB = b"I"  # §3: grab and JPEG-encode one frame
CMD_UPTIME = b"t"  # §3: ``##time - millisecs:  <n>``
CMD_BATTERY = b"D"  # §3: ``##D - battery voltage okay`` / ``... low battery voltage detected``
FRAME_MAGIC = b"##IMJ"  # §3, image frame offset 0
FRAME_HEADER_LEN = 10  # magic (5) + size code (1) + length (4)
VERSION_PREFIX = b"##Version"
QUALITY_PREFIX = b"##quality - "
UPTIME_PREFIX = b"##time - millisecs:"
BATTERY_PREFIX = b"##D - "
JPEG_START = b"\xff\xd8"  # SOI marker
JPEG_END = b"\xff\xd9"  # EOI marker

# §3: the size commands and their size codes. The firmware acks both ``d`` and ``A`` with ``#d``; the protocol page
# says ``#A`` for ``A``. We send ``A`` (named on both sources) and accept either ack.
_SIZE_COMMANDS: dict[str, tuple[bytes, tuple[bytes, ...]]] = {
    "3": (b"a", (b"#a",)),
    "5": (b"b", (b"#b",)),
    "7": (b"c", (b"#c",)),
    "9": (b"A", (b"#d", b"#A")),
}


class ProtocolError(ValueError):
    """Bytes that do not follow the SRV-1 protocol; the message says what was expected and what was received."""


@dataclass(frozen=True)
class VersionInfo:
    """The reply to ``V``.

    Attributes:
        text: the line without its ``\\r\\n``, e.g. ``##Version - SRV-1 Blackfin w/PicoC v2.1 ... (stereo master)``.
        role: ``"master"`` (left, port 10001), ``"slave"`` (right, port 10002) or ``"unknown"`` (not a stereo build).
    """

    text: str
    role: str


@dataclass(frozen=True)
class FrameHeader:
    """The 10-byte ``##IMJ`` header of an image frame (§3).

    Attributes:
        size_code: ASCII size code, one of ``'3' '5' '7' '9'``.
        width, height: frame size in pixels for that code.
        length: JPEG length in bytes that follows the header.
    """

    size_code: str
    width: int
    height: int
    length: int


@dataclass(frozen=True)
class ParsedFrame:
    """A complete frame: its header, its JPEG bytes, how many stray bytes preceded it, and whether a ``##Version``
    banner was among them (the board was reset: its frames are at its power-on settings)."""

    header: FrameHeader
    jpeg: bytes
    skipped_bytes: int
    after_banner: bool = False


@dataclass(frozen=True)
class BadFrame:
    """A frame whose header parsed but whose body failed the JPEG marker check; ``reason`` says how."""

    header: FrameHeader
    reason: str
    skipped_bytes: int


def describe_bytes(data: bytes, limit: int = 40) -> str:
    """A short printable rendering of ``data`` for error messages, e.g. ``12 bytes b'#?##IMJ5...'``."""
    shown = bytes(data[:limit])
    more = "..." if len(data) > limit else ""
    return f"{len(data)} bytes {shown!r}{more}"


def size_code_for(size_wh: tuple[int, int]) -> str:
    """The ASCII size code of a frame size ``(width, height)`` in pixels; raises ``InputError`` if it has none."""
    try:
        got = tuple(size_wh)
    except TypeError:  # None or 320 is a bad size too: it was "TypeError: 'NoneType' object is not iterable"
        got = size_wh
    for code, wh in SVS_RESOLUTIONS.items():
        if got == wh:
            return code
    allowed = ", ".join(f"{w}x{h}" for w, h in SVS_RESOLUTIONS.values())
    raise InputError(f"size_wh: expected one of {allowed}, got {got!r}")


def size_command(size_code: str) -> bytes:
    """The one-byte command selecting a size code (``'5'`` → ``b"b"``)."""
    if size_code not in _SIZE_COMMANDS:
        raise InputError(f"size_code: expected one of {sorted(_SIZE_COMMANDS)}, got {size_code!r}")
    return _SIZE_COMMANDS[size_code][0]


def size_acks(size_code: str) -> tuple[bytes, ...]:
    """The two-byte acks that confirm a size command (``'5'`` → ``(b"#b",)``)."""
    size_command(size_code)
    return _SIZE_COMMANDS[size_code][1]


def quality_command(quality: int) -> bytes:
    """``q`` + one ASCII digit, JPEG quality 1 (best) … 8 (worst), §3."""
    if not isinstance(quality, int) or not 1 <= quality <= 8:
        raise InputError(f"quality: expected an integer 1 (best) to 8 (worst), got {quality!r}")
    return b"q" + str(quality).encode("ascii")


def _strip_line(line: bytes, prefix: bytes, what: str) -> str:
    if not line.startswith(prefix):
        raise ProtocolError(f"{what}: expected a line starting {prefix!r}, got {describe_bytes(line)}")
    return line.rstrip(b"\r\n").decode("ascii", errors="replace")


def parse_version_line(line: bytes) -> VersionInfo:
    """Parse the reply to ``V`` (one line, with or without its ``\\r\\n``) into a :class:`VersionInfo`."""
    text = _strip_line(line, VERSION_PREFIX, "version reply")
    role = "master" if "(stereo master)" in text else "slave" if "(stereo slave)" in text else "unknown"
    return VersionInfo(text=text, role=role)


def parse_quality_reply(line: bytes) -> int:
    """Parse ``##quality - <digit>\\r\\n`` into the quality digit 1..8."""
    text = _strip_line(line, QUALITY_PREFIX, "quality reply")
    digit = text[len(QUALITY_PREFIX):].strip()
    if not (digit.isdigit() and 1 <= int(digit) <= 8):
        raise ProtocolError(f"quality reply: expected a digit 1..8 after {QUALITY_PREFIX!r}, got {digit!r}")
    return int(digit)


def parse_uptime_reply(line: bytes) -> int:
    """Parse ``##time - millisecs:  <n>\\r\\n`` into milliseconds since power-up."""
    text = _strip_line(line, UPTIME_PREFIX, "uptime reply")
    value = text[len(UPTIME_PREFIX):].strip()
    if not value.isdigit():
        raise ProtocolError(f"uptime reply: expected an integer after {UPTIME_PREFIX!r}, got {value!r}")
    return int(value)


def parse_battery_reply(line: bytes) -> bool:
    """Parse the reply to ``D``: True for ``battery voltage okay``, False for ``low battery voltage detected``."""
    text = _strip_line(line, BATTERY_PREFIX, "battery reply")
    if "okay" in text:
        return True
    if "low battery" in text:
        return False
    raise ProtocolError(f"battery reply: expected 'okay' or 'low battery voltage detected', got {text!r}")


def max_jpeg_length(width: int, height: int) -> int:
    """Largest JPEG length in bytes accepted for a frame: 3 bytes per pixel (raw RGB) plus 4 KiB of headers.

    A 4:2:2 JPEG carries 2 samples per pixel, so a real frame stays far below this; a larger announced length is
    a corrupt header, and bounding it bounds the read timeout derived from it.
    """
    return 3 * width * height + 4096


def parse_frame_header(header: bytes) -> FrameHeader:
    """Parse the 10-byte ``##IMJ`` header (§3): magic, size code, little-endian length with a zero fourth byte."""
    _check_bytes(header, "header")
    if len(header) != FRAME_HEADER_LEN:
        raise ProtocolError(f"frame header: expected {FRAME_HEADER_LEN} bytes, got {describe_bytes(header)}")
    if header[:5] != FRAME_MAGIC:
        raise ProtocolError(f"frame header: expected it to start {FRAME_MAGIC!r}, got {describe_bytes(header)}")
    code = chr(header[5])
    if code not in SVS_RESOLUTIONS:
        raise ProtocolError(f"frame header: expected a size code in {sorted(SVS_RESOLUTIONS)}, got {code!r}")
    if header[9] != 0:
        raise ProtocolError(f"frame header: expected the length's fourth byte to be 0, got {header[9]}")
    length = int.from_bytes(header[6:10], "little")
    width, height = SVS_RESOLUTIONS[code]
    if not 4 <= length <= max_jpeg_length(width, height):
        raise ProtocolError(f"frame header: expected a JPEG length of 4..{max_jpeg_length(width, height)} bytes "
                            f"for {width}x{height}, got {length}")
    return FrameHeader(size_code=code, width=width, height=height, length=length)


def check_jpeg(data: bytes) -> None:
    """Check the JPEG start (``FF D8``) and end (``FF D9``) markers; raises :class:`ProtocolError` naming the miss."""
    if data[:2] != JPEG_START:
        raise ProtocolError(f"JPEG data: expected it to start FF D8, got {data[:2].hex(' ').upper() or 'nothing'}")
    if data[-2:] != JPEG_END:
        raise ProtocolError(f"JPEG data: expected it to end FF D9, got {data[-2:].hex(' ').upper() or 'nothing'}")


def encode_frame(size_code: str, jpeg: bytes, announced_length: int | None = None) -> bytes:
    """The bytes of an image frame reply: ``##IMJ`` + size code + length (LE, 4 bytes) + JPEG.

    ``announced_length`` overrides the length written in the header (the emulator's wrong-length fault).
    """
    if size_code not in SVS_RESOLUTIONS:  # 'Z' was encoded, a frame no board sends
        raise InputError(f"size_code: expected one of {sorted(SVS_RESOLUTIONS)}, got {size_code!r}")
    _check_bytes(jpeg, "jpeg")
    length = len(jpeg) if announced_length is None else announced_length
    if not 0 <= length < 2 ** 24:
        raise InputError(f"announced_length: expected 0 <= length < 2**24 (fourth byte 0), got {length}")
    return FRAME_MAGIC + size_code.encode("ascii") + length.to_bytes(4, "little") + jpeg


def _check_bytes(data: object, name: str) -> None:
    """InputError naming ``name`` unless ``data`` is bytes-like (a str was concatenated to the buffer deep inside)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise InputError(f"{name}: expected bytes read from the link, got {type(data).__name__}")


def find_token(buffer: bytes, tokens: tuple[bytes, ...]) -> tuple[bytes, int] | None:
    """The first of ``tokens`` found in ``buffer`` and the index just past it, or None (stray bytes allowed)."""
    best: tuple[bytes, int] | None = None
    for token in tokens:
        at = buffer.find(token)
        if at >= 0 and (best is None or at + len(token) < best[1]):
            best = (token, at + len(token))
    return best


def find_line(buffer: bytes, prefix: bytes) -> tuple[bytes, int] | None:
    """The first complete line starting with ``prefix`` and the index just past it, or None. A line ends ``\\r\\n``
    (§3), or ``\\n\\r`` as other public SRV-1 firmware trees end theirs (``##quality - 4\\n\\r``): §7 leaves the
    firmware version open, and such a board's ``V`` failed three times, its version line unread (an audit)."""
    start = buffer.find(prefix)
    if start < 0:
        return None
    newline = buffer.find(b"\n", start)
    if newline < 0:
        return None
    end = newline + 1
    if buffer[newline - 1:newline] != b"\r" and buffer[end:end + 1] == b"\r":  # (\n\r; a \r still on the way is
        end += 1  # a stray byte before the next reply, skipped as any other)
    return bytes(buffer[start:end]), end


class FrameParser:
    """Incremental parser of image frames from a byte stream, tolerant of stray bytes.

    Feed it whatever arrived; it scans for ``##IMJ``, skips (and counts) bytes that cannot start a frame, rejects
    headers with a bad size code or length (and keeps scanning one byte further), then collects exactly the
    announced number of JPEG bytes. :attr:`bytes_needed` never reaches past the end of the current frame, so a
    reader that asks for exactly that many bytes never consumes a following reply.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._header: FrameHeader | None = None
        self.skipped_bytes = 0  # stray bytes discarded before the current frame
        self.last_rejection: str | None = None  # why the last ``##IMJ`` candidate was not a header
        self.saw_banner = False  # a ``##Version`` banner among the bytes skipped before the current frame
        self._skipped_tail = b""  # the last skipped bytes, to find a banner split between two drops

    def reset(self) -> None:
        """Forget buffered bytes, any half-read frame and the counters."""
        self._buffer.clear()
        self._header, self.skipped_bytes, self.last_rejection = None, 0, None
        self.saw_banner, self._skipped_tail = False, b""

    @property
    def header(self) -> FrameHeader | None:
        """The header of the frame being collected, or None while scanning."""
        return self._header

    @property
    def buffered(self) -> int:
        """Bytes held: a partial header while scanning, the JPEG bytes so far while collecting."""
        return len(self._buffer)

    @property
    def bytes_needed(self) -> int:
        """How many more bytes can be read without reading past the current frame (at least 1)."""
        if self._header is not None:
            return max(1, self._header.length - len(self._buffer))
        return max(1, FRAME_HEADER_LEN - len(self._buffer))

    def feed(self, data: bytes) -> list[ParsedFrame | BadFrame]:
        """Add bytes; return the frames (good or bad) completed by them, in order."""
        _check_bytes(data, "data")
        self._buffer += data
        out: list[ParsedFrame | BadFrame] = []
        while True:
            if self._header is None and not self._scan():
                return out
            if self._header is None or len(self._buffer) < self._header.length:
                return out
            out.append(self._finish_frame())

    def _scan(self) -> bool:
        """Advance to a valid header; True once one is parsed, False when more bytes are needed."""
        while True:
            at = self._buffer.find(FRAME_MAGIC)
            if at < 0:
                keep = _magic_prefix_len(self._buffer)
                self._drop(len(self._buffer) - keep)
                return False
            self._drop(at)
            if len(self._buffer) < FRAME_HEADER_LEN:
                return False
            try:
                self._header = parse_frame_header(bytes(self._buffer[:FRAME_HEADER_LEN]))
            except ProtocolError as err:
                self.last_rejection = str(err)
                self._drop(1)
                continue
            del self._buffer[:FRAME_HEADER_LEN]
            return True

    def _finish_frame(self) -> ParsedFrame | BadFrame:
        header = self._header  # not None: only called while collecting a frame
        jpeg = bytes(self._buffer[:header.length])
        del self._buffer[:header.length]
        skipped, self.skipped_bytes, self._header = self.skipped_bytes, 0, None
        banner, self.saw_banner, self._skipped_tail = self.saw_banner, False, b""
        try:
            check_jpeg(jpeg)
        except ProtocolError as err:
            return BadFrame(header=header, reason=str(err), skipped_bytes=skipped)
        return ParsedFrame(header=header, jpeg=jpeg, skipped_bytes=skipped, after_banner=banner)

    def _drop(self, count: int) -> None:
        if count > 0:
            window = self._skipped_tail + bytes(self._buffer[:count])
            self.saw_banner = self.saw_banner or VERSION_PREFIX in window
            self._skipped_tail = window[-(len(VERSION_PREFIX) - 1):]
            del self._buffer[:count]
            self.skipped_bytes += count


def _magic_prefix_len(buffer: bytearray) -> int:
    """Length of the longest suffix of ``buffer`` that is a proper prefix of ``##IMJ``."""
    for size in range(min(len(FRAME_MAGIC) - 1, len(buffer)), 0, -1):
        if buffer[-size:] == FRAME_MAGIC[:size]:
            return size
    return 0
