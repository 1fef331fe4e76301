"""What a grab of the SVS stereo camera gives (:mod:`.stereo`): each board's decoded frame, a pair of them, and a batch
of pairs as :meth:`~.stereo.SVSStereoCamera.stream_batches` yields it.

A pair's two frames are two boards' grabs, not hardware-synchronised (``SVS_PROTOCOL.md`` §1): how far apart they
were taken is known from when each board began its reply (the frame's header, sent once the board had grabbed and
encoded it), not from when its last byte came, which follows as many bytes as the scene made the JPEG: on a slow
link (a 115,200-baud build) two frames of one moment ended 0.4 s apart by their lengths alone (an audit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.image_files import JPEG_GRAY_DECODE, damaged_jpeg, declared_size, decode_collecting
from ..core.types import StereoBatch
from .link_types import CaptureError, DamagedFrameError, RawFrame

__all__ = ["Frame", "PairBatch", "StereoPair", "decode_frame", "time_between_frames_s"]


@dataclass(frozen=True)
class Frame:
    """One decoded frame of one camera.

    Attributes:
        camera: ``"left"`` or ``"right"``.
        image: grayscale ``(H, W)`` uint8, decoded from ``jpeg``.
        jpeg: the JPEG bytes exactly as the board sent them (colour, 4:2:2).
        request_monotonic_s: ``time.monotonic()`` when the ``I`` for this frame was sent, seconds.
        arrival_monotonic_s: ``time.monotonic()`` when its last byte arrived, seconds.
        arrival_wall_s: ``time.time()`` at arrival (Unix seconds).
        attempts: ``I`` commands it took (1 = no retry).
        header_monotonic_s: ``time.monotonic()`` when its frame header arrived, the board's frame grabbed and encoded
            (None: not known, a frame made by hand), seconds.
    """

    camera: str
    image: np.ndarray
    jpeg: bytes
    request_monotonic_s: float
    arrival_monotonic_s: float
    arrival_wall_s: float
    attempts: int
    header_monotonic_s: float | None = None

    @property
    def size_wh(self) -> tuple[int, int]:
        return self.image.shape[1], self.image.shape[0]


@dataclass(frozen=True)
class StereoPair:
    """A left and a right frame grabbed together.

    Attributes:
        index: sequence number of the pair since the camera was opened.
        left, right: the frames.
        time_between_frames_s: :func:`time_between_frames_s` of the two, seconds (signed: right − left).
    """

    index: int
    left: Frame
    right: Frame
    time_between_frames_s: float


@dataclass(frozen=True)
class PairBatch:
    """One item of :meth:`SVSStereoCamera.stream_batches`: the batch, its pairs, and how many pairs were skipped."""

    batch: StereoBatch
    pairs: tuple[StereoPair, ...]
    num_dropped: int


def decode_frame(raw: RawFrame, camera: str, where: str) -> Frame:
    """Decode a received JPEG to grayscale (as ``estimate`` reads a file); raises :class:`CaptureError` naming
    ``where`` if it is not a JPEG, and :class:`DamagedFrameError` (the pair is grabbed again) if it does not decode
    to the size its frame header announced, or libjpeg says its image data was damaged (it decodes, its lost
    blocks gray: ranged, a gray block is a wall that is not there)."""
    want = (raw.header.height, raw.header.width)
    if raw.jpeg[:2] != b"\xff\xd8":
        raise CaptureError(f"{where}: expected a JPEG of {want[1]}x{want[0]}, got no JPEG in {len(raw.jpeg)} bytes")
    # The size its JPEG header declares, before decoding: a frame whose SOF said 30000x30000 (78 kB, it passes the
    # link's length and marker checks) took 3.4 s and 2 GB to decode before the size refused it. A size other
    # than the announced one, as a frame that does not decode, is grabbed again (one such frame stopped capture).
    declared = declared_size(raw.jpeg)
    if declared is not None and declared != want[::-1]:
        raise DamagedFrameError(f"{where}: expected a JPEG of {want[1]}x{want[0]}, got a header declaring "
                                f"{declared[0]}x{declared[1]} in {len(raw.jpeg)} bytes")
    image, complaints = decode_collecting(np.frombuffer(raw.jpeg, dtype=np.uint8), JPEG_GRAY_DECODE)
    if image is None or image.shape != want:
        got = "nothing" if image is None else f"{image.shape[1]}x{image.shape[0]}"
        raise DamagedFrameError(f"{where}: expected a JPEG of {want[1]}x{want[0]}, decoded {got} "
                                f"from {len(raw.jpeg)} bytes")
    damaged = damaged_jpeg(complaints)
    if damaged is not None:
        raise DamagedFrameError(f"{where}: a JPEG damaged on the link (libjpeg: {damaged}), {len(raw.jpeg)} bytes")
    return Frame(camera=camera, image=image, jpeg=raw.jpeg, request_monotonic_s=raw.request_monotonic_s,
                 arrival_monotonic_s=raw.arrival_monotonic_s, arrival_wall_s=raw.arrival_wall_s,
                 attempts=raw.attempts, header_monotonic_s=raw.header_monotonic_s)


def time_between_frames_s(left: Frame, right: Frame) -> float:
    """How far apart two boards' frames were taken, right − left, seconds: from when each frame's header arrived
    (each board grabs and encodes, then sends the header and the JPEG), else, for a frame without it, from when
    its last byte did. Not the last bytes' gap: on a slow link that is mostly the two JPEGs' lengths (at 115,200
    baud, 50 and 55 kB of one 640x480 moment ended 0.4 s apart, and every pair was grabbed again and refused)."""
    if left.header_monotonic_s is None or right.header_monotonic_s is None:
        return right.arrival_monotonic_s - left.arrival_monotonic_s
    return right.header_monotonic_s - left.header_monotonic_s
