"""The capture driver against hostile or odd device behaviour: ports already held, and the like."""

from __future__ import annotations

import os
import time

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
            with pytest.raises(CaptureError, match=r"right camera \(/dev/.*\): could not open the link: .*lock.*"
                                                   r"another program holds it"):
                second.open()
            assert first.identify().role == "master"  # the holder is untouched
        finally:
            first.close()
        second.open()  # free again once closed
        second.close()


def test_cli_capture_warns_of_pairs_whose_two_frames_are_one_image(tmp_path, capsys):
    # guide refuses a pair whose two frames are one image (identical_views: a relay or a URL that sent one board's
    # frame for both); capture saved such pairs without a word, though it warns of each kind guide refuses.
    import argparse

    from svs_torch.cli.capture import add_parser

    def run_capture(*argv: str) -> int:
        parser = argparse.ArgumentParser(prog="svs-depth")
        add_parser(parser.add_subparsers(dest="command", required=True))
        args = parser.parse_args(["capture", *argv])
        return args.func(args)

    for source, warned in ((flat_source, True), (lambda camera, *rest: flat_source(camera, *rest) // 2 + (
            camera == "left"), False)):
        out = tmp_path / str(warned)
        with EmulatorServer(left_port=0, right_port=0, source=source) as server:
            code = run_capture("--left", server.urls["left"], "--right", server.urls["right"], "--count", "2",
                               "--size", "160x120", "--out", str(out))
        err = capsys.readouterr().err
        assert code == 0 and "saved 2 pairs" in err
        assert ("warning: 2 of 2 pairs have one image for both cameras, pixel for pixel" in err) == warned, err


def test_the_emulators_urls_on_an_ipv6_host_are_ones_the_driver_opens():
    # python -m hw.emulator --host ::1 printed socket://::1:10001, which the driver refused ("expected
    # socket://HOST:PORT"): an IPv6 address in a URL is bracketed. (The host is set after binding: a machine without
    # IPv6 cannot bind ::1, and only the URL is in question.)
    from svs_torch.capture.link_types import check_link_url

    server = EmulatorServer(left_port=0, right_port=0, source=flat_source)
    try:
        server.host = "::1"
        urls = server.urls
        for name, url in urls.items():
            check_link_url(url, name)
        assert urls["left"].startswith("socket://[::1]:")
    finally:
        server.stop()


def test_the_emulator_refuses_an_image_step_its_clock_overflows(data_dir, capsys):
    # --image-step 5e-324 was taken (positive), and each grab's pair index overflowed ("cannot convert float
    # infinity to integer"): neither board sent a frame, the emulator looking alive.
    from hw.emulator_args import parse_args
    from hw.frames import ImageFolderSource

    with pytest.raises(SystemExit):
        parse_args(["--image-step", "5e-324"], "", 1.0)
    assert "--image-step: expected seconds from 1e-06, got '5e-324'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="step_s"):
        ImageFolderSource(data_dir / "opencv_samples", step_s=5e-324)
    assert parse_args(["--image-step", "0.001"], "", 1.0).image_step == 0.001
    source = ImageFolderSource(data_dir / "opencv_samples", step_s=1e-6)
    assert source("left", 160, 120, 1000.0).shape == (120, 160)


def test_the_emulators_drop_after_counts_frames_from_one(capsys):
    # --drop-after 0 was taken and dropped the link after the first frame, as --drop-after 1 does: refused.
    from hw.emulator_args import faults_from_args, parse_args

    with pytest.raises(SystemExit):
        parse_args(["--drop-after", "0"], "", 1.0)
    assert "argument --drop-after: expected a positive integer, got '0'" in capsys.readouterr().err
    assert faults_from_args(parse_args(["--drop-after", "1"], "", 1.0)).drop_after_frames == 1


