"""The capture driver against the SVS emulator (loopback TCP on free ports, and pseudo-terminals).

The emulator's board logic is tested on its own first (pure: bytes in, reply out), then the driver is run
against it, fault by fault: each injected fault must either be recovered from or end in a CaptureError that
names the camera and URL, within the bound the link states. Real-device tests are marked ``hardware``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import socket
import time
import weakref

import cv2
import numpy as np
import pytest
import torch
from hw.emulator import EmulatorServer
from hw.emulator_state import CameraState, Faults, version_line
from hw.frames import ImageFolderSource, ObstacleTrack, SyntheticSource

from svs_torch.capture import CaptureError, LinkConfig, SVSStereoCamera, to_stereo_batch
from svs_torch.capture.command_gap import HOLD_OFF_STEP_S
from svs_torch.capture.protocol import FrameParser, ParsedFrame
from svs_torch.core.camera import SVS_CAMERA
from svs_torch.core.checks import InputError

# Short timeouts keep the whole file fast; loopback delivers a frame in well under a millisecond.
FAST = LinkConfig(reply_timeout_s=0.25, transfer_margin_s=0.1, reconnect_delay_s=0.05, drain_quiet_s=0.02,
                  drain_max_s=0.2, poll_s=0.01)


_TEXTURES: dict[tuple[int, int], np.ndarray] = {}


def flat_source(camera: str, width: int, height: int, time_s: float) -> np.ndarray:
    """A cheap deterministic frame: seeded noise (JPEGs of realistic size, ~20 KB at 320x240), left brighter."""
    if (width, height) not in _TEXTURES:
        _TEXTURES[(width, height)] = np.random.default_rng(width).integers(0, 200, (height, width), dtype=np.uint8)
    return _TEXTURES[(width, height)] + np.uint8(40 if camera == "left" else 0)


def attempt_bound_s(config: LinkConfig = FAST, code: str = "5") -> float:
    """The link's stated worst case for one frame (all retries), plus scheduling slack on a shared machine."""
    return (config.max_retries + 1) * config.frame_attempt_timeout_s(code) + 0.5


@pytest.fixture
def emulator():
    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server:
        yield server


@pytest.fixture
def camera(emulator):
    # The link's own retries are what these tests count: a pair is not grabbed again for its frames' gap here
    # (test_a_pair_whose_frames_came_apart_is_grabbed_again).
    with SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], config=FAST, max_frame_gap_s=None) as cam:
        yield cam


# ------------------------------------------------------------------------------------- board logic (pure)

def make_board(role: str = "master", **kwargs) -> CameraState:
    return CameraState("left" if role == "master" else "right", role, flat_source, **kwargs)


def test_board_banner_only_on_master():
    assert make_board("master").banner().startswith(version_line("master"))
    assert make_board("slave").banner() == b""


def test_board_commands():
    board, now = make_board("slave", holdoff_s=0.0), 0.0
    expected = {b"V": version_line("slave"), b"a": b"#a", b"b": b"#b", b"c": b"#c", b"d": b"#d", b"A": b"#d",
                b"y": b"#y", b"Y": b"#Y", b"o": b"#o", b"O": b"#O", b"q7": b"##quality - 7\r\n",
                b"q9": b"#?", b"x": b"#?", b"D": b"##D - battery voltage okay\r\n"}
    for command, reply in expected.items():
        now += 1.0
        assert board.feed(command, now).data == reply, command
    assert board.feed(b"t", 20.5).data == b"##time - millisecs:  20500\r\n"
    assert board.size_code == "9" and board.quality == 7


@pytest.mark.parametrize("command, code, size", [(b"a", "3", (160, 120)), (b"b", "5", (320, 240)),
                                                 (b"c", "7", (640, 480)), (b"A", "9", (1280, 1024))])
def test_board_frame_at_current_size(command, code, size):
    board = make_board()
    board.feed(command, 0.0)
    (event,) = FrameParser().feed(board.feed(b"I", 1.0).data)
    assert isinstance(event, ParsedFrame) and event.header.size_code == code
    assert (event.header.width, event.header.height) == size


