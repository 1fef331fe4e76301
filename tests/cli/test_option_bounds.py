"""Option values out of what they can mean are refused when parsed, exit 2 with one line naming the option and the
range it takes (an audit of option bounds: each was taken before, and ran to nonsense or to a hang)."""

from __future__ import annotations

import pytest

from svs_torch.cli import main

def _refused(capsys, argv: list[str]) -> str:
    """The one error line of ``svs-depth argv``, which must exit 2 before anything runs."""
    with pytest.raises(SystemExit) as exited:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exited.value.code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("command", ["estimate", "eval"])
@pytest.mark.parametrize("option, value, expected", [
    # 1e30 ranged Teddy at 3e27 m with the status OK; 1e39 overflowed float32 ("focal_px: ... got inf")
    ("--focal-px", "1e30", "a focal length in pixels from 1 to 1,000,000"),
    ("--focal-px", "1e39", "a focal length in pixels from 1 to 1,000,000"),
    ("--baseline-m", "1e20", "a baseline in metres from 0.001 to 2 (millimetres / 1000)"),
    # the SVS's baseline in millimetres: every distance 1000 times too far, status OK (an audit)
    ("--baseline-m", "107", "a baseline in metres from 0.001 to 2 (millimetres / 1000)"),
    # every object at 0.000 m, status OK (an audit of numbers read from files, whose bounds these are too)
    ("--focal-px", "1e-30", "a focal length in pixels from 1 to 1,000,000"),
    ("--baseline-m", "1e-30", "a baseline in metres from 0.001 to 2 (millimetres / 1000)"),
    # every object at 0.000 m, status OK
    ("--doffs-px", "1e30", "pixels from -1,000,000 to 1,000,000"),
])
def test_calibration_options_out_of_any_rig_are_refused(capsys, command, option, value, expected):
    # (refused when parsed: the pair's files are never read)
    err = _refused(capsys, [command, "left.png", "right.png", f"{option}={value}"] if command == "estimate"
                   else [command, "scenes/", f"{option}={value}"])
    assert f"argument {option}: expected {expected}, got '{value}'" in err


def test_calibration_options_of_real_rigs_are_taken():
    """The bounds' own values and the shared data's rigs (KITTI's focal and baseline, MiddEval3's doffs) parse."""
    from svs_torch.cli.rig import baseline_m_value, doffs_px_value, focal_px_value

    assert focal_px_value("1e6") == 1e6 and focal_px_value("721.5") == 721.5 and focal_px_value("1") == 1
    assert baseline_m_value("2") == 2 and baseline_m_value("0.54") == 0.54 and baseline_m_value("0.001") == 0.001
    assert doffs_px_value("-1e6") == -1e6 and doffs_px_value("131.111") == 131.111


@pytest.mark.parametrize("command", ["capture", "guide"])
@pytest.mark.parametrize("value", ["1", "9599", "12000001", "10000000000000"])
def test_baud_outside_serial_speeds_is_refused(capsys, tmp_path, command, value):
    """``--baud 1`` allowed each frame attempt 40 days (a board that stopped mid-frame held the run, silent), and
    ``--baud 1e13`` allowed every frame 2 s whatever its size."""
    # (--count 1: what the old code ran, ended)
    argv = [command, "--emulator", "--count", "1", f"--baud={value}"] + (
        ["--out", str(tmp_path / "x")] if command == "capture" else ["--no-speech"])
    assert f"argument --baud: expected a UART speed from 9600 to 12000000 baud, got '{value}'" in _refused(capsys, argv)
    assert not (tmp_path / "x").exists()


def test_baud_of_real_boards_is_taken():
    from svs_torch.cli import build_parser

    for baud in (9600, 115200, 2304000, 12000000):
        assert build_parser().parse_args(["capture", "--out", "x", "--baud", str(baud)]).baud == baud