def test_a_size_change_one_board_refused_gives_no_pair_of_two_sizes(monkeypatch):
    # set_size on both boards, the right one refusing: the left link was left at 640x480, and each link checks only
    # its own frames, so the next pairs joined a 640x480 left frame with a 320x240 right one, silently.
    from svs_torch.capture import SVSStereoCamera

    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server, \
            SVSStereoCamera(server.urls["left"], server.urls["right"], config=FAST, max_frame_gap_s=None) as camera:
        right = camera.links["right"]
        refused = CaptureError("right camera: sent b'c' 3 times, expected b'#c'")
        monkeypatch.setattr(right, "set_size", lambda code, **kwargs: (_ for _ in ()).throw(refused))
        with pytest.raises(CaptureError, match="expected b'#c'"):
            camera.set_size((640, 480))
        with pytest.raises(CaptureError, match=r"expected both frames at 320x240, got left 640x480, right 320x240"):
            camera.grab_pair()
        monkeypatch.undo()
        camera.set_size((640, 480))  # set again: whole pairs at the new size
        assert camera.grab_pair().right.size_wh == (640, 480)


def test_a_garbled_quality_echo_is_the_cameras_error_not_an_internal_one(monkeypatch):
    # A board whose '##quality - ' echo came garbled ('x' for the digit: the protocol has no checksums) ended
    # capture with "internal error: ProtocolError ... (please report it)": a CaptureError naming the camera now.
    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server:
        link = CameraLink(server.urls["right"], "right", FAST)
        link.open()
        try:
            monkeypatch.setattr(link, "command_line", lambda *args, **kwargs: b"##quality - x\r\n")
            with pytest.raises(CaptureError, match=r"right camera \(socket://.*\): sent quality 4, the board replied"):
                link.set_quality(4)
            assert link.quality is None
        finally:
            link.close()


@pytest.mark.parametrize("size_wh", [None, 320, (320,), (320, 240, 1), "320x240"])
def test_a_camera_size_that_is_not_a_pair_of_pixels_is_refused_by_name(size_wh):
    # SVSStereoCamera(..., size_wh=None) failed with "TypeError: 'NoneType' object is not iterable", naming nothing.
    from svs_torch.capture import SVSStereoCamera
    from svs_torch.core.errors import InputError

    with pytest.raises(InputError, match=r"size_wh: expected one of 160x120, 320x240, 640x480, 1280x1024, got"):
        SVSStereoCamera("socket://127.0.0.1:1", "socket://127.0.0.1:2", size_wh)
    from svs_torch.capture.protocol import size_code_for

    assert size_code_for(np.array([320, 240])) == "5"  # a sequence of another kind is still read


def test_the_emulator_drops_both_boards_links_at_once_and_the_camera_reconnects_both():
    # The WiFi module dropping takes both ports: drop_connection("both") was refused ("expected 'left', 'right'
    # (or 'both')"), though set_faults takes it and the error offered it.
    from svs_torch.capture import SVSStereoCamera

    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server, \
            SVSStereoCamera(server.urls["left"], server.urls["right"], config=FAST, max_frame_gap_s=None) as camera:
        camera.grab_pair()
        server.drop_connection("both")
        time.sleep(0.2)  # (the boards' threads close their clients within their poll)
        camera.grab_pair()
        assert [link.stats.reconnects for link in camera.links.values()] == [1, 1]
        with pytest.raises(ValueError, match="camera: expected 'left', 'right'"):
            server.drop_connection("middle")


@pytest.mark.parametrize("errno_, said", [
    (2, r"no such serial device: is the camera's USB serial adapter plugged in\?"),
    (13, r"your user may not open it: .*ls -l /dev/ttyUSB0; usually dialout: sudo usermod -aG dialout \$USER"),
    (16, "another program holds it"),
], ids=["missing", "permission", "busy"])
def test_a_serial_device_that_will_not_open_says_what_to_do(monkeypatch, errno_, said):
    # A wired SVS's user met pyserial's "[Errno 13] could not open port /dev/ttyUSB0: ... Permission denied" (no word
    # of the dialout group), "No such file or directory" and "Could not exclusively lock port", naming the camera and
    # its device but not what to do. (Errors faked: a test run as root opens any device.)
    import serial

    def refuse(url, **kwargs):
        raise serial.SerialException(errno_, f"could not open port {url}: [Errno {errno_}] {os.strerror(errno_)}")

    monkeypatch.setattr(serial, "serial_for_url", refuse)
    with pytest.raises(CaptureError, match=rf"left camera \(/dev/ttyUSB0\): could not open the link: .*; {said}"):
        CameraLink("/dev/ttyUSB0", "left", FAST).open()
    with pytest.raises(CaptureError) as refused:  # over WiFi, none of it applies
        CameraLink("socket://127.0.0.1:10001", "left", FAST).open()
    assert str(refused.value).endswith(os.strerror(errno_))