def _frame_pixels(board: CameraState, now_s: float) -> np.ndarray:
    import cv2

    (event,) = FrameParser().feed(board.feed(b"I", now_s).data)
    return cv2.imdecode(np.frombuffer(event.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE).astype(np.float64)


def test_board_sensor_noise_is_gaussian_seeded_and_independent():
    """--noise-sigma: each frame gets fresh Gaussian noise of the given σ before the JPEG, reproducible from the
    seed and independent between boards with different seeds; σ 0 is the noise-free frame."""
    quiet, noisy, same, other = (make_board(holdoff_s=0.0, noise_sigma=sigma, noise_seed=seed)
                                 for sigma, seed in ((0.0, 0), (6.0, 0), (6.0, 0), (6.0, 1)))
    for board in (quiet, noisy, same, other):
        board.feed(b"q1", 0.0)  # the best quality: the JPEG keeps most of the noise
    clean = _frame_pixels(quiet, 1.0)
    first, second = _frame_pixels(noisy, 1.0), _frame_pixels(noisy, 2.0)
    # flat_source's texture spans 40-240 for the left board: no clipping, so the difference is the noise + JPEG.
    assert 5.0 < float((first - clean).std()) < 7.5 and abs(float((first - clean).mean())) < 0.5
    assert float((second - first).std()) > 7  # a new draw each frame
    assert np.array_equal(first, _frame_pixels(same, 1.0))  # seeded
    assert float((_frame_pixels(other, 1.0) - first).std()) > 7  # another seed: independent noise (√2·σ apart)
    with pytest.raises(ValueError, match="noise_sigma"):
        make_board(noise_sigma=-1.0)


def test_a_loosely_mounted_right_board_is_seen_through_its_deviation_and_ranged_as_the_ideal_rig():
    """hw.emulator --right-roll-deg ... / svs-depth guide --emulator --emulator-loose-rig: the right board's frame is
    what deviate_view makes of the ideal camera's view (before its JPEG), the left board's is untouched, and the
    pipeline aligns the loose pair and ranges it as the ideal rig's (the same obstacle within 1 %)."""
    from hw.emulator_args import parse_args
    from svs_torch.core.types import StereoBatch
    from svs_torch.data.rig_deviation import LOOSE_RIG, RigDeviation, deviate_view
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    source = SyntheticSource(renderer="simple")

    def frame(board: CameraState) -> np.ndarray:
        board.feed(b"q1", 3.0)  # the best quality: the frame is the view to a level or two
        (event,) = FrameParser().feed(board.feed(b"I", 3.5).data)
        return cv2.imdecode(np.frombuffer(event.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)

    left = frame(CameraState("left", "master", source, holdoff_s=0.0))
    ideal = frame(CameraState("right", "slave", source, holdoff_s=0.0))
    loose = frame(CameraState("right", "slave", source, holdoff_s=0.0, deviation=LOOSE_RIG))
    seen = deviate_view(source("right", 320, 240, 3.5), LOOSE_RIG, SVS_CAMERA.focal_px(320))
    assert float(np.abs(loose.astype(float) - seen).mean()) < 2 < float(np.abs(loose.astype(float) - ideal).mean())
    views = lambda frames: torch.from_numpy(np.stack(frames))[:, None].float() / 255  # noqa: E731
    batch = StereoBatch.from_images(views([left, left]), views([ideal, loose]), focal_px=SVS_CAMERA.focal_px(320),
                                    baseline_m=SVS_CAMERA.baseline_m)
    result = estimate_obstacle_depth(batch, PipelineConfig())
    assert result.status.tolist() == [0, 0] and result.row_aligned.tolist() == [False, True]
    ideal_m, loose_m = result.depth.nearest.depth_m.tolist()
    assert loose_m == pytest.approx(ideal_m, rel=0.01)
    # The emulator's options: only the right board deviates; no option, no deviation; a roll of 90° refused.
    args = parse_args(["--right-roll-deg", "1", "--right-shift-percent", "-2", "--right-gain-percent", "-20"], "", 1.0)
    assert args.right_deviation == RigDeviation(roll_deg=1.0, shift_y_fraction=-0.02, gain=-0.2)
    assert parse_args([], "", 1.0).right_deviation is None
    with pytest.raises(SystemExit):
        parse_args(["--right-roll-deg", "90"], "", 1.0)
    with EmulatorServer(left_port=0, right_port=0, source=source, right_deviation=LOOSE_RIG) as server:
        assert server.cameras["left"].deviation is None and server.cameras["right"].deviation == LOOSE_RIG


def test_board_discards_input_while_busy():
    board = make_board(holdoff_s=0.01)
    assert board.feed(b"VV", 0.0).data == version_line("master")  # the second V arrived while busy
    board.reply_sent(1.0)
    assert board.feed(b"V", 1.005) is None  # within the hold-off after the reply
    assert board.feed(b"V", 1.02).data == version_line("master")
    assert board.discarded_bytes == 2
    board.feed(b"q", 2.0)  # a parameter byte is part of its command, even in another chunk
    assert board.feed(b"2", 2.0).data == b"##quality - 2\r\n"


def test_board_faults_count_down():
    board = make_board(faults=Faults(silent_grabs=1, garbage_frames=1, truncated_frames=1))
    assert board.feed(b"I", 0.0) is None
    data = board.feed(b"I", 1.0).data
    assert data.startswith(Faults().garbage)
    assert FrameParser().feed(data) == []  # truncated: the header announces more than was sent
    (event,) = FrameParser().feed(board.feed(b"I", 2.0).data)
    assert isinstance(event, ParsedFrame) and event.skipped_bytes == 0


def test_the_emulators_freeze_fault_sends_the_last_frames_bytes_again():
    """A stalled sensor: the board answers each grab with its last frame's buffer again (``--freeze N``)."""
    from hw.emulator_args import faults_from_args, parse_args

    def source(camera, width, height, time_s):
        return np.random.default_rng(int(time_s * 1000)).integers(0, 255, (height, width), dtype=np.uint8)

    board = CameraState("left", "master", source, holdoff_s=0.0, faults=Faults(frozen_grabs=2))
    jpegs = [FrameParser().feed(board.feed(b"I", float(grab)).data)[0].jpeg for grab in range(4)]
    assert jpegs[0] == jpegs[1] == jpegs[2] != jpegs[3] and board.faults.frozen_grabs == 0
    board.set_faults(frozen_grabs=1)
    board.feed(b"a", 5.0)  # 160x120: a frame of the old size is not sent under the new size's header
    (event,) = FrameParser().feed(board.feed(b"I", 6.0).data)
    assert event.jpeg != jpegs[3] and cv2.imdecode(np.frombuffer(event.jpeg, np.uint8), 0).shape == (120, 160)
    assert board.faults.frozen_grabs == 1
    args = parse_args(["--freeze", "3", "--fault-camera", "right"], "emulator", 1.0)
    assert faults_from_args(args).frozen_grabs == 3


def test_synthetic_source_depths_oscillate_in_range():
    track = ObstacleTrack()
    depths = np.stack([track.depths_m(i) for i in range(track.num_keyframes)])
    assert depths.min() >= 0.8 - 1e-9 and depths.max() <= 3.0 + 1e-9
    assert depths.max() - depths.min() > 2.0
    source = SyntheticSource(renderer="simple")
    left, right = source("left", 320, 240, 0.0), source("right", 320, 240, 0.0)
    assert left.shape == (240, 320) and left.dtype == np.uint8 and not np.array_equal(left, right)


def test_the_stand_in_frames_wall_has_its_own_disparity():
    """Found by an audit: the stand-in renderer (--simple-frames, and every emulator's first frames before
    --prepare's) drew the 4 m wall at a disparity of -7 px, which the pipeline ranged as obstacles 0.3-0.6 m
    ahead ("Stop"). The wall's disparity is f B / 4 m: the left row equals the right row shifted by it; and the
    pipeline ranges the rectangles at their depths."""
    from hw.frames import render_simple_pair

    from svs_torch.core.types import StereoBatch
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    depths = np.array([1.9, 0.9])
    left, right = render_simple_pair(depths, np.array([[-0.3, 0.0], [0.25, 0.0]]), np.array([[0.3, 0.4]] * 2),
                                     (320, 240))
    shift = int(round(SVS_CAMERA.focal_px(320) * SVS_CAMERA.baseline_m / 4.0))
    assert np.array_equal(left[:8, shift:], right[:8, :320 - shift])  # the top rows: wall only
    batch = StereoBatch.from_images(torch.from_numpy(left / 255.0).float()[None, None],
                                    torch.from_numpy(right / 255.0).float()[None, None],
                                    SVS_CAMERA.focal_px(320), SVS_CAMERA.baseline_m)
    result = estimate_obstacle_depth(batch, PipelineConfig())
    ranged = sorted(float(d) for d, ok in zip(result.depth.objects.depth_median_m[0], result.depth.objects.valid[0])
                    if ok)
    assert ranged and abs(ranged[0] - 0.9) < 0.05 and result.depth.nearest.surface_m[0] > 0.8


def test_synthetic_source_with_a_floor_is_not_warned_of_the_floor():
    """The emulator's walker view (--floor-height-m 1.3 --camera-pitch-deg 20): the floor is seen from 1.8 m on;
    with both obstacles farther (keyframe 9: 2.68 and 2.36 m) the warning distance with the floor left out
    (``guide``'s default) is the nearer obstacle's, where with the floor kept (``--floor off``, ``estimate``'s
    default) it is the floor's."""
    from hw.frames import _render_torch_pair

    from svs_torch.core.types import StereoBatch
    from svs_torch.evaluation.overrides import apply_overrides
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    track = ObstacleTrack(floor_height_m=1.3, camera_pitch_deg=20.0)
    left, right = (torch.from_numpy(v).float().div(255).view(1, 1, 240, 320)
                   for v in _render_torch_pair(track, 9, (320, 240), SVS_CAMERA, 0))
    batch = StereoBatch.from_images(left, right, SVS_CAMERA.focal_px(320), SVS_CAMERA.baseline_m)
    nearest = min(track.depths_m(9))
    warnings = []
    for config in (apply_overrides(PipelineConfig(), {"segmentation.ground": True}), PipelineConfig()):
        found = estimate_obstacle_depth(batch, config).depth.nearest
        assert bool(found.valid[0])
        warnings.append(float(found.surface_m[0]))
    assert abs(warnings[0] - nearest) < 0.1 * nearest
    assert warnings[1] < 0.85 * nearest


def test_synthetic_source_with_a_heap_on_the_floor_is_warned_of_the_heap():
    """--floor-height-m 1.3 --heap-ahead-m 1.5: a heap of rocks on the floor 1.5 m ahead (0.45 m in radius, its front
    about 1.1–1.4 m away along the axis) is warned of with the floor left out (``guide``'s default), nearer than the
    boxes (keyframe 9: 2.68 and 2.36 m); the same view without the heap is warned of at the nearer box. A heap
    needs a floor."""
    from hw.frames import _render_torch_pair

    from svs_torch.core.types import StereoBatch
    from svs_torch.evaluation.overrides import apply_overrides
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    config = apply_overrides(PipelineConfig(), {"segmentation.ground": True})
    warnings = []
    for heap in (1.5, None):
        track = ObstacleTrack(floor_height_m=1.3, camera_pitch_deg=20.0, heap_ahead_m=heap)
        left, right = (torch.from_numpy(v).float().div(255).view(1, 1, 240, 320)
                       for v in _render_torch_pair(track, 9, (320, 240), SVS_CAMERA, 0))
        batch = StereoBatch.from_images(left, right, SVS_CAMERA.focal_px(320), SVS_CAMERA.baseline_m)
        found = estimate_obstacle_depth(batch, config).depth.nearest
        assert bool(found.valid[0])
        warnings.append(float(found.surface_m[0]))
    assert 1.0 < warnings[0] < 1.5 and abs(warnings[1] - min(track.depths_m(9))) < 0.1 * min(track.depths_m(9))
    with pytest.raises(ValueError, match="heap_ahead_m: expected a distance > 0 metres on a floor"):
        ObstacleTrack(heap_ahead_m=1.5)


def test_image_folder_source(tmp_path):
    for name, value in (("left01.png", 50), ("right01.png", 150)):
        import cv2
        cv2.imwrite(str(tmp_path / name), np.full((48, 64), value, np.uint8))
    source = ImageFolderSource(tmp_path)
    assert source("left", 32, 24, 0.0).shape == (24, 32)
    assert source("right", 32, 24, 5.0)[0, 0] == 150
    with pytest.raises(ValueError, match="no left/right image pairs"):
        ImageFolderSource(tmp_path / "left01.png")


# ------------------------------------------------------------------------------------------- normal use

def test_capture_pairs_over_tcp(camera):
    assert camera.versions["left"].role == "master" and camera.versions["right"].role == "slave"
    pairs = camera.grab_pairs(3)
    for pair in pairs:
        assert pair.left.image.shape == (240, 320) and pair.right.image.shape == (240, 320)
        assert pair.left.jpeg[:2] == b"\xff\xd8" and pair.left.attempts == 1
        for frame in (pair.left, pair.right):
            assert frame.request_monotonic_s <= frame.arrival_monotonic_s
        assert pair.time_between_frames_s == pair.right.header_monotonic_s - pair.left.header_monotonic_s
        assert abs(pair.time_between_frames_s) < 0.2
    assert [p.index for p in pairs] == [0, 1, 2]
    assert pairs[0].left.image.mean() > pairs[0].right.image.mean()  # the source's left is brighter


def test_to_stereo_batch(camera):
    batch = to_stereo_batch(camera.grab_pairs(2), dtype=torch.float64)
    assert batch.left.shape == (2, 1, 240, 320) and batch.left.dtype == torch.float64
    assert 0.0 <= float(batch.left.min()) and float(batch.right.max()) <= 1.0
    assert torch.allclose(batch.focal_px, torch.full((2,), SVS_CAMERA.focal_px(320), dtype=torch.float64))
    assert torch.allclose(batch.baseline_m, torch.full((2,), SVS_CAMERA.baseline_m, dtype=torch.float64))
    assert not batch.calibrated.any() and batch.names == ("pair0", "pair1")
    with pytest.raises(InputError, match="pairs: expected at least one"):
        to_stereo_batch([])


def test_resolution_changes(camera):
    for size in ((640, 480), (160, 120), (1280, 1024), (320, 240)):
        camera.set_size(size)
        pair = camera.grab_pair()
        assert pair.left.size_wh == size and pair.right.size_wh == size
    with pytest.raises(InputError, match="size_wh"):
        camera.set_size((100, 100))


def test_quality_changes_jpeg_size(emulator):
    sizes = {}
    for quality in (1, 8):
        with SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], quality=quality, config=FAST) as cam:
            sizes[quality] = len(cam.grab_pair().left.jpeg)
    assert sizes[1] > sizes[8]
    with pytest.raises(InputError, match="quality"):
        SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], quality=9, config=FAST)


def test_a_paced_link_sends_frames_no_faster_than_the_boards_uart():
    """``link_bytes_per_s``: each frame arrives no sooner than its bytes take at that rate (the SVS's UART,
    ``SVS_LINK_BYTES_PER_S``, for the command line's --emulator); unpaced, the same frames come at once."""
    from hw.emulator import SVS_LINK_BYTES_PER_S

    assert SVS_LINK_BYTES_PER_S == 253_000  # 2.53 Mbit/s actual at 2,304,000 baud, 10 bits a byte (SVS_PROTOCOL §1)
    rate = 50_000.0  # a 20 kB frame: 0.4 s on such a link, under a millisecond on loopback
    for paced in (True, False):
        with EmulatorServer(left_port=0, right_port=0, source=flat_source,
                            link_bytes_per_s=rate if paced else None) as server:
            link = dataclasses.replace(FAST, link_bytes_per_s=rate)  # the driver's timeouts for that link
            with SVSStereoCamera(server.urls["left"], server.urls["right"], config=link) as cam:
                frame = cam.grab_pair().left
                took_s = frame.arrival_monotonic_s - frame.request_monotonic_s
                if paced:
                    assert took_s >= (10 + len(frame.jpeg)) / rate - 0.002  # header + JPEG on the wire
                else:
                    assert took_s < 0.5 * len(frame.jpeg) / rate
    with pytest.raises(ValueError, match="link_bytes_per_s"):
        EmulatorServer(left_port=0, right_port=0, source=flat_source, link_bytes_per_s=0)


def test_stream_batches(camera):
    items = list(camera.stream_batches(3, num_batches=2))
    assert len(items) == 2
    for item in items:
        assert item.batch.left.shape == (3, 1, 240, 320) and item.num_dropped >= 0
        assert [p.index for p in item.pairs] == sorted(p.index for p in item.pairs)
    assert items[1].pairs[0].index > items[0].pairs[-1].index


