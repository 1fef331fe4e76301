"""What a link to one SVS board is configured with (:class:`LinkConfig`), counts (:class:`LinkStats`) and
receives (:class:`RawFrame`), and how it fails (:class:`CaptureError`, the words of :func:`frame_timeout_reason`
and :func:`attempt_reasons`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from ..core.camera import SVS_RESOLUTIONS
from ..core.errors import InputError
from .protocol import CMD_GRAB, FrameHeader, FrameParser, describe_bytes, max_jpeg_length

__all__ = ["CaptureError", "LinkConfig", "LinkStats", "RawFrame", "attempt_reasons", "check_link_url",
           "frame_timeout_reason", "got_words", "open_hint", "write_failure"]

#: pyserial's URL handlers a board can be reached through (a plain path is a serial device).
LINK_SCHEMES = ("socket", "rfc2217", "loop", "spy", "alt", "hwgrep", "cp2110")


def check_link_url(url: object, name: str) -> None:
    """``url`` (named ``name`` in the error) as a link pyserial can open: a serial device path or a URL of one of
    :data:`LINK_SCHEMES`, ``socket://`` with its host and port. Why: ``""``, ``None`` and ``socket://HOST`` failed
    inside pyserial ("could not open port :", "Port must be configured", "'<=' not supported between 'int' and
    'NoneType'"), and ``http://...`` as a capture error, not a bad argument. A link with a space before or after
    it (pasted) is refused too: ``" socket://..."`` passed ``urlsplit``, which strips it, and failed in pyserial
    ("protocol ' socket' not known"), a capture error with exit 1."""
    from urllib.parse import urlsplit

    if not isinstance(url, str) or not url.strip():
        raise InputError(f"{name}: expected a serial device or socket://HOST:PORT, got {url!r}")
    if url != url.strip():
        raise InputError(f"{name}: expected a serial device or socket://HOST:PORT with no space before or after "
                         f"it, got {url!r}")
    if "://" not in url:
        return  # a serial device
    parts = urlsplit(url)
    if parts.scheme not in LINK_SCHEMES:
        raise InputError(f"{name}: expected a serial device or socket://HOST:PORT, got {url!r}")
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme == "socket" and not (parts.hostname and port):
        raise InputError(f"{name}: expected socket://HOST:PORT (the left board 10001, the right 10002), got {url!r}")


def open_hint(url: str, err: BaseException) -> str:
    """What to do about a serial device ``url`` that would not open with ``err`` (pyserial's error, its errno), as
    ``"; ..."`` to follow it; ``""`` for a URL (``socket://``...) or an error with no known cause. Why: a wired SVS's
    user met "[Errno 13] ... Permission denied", "[Errno 2] ... No such file or directory" (an adapter unplugged,
    mid-run too) and "Could not exclusively lock port" with nothing said of what to do (an audit of the serial path).
    """
    import errno

    if "://" in url:
        return ""
    code = getattr(err, "errno", None)
    if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
        return ("; no such serial device: is the camera's USB serial adapter plugged in? (ls /dev/ttyUSB* "
                "/dev/ttyACM* lists those there)")
    if code in (errno.EACCES, errno.EPERM):
        return (f"; your user may not open it: add it to the device's group (ls -l {url}; usually dialout: "
                "sudo usermod -aG dialout $USER, then log in again)")
    if code in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY):
        return ("; another program holds it (a serial terminal, ModemManager, another svs-depth): close that "
                "program, or check that --left and --right are the two boards' own devices")
    if "Inappropriate ioctl" in str(err) or code == errno.EISDIR:
        return "; it is no serial device: give the USB serial adapter's, e.g. /dev/ttyUSB0"
    return ""


def got_words(link: object, received: bytes) -> str:
    """What a ``link`` (a :class:`~.link.CameraLink`) got instead of a command's reply, said for its error: ``received``
    as :func:`~.protocol.describe_bytes` gives it, and on a serial device what to check where those bytes are mostly no
    text (the port at another speed than the board's UART) or there were none. Why: a wired SVS's user who gave the
    wrong ``--baud`` read "expected a line starting b'##Version' ..., last got 23 bytes b'\\xa3\\xfa7...'" and no
    word of the speed (an audit of the serial path; hw/README.md named it, the error did not)."""
    said = describe_bytes(received)
    if "://" in link.url:  # over WiFi the module, not this port, runs at the board's speed
        return said
    baud = link.config.baudrate
    if not received:
        return f"{said} (is the board powered, its UART wired to the adapter, and at --baud {baud}?)"
    text = sum(32 <= byte < 127 or byte in b"\r\n" for byte in received)
    if text < 0.6 * len(received):
        return (f"{said} (bytes that are no text: is --baud {baud} the board's UART speed? The SVS's is 2304000 "
                "(or try 2530000, its actual rate), some builds' 115200)")
    return said


def write_failure(url: str, err: BaseException) -> str:
    """How a link to ``url`` says that a write failed with ``err``; on a serial device, a write that timed out
    (pyserial's ``SerialTimeoutException``) says why it may have. Why: a UART with RTS/CTS flow control (§1, on
    unless ``--no-flow-control``) sends no byte while the board holds its CTS line low (an adapter without those
    wires), and a wired SVS's user read "link dropped while sending b'V' ...: write: Write timeout", no word of the
    wires (an audit)."""
    said = f"write: {err}"
    if "://" in url or type(err).__name__ != "SerialTimeoutException":
        return said
    return (f"{said} (the adapter sent no byte: RTS/CTS flow control is on, as the SVS's UART wants, so check that the "
            "adapter's RTS and CTS wires reach the board's, or give --no-flow-control for a 3-wire cable)")


class CaptureError(RuntimeError):
    """A camera link failed; the message names the camera, its URL, and what was expected vs received. ``camera``:
    ``"left"`` or ``"right"`` where one board of a stereo camera failed (``guide`` says which), else None."""

    camera: str | None = None


class DamagedFrameError(CaptureError):
    """A frame arrived whole (its announced length) but its JPEG data was damaged on the way: libjpeg decodes
    it with its lost blocks gray, an image that is not the scene (:func:`svs_torch.capture.stereo.decode_frame`)."""


@dataclass(frozen=True)
class LinkConfig:
    """Settings of one camera link (times in seconds); the defaults suit a real SVS."""

    baudrate: int = 2_304_000  # UART baud, 8N1 (§1; a 115,200 build exists); ignored by socket://
    rtscts: bool = True  # UART hardware flow control (§1)
    # Throughput for transfer timeouts, bytes/s; None = baudrate / 10 (8N1 sends 10 bits a byte). Right for
    # socket:// too: the board's UART is the bottleneck behind the WiFi module.
    link_bytes_per_s: float | None = None
    reply_timeout_s: float = 1.0  # command sent → short reply complete, or frame header in (grab + encode)
    transfer_margin_s: float = 0.5  # added to a frame's nominal transfer time
    transfer_slack: float = 1.5  # factor on a frame's nominal transfer time
    max_retries: int = 2  # extra attempts after a silent or broken reply (§3: I sometimes returns nothing)
    max_reconnects: int = 2  # reopenings of a dropped link per command
    reconnect_delay_s: float = 0.2  # pause before each reopening
    command_gap_s: float = 0.002  # pause after a reply before the next command (§2: input discarded just after;
    # the link widens it where a board proves slower: link.HOLD_OFF_SUSPECT_S)
    drain_quiet_s: float = 0.05  # resync: discard input until nothing arrived for this long...
    drain_max_s: float = 0.5  # ...or for at most this long
    poll_s: float = 0.02  # pyserial read timeout; deadlines are honoured to within it
    write_timeout_s: float = 1.0  # pyserial write timeout (a UART stalled by RTS/CTS)

    def __post_init__(self) -> None:
        """Each field a value the link can wait by, refused by name. Why: a reply_timeout_s of 0, -1 or NaN was taken
        and opening said the boards did not answer 'V' "within nan s"; poll_s -1 failed inside pyserial ("Not a valid
        timeout"); max_retries -1 "sent b'V' 0 times"; link_bytes_per_s -1 gave every frame a negative time."""
        for item in fields(self):
            value, name = getattr(self, item.name), item.name
            if name == "rtscts" or (name == "link_bytes_per_s" and value is None):
                continue
            whole = name in ("baudrate", "max_retries", "max_reconnects")
            number = not isinstance(value, bool) and isinstance(value, int if whole else (int, float))
            # A wait of 0 never reads a reply, an endless one hangs on a silent board; pauses may be 0.
            positive = name in ("baudrate", "reply_timeout_s", "transfer_slack", "poll_s", "write_timeout_s")
            if not (number and math.isfinite(value) and (value > 0 if positive else value >= 0)):
                seconds = name.endswith("_s") and name != "link_bytes_per_s"
                kind = "an integer" if whole else "a finite number of seconds" if seconds else "a finite number"
                raise InputError(f"LinkConfig.{name}: expected {kind} {'> 0' if positive else '>= 0'}, got {value!r}")

    @property
    def bytes_per_s(self) -> float:
        """Throughput used for transfer timeouts, bytes/s."""
        return self.link_bytes_per_s if self.link_bytes_per_s else self.baudrate / 10.0

    def transfer_timeout_s(self, length: int) -> float:
        """Seconds allowed for ``length`` JPEG bytes after their header."""
        return self.transfer_margin_s + self.transfer_slack * length / self.bytes_per_s

    def frame_attempt_timeout_s(self, size_code: str) -> float:
        """Worst-case seconds of one ``I`` attempt at a size code (largest plausible JPEG, then a drain)."""
        width, height = SVS_RESOLUTIONS[size_code]
        return (self.command_gap_s + self.reply_timeout_s + self.transfer_timeout_s(max_jpeg_length(width, height))
                + self.drain_max_s + 2 * self.poll_s)


@dataclass
class LinkStats:
    """Counters of one link since it was created."""

    frames: int = 0  # good frames returned
    retries: int = 0  # commands re-sent after a silent or broken reply
    reconnects: int = 0  # links reopened after a drop
    stray_bytes: int = 0  # bytes skipped or drained that belonged to no expected reply
    stale_inputs: int = 0  # grabs before which bytes already waiting (a late reply) were dropped
    command_gap_s: float | None = None  # the pause before each command, where silences widened it (None: the config's)
    failures: list[str] = field(default_factory=list)  # the last few failure descriptions, newest last


@dataclass(frozen=True)
class RawFrame:
    """One frame as received: the header, the JPEG bytes exactly as the board sent them, and when they came."""

    header: FrameHeader  # size code, width, height, JPEG length
    jpeg: bytes
    request_monotonic_s: float  # time.monotonic() when the I that produced this frame was sent
    arrival_monotonic_s: float  # time.monotonic() when the frame's last byte was read
    arrival_wall_s: float  # time.time() at the same moment (Unix seconds)
    attempts: int  # I commands sent for this frame (1 = no retry)
    skipped_bytes: int  # stray bytes skipped before the header
    # time.monotonic() when the frame's header was read: the board had grabbed and encoded the frame, and its JPEG's
    # bytes follow, as many as the scene makes (None: not known, a frame made by hand; the arrival stands in)
    header_monotonic_s: float | None = None


class _Dropped(Exception):
    """Internal: the link broke (EOF, reset, device gone); carries the original error text."""


@dataclass
class _Attempt:
    """Internal: why one frame attempt failed."""

    reason: str
    wrong_size: bool = False
    silent: bool = False  # nothing at all came back


def frame_timeout_reason(cfg: LinkConfig, size_code: str | None, parser: FrameParser, received: bytes,
                         silent_s: float = 0.0) -> str:
    """Why a frame attempt of a link (``cfg``, its ``size_code``) got no frame: ``parser`` fed what came, ``received``
    its first bytes, ``silent_s`` how long nothing had come when it timed out."""
    if parser.header is not None:
        h = parser.header
        window = cfg.transfer_timeout_s(h.length)
        # A board whose UART is slower than the link assumes (a 115,200-baud build behind the WiFi module too)
        # sends too slowly for the transfer timeout: say which speed was assumed. One that stopped sending
        # (a frame cut on the link) is said so: a slower --baud would not help it.
        why = (f"nothing came for the last {silent_s:.2f} s: the frame was cut short" if silent_s >= window / 2
               else f"the timeout assumes {cfg.bytes_per_s * 10:,.0f} baud: a slower board's --baud")
        return (f"expected {h.length} JPEG bytes of a {h.width}x{h.height} frame within {window:.2f} s of its "
                f"header, got {parser.buffered} ({why})")
    size = f" of {'x'.join(map(str, SVS_RESOLUTIONS[size_code]))}" if size_code else ""
    reason = (f"sent {CMD_GRAB!r}, expected a '##IMJ' frame{size} within {cfg.reply_timeout_s:g} s, "
              f"got {describe_bytes(received)}")
    if parser.last_rejection:
        reason += f" (rejected: {parser.last_rejection})"
    return reason


def attempt_reasons(first: str, last: str) -> str:
    """The failed attempts' reasons a link's error gives: the first one's too where the last differs. Why: a board
    slower than --baud assumes timed out first with that hint, and its retries then met the rest of that frame's
    JPEG bytes, so the error gave only "expected a '##IMJ' frame ..., got 64 bytes b'!..." (an audit)."""
    return f"last attempt: {last}" if first == last else f"first attempt: {first}; last attempt: {last}"
