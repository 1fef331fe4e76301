"""One emulated SRV-1 Blackfin board as a pure state machine: bytes in, a reply plan out (no I/O).

Behaviour follows ``../shared/SVS_PROTOCOL.md`` (§n): the master prints a power-up banner, the slave nothing;
``V`` identifies; ``a b c d A`` set the size and ack ``#a #b #c #d``; ``q<digit>`` sets the JPEG quality;
``y Y o O`` ack with ``#`` + the command; ``t`` and ``D`` reply one line; ``I`` replies an ``##IMJ`` frame at the
current size; any other byte replies ``#?``. Once a command byte is taken, the rest of that input chunk, and
anything arriving within ``holdoff_s`` after its reply was sent, is discarded (§2).

Emulator choices the spec leaves open: ``q`` followed by a non-digit or 0/9 replies ``#?``; the JPEG quality
digit maps to OpenCV quality by :data:`JPEG_QUALITY_FOR_DIGIT`; the frame is colour 4:2:2 like the board's.
Faults (:class:`Faults`) change the replies to ``I`` and can be changed while the emulator runs.
"""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from .frames import FrameSource
from svs_torch.capture.protocol import encode_frame
from svs_torch.data.camera_frames import JPEG_QUALITY_FOR_DIGIT
from svs_torch.core.camera import SVS_CAMERA, SVS_RESOLUTIONS
from svs_torch.data.rig_deviation import RigDeviation, deviate_view

__all__ = ["Faults", "Reply", "CameraState", "JPEG_QUALITY_FOR_DIGIT", "version_line"]

_BUILD = "built:12:00:00 - Feb 14 2011"
_SIZE_COMMANDS = {ord("a"): ("3", b"#a"), ord("b"): ("5", b"#b"), ord("c"): ("7", b"#c"),
                  ord("d"): ("9", b"#d"), ord("A"): ("9", b"#d")}
_TOGGLES = {ord("y"): ("flipped", True), ord("Y"): ("flipped", False),
            ord("o"): ("overlay", True), ord("O"): ("overlay", False)}


def version_line(role: str) -> bytes:
    """The ``V`` reply of a stereo board whose role is ``"master"`` or ``"slave"`` (§3)."""
    return f"##Version - SRV-1 Blackfin w/PicoC v2.1 {_BUILD} (stereo {role})\r\n".encode("ascii")


@dataclass
class Faults:
    """Faults injected into the replies to ``I``; counters count down as they fire.

    Attributes:
        silent_grabs: the next n ``I`` get no reply at all (§3: the camera was busy).
        garbage_frames: the next n frames are preceded by ``garbage``.
        garbage: the stray bytes (by default they contain partial ``##IMJ`` magic to test the scanner).
        truncated_frames: the next n frames announce their full length but stop after half the JPEG.
        damaged_frames: the next n frames have 2 000 bytes from the middle of their JPEG zeroed (a link's bit
            errors): the length is right and libjpeg still decodes them, the lost blocks gray.
        wrong_length_frames: the next n frames announce ``len + wrong_length_delta`` bytes.
        wrong_length_delta: bytes added to the announced length (negative: announce fewer than sent).
        drip_chunk_bytes: when > 0, every reply is sent in chunks of this many bytes...
        drip_delay_s: ...with this pause between chunks, seconds.
        drop_after_frames: close the connection right after sending this many more frames (TCP only), once.
        grab_delay_s: time the board takes to grab and encode a frame before replying, seconds.
        frozen_grabs: the next n ``I`` are answered with the JPEG bytes of the board's last frame again (a stalled
            sensor whose firmware keeps sending the same frame buffer; a board that sent none yet sends one first).
    """

    silent_grabs: int = 0
    garbage_frames: int = 0
    garbage: bytes = b"\x00\xff#?##IM\r\n#IMJ##"
    truncated_frames: int = 0
    damaged_frames: int = 0
    wrong_length_frames: int = 0
    wrong_length_delta: int = 64
    drip_chunk_bytes: int = 0
    drip_delay_s: float = 0.0
    drop_after_frames: int | None = None
    grab_delay_s: float = 0.0
    frozen_grabs: int = 0


@dataclass(frozen=True)
class Reply:
    """What the board sends for one command, and how the I/O layer should send it.

    Attributes:
        data: the reply bytes.
        delay_s: wait before sending, seconds (grab time).
        chunk_bytes: send in chunks of this many bytes (0: all at once)...
        chunk_delay_s: ...with this pause between chunks, seconds.
        drop_after: close the connection once the reply is sent.
    """

    data: bytes
    delay_s: float = 0.0
    chunk_bytes: int = 0
    chunk_delay_s: float = 0.0
    drop_after: bool = False