def test_stream_batches_holds_few_pairs_while_its_consumer_is_busy(camera, monkeypatch):
    """Was (an audit of long runs): every pair grabbed while the consumer did not take one stayed queued until it did,
    so ``guide --json`` whose reader stalled (a paused pipe; a terminal stopped by Ctrl-S), which blocks guide's
    next write, grew by 3.2 MB a second (RSS 357 -> 531 MB in 55 s, without bound) while the walker heard nothing.
    Now the grabbing thread keeps at most ``batch_size`` pairs not taken; the older ones are counted dropped, and
    the batch is still the newest pairs."""
    real = camera.grab_pair()
    grabbed: list[int] = []
    handed: list[weakref.ref] = []  # (a pair is no set member: its frames' arrays do not hash)

    def grab_pair():
        time.sleep(0.001)
        pair = dataclasses.replace(real, index=len(grabbed))
        grabbed.append(pair.index)
        handed.append(weakref.ref(pair))
        return pair

    monkeypatch.setattr(camera, "grab_pair", grab_pair)
    stream = camera.stream_batches(2)
    try:
        first = next(stream)
        time.sleep(0.5)  # the consumer busy (its stdout blocked): pairs keep coming
        assert len(grabbed) > first.pairs[-1].index + 50  # (the grabber ran meanwhile)
        alive = sum(ref() is not None for ref in handed)
        assert alive <= 2 + 2 + 1, alive  # the batch in hand, the queue's 2 (and one more being put)
        waited = len(grabbed)  # (read before the take: the grabber goes on until close, longer on a loaded machine)
        second = next(stream)
    finally:
        stream.close()
    assert second.pairs[0].index >= waited - 4  # the newest pairs, not the ones from before the wait
    assert [p.index for p in second.pairs] == [second.pairs[0].index, second.pairs[0].index + 1]
    assert second.num_dropped == second.pairs[0].index - first.pairs[-1].index - 1  # every pair between, counted


def test_stream_batches_ticks_while_no_pair_comes(emulator, camera):
    """``idle_s``: None each idle_s seconds no pair came (guide judges sight on time, not only on pairs: a frozen
    link was seconds of silence); pairs still come as before."""
    emulator.set_faults("left", grab_delay_s=0.35)
    try:
        items = list(camera.stream_batches(1, num_batches=2, idle_s=0.1))
    finally:
        emulator.set_faults("left", grab_delay_s=0.0)
    assert [item is None for item in items].count(False) == 2 and items[-1] is not None
    assert items.count(None) >= 2  # at least two ticks before the first delayed pair
    with pytest.raises(InputError, match="idle_s: expected None or a positive number of seconds"):
        next(camera.stream_batches(1, idle_s=0))


def test_banner_is_drained():
    with EmulatorServer(left_port=0, right_port=0, source=flat_source, banner=True) as server:
        with SVSStereoCamera(server.urls["left"], server.urls["right"], config=FAST) as cam:
            assert cam.versions["left"].role == "master"
            assert cam.grab_pair().left.attempts == 1


def test_swapped_urls_warn_or_raise(emulator):
    with pytest.warns(RuntimeWarning, match="expected the left board .* to be the stereo master"):
        SVSStereoCamera(emulator.urls["right"], emulator.urls["left"], config=FAST).close()
    with pytest.raises(CaptureError, match=r"check the URLs \(port 10001 is the master\) and cover one lens"):
        SVSStereoCamera(emulator.urls["right"], emulator.urls["left"], config=FAST, strict_roles=True)


def test_swapped_serial_devices_are_not_told_of_a_wifi_port():
    """An audit of a wired SVS: boards on two serial devices given the other way round were told to check 'port
    10001', which only the WiFi bridge has."""
    with EmulatorServer(left_port=0, right_port=0, source=flat_source, use_pty=True) as server, \
            pytest.raises(CaptureError, match=r"\(the master's serial device is the left camera's\)") as caught:
        SVSStereoCamera(server.pty_paths["right"], server.pty_paths["left"], config=FAST, strict_roles=True)
    assert "10001" not in str(caught.value)


def test_cli_capture_marks_and_warns_of_boards_answering_in_each_others_roles(emulator, tmp_path, capsys):
    """Found by an audit of a rig set up against the emulator with its ports given the other way round: capture
    warned once as it started and saved every pair unmarked, each left image the right camera's view, and estimate of
    the index asked "are LEFT and RIGHT swapped?" with nothing in it to say so. Each index line now says
    ``cameras_swapped`` (false for boards in their roles) and the end warns of it with what to do."""
    from svs_torch.cli import main

    urls = emulator.urls
    assert main(["capture", "--left", urls["right"], "--right", urls["left"], "--count", "2", "--size", "160x120",
                 "--out", str(tmp_path / "swapped")]) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert "expected the left board" in err  # as it starts (the driver's), and at its end:
    assert "warning: the left board answered as the stereo slave and the right as the master (cameras_swapped in " \
           "index.jsonl, on each of the 2 pairs kept)" in err and "--left and --right URLs the other way round" in err
    assert main(["capture", "--left", urls["left"], "--right", urls["right"], "--count", "1", "--size", "160x120",
                 "--out", str(tmp_path / "sound")]) == 0
    assert "cameras_swapped" not in capsys.readouterr().err
    for folder, swapped in (("swapped", [True, True]), ("sound", [False])):
        lines = (tmp_path / folder / "index.jsonl").read_text().splitlines()
        assert [json.loads(line)["cameras_swapped"] for line in lines] == swapped


def test_unreachable_url_names_camera():
    with socket.socket() as probe:  # a free port that nobody listens on
        probe.bind(("127.0.0.1", 0))
        url = f"socket://127.0.0.1:{probe.getsockname()[1]}"
    with pytest.raises(CaptureError, match=r"left camera \(socket://127\.0\.0\.1:\d+\): could not open"):
        SVSStereoCamera(url, url, config=FAST)


def test_capture_over_pty():
    with EmulatorServer(left_port=0, right_port=0, source=flat_source, use_pty=True) as server:
        paths = server.pty_paths
        assert set(paths) == {"left", "right"} and all(p.startswith("/dev/") for p in paths.values())
        with SVSStereoCamera(paths["left"], paths["right"], (640, 480), config=FAST, max_frame_gap_s=None) as cam:
            assert cam.versions["right"].role == "slave"
            assert cam.grab_pair().left.size_wh == (640, 480)
            server.set_faults("right", silent_grabs=1, garbage_frames=1)
            pair = cam.grab_pair()
            assert pair.right.attempts == 2 and pair.left.attempts == 1


# ------------------------------------------------------------------------------------------------ faults

@pytest.mark.parametrize("faults, attempts", [
    ({"silent_grabs": 2}, 3),
    ({"garbage_frames": 1}, 1),
    ({"truncated_frames": 1}, 2),
    ({"wrong_length_frames": 1, "wrong_length_delta": 100}, 2),
    ({"wrong_length_frames": 1, "wrong_length_delta": -100}, 2),
    ({"drip_chunk_bytes": 2000, "drip_delay_s": 0.005}, 1),
], ids=["silent", "garbage", "truncated", "length-too-long", "length-too-short", "slow-drip"])
def test_fault_recovers(emulator, camera, faults, attempts):
    camera.grab_pair()
    emulator.set_faults("left", **faults)
    start = time.monotonic()
    pair = camera.grab_pair()
    assert time.monotonic() - start < attempt_bound_s()
    assert pair.left.attempts == attempts and pair.right.attempts == 1
    assert pair.left.image.shape == (240, 320)
    emulator.set_faults("left", drip_chunk_bytes=0)
    assert camera.grab_pair().left.attempts == 1  # and the link is clean afterwards


@pytest.mark.parametrize("faults, message", [
    ({"silent_grabs": 10}, r"expected a '##IMJ' frame of 320x240 within 0.25 s, got 0 bytes"),
    # a board that stopped sending is said so (it was pointed at a slower --baud, which cannot help)
    ({"truncated_frames": 10}, r"expected \d+ JPEG bytes of a 320x240 frame within .*the frame was cut short\)"),
    ({"wrong_length_frames": 10, "wrong_length_delta": -100}, "expected it to end FF D9"),
    ({"drip_chunk_bytes": 500, "drip_delay_s": 0.03}, r"no valid frame after 3 attempts"),
], ids=["silent", "truncated", "wrong-length", "too-slow-drip"])
def test_persistent_fault_fails_clearly_in_time(emulator, camera, faults, message):
    emulator.set_faults("right", **faults)
    start = time.monotonic()
    with pytest.raises(CaptureError, match=message) as info:
        camera.grab_pair()
    assert time.monotonic() - start < attempt_bound_s()
    assert f"right camera ({emulator.urls['right']})" in str(info.value)
    assert "no valid frame after 3 attempts of b'I'" in str(info.value)


def test_a_frame_cut_short_and_a_slow_board_are_told_apart():
    """A frame whose bytes stopped coming was told "the timeout assumes 2,304,000 baud: a slower board's --baud",
    which cannot help it; now the hint goes to a board that was still sending when its time ran out."""
    from svs_torch.capture.link_types import frame_timeout_reason
    from svs_torch.capture.protocol import FrameParser, encode_frame

    parser = FrameParser()
    parser.feed(encode_frame("5", b"\xff\xd8" + bytes(2000) + b"\xff\xd9")[:500])
    window = FAST.transfer_timeout_s(parser.header.length)
    assert "the frame was cut short" in frame_timeout_reason(FAST, "5", parser, b"", silent_s=window)
    assert "a slower board's --baud" in frame_timeout_reason(FAST, "5", parser, b"", silent_s=0.01)


def test_a_board_slower_than_the_baud_assumed_is_told_so_whatever_its_retries_met(emulator, camera):
    """A board sending slower than --baud assumes timed out with that hint, and its retries then read the rest of
    that frame's JPEG bytes: the error gave only the last attempt's "got 64 bytes b'...'". Now the first attempt's
    reason comes too, where it differs from the last."""
    camera.grab_pair()
    emulator.set_faults("right", drip_chunk_bytes=500, drip_delay_s=0.03)
    with pytest.raises(CaptureError, match=r"after 3 attempts of b'I' in [\d.]+ s; first attempt: expected \d+ JPEG "
                                           r"bytes .*a slower board's --baud\); last attempt: ") as info:
        camera.grab_pair()
    assert str(info.value).count("a slower board's --baud") == 1