@pytest.mark.parametrize("argv, message", [
    # 10**9: after 1000 pairs of a clear way a new obstacle went unwarned for 1001 pairs
    (["--confirm-frames", "22"], "argument --confirm-frames: expected a number of pairs from 1 to 21, got '22'"),
    (["--confirm-frames", "1000000000"], "expected a number of pairs from 1 to 21"),
    # 1e9: no floor in view, unsaid (none of its pixels seen from 3 m up at 320x240)
    (["--emulator-floor-m", "3"], "argument --emulator-floor-m: expected metres from 0.01 to under 3 (higher, the "
                                  "emulator's cameras see no floor before its wall 4 m ahead), got '3'"),
    (["--emulator-floor-m", "1e9"], "argument --emulator-floor-m: expected metres from 0.01 to under 3"),
    # 1e-300: the renderer's floor disparities overflowed float32, its thread died with a traceback, and guide ranged
    # the stand-in's frames, which have no floor, unsaid
    (["--emulator-floor-m", "1e-300"], "argument --emulator-floor-m: expected metres from 0.01 (lower, the cameras "
                                       "lie on the floor) to under 3, got '1e-300'"),
    (["--emulator-floor-m", "0.009"], "argument --emulator-floor-m: expected metres from 0.01"),
])
def test_guide_values_past_their_meaning_are_refused(capsys, argv, message):
    assert message in _refused(capsys, ["guide", "--emulator", "--no-speech", "--count", "1", *argv])


def test_guide_values_in_range_are_taken():
    from svs_torch.cli import build_parser

    args = build_parser().parse_args(["guide", "--emulator", "--confirm-frames", "21", "--emulator-floor-m", "2.9"])
    assert (args.confirm_frames, args.emulator_floor_m) == (21, 2.9)
    assert build_parser().parse_args(["guide", "--emulator", "--emulator-floor-m", "0.01"]).emulator_floor_m == 0.01


def test_emulator_noise_sigma_is_bounded_as_svs_depths_emulator_noise(capsys):
    """``python -m hw.emulator --noise-sigma 1e9`` served frames of pixels all 0 or 255 (no scene left); the σ now
    takes 0 to 255 8-bit levels, as ``svs-depth guide/capture --emulator-noise``."""
    from hw.emulator import main as emulator_main

    with pytest.raises(SystemExit) as stopped:
        emulator_main(["--noise-sigma", "1e9", "--left-port", "0", "--right-port", "0"])
    err = capsys.readouterr().err
    assert stopped.value.code == 2 and "argument --noise-sigma: expected a noise σ in 8-bit levels, 0 to 255" in err


@pytest.mark.parametrize("argv, message", [
    # 1e9 served frames with no floor in them, unsaid; 1280x1024 pitched 20 degrees sees none from 3.11 m up
    (["--floor-height-m", "1e9"], "--floor-height-m: expected under 3.11 m with --camera-pitch-deg 20 (higher, no "
                                  "size a board sends shows any floor before the wall 4 m ahead), got 1e+09"),
    (["--floor-height-m", "1.3", "--camera-pitch-deg", "-30"],
     "--floor-height-m: cameras at --camera-pitch-deg -30 see no floor at any height"),
    # 1e-300: the render thread died (float32 disparities of the floor overflowed) and every frame was the stand-in's
    (["--floor-height-m", "1e-300"], "--floor-height-m: expected at least 0.01 m (lower, the cameras lie on the "
                                     "floor), got 1e-300"),
])
def test_emulator_floor_out_of_view_is_refused(capsys, argv, message):
    """``python -m hw.emulator --floor-height-m`` above what its cameras see of the floor before the synthetic wall
    (checked against the renderer: at pitch 0, 20, 60 and -20 degrees, 5 cm below the bound some floor pixels, 5 cm
    above none)."""
    from hw.emulator_args import parse_args

    with pytest.raises(SystemExit) as stopped:
        parse_args(argv, "emulator", 230400.0)
    assert stopped.value.code == 2 and message in capsys.readouterr().err
    assert parse_args(["--floor-height-m", "3.1"], "emulator", 230400.0).floor_height_m == 3.1


def test_emulator_floor_bound_is_where_the_renderer_stops_drawing_floor():
    import math

    import torch

    from hw.emulator_args import _highest_floor_seen_m
    from svs_torch.data.synthetic import render_obstacle_scenes

    for pitch_deg in (0.0, 20.0):
        highest_m = _highest_floor_seen_m(pitch_deg)
        assert math.isclose(highest_m, {0.0: 1.853, 20.0: 3.110}[pitch_deg], abs_tol=1e-3)
        seen = [int(render_obstacle_scenes(torch.tensor([[2.0]]), torch.tensor([[[5.0, 0.0]]]),
                                           torch.tensor([[[0.1, 0.1]]]), size_wh=(1280, 1024), supersample=1,
                                           generator=torch.Generator().manual_seed(0), floor_height_m=height_m,
                                           camera_pitch_deg=pitch_deg).floor_mask.sum())
                for height_m in (highest_m - 0.05, highest_m + 0.05)]
        assert seen[0] > 0 and seen[1] == 0, (pitch_deg, seen)
