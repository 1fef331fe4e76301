"""Capture from the Surveyor SVS stereo camera: the SRV-1 byte protocol, one board's link, the stereo pair.

``protocol`` is pure (bytes in, values out); ``link`` speaks it over pyserial (UART or ``socket://``);
``stereo`` grabs timestamped pairs and turns them into :class:`~svs_torch.core.types.StereoBatch`; ``guide`` holds the
reusable pieces of a live warning loop (rate-limited warnings, speech, frame-rate meter), with ``speech``
(``espeak-ng`` when installed, the text always), ``sight`` (whether guide can see: silence must never mean
"nothing measured") and ``frozen`` (whether one board keeps sending one frame); ``link_types`` what a link is
configured with, counts and receives.

May import: ``svs_torch.core`` only (pyserial; torch only where ``stereo`` and ``frozen`` are used). The CLI imports
it.
"""

from ..core.lazy_names import lazy_names

#: Each name's submodule, imported on first use (PEP 562): ``svs_torch.capture.protocol`` and ``link_types`` load
#: without torch, so ``capture`` and ``guide`` check their arguments in a fraction of a second (an audit: a missing
#: --left took 3 s to be told, the time torch takes to load, which ``stereo`` needs).
_SUBMODULE = {
    "FpsMeter": "guide", "LiveGuide": "guide", "Speaker": "speech", "WarningPolicy": "guide",
    "CameraLink": "link",
    "CaptureError": "link_types", "DamagedFrameError": "link_types", "LinkConfig": "link_types",
    "LinkStats": "link_types", "RawFrame": "link_types",
    "FrameParser": "protocol", "ProtocolError": "protocol", "VersionInfo": "protocol",
    "Frame": "stereo", "PairBatch": "stereo", "StereoPair": "stereo", "SVSStereoCamera": "stereo",
    "decode_frame": "stereo", "to_stereo_batch": "stereo",
}
__getattr__, __dir__ = lazy_names(__name__, _SUBMODULE)
__all__ = sorted(_SUBMODULE)