def test_a_frame_damaged_on_the_link_is_grabbed_again(data_dir):
    """Was: a frame whose JPEG data was damaged on the link (its length right) decoded with its lost blocks gray,
    and guide ranged it: a gray block is a wall that is not there. Now the pair is grabbed again, both boards, and
    frames damaged every time are the camera's failure. (A real view: libjpeg says "premature end of data segment"
    for it; on the seeded noise of flat_source the same damage reads as extraneous bytes, which cameras also write
    and which is not refused.)"""
    from svs_torch.capture import DamagedFrameError

    view = cv2.imread(str(data_dir / "middlebury_eval3_Q" / "Teddy" / "im0.png"), cv2.IMREAD_GRAYSCALE)

    def real_source(camera: str, width: int, height: int, time_s: float) -> np.ndarray:
        return cv2.resize(view, (width, height), interpolation=cv2.INTER_AREA)

    with EmulatorServer(left_port=0, right_port=0, source=real_source) as emulator, \
            SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], config=FAST) as camera:
        camera.grab_pair()
        emulator.set_faults("right", damaged_frames=1)
        sent = emulator.cameras["left"].frames_sent
        pair = camera.grab_pair()
        assert emulator.cameras["left"].frames_sent == sent + 2  # the left board's frame of that moment too
        assert pair.right.image.shape == (240, 320) and pair.right.attempts == 1
        emulator.set_faults("right", damaged_frames=10)
        with pytest.raises(DamagedFrameError, match=r"right camera .*: a JPEG damaged on the link \(libjpeg: Corrupt"):
            camera.grab_pair()
        emulator.set_faults("right", damaged_frames=0)
        assert camera.grab_pair().right.attempts == 1


def test_wrong_size_frame_is_fixed(emulator, camera):
    emulator.cameras["left"].size_code = "7"  # the board changed size behind the driver's back
    pair = camera.grab_pair()
    assert pair.left.size_wh == (320, 240) and pair.left.attempts == 2
    assert "expected size code '5' (320x240), got '7' (640x480)" in camera.links["left"].stats.failures[-1]


@pytest.mark.parametrize("max_gap_s", [0.25, None])
def test_a_pair_whose_frames_came_apart_is_grabbed_again(emulator, max_gap_s):
    """Found by a review of the capture side: when one board needed a retry, the other's frame waited for it and
    the pair's frames came a reply timeout apart (4 s at guide's default), yet were ranged as one stereo pair. Such
    a pair is now grabbed again from both boards (max_frame_gap_s; None: as before)."""
    with SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], config=FAST,
                         max_frame_gap_s=max_gap_s) as cam:
        cam.grab_pair()
        emulator.set_faults("right", silent_grabs=1)
        pair = cam.grab_pair()
    if max_gap_s is None:
        assert pair.right.attempts == 2 and pair.time_between_frames_s > FAST.reply_timeout_s
    else:
        assert pair.left.attempts == pair.right.attempts == 1 and abs(pair.time_between_frames_s) <= max_gap_s
    with pytest.raises(InputError, match="max_frame_gap_s"):
        SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], max_frame_gap_s=0)


def plain_left_noisy_right(camera: str, width: int, height: int, time_s: float) -> np.ndarray:
    """One moment whose two JPEGs differ in length about tenfold: a plain left view, a noisy right one."""
    if camera == "left":
        return np.full((height, width), 128, dtype=np.uint8)
    return np.random.default_rng(height).integers(0, 255, (height, width), dtype=np.uint8)


def test_frames_of_one_moment_are_one_moment_on_a_slow_link():
    """An audit of a wired SVS at 115,200 baud: the pair's two frames were timed by their last bytes, which on a slow
    link follow as many bytes as each JPEG has, so two frames of one 640x480 moment (50 and 55 kB) came 0.4 s apart,
    every pair was grabbed three times and then refused by guide as "not one stereo moment". The boards' replies
    begin together: the gap is now taken from each frame's header (time_between_frames_s), the last bytes still
    recorded as they came."""
    rate = 16_000.0  # bytes a second: a 160x120 noise JPEG (about 10 kB) takes over half a second, the plain one 0.05
    slow = dataclasses.replace(FAST, link_bytes_per_s=rate, reply_timeout_s=1.0)
    with EmulatorServer(left_port=0, right_port=0, source=plain_left_noisy_right, link_bytes_per_s=rate) as server, \
            SVSStereoCamera(server.urls["left"], server.urls["right"], (160, 120), config=slow) as cam:
        pair = cam.grab_pair()
    assert len(pair.right.jpeg) - len(pair.left.jpeg) > 0.3 * rate  # (the lengths alone part the last bytes)
    assert pair.right.arrival_monotonic_s - pair.left.arrival_monotonic_s > 0.3
    assert pair.left.attempts == pair.right.attempts == 1  # not grabbed again for the lengths' gap
    assert abs(pair.time_between_frames_s) < 0.1
    assert pair.time_between_frames_s == pair.right.header_monotonic_s - pair.left.header_monotonic_s
    for frame in (pair.left, pair.right):
        assert frame.request_monotonic_s <= frame.header_monotonic_s <= frame.arrival_monotonic_s


def test_a_reply_already_waiting_is_not_taken_for_the_next_grab(emulator, camera):
    """Found by an audit of the device side: a reply that came late (to an I re-sent after its timeout, or a board
    answering twice) was read as the next grab's frame, one grab old, and on a board with no hold-off every later
    frame stayed one behind while the record said the pair's frames came together. Bytes already waiting are now
    dropped before each I."""
    link = camera.links["right"]
    camera.grab_pair()
    for _ in range(2):  # two replies nobody will read, each after the board's hold-off
        link._serial.write(b"I")
        time.sleep(0.3)
    assert link._serial.in_waiting
    frame = link.grab()
    time.sleep(0.3)
    assert not link._serial.in_waiting  # nothing left to be read as the next grab's frame
    assert link.stats.stale_inputs == 1 and frame.attempts == 1


def test_a_reset_or_reconnected_board_gets_every_setting_again(emulator):
    """Found by a review of the capture side: a board that came back at its power-on settings (a frame of another
    size) got its size again but not its quality, and a reconnected one its size and quality but not its flip."""
    with SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], (640, 480), quality=8, flip=True,
                         config=FAST) as cam:
        board = emulator.cameras["left"]
        cam.grab_pair()
        board.size_code, board.quality, board.flipped = "5", 4, False  # a brown-out: power-on settings
        cam.grab_pair()
        assert (board.size_code, board.quality, board.flipped) == ("7", 8, True)
        emulator.drop_connection("left")
        time.sleep(0.2)  # the emulator closes the socket in its own thread
        board.flipped = False
        cam.grab_pair()
        assert cam.links["left"].stats.reconnects >= 1 and board.flipped and board.quality == 8


def test_a_board_reset_at_its_power_on_size_gets_its_settings_again(emulator):
    """Found by an audit of the device side: a board reset at the size it powers on at (320x240) sent its
    ``##Version`` banner, which was skipped as stray bytes, and its frames went on at its power-on quality and flip
    without a word (the settings came back only with a frame of another size). The banner before a frame now
    counts as a reset: that frame is dropped and every setting sent again."""
    with SVSStereoCamera(emulator.urls["left"], emulator.urls["right"], quality=8, flip=True, config=FAST,
                         max_frame_gap_s=None) as cam:
        board = emulator.cameras["left"]
        cam.grab_pair()
        board.quality, board.flipped = 4, False  # power-on settings at the same size
        emulator.set_faults("left", garbage_frames=1, garbage=version_line("master"))
        pair = cam.grab_pair()
        assert (board.quality, board.flipped) == (8, True) and pair.left.attempts == 2
        assert "power-on banner" in cam.links["left"].stats.failures[-1]
        assert cam.grab_pair().left.attempts == 1


def test_dropped_link_reconnects(emulator, camera):
    emulator.set_faults("left", drop_after_frames=1)
    camera.grab_pair()  # the link drops right after this frame
    start = time.monotonic()
    pair = camera.grab_pair()
    assert time.monotonic() - start < 2.0
    assert camera.links["left"].stats.reconnects == 1 and pair.left.size_wh == (320, 240)
    emulator.drop_connection("right")
    time.sleep(0.1)
    camera.set_size((640, 480))  # a command (not a grab) on a dropped link reconnects too
    assert camera.grab_pair().right.size_wh == (640, 480)
    assert camera.links["right"].stats.reconnects == 1


def test_link_gone_for_good_fails_clearly(emulator, camera):
    camera.grab_pair()
    emulator.stop()
    start = time.monotonic()
    with pytest.raises(CaptureError, match=r"(left|right) camera \(socket://127\.0\.0\.1:\d+\)"):
        camera.grab_pair()
    assert time.monotonic() - start < 3.0


# ---------------------------------------------------------------------------------------------- hardware

@pytest.mark.hardware
@pytest.mark.skipif(not (os.environ.get("SVS_LEFT_URL") and os.environ.get("SVS_RIGHT_URL")),
                    reason="set SVS_LEFT_URL and SVS_RIGHT_URL to the device links to run hardware tests")
def test_real_camera_pair():
    with SVSStereoCamera(os.environ["SVS_LEFT_URL"], os.environ["SVS_RIGHT_URL"]) as cam:
        assert {v.role for v in cam.versions.values()} <= {"master", "slave", "unknown"}
        pair = cam.grab_pair()
        assert pair.left.size_wh == (320, 240) and pair.right.size_wh == (320, 240)
        assert abs(pair.time_between_frames_s) < 1.0


# ------------------------------------------------------------------------------------------- capture CLI

def run_capture(*argv: str) -> int:
    import argparse

    from svs_torch.cli.capture import add_parser

    parser = argparse.ArgumentParser(prog="svs-depth")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["capture", *argv])
    return args.func(args)


def test_the_builtin_emulator_runs_without_termios(tmp_path):
    """Windows has no ``termios``: the emulator imported ``tty`` (for its optional --pty) at the top, and ``capture
    --emulator`` and ``guide --emulator`` were an internal error there. Now only --pty needs it."""
    import subprocess
    import sys

    from conftest import REPO_ROOT

    # (pyserial first: off Windows its backend needs termios; on Windows it has its own)
    code = ("import sys, serial; sys.modules['termios'] = sys.modules['tty'] = None\n"
            "from svs_torch.cli import main\n"
            f"sys.exit(main(['capture', '--emulator', '--count', '1', '--size', '160x120', '--out', "
            f"{str(tmp_path)!r}]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO_ROOT,
                          env={**os.environ, "PYTHONPATH": str(REPO_ROOT), "SVS_TORCH_KERNELS": "torch"})
    assert done.returncode == 0, done.stderr
    assert len((tmp_path / "index.jsonl").read_text().splitlines()) == 1