def test_a_device_missing_from_the_start_and_one_unplugged_mid_run_say_so():
    # An unplugged USB serial adapter's device node disappears: opening it said pyserial's "No such file or
    # directory" alone, and after pairs (the link dropped, then reopening failed) "could not open the link", as if
    # it never had. The emulator's pty disappears with it, as the adapter's node does.
    with pytest.raises(CaptureError, match=r"right camera \(/dev/h6-no-such-tty\): .*No such file.*plugged in"):
        CameraLink("/dev/h6-no-such-tty", "right", FAST).open()
    server = EmulatorServer(left_port=0, right_port=0, source=flat_source, use_pty=True).start()
    link = CameraLink(server.pty_paths["left"], "left", FAST)
    try:
        link.open()
        link.request_frame()
        assert link.read_frame().header.width == 320
        server.stop()
        assert not os.path.exists(link.url)
        link.request_frame()
        with pytest.raises(CaptureError, match=r"left camera \(/dev/.*\): .*No such file.*plugged in.* \(after the "
                                               r"link dropped: read: "):
            link.read_frame()
    finally:
        link.close()
        server.stop()


@pytest.mark.parametrize("answer, said", [
    (lambda sent: bytes((97 * i + 13) % 256 for i in range(3 * len(sent) + 20)),
     r"bytes that are no text: is --baud 115200 the board's UART speed\? The SVS's is 2304000"),
    (lambda sent: b"", r"0 bytes b'' \(is the board powered, its UART wired to the adapter, and at --baud 115200\?\)"),
], ids=["garbled", "silent"])
def test_a_serial_board_at_another_speed_or_silent_is_told_what_to_check(answer, said):
    # A port at another speed than the board's UART reads bytes that are no text: "expected a line starting
    # b'##Version' ..., last got 23 bytes b'\xa3\xfa7...'", with no word of --baud (an audit that served a pty
    # answering such bytes); a silent one "last got 0 bytes b''". A pty stands in for the USB serial adapter.
    import select
    import threading
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    stop = threading.Event()

    def board() -> None:
        while not stop.is_set():
            if select.select([master], [], [], 0.02)[0]:
                reply = answer(os.read(master, 4096))
                if reply:
                    os.write(master, reply)

    thread = threading.Thread(target=board, daemon=True)
    thread.start()
    link = CameraLink(os.ttyname(slave), "right", LinkConfig(baudrate=115_200, reply_timeout_s=0.1, max_retries=0,
                                                             drain_quiet_s=0.02, drain_max_s=0.05, poll_s=0.01))
    try:
        link.open()
        with pytest.raises(CaptureError, match=rf"right camera \(/dev/.*\): sent b'V' 1 times, .*{said}"):
            link.identify()
    finally:
        link.close()
        stop.set()
        thread.join()
        os.close(master)
        os.close(slave)
    from svs_torch.capture.link_types import got_words

    wifi = CameraLink("socket://127.0.0.1:1", "right")  # over WiFi, the module runs at the board's speed
    assert got_words(wifi, b"\xa3\xfa") == "2 bytes b'\\xa3\\xfa'"


def test_a_serial_write_that_times_out_names_the_flow_control_wires(monkeypatch):
    # RTS/CTS flow control is on (SVS_PROTOCOL.md §1): an adapter whose CTS wire does not reach the board sends no
    # byte, and the error said "link dropped while sending b'V' ...: write: Write timeout", nothing of the wires.
    import serial

    def stalled(self, data):
        raise serial.SerialTimeoutException("Write timeout")

    with EmulatorServer(left_port=0, right_port=0, source=flat_source, use_pty=True) as server:
        link = CameraLink(server.pty_paths["left"], "left", FAST)
        link.open()
        try:
            monkeypatch.setattr(type(link._serial), "write", stalled)
            with pytest.raises(CaptureError, match=r"left camera \(/dev/.*\): link dropped while sending b'V' .*"
                                                   r"write: Write timeout \(.*RTS/CTS flow control is on.*RTS and CTS"
                                                   r".*--no-flow-control for a 3-wire cable"):
                link.identify()
        finally:
            monkeypatch.undo()
            link.close()
