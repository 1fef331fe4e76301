"""Capture from the Surveyor SVS stereo camera: the SRV-1 byte protocol, one board's link, the stereo pair.

``protocol`` is pure (bytes in, values out); ``link`` speaks it over pyserial (UART or ``socket://``);
``stereo`` grabs timestamped pairs and turns them into :class:`~svs_torch.core.types.StereoBatch`; ``guide`` holds the
reusable pieces of a live warning loop (rate-limited warnings, speech, frame-rate meter); ``link_types`` what a
link is configured with, counts and receives.

May import: ``svs_torch.core`` only (pyserial, no torch at import). The CLI imports it.
"""

from .guide import FpsMeter, LiveGuide, Speaker, WarningPolicy
from .link import CameraLink
from .link_types import CaptureError, DamagedFrameError, LinkConfig, LinkStats, RawFrame
from .protocol import FrameParser, ProtocolError, VersionInfo
from .stereo import Frame, PairBatch, StereoPair, SVSStereoCamera, decode_frame, to_stereo_batch

__all__ = [
    "CameraLink",
    "CaptureError",
    "DamagedFrameError",
    "FpsMeter",
    "Frame",
    "FrameParser",
    "LinkConfig",
    "LinkStats",
    "LiveGuide",
    "PairBatch",
    "ProtocolError",
    "RawFrame",
    "SVSStereoCamera",
    "Speaker",
    "StereoPair",
    "VersionInfo",
    "WarningPolicy",
    "decode_frame",
    "to_stereo_batch",
]