def test_cli_capture_with_builtin_emulator(tmp_path, capsys):
    import cv2
    import json

    assert run_capture("--emulator", "--count", "3", "--size", "160x120", "--out", str(tmp_path / "run")) == 0
    lines = (tmp_path / "run" / "index.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    assert [r["index"] for r in records] == [0, 1, 2]
    for record in records:
        assert (record["width"], record["height"]) == (160, 120)
        image = cv2.imread(str(tmp_path / "run" / record["left"]), cv2.IMREAD_GRAYSCALE)
        assert image.shape == (120, 160) and record["left_bytes"] == (tmp_path / "run" / record["left"]).stat().st_size
        assert record["time_between_frames_s"] == pytest.approx(
            record["right_header_monotonic_s"] - record["left_header_monotonic_s"])
        assert record["left_request_monotonic_s"] <= record["left_header_monotonic_s"] <= record[
            "left_arrival_monotonic_s"]
    err = capsys.readouterr().err
    assert "saved 3 pairs" in err
    # The last line gives the estimate command that ranges them as camera frames, as guide --record's summary does.
    import shlex

    from svs_torch.cli import build_parser

    replay = shlex.split(err.strip().splitlines()[-1].split("range them with: ")[1])
    args = build_parser().parse_args(replay[1:])
    assert args.pairs == str(tmp_path / "run" / "index.jsonl") and args.camera_frames and args.json
    assert run_capture("--emulator", "--count", "1", "--out", str(tmp_path / "run")) == 2  # index exists


def test_cli_capture_error_keeps_only_complete_pairs(tmp_path, capsys):
    calls = []

    def failing_later(camera, width, height, time_s):
        calls.append(camera)
        if calls.count("right") == 2:  # after the second right frame the right board goes silent
            server.cameras["right"].faults.silent_grabs = 1000
        return flat_source(camera, width, height, time_s)

    with EmulatorServer(left_port=0, right_port=0, source=failing_later) as server:
        start = time.monotonic()
        code = run_capture("--left", server.urls["left"], "--right", server.urls["right"], "--count", "5",
                           "--timeout", "0.2", "--out", str(tmp_path / "run"))
        assert time.monotonic() - start < 5.0
    err, replay = capsys.readouterr().err.strip().splitlines()[-2:]
    assert code == 1 and replay.startswith("svs-depth capture: range the pairs kept with: svs-depth estimate --pairs")
    assert err.startswith("svs-depth capture: error: right camera (socket://127.0.0.1:")
    assert "(2 of 5 pairs saved in" in err
    assert len((tmp_path / "run" / "index.jsonl").read_text().splitlines()) == 2
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [
        "index.jsonl", "pair000000_left.jpg", "pair000000_right.jpg", "pair000001_left.jpg", "pair000001_right.jpg"]


@pytest.mark.parametrize("retries, code", [(0, 1), (1, 0)])
def test_cli_capture_retries_sets_how_often_a_grab_is_sent_again(tmp_path, capsys, retries, code):
    """capture and guide allowed a board three grabs a frame and no option to change that (LinkConfig.max_retries):
    --retries N sends a silent board's grab again N times."""
    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server:
        server.set_faults("left", silent_grabs=1)
        assert run_capture("--left", server.urls["left"], "--right", server.urls["right"], "--count", "1",
                           "--timeout", "0.2", "--retries", str(retries), "--out", str(tmp_path / "run")) == code
    err = capsys.readouterr().err
    assert ("no valid frame after 1 attempt of" in err) == (code == 1)
    with pytest.raises(SystemExit) as refused:
        run_capture("--emulator", "--retries", "11", "--out", str(tmp_path / "other"))
    assert refused.value.code == 2 and "--retries: expected a number of retries from 0 to 10" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


@pytest.mark.parametrize("signum", ["SIGTERM", "SIGINT"])
def test_a_signal_while_a_pair_is_saved_leaves_it_listed_or_gone(tmp_path, capsys, monkeypatch, signum):
    """Found by an audit of the device side: a SIGTERM between writing a pair's images and listing them left the
    images unlisted in index.jsonl (1 run of 4 of guide --record). The two are now one step: the signal is held
    until the line is written, then stops the command as before."""
    import signal

    import svs_torch.cli.capture as capture_command
    from svs_torch.cli import main

    save = capture_command.save_pair

    def saved_then_signalled(out, pair, option):
        record = save(out, pair, option)
        if pair.index == 1:  # between the images and their index line
            os.kill(os.getpid(), getattr(signal, signum))
        return record

    monkeypatch.setattr(capture_command, "save_pair", saved_then_signalled)
    out = tmp_path / "run"
    assert main(["capture", "--emulator", "--count", "4", "--size", "160x120", "--out", str(out)]) == (
        143 if signum == "SIGTERM" else 130)
    listed = [json.loads(line) for line in (out / "index.jsonl").read_text().splitlines()]
    assert [line["index"] for line in listed] == [0, 1]
    assert sorted(p.name for p in out.glob("pair*.jpg")) == sorted(line[view] for line in listed
                                                                   for view in ("left", "right"))
    assert "after 2 pairs" in capsys.readouterr().err


def test_cli_capture_says_what_it_saved_when_terminated_or_when_no_camera_opened(tmp_path, capsys, monkeypatch):
    """Found by an audit: SIGTERM ended capture with "terminated" only (Ctrl-C says how many pairs the index lists),
    and a camera that never opened ended with "(0 of 2 pairs saved in DIR)" for a folder never made."""
    from svs_torch.cli.common import Terminated

    grab = SVSStereoCamera.grab_pair
    calls = []

    def terminated_at_the_third(camera):
        calls.append(1)
        if len(calls) == 3:
            raise Terminated()
        return grab(camera)

    monkeypatch.setattr(SVSStereoCamera, "grab_pair", terminated_at_the_third)
    assert run_capture("--emulator", "--count", "5", "--size", "160x120", "--out", str(tmp_path / "run")) == 143
    assert capsys.readouterr().err.strip().splitlines()[-2].endswith(
        "capture: terminated after 2 pairs (index.jsonl lists them)")  # (then the command that ranges them)
    assert len((tmp_path / "run" / "index.jsonl").read_text().splitlines()) == 2
    monkeypatch.undo()

    def terminated_while_opening(camera):  # before the boards answered: no folder was made
        raise Terminated()

    monkeypatch.setattr(SVSStereoCamera, "__enter__", terminated_while_opening)
    assert run_capture("--emulator", "--count", "5", "--size", "160x120", "--out", str(tmp_path / "early")) == 143
    assert capsys.readouterr().err.strip().endswith("capture: terminated after 0 pairs: nothing saved")
    assert not (tmp_path / "early").exists()  # it said "(index.jsonl lists them)" of a folder never made
    monkeypatch.undo()
    with socket.socket() as left, socket.socket() as right:  # ports nothing listens on
        left.bind(("127.0.0.1", 0))
        right.bind(("127.0.0.1", 0))
        urls = [f"socket://127.0.0.1:{port.getsockname()[1]}" for port in (left, right)]
    assert run_capture("--left", urls[0], "--right", urls[1], "--count", "2", "--timeout", "0.2",
                       "--out", str(tmp_path / "none")) == 1
    assert capsys.readouterr().err.strip().endswith("(nothing saved)") and not (tmp_path / "none").exists()


def test_cli_capture_index_says_the_jpeg_quality(tmp_path):
    """Found by an audit: index.jsonl did not say at which --quality its frames were sent, and a board keeps the
    digit an earlier run set, so a folder's JPEG quality could not be told. Now each line has it (null: not set)."""
    def qualities(out):
        return [json.loads(line)["quality"] for line in (out / "index.jsonl").read_text().splitlines()]

    assert run_capture("--emulator", "--count", "2", "--size", "160x120", "--quality", "7",
                       "--out", str(tmp_path / "q7")) == 0
    assert qualities(tmp_path / "q7") == [7, 7]
    assert run_capture("--emulator", "--count", "1", "--size", "160x120", "--out", str(tmp_path / "own")) == 0
    assert qualities(tmp_path / "own") == [None]


def test_cli_capture_warns_of_pairs_whose_frames_came_apart(tmp_path, capsys):
    """Found by a fuzz of the device side: a right board late on every frame was saved pair after pair, each frame
    0.5 s from its partner, without a word (guide refuses such pairs). They are kept, the index says when each frame
    came, and the last lines count them."""
    import json

    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server:
        server.set_faults("right", grab_delay_s=0.3)
        code = run_capture("--left", server.urls["left"], "--right", server.urls["right"], "--count", "1",
                           "--out", str(tmp_path / "run"))
    err = capsys.readouterr().err
    assert code == 0 and "saved 1 pair to" in err  # (was "saved 1 pairs")
    assert "warning: 1 of 1 pairs' frames came over 0.25 s apart after their regrabs" in err
    record = json.loads((tmp_path / "run" / "index.jsonl").read_text())
    assert record["time_between_frames_s"] > 0.25


def _capture_frozen(tmp_path, capsys, cameras: tuple[str, ...], count: int) -> tuple[int, str, list[dict]]:
    """capture of ``count`` pairs from the emulator with the ``cameras``' sensors stalled (--freeze) and noise
    sigma 2 (the other board's frames change from grab to grab, as a real sensor's do) into tmp_path/run: its exit
    status, stderr and index lines."""
    faults = {camera: Faults(frozen_grabs=10**6) for camera in cameras}
    with EmulatorServer(left_port=0, right_port=0, source=SyntheticSource(renderer="simple"), noise_sigma=2.0,
                        faults=faults) as server:
        code = run_capture("--left", server.urls["left"], "--right", server.urls["right"], "--count", str(count),
                           "--size", "160x120", "--out", str(tmp_path / "run"))
    records = [json.loads(line) for line in (tmp_path / "run" / "index.jsonl").read_text().splitlines()]
    return code, capsys.readouterr().err, records


@pytest.mark.parametrize("camera", ["left", "right"])
def test_cli_capture_warns_of_and_marks_the_pairs_of_a_board_that_sends_one_frame_again(tmp_path, capsys, camera):
    """Found by an audit of capture: with one board's sensor stalled (the emulator's --freeze: each grab answered
    with its last frame's bytes again) capture saved every pair, an old view beside a new one, without a word, into
    a researcher's data set. They are kept (capture records what the boards sent), each index line says which camera
    was frozen (guide's rule: from the second such pair in a row), and the last lines count them."""
    code, err, records = _capture_frozen(tmp_path, capsys, (camera,), 5)
    assert code == 0 and "saved 5 pairs" in err
    assert [record["frozen_camera"] for record in records] == [None, None, camera, camera, camera]
    assert f"warning: 3 of 5 pairs have the {camera} camera's frame sent again, pixel for pixel" in err
    assert f"check the {camera} camera" in err and "came over" not in err
    # a sound capture says nothing of it, and its lines say null
    assert run_capture("--emulator", "--count", "2", "--size", "160x120", "--out", str(tmp_path / "sound")) == 0
    assert "warning" not in capsys.readouterr().err
    assert [json.loads(line)["frozen_camera"] for line in (tmp_path / "sound" / "index.jsonl").read_text().split(
        "\n") if line] == [None, None]


def test_cli_capture_marks_and_warns_of_both_boards_sending_one_old_pair_again(tmp_path, capsys, monkeypatch):
    """Found by an audit of recordings: with both boards' sensors stalled (the emulator's --freeze on both, noise
    sigma 2) capture saved one old pair again and again, 40 pairs over 4 s, neither marked nor warned of: it judged
    each camera against the other's change, never both by guide's rule (both frames the same again for
    BOTH_FROZEN_S, here 0 so that the test takes a few pairs). Now such pairs are marked "both" and counted, and
    estimate --pairs of the folder warns of them."""
    import functools

    import svs_torch.capture.frozen as frozen_module
    from svs_torch.cli import main

    monkeypatch.setattr(frozen_module, "FrozenCameraWatch",
                        functools.partial(frozen_module.FrozenCameraWatch, both_frozen_s=0.0))
    code, err, records = _capture_frozen(tmp_path, capsys, ("left", "right"), 4)
    assert code == 0 and [record["frozen_camera"] for record in records] == [None, "both", "both", "both"]
    assert "warning: 3 of 4 pairs have both cameras' frames sent again, pixel for pixel, for 3 s or more" in err
    assert main(["estimate", "--pairs", str(tmp_path / "run" / "index.jsonl"), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert "warning: 3 of 4 listed pairs have both cameras' frames sent again for 3 s or more" in err


@pytest.mark.parametrize("stop, code", [(KeyboardInterrupt, 130), ("Terminated", 143)])
def test_a_capture_stopped_early_still_warns_of_the_pairs_it_kept(tmp_path, capsys, monkeypatch, stop, code):
    """Found by an audit of capture: a long capture is ended with Ctrl-C (or a service's SIGTERM), and then it said
    nothing of the frozen or torn pairs it had kept, nor how to range them (guide --record says it at every end);
    both came only after --count pairs."""
    from svs_torch.cli.common import Terminated

    grab, calls = SVSStereoCamera.grab_pair, []

    def stopped_at_the_fifth(camera):
        calls.append(1)
        if len(calls) == 5:
            raise Terminated() if stop == "Terminated" else stop()
        return grab(camera)

    monkeypatch.setattr(SVSStereoCamera, "grab_pair", stopped_at_the_fifth)
    with EmulatorServer(left_port=0, right_port=0, source=SyntheticSource(renderer="simple"), noise_sigma=2.0,
                        faults={"right": Faults(frozen_grabs=10**6)}) as server:
        assert run_capture("--left", server.urls["left"], "--right", server.urls["right"], "--count", "100",
                           "--size", "160x120", "--out", str(tmp_path / "run")) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-3].endswith("after 4 pairs (index.jsonl lists them)")
    assert err[-2] == f"svs-depth capture: range the pairs kept with: svs-depth estimate --pairs {tmp_path}/run/" \
                      "index.jsonl --camera-frames --json"
    assert "warning: 2 of 4 pairs have the right camera's frame sent again" in err[-1]


def test_cli_defaults_match_link_defaults():
    from svs_torch.cli import capture

    from svs_torch.cli import build_parser, common

    from svs_torch.cli import link_options

    assert (link_options.DEFAULT_BAUD, capture.DEFAULT_TIMEOUT_S) == (LinkConfig().baudrate,
                                                                      LinkConfig().reply_timeout_s)
    assert common.DEFAULT_RETRIES == LinkConfig().max_retries
    assert build_parser().parse_args(["guide", "--emulator", "--retries", "5"]).retries == 5
    for argv in (["capture", "--emulator", "--out", "run"], ["guide", "--emulator"]):
        assert build_parser().parse_args(argv).no_flow_control is False


@pytest.mark.parametrize("option, rtscts", [((), True), (("--no-flow-control",), False)])
def test_flow_control_can_be_turned_off_for_a_three_wire_cable(tmp_path, option, rtscts):
    """An audit of a wired SVS: RTS/CTS flow control was always on (as the SVS's UART wants, §1), so a USB serial
    adapter wired TX, RX and ground only, whose CTS never rises, timed out on every write, with no option to turn it
    off. ``--no-flow-control`` (capture and guide) opens the serial devices without it."""
    import contextlib

    from svs_torch.cli import build_parser
    from svs_torch.cli.capture import open_stereo_camera

    with EmulatorServer(left_port=0, right_port=0, source=flat_source, use_pty=True) as server, \
            contextlib.ExitStack() as stack:
        args = build_parser().parse_args(["capture", "--left", server.pty_paths["left"], "--right",
                                          server.pty_paths["right"], "--out", str(tmp_path / "run"), *option])
        camera = open_stereo_camera(args, (320, 240), stack)
        assert camera.config.rtscts is rtscts
        assert all(link._serial.rtscts is rtscts for link in camera.links.values())
        assert camera.grab_pair().left.size_wh == (320, 240)


@pytest.mark.parametrize("argv, message", [
    (["--count", "0", "--emulator"], "--count: expected a number of pairs from 1 to 100000000, got '0'"),
    (["--size", "100x100", "--emulator"], "--size: expected 160x120"),
    # Were "argument --quality: invalid int value: '4.5'", which said nothing of what was expected.
    (["--quality", "4.5", "--emulator"], "--quality: expected a JPEG quality digit, 1 (best) to 8 (worst), got '4.5'"),
    (["--quality", "best", "--emulator"], "--quality: expected a JPEG quality digit, 1 (best) to 8 (worst), got"),
    (["--quality", "9", "--emulator"], "--quality: expected a JPEG quality digit, 1 (best) to 8 (worst), got '9'"),
    (["--left", "socket://x:1", "--emulator"], "--left, --right: not used with --emulator"),
    (["--left", "socket://x:1"], "--left, --right: both board URLs are needed"),
    # Were: pyserial's "'<=' not supported between instances of 'int' and 'NoneType'" (no port), a capture error
    # with exit 1 (http), and "the link closed right after opening" (one URL twice).
    (["--left", "socket://127.0.0.1", "--right", "socket://127.0.0.1:10002"], "--left: expected socket://HOST:PORT"),
    (["--left", "http://x:1", "--right", "socket://x:2"], "--left: expected a serial device or socket://HOST:PORT"),
    (["--left", "socket://x:1", "--right", "socket://x:1"], "--left, --right: expected the two boards' links"),
    # Was: a capture error, exit 1 ("protocol ' socket' not known"): urlsplit strips the space, pyserial does not.
    (["--left", " socket://x:1", "--right", "socket://x:2"], "--left: expected a serial device or socket://HOST:PORT "
     "with no space before or after it, got ' socket://x:1'"),
    (["--left", "socket://x:1", "--right", "/dev/ttyUSB1\n"], "--right: expected a serial device or socket://"),
    # Was accepted and did nothing: the boards send what they see.
    (["--left", "socket://x:1", "--right", "socket://x:2", "--emulator-noise", "4"],
     "--emulator-noise: only with --emulator"),
    (["--left", "socket://x:1", "--right", "socket://x:2", "--emulator-loose-rig"],
     "--emulator-loose-rig: only with --emulator"),
])
def test_cli_capture_bad_arguments(tmp_path, capsys, argv, message):
    from svs_torch.cli import main

    # Through the real entry point: some values are refused by the option's type (one line, exit 2), others by
    # the command; both must name the option and write nothing.
    try:
        status = main(["capture", *argv, "--out", str(tmp_path / "x")])
    except SystemExit as exit_:  # argparse's own exit for a value its type refused
        status = exit_.code
    assert status == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("argv, message", [
    (["--image-step", "0"], "argument --image-step: expected a finite positive number, got '0'"),
    (["--wrong-length-delta", "20000000"], "argument --wrong-length-delta: expected -65536..65536 bytes"),
    (["--floor-height-m", "-1"], "argument --floor-height-m: expected a finite positive number"),
    (["--left-port", "70000"], "argument --left-port: expected a TCP port 0..65535"),
    # Was exit 1, "Address already in use", with no other program on the port (an audit of the device side).
    (["--left-port", "10007", "--right-port", "10007"], "--left-port, --right-port: expected two ports (one per "
                                                       "board), got 10007 for both"),
    (["--prepare", "abc"], "--prepare: expected WIDTHxHEIGHT"),
    (["--heap-ahead-m", "1.5"], "--heap-ahead-m: expected --floor-height-m too"),
    (["--noise-sigma", "-1"], "argument --noise-sigma: expected a noise σ in 8-bit levels, 0 to 255"),
    (["--camera-pitch-deg", "95"], "--camera-pitch-deg: expected degrees in [-30, 60]"),
    # Accepted up to ±90 before, but the renderer refuses what is outside [-30, 60]: its thread died at the first
    # keyframe and every frame was the stand-in's, with no floor (an audit of the synthetic truth).
    (["--floor-height-m", "1.3", "--camera-pitch-deg", "70"], "--camera-pitch-deg: expected degrees in [-30, 60]"),
    (["--floor-height-m", "1.3", "--camera-pitch-deg", "-45"], "--camera-pitch-deg: expected degrees in [-30, 60]"),
    # The stand-in renderer and an image folder draw no floor: the option was ignored without a word (an audit).
    (["--floor-height-m", "1.3", "--simple-frames"], "--floor-height-m: only the synthetic frames"),
    (["--floor-height-m", "1.3", "--images", "."], "--floor-height-m: only the synthetic frames"),
    # An empty folder name (``--images "$DIR"``, DIR unset) served the synthetic obstacles, unsaid (an audit).
    (["--images", ""], "--images: expected a folder of left/right image pairs, got ''"),
    (["--images", " "], "--images: expected a folder of left/right image pairs, got ' '"),
])
def test_emulator_refuses_values_that_killed_a_board_thread(capsys, argv, message):
    """Found by an audit: these ran, and a board's thread died at its first grab (a ZeroDivisionError, the frame
    encoder's error), its port closed while the emulator looked alive; or they ended with exit 1 as if a port were
    taken. Each is a usage error now (exit 2), before anything listens."""
    from hw.emulator import main as emulator_main

    with pytest.raises(SystemExit) as stopped:
        emulator_main([*argv, "--left-port", "0", "--right-port", "0"] if "--left-port" not in argv else argv)
    assert stopped.value.code == 2 and message in capsys.readouterr().err


def test_emulator_prepares_only_the_sizes_a_board_sends(capsys):
    """Found by an audit of capture: ``--prepare 321x240`` was taken and its keyframes rendered, a size no board
    sends, while the 320x240 meant was served by the stand-in renderer. A usage error now (exit 2). Through
    parse_args: the emulator itself, given a size it takes, would serve until stopped."""
    from hw.emulator_args import parse_args

    assert parse_args(["--prepare", "320x240,160x120"], "", 1.0).prepare_sizes == [(320, 240), (160, 120)]
    with pytest.raises(SystemExit) as stopped:
        parse_args(["--prepare", "320x240,321x240"], "", 1.0)
    assert stopped.value.code == 2
    assert "--prepare: expected 160x120, 320x240, 640x480 or 1280x1024 (the sizes a board sends), got 321x240" in (
        capsys.readouterr().err)


@pytest.mark.parametrize("argv, message", [
    (["--grab-delay", "1e300"], "argument --grab-delay: expected seconds from 0 to 86400 (a day), got '1e300'"),
    (["--drip-delay", "1e300"], "argument --drip-delay: expected seconds from 0 to 86400 (a day), got '1e300'"),
    (["--link-rate", "1e-300"], "argument --link-rate: expected 0 (unpaced) or at least 960 bytes a second"),
    # Taken before, and each board answered its first command, then discarded every other one (an audit).
    (["--holdoff-ms", "1e300"], "argument --holdoff-ms: expected ms from 0 to 86400000 (a day), got '1e300'"),
])
def test_emulator_refuses_waits_past_the_platforms_longest(capsys, argv, message):
    """Found by an audit of the device side: these were taken, and each board's thread died at its first grab
    (OverflowError: timestamp out of range for platform time_t), its port closed while the emulator looked alive;
    the driver then said "Connection refused". Through parse_args: the emulator itself would serve until stopped."""
    from hw.emulator_args import parse_args

    assert parse_args(["--grab-delay", "86400", "--link-rate", "960"], "", 1.0).grab_delay == 86400
    assert parse_args(["--link-rate", "0"], "", 1.0).link_rate == 0
    assert parse_args(["--holdoff-ms", "86400000"], "", 1.0).holdoff_ms == 86400000
    with pytest.raises(SystemExit) as stopped:
        parse_args(argv, "", 1.0)
    assert stopped.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("seed", ["18446744073709551616", "-1"])
def test_emulator_noise_seed_is_one_torch_takes(capsys, seed):
    """Found by an audit of the device side: ``--noise-seed 2**64`` ended "hw.emulator: error: Overflow when
    unpacking long long", naming no option (torch's words); -1 was taken while svs-depth's seeds refuse it."""
    from hw.emulator_args import parse_args

    assert parse_args(["--noise-seed", str(2**63 - 1)], "", 1.0).noise_seed == 2**63 - 1  # the right's 2**63: taken
    with pytest.raises(SystemExit) as stopped:
        parse_args(["--noise-seed", seed], "", 1.0)
    assert stopped.value.code == 2
    assert f"argument --noise-seed: expected an integer from 0 to {2**63 - 1}, got '{seed}'" in capsys.readouterr().err


def test_emulator_refuses_an_image_folder_with_a_file_it_cannot_read(capsys, tmp_path, data_dir):
    import shutil

    from hw.emulator import main as emulator_main

    shutil.copy(data_dir / "opencv_samples" / "left01.jpg", tmp_path / "left01.jpg")
    (tmp_path / "right01.jpg").write_bytes(b"")
    assert emulator_main(["--images", str(tmp_path), "--left-port", "0", "--right-port", "0"]) == 2
    assert f"images: {tmp_path / 'right01.jpg'} is not an image OpenCV can read" in capsys.readouterr().err


def test_a_frame_the_source_cannot_make_is_no_reply_and_the_board_serves_on(capsys):
    """A source that raises (a file gone from the folder mid-run) was a board thread's death; now that grab gets
    no reply (a busy board, which the driver retries) and the next one is served."""
    calls = []

    def flaky(camera, width, height, time_s):
        calls.append(camera)
        if len(calls) == 1:
            raise ValueError("images: cannot read gone.jpg")
        return np.full((height, width), 128, np.uint8)

    with EmulatorServer(left_port=0, right_port=0, source=flaky) as server:
        with SVSStereoCamera(server.urls["left"], server.urls["right"], config=FAST) as cam:
            pair = cam.grab_pair()
    assert pair.left.image.shape == (240, 320) and "no reply: images: cannot read gone.jpg" in capsys.readouterr().err


def test_guide_says_what_quality_it_expected(capsys):
    """Found by an audit of capture: ``--quality 4.5`` was "invalid int value: '4.5'" in capture and guide alike."""
    from svs_torch.cli import main

    with pytest.raises(SystemExit) as refused:
        main(["guide", "--emulator", "--quality", "4.5", "--no-speech"])
    err = capsys.readouterr().err
    assert refused.value.code == 2 and err.count("\n") == 1
    assert "argument --quality: expected a JPEG quality digit, 1 (best) to 8 (worst), got '4.5'" in err


def test_guide_refuses_the_emulator_s_scene_beside_real_boards(capsys):
    """``guide --left URL --right URL --emulator-floor-m 1.3`` ran on the boards and ignored the floor, unsaid."""
    from svs_torch.cli import main

    assert main(["guide", "--left", "socket://127.0.0.1:1", "--right", "socket://127.0.0.1:2", "--emulator-floor-m",
                 "1.3", "--emulator-heap-m", "1.5", "--no-speech"]) == 2
    assert "--emulator-floor-m, --emulator-heap-m: only with --emulator" in capsys.readouterr().err


def test_emulator_refuses_a_heap_it_would_not_show(capsys):
    """Found by an audit: ``--heap-ahead-m`` had no far bound (svs-depth's --emulator-heap-m had), so a heap behind
    the wall (100 m at 1.3 m high) was taken and not a pixel of it rendered, unsaid; and pitched 60° down, a heap 3 m
    ahead lay above the view. Both are usage errors now, with svs-depth's bounds at the emulator's own pitch, held
    at 1280x1024 (the loosest size a board sends) against the renderer's heap mask."""
    import torch

    from hw.emulator_args import parse_args
    from svs_torch.data.synthetic import render_obstacle_scenes

    assert parse_args(["--floor-height-m", "1.3", "--heap-ahead-m", "1.5"], "", 1.0).heap_ahead_m == 1.5
    for argv, why in ((["--heap-ahead-m", "100"], r"behind the emulator's wall, 4 m along their axis"),
                      (["--camera-pitch-deg", "60", "--heap-ahead-m", "3"], "above their view")):
        with pytest.raises(SystemExit) as stopped:
            parse_args(["--floor-height-m", "1.3", *argv], "", 1.0)
        err = capsys.readouterr().err
        found = re.search(r"--heap-ahead-m: expected .+ to (\S+) metres, .* at 1280x1024; got \S+ \(farther, .*"
                          + why, err)
        assert stopped.value.code == 2 and found, err
    farthest_m = float(found.group(1))
    assert parse_args(["--floor-height-m", "1.3", "--camera-pitch-deg", "60", "--heap-ahead-m", str(farthest_m)], "",
                      1.0).heap_ahead_m == farthest_m

    def heap_pixels(ahead_m: float) -> int:
        scenes = render_obstacle_scenes(torch.tensor([[2.0]]), torch.tensor([[[9.0, 0.0]]]),
                                        torch.tensor([[[0.1, 0.1]]]), size_wh=(1280, 1024), floor_height_m=1.3,
                                        camera_pitch_deg=60.0, heaps=torch.tensor([[0.0, ahead_m, 0.45, 0.35]]),
                                        generator=torch.Generator().manual_seed(0))
        return int(scenes.heap_mask.sum())

    assert heap_pixels(farthest_m) > 0 and heap_pixels(farthest_m + 0.05) == 0


@pytest.mark.parametrize("field, value, expected", [
    ("reply_timeout_s", 0, "a finite number of seconds > 0"), ("reply_timeout_s", -1, "a finite number of seconds > 0"),
    ("reply_timeout_s", math.nan, "a finite number of seconds > 0"),
    ("reply_timeout_s", math.inf, "a finite number of seconds > 0"), ("poll_s", -1, "a finite number of seconds > 0"),
    ("max_retries", -1, "an integer >= 0"), ("max_reconnects", 1.5, "an integer >= 0"),
    ("link_bytes_per_s", -1, "a finite number >= 0"), ("baudrate", True, "an integer > 0"),
    ("drain_max_s", "1", "a finite number of seconds >= 0"),
])
def test_link_config_refuses_a_value_it_cannot_wait_by(field, value, expected):
    """Found by an audit of the capture API: these were taken, and opening the camera failed far from the cause
    (the boards "did not answer 'V' within nan s", "sent b'V' 0 times", pyserial's "Not a valid timeout: -1"), or
    an endless reply timeout would hang on a silent board. Each is refused by its field's name now; 0 stays the
    pause it means where a pause may be none, and None the baud rate's throughput."""
    LinkConfig(link_bytes_per_s=0, command_gap_s=0, reconnect_delay_s=0, max_retries=0, max_reconnects=0)
    LinkConfig(link_bytes_per_s=None)
    with pytest.raises(InputError, match=f"^LinkConfig.{field}: expected {expected}, got {value!r}"):
        LinkConfig(**{field: value})


@pytest.mark.parametrize("url, expected", [
    ("", "expected a serial device or socket://HOST:PORT, got ''"),
    (None, "expected a serial device or socket://HOST:PORT, got None"),
    ("socket://", "expected socket://HOST:PORT (the left board 10001, the right 10002), got 'socket://'"),
    ("socket://127.0.0.1", "expected socket://HOST:PORT"), ("http://x:1", "expected a serial device or socket://"),
    (" socket://127.0.0.1:10001", "expected a serial device or socket://HOST:PORT with no space before or after it"),
])
def test_camera_refuses_a_url_pyserial_cannot_open(url, expected):
    """Found by an audit of the capture API: SVSStereoCamera took these and failed opening them, inside pyserial
    ("could not open port :", "Port must be configured before it can be used", "'<=' not supported between
    instances of 'int' and 'NoneType'"), a CaptureError naming no argument. Refused now by the argument's name,
    before any link opens, as capture's --left/--right were."""
    with pytest.raises(InputError, match=f"^left_url: {re.escape(expected)}"):
        SVSStereoCamera(url, "socket://127.0.0.1:10002")
    with pytest.raises(InputError, match=f"^right_url: {re.escape(expected)}"):
        SVSStereoCamera("socket://127.0.0.1:10001", url)


def test_a_board_that_ignores_input_longer_after_a_reply_widens_the_pause_before_each_command():
    """Found by an audit against SVS_PROTOCOL §2 (input discarded for a short time after a reply, its length not
    given): with the emulator's hold-off at 30 ms, the first try of every command sent right after a reply was lost,
    a reply_timeout_s each (opening 3.3 s, three pairs 3.6 s). The link now widens its pause after such a silence."""
    with EmulatorServer(left_port=0, right_port=0, source=flat_source, holdoff_s=0.03) as server:
        with SVSStereoCamera(server.urls["left"], server.urls["right"], quality=4, config=FAST,
                             max_frame_gap_s=None) as cam:
            for _ in range(6):
                cam.grab_pair()
            for link in cam.links.values():
                assert link.stats.retries <= 1 and link.stats.command_gap_s == 0.05, link.stats
    # A silence long after the last reply (a board busy grabbing, §3) is no hold-off: the pause stays as it was.
    with EmulatorServer(left_port=0, right_port=0, source=flat_source,
                        faults={"left": Faults(silent_grabs=1)}) as server:
        with SVSStereoCamera(server.urls["left"], server.urls["right"], config=FAST, max_frame_gap_s=None) as cam:
            time.sleep(0.15)
            cam.grab_pair()
            assert cam.links["left"].stats.retries == 1 and cam.links["left"].stats.command_gap_s is None


def test_one_grab_a_board_stalled_on_does_not_widen_the_pause_for_good():
    """Found by an audit of guide against the emulator: the right board stalled on one grab (1.2 s, past the reply
    timeout; its late reply drained) in the middle of a walk, and its pause before each command went from 2 to 50 ms
    for good: every later pair's right frame came 50 ms after the left one, 16 -> 9 pairs a second. Its prompt
    commands had been answered all along: one silence among them is no hold-off (a second one is)."""
    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server:
        with SVSStereoCamera(server.urls["left"], server.urls["right"], config=FAST, max_frame_gap_s=None) as cam:
            for _ in range(3):
                cam.grab_pair()
            server.set_faults("right", silent_grabs=1)  # (the stall's late reply is drained: the same silence)
            for _ in range(4):
                cam.grab_pair()
            assert cam.links["right"].stats.retries == 1 and cam.links["right"].stats.command_gap_s is None
            server.set_faults("right", silent_grabs=1)  # a second silence among the last prompt commands: widened
            cam.grab_pair()
            assert cam.links["right"].stats.command_gap_s == HOLD_OFF_STEP_S


def test_opening_turns_off_a_caption_overlay_an_earlier_session_left_on():
    """Found by an audit of the driver against SVS_PROTOCOL §3: a board keeps its caption overlay (``o``) across
    reconnects, and the driver never sent ``O``: an earlier session's captions were burnt into every frame."""
    with EmulatorServer(left_port=0, right_port=0, source=flat_source) as server:
        server.cameras["left"].overlay = server.cameras["right"].overlay = True
        with SVSStereoCamera(server.urls["left"], server.urls["right"], config=FAST, max_frame_gap_s=None) as cam:
            cam.grab_pair()
        assert not server.cameras["left"].overlay and not server.cameras["right"].overlay


def test_emulator_stops_on_sigterm_while_it_prepares_its_keyframes(monkeypatch, capsys):
    """Found by an audit of the emulator as a tool: a SIGTERM (``kill``, ``timeout``, a service manager) while
    ``--prepare 1280x1024`` rendered was not heeded until every keyframe was rendered (17 s on an idle machine); then
    the URLs were printed and the emulator ended. Now it ends within a poll, serving nothing. The signal is sent
    from inside a render that takes 10 s, through the handler main installs."""
    import signal as signals

    import hw.emulator as emulator

    handlers = {}
    monkeypatch.setattr(emulator.signal, "signal", lambda sig, handler: handlers.__setitem__(sig, handler))
    began = []

    def slow_prepare(self, size_wh, timeout_s=60.0, *, complete=True):
        if not began:
            began.append(time.monotonic())
            handlers[signals.SIGTERM](signals.SIGTERM, None)  # SIGTERM arrives as the first keyframes render
        left_s = began[0] + 10.0 - time.monotonic()
        time.sleep(max(0.0, min(timeout_s, left_s)))
        return left_s <= timeout_s

    monkeypatch.setattr(SyntheticSource, "prepare", slow_prepare)
    assert emulator.main(["--prepare", "1280x1024", "--left-port", "0", "--right-port", "0"]) == 0
    assert time.monotonic() - began[0] < 2.0 and capsys.readouterr().out == ""


@pytest.mark.parametrize("board", ["left", "right"])
def test_emulator_names_the_option_of_a_port_it_cannot_listen_on(capsys, board):
    """Found by an audit of the emulator as a tool: a port another program held ended "hw.emulator: error: [Errno 98]
    Address already in use (while attempting to bind on address ('127.0.0.1', N))", exit 1, naming neither the
    board nor the option; an address not this machine's said "[Errno 99] Cannot assign requested address". Each is
    one line naming the option to change now, exit 2 as for any other bad value, nothing served, the ptys closed."""
    from hw.emulator import ListenError
    from hw.emulator import main as emulator_main

    held = socket.create_server(("127.0.0.1", 0))
    try:
        port = held.getsockname()[1]
        ports = {"left": "0", "right": "0", board: str(port)}
        status = emulator_main(["--pty", "--left-port", ports["left"], "--right-port", ports["right"]])
    finally:
        held.close()
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1, err
    assert f"error: --{board}-port: the {board} board cannot listen on 127.0.0.1 port {port}: Address already in " \
           "use; another program listens there (0 picks a free port)" in err
    assert emulator_main(["--host", "192.0.2.1", "--left-port", "0", "--right-port", "0"]) == 2  # TEST-NET-1
    assert "error: --host: the left board cannot listen on 192.0.2.1 port 0: " in capsys.readouterr().err
    assert issubclass(ListenError, OSError)  # what callers of EmulatorServer caught stays caught


def test_emulator_says_an_image_folder_it_may_not_read_in_one_line(capsys, monkeypatch, tmp_path):
    """Found by reviewing the change that named the option of a port that cannot listen: main then caught that
    error alone, so an image folder the user may not list (PermissionError, as a non-root user meets it) came out as a
    traceback where it had been one line, exit 1."""
    import hw.frames as frames
    from hw.emulator import main as emulator_main

    def denied(folder):
        raise PermissionError(13, "Permission denied", str(folder))

    monkeypatch.setattr(frames, "_find_pairs", denied)
    assert emulator_main(["--images", str(tmp_path), "--left-port", "0", "--right-port", "0"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"hw.emulator: error: [Errno 13] Permission denied: '{tmp_path}'" in err, err


def test_emulator_names_pty_not_the_port_where_no_pseudo_terminal_opens(capsys, monkeypatch):
    """Found by the same review: a --pty the system could not give (a container without /dev/pts: "out of pty
    devices") was said as "--left-port: the left board cannot listen on 127.0.0.1 port 0: out of pty devices", the
    wrong option to change, and the board's listening socket was left open."""
    import hw.emulator as emulator

    listeners = []
    real_create_server = socket.create_server

    def create_server(*args, **kwargs):
        listeners.append(real_create_server(*args, **kwargs))
        return listeners[-1]

    def no_pty():
        raise OSError("out of pty devices")

    monkeypatch.setattr(emulator.socket, "create_server", create_server)
    monkeypatch.setattr(emulator.os, "openpty", no_pty)
    assert emulator.main(["--pty", "--left-port", "0", "--right-port", "0"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "hw.emulator: error: --pty: the left board cannot open a pseudo-terminal: out " \
                                      "of pty devices" in err, err
    assert listeners and all(listener.fileno() == -1 for listener in listeners)  # closed



def test_a_paced_drip_keeps_its_chunks_and_pauses(monkeypatch):
    """Found by reviewing the change that sends a paced frame's header first (16 bytes, as a UART sends it): under
    ``--drip-chunk 100 --drip-delay D`` at the emulator's default link rate, the header split became a drip chunk of
    its own, so a 300-byte reply paused three times (after 16, 116 and 216 bytes) instead of twice, after 100 and 200
    bytes, as the fault says ("every reply is sent in chunks of this many bytes")."""
    from types import SimpleNamespace

    from hw.emulator import _BoardPort
    from hw.emulator_state import Reply

    pauses, pieces = [], []

    class Clock:
        @staticmethod
        def wait(seconds):
            if seconds == 0.01:
                pauses.append(sum(map(len, pieces)))  # bytes sent before the pause
            return False

    board = SimpleNamespace(link_bytes_per_s=1e12, stop_event=Clock(),
                            _write=lambda out, data: pieces.append(bytes(data)) or True)
    data = bytes(range(256)) + bytes(44)
    assert _BoardPort._send_reply(board, Reply(data, chunk_bytes=100, chunk_delay_s=0.01), None) is not None
    assert b"".join(pieces) == data and pauses == [100, 200]
    assert len(pieces[0]) == 16  # the header still leaves first
    pieces.clear()
    assert _BoardPort._send_reply(board, Reply(b""), None) is not None and pieces == []  # nothing, no empty write
