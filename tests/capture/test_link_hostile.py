"""The capture driver against hostile or odd device behaviour: ports already held, and the like."""

from __future__ import annotations

import numpy as np
import pytest
from hw.emulator import EmulatorServer

from svs_torch.capture import CameraLink, CaptureError, LinkConfig

FAST = LinkConfig(reply_timeout_s=0.25, transfer_margin_s=0.1, reconnect_delay_s=0.05, drain_quiet_s=0.02,
                  drain_max_s=0.2, poll_s=0.01)


def flat_source(camera: str, width: int, height: int, time_s: float) -> np.ndarray:
    return np.random.default_rng(width).integers(0, 200, (height, width), dtype=np.uint8)


def test_a_serial_device_another_link_holds_is_refused_not_shared():
    # Two programs on one /dev/ttyUSB0 (or one camera's device reached by two paths) each read part of the other's
    # replies, and both failed on frames "cut short": the second is refused at once, naming the camera.
    with EmulatorServer(left_port=0, right_port=0, source=flat_source, use_pty=True) as server:
        path = server.pty_paths["left"]
        first = CameraLink(path, "left", FAST)
        first.open()
        try:
            second = CameraLink(path, "right", FAST)
            with pytest.raises(CaptureError, match=r"right camera \(/dev/.*\): could not open the link: .*lock"):
                second.open()
            assert first.identify().role == "master"  # the holder is untouched
        finally:
            first.close()
        second.open()  # free again once closed
        second.close()