class CameraState:
    """One board. ``camera`` is ``"left"`` or ``"right"`` (what the source renders), ``role`` ``"master"``/``"slave"``.

    Args:
        source: frame source, called as ``source(camera, width, height, time_s)``.
        holdoff_s: input is discarded for this long after a reply is sent, seconds.
        start_s: the clock reading at power-up (for ``t`` and the source's time), seconds.
        faults: initial faults (copied).
        low_battery: what ``D`` reports.
        noise_sigma: Gaussian sensor noise added to every frame before encoding, 8-bit levels (the OV9655's own
            noise, independent in each camera); 0: none.
        noise_seed: seed of this board's noise (``torch.Generator``); the two boards of a server get different
            seeds so their noise is independent.
        deviation: how this board's camera deviates from the ideal rig (a loosely mounted right board,
            :class:`~svs_torch.data.rig_deviation.RigDeviation`): each frame is seen through it, at the SVS lens's
            focal length for its size, before the noise; None: the ideal camera.
        view: the camera position whose view this board's sensor sends (``"left"`` or ``"right"``); None: its own,
            ``camera``. The other's: the two boards mounted in each other's place, their roles and links as wired.
    """

    def __init__(self, camera: str, role: str, source: FrameSource, *, holdoff_s: float = 0.001,
                 start_s: float = 0.0, faults: Faults | None = None, low_battery: bool = False,
                 noise_sigma: float = 0.0, noise_seed: int = 0, deviation: RigDeviation | None = None,
                 view: str | None = None) -> None:
        if not (np.isfinite(noise_sigma) and noise_sigma >= 0):
            raise ValueError(f"noise_sigma: expected a finite σ >= 0 in 8-bit levels, got {noise_sigma!r}")
        if deviation is not None and not isinstance(deviation, RigDeviation):
            raise ValueError(f"deviation: expected a RigDeviation or None, got {type(deviation).__name__}")
        self.deviation = None if deviation is None or deviation.is_identity else deviation
        self.noise_sigma = float(noise_sigma)
        self._noise = torch.Generator().manual_seed(noise_seed)
        self.camera = camera
        self.view = camera if view is None else view
        self.role = role
        self.source = source
        self.holdoff_s = holdoff_s
        self.start_s = start_s
        self.faults = dataclasses.replace(faults) if faults is not None else Faults()
        self.low_battery = low_battery
        self.size_code = "5"  # §3: 320×240 at power-on
        self.quality = 4  # §3: default quality digit
        self.flipped = False
        self.overlay = False
        self.frames_sent = 0
        self.discarded_bytes = 0
        self._last_jpeg: tuple[str, bytes] | None = None  # (size code, JPEG) of the last frame, for frozen_grabs
        self._pending_q = False
        self._busy_until_s = float("-inf")
        self._lock = threading.Lock()

    def banner(self) -> bytes:
        """What the board prints at power-up: the master's version and autorun lines, nothing for the slave."""
        if self.role != "master":
            return b""
        return version_line(self.role) + b"##checking for autorun() ... \r\n"

    def set_faults(self, **changes: object) -> None:
        """Change fault fields (names of :class:`Faults`) while running."""
        with self._lock:
            self.faults = dataclasses.replace(self.faults, **changes)

    def feed(self, data: bytes, now_s: float) -> Reply | None:
        """Take the bytes that arrived at ``now_s``; the reply to the command they complete, if any."""
        with self._lock:
            for at, byte in enumerate(data):
                if now_s < self._busy_until_s:
                    self.discarded_bytes += len(data) - at
                    return None
                if self._pending_q:
                    self._pending_q = False
                    reply = self._quality(byte)
                elif byte == ord("q"):
                    self._pending_q = True
                    continue
                else:
                    reply = self._command(byte, now_s)
                # The board handles one command at a time: the rest of this chunk arrived while it was busy.
                self.discarded_bytes += len(data) - at - 1
                self._busy_until_s = now_s + self.holdoff_s
                return reply
            return None

    def reply_sent(self, now_s: float) -> None:
        """Tell the board its reply went out at ``now_s``: input is discarded until ``now_s + holdoff_s``."""
        with self._lock:
            self._busy_until_s = max(self._busy_until_s, now_s + self.holdoff_s)

    def _quality(self, byte: int) -> Reply:
        digit = byte - ord("0")
        if not 1 <= digit <= 8:
            return Reply(b"#?")
        self.quality = digit
        return Reply(f"##quality - {digit}\r\n".encode("ascii"))

    def _command(self, byte: int, now_s: float) -> Reply | None:
        if byte == ord("V"):
            return Reply(version_line(self.role))
        if byte in _SIZE_COMMANDS:
            self.size_code, ack = _SIZE_COMMANDS[byte]
            return Reply(ack)
        if byte in _TOGGLES:
            name, value = _TOGGLES[byte]
            setattr(self, name, value)
            return Reply(b"#" + bytes([byte]))
        if byte == ord("t"):
            millis = int(max(0.0, now_s - self.start_s) * 1000)
            return Reply(f"##time - millisecs:  {millis}\r\n".encode("ascii"))
        if byte == ord("D"):
            state = "low battery voltage detected" if self.low_battery else "battery voltage okay"
            return Reply(f"##D - {state}\r\n".encode("ascii"))
        if byte == ord("I"):
            return self._grab(now_s)
        return Reply(b"#?")

    def encode_jpeg(self, now_s: float) -> bytes:
        """The current view as the board would encode it: current size, flip, overlay and quality."""
        width, height = SVS_RESOLUTIONS[self.size_code]
        image = np.ascontiguousarray(self.source(self.view, width, height, now_s - self.start_s))
        if image.shape != (height, width):
            raise ValueError(f"source: expected a ({height}, {width}) image, got {image.shape}")
        if self.deviation is not None:  # what the loosely mounted camera sees, then its sensor's noise
            image = deviate_view(image.astype(np.uint8), self.deviation, SVS_CAMERA.focal_px(width))
        if self.noise_sigma > 0:
            noise = torch.randn(image.shape, generator=self._noise, dtype=torch.float64).numpy() * self.noise_sigma
            image = np.clip(np.rint(image.astype(np.float64) + noise), 0, 255).astype(np.uint8)
        if self.flipped:
            image = image[::-1, ::-1]
        bgr = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_GRAY2BGR)
        if self.overlay:
            cv2.putText(bgr, f"{self.role} {self.frames_sent}", (4, 14), cv2.FONT_HERSHEY_PLAIN, 1.0,
                        (255, 255, 255), 1)
        params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY_FOR_DIGIT[self.quality],
                  cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422]
        ok, encoded = cv2.imencode(".jpg", bgr, params)
        if not ok:
            raise RuntimeError(f"{self.camera} emulator: JPEG encoding failed")
        return encoded.tobytes()

    def _grab(self, now_s: float) -> Reply | None:
        f = self.faults
        if f.silent_grabs > 0:
            f.silent_grabs -= 1
            return None
        if f.frozen_grabs > 0 and self._last_jpeg is not None and self._last_jpeg[0] == self.size_code:
            f.frozen_grabs -= 1
            jpeg = self._last_jpeg[1]  # the same bytes: the stalled sensor's buffer, sent again
        else:
            jpeg = self.encode_jpeg(now_s)
            self._last_jpeg = (self.size_code, jpeg)
        announced = len(jpeg)
        if f.wrong_length_frames > 0:
            f.wrong_length_frames -= 1
            announced = max(0, len(jpeg) + f.wrong_length_delta)
        if f.truncated_frames > 0:
            f.truncated_frames -= 1
            jpeg = jpeg[:len(jpeg) // 2]
        if f.damaged_frames > 0:
            f.damaged_frames -= 1
            middle = len(jpeg) // 2
            zeroed = max(0, min(2000, len(jpeg) - middle - 2))  # the end-of-image marker kept
            jpeg = jpeg[:middle] + bytes(zeroed) + jpeg[middle + zeroed:]
        data = encode_frame(self.size_code, jpeg, announced_length=announced)
        if f.garbage_frames > 0:
            f.garbage_frames -= 1
            data = f.garbage + data
        drop = False
        if f.drop_after_frames is not None:
            f.drop_after_frames -= 1
            if f.drop_after_frames <= 0:
                drop, f.drop_after_frames = True, None
        self.frames_sent += 1
        return Reply(data, delay_s=f.grab_delay_s, chunk_bytes=f.drip_chunk_bytes, chunk_delay_s=f.drip_delay_s,
                     drop_after=drop)
