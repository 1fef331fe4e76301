"""svs-depth calibrate and --calibration: OpenCV's stereo calibration of the shared chessboard pairs, the file, and
pairs rectified with it (checked by finding the board again in the rectified images, independently of the maps)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.cli import main
from svs_torch.data import load_image_pair, resize_stereo_batch
from svs_torch.geometry.calibration import read_calibration, rectify_with_calibration, write_calibration
from svs_torch.geometry.chessboard import (board_image_u8, calibrate_stereo_rig, collect_board_views, fit_doubts,
                                          find_board_corners)
from svs_torch.plotting.rectified import spread_rows
from svs_torch.segmentation.segment import SegmentationConfig

BOARD = (9, 6)
SQUARE_M = 0.025  # nominal: the shared set's square size is unknown (MANIFEST: |T| = 3.34 squares)


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as stop:  # argparse's usage errors
        code = stop.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def samples(data_dir) -> Path:
    return data_dir / "opencv_samples"


@pytest.fixture(scope="module")
def rig(samples):
    """The shared set calibrated once (about 0.3 s): (calibration, board views)."""
    lefts = sorted(samples.glob("left*.jpg"))
    pairs = [(str(f), cv2.imread(str(f), 0), cv2.imread(str(f).replace("left", "right"), 0)) for f in lefts]
    views = collect_board_views(pairs, BOARD)
    return calibrate_stereo_rig(views, SQUARE_M, BOARD, "test"), views


def _row_error_found_again(batch, index: int = 0) -> np.ndarray:
    """|y_left − y_right| of the board's corners found by OpenCV in the rectified images of pair ``index``."""
    corners = [find_board_corners((image[index, 0].numpy() * 255).round().astype(np.uint8), BOARD)
               for image in (batch.left, batch.right)]
    assert corners[0] is not None and corners[1] is not None
    return np.abs(corners[0][:, 1] - corners[1][:, 1])


def test_shared_chessboards_calibrate_with_small_errors(rig):
    calibration, views = rig
    assert len(views.names) == 13 and not views.skipped  # MANIFEST: all 13 pairs give 9x6 corners
    assert max(calibration.rms_left_px, calibration.rms_right_px, calibration.rms_stereo_px) < 1.0
    assert calibration.row_error_mean_px < 0.3
    # MANIFEST (an independent run of OpenCV's stereo calibration): fx about 536 px, |T| about 3.34 squares.
    assert calibration.K_left[0, 0] == pytest.approx(536, rel=0.01)
    assert np.linalg.norm(calibration.T) == pytest.approx(3.34 * SQUARE_M, rel=0.01)
    assert calibration.baseline_m == pytest.approx(np.linalg.norm(calibration.T), rel=1e-3)
    assert calibration.doffs_px == pytest.approx(calibration.P2[0, 2] - calibration.P1[0, 2])


def test_a_board_named_rows_first_calibrates_as_columns_first(rig, samples):
    """Found by an audit: --board 6x9 for the 9x6 board refined its corners in windows sized by the spacing along
    the board's short side only (11 px where 7 fit): stereo RMS 0.42 px and a row error of 3.6 px, for 0.20 / 0.63."""
    calibration, _ = rig
    lefts = sorted(samples.glob("left*.jpg"))
    pairs = [(str(f), cv2.imread(str(f), 0), cv2.imread(str(f).replace("left", "right"), 0)) for f in lefts]
    transposed = calibrate_stereo_rig(collect_board_views(pairs, BOARD[::-1]), SQUARE_M, BOARD[::-1])
    assert transposed.rms_stereo_px == pytest.approx(calibration.rms_stereo_px, abs=1e-3)
    assert transposed.row_error_max_px == pytest.approx(calibration.row_error_max_px, abs=1e-2)
    assert transposed.baseline_m == pytest.approx(calibration.baseline_m, rel=1e-4)


def test_rectified_pair_has_the_board_on_the_same_rows(rig, samples):
    calibration, _ = rig
    raw = load_image_pair(samples / "left01.jpg", samples / "right01.jpg")
    assert np.median(_row_error_found_again(raw)) > 5  # the raw pair's rows do not agree
    batch = rectify_with_calibration(raw, calibration)
    assert np.median(_row_error_found_again(batch)) < 0.3
    assert bool(batch.calibrated[0]) and float(batch.focal_px[0]) == pytest.approx(calibration.P1[0, 0])
    # The batched grid_sample against OpenCV's own remap of the same maps.
    maps = cv2.initUndistortRectifyMap(calibration.K_left, calibration.dist_left, calibration.R1, calibration.P1,
                                       calibration.image_wh, cv2.CV_32FC1)
    reference = cv2.remap(cv2.imread(str(samples / "left01.jpg"), 0), *maps, cv2.INTER_LINEAR) / 255.0
    assert np.abs(batch.left[0, 0].numpy() - reference).max() < 0.01


def test_resized_pair_uses_scaled_intrinsics(rig, samples, tmp_path):
    calibration, _ = rig
    raw = resize_stereo_batch(load_image_pair(samples / "left03.jpg", samples / "right03.jpg"), (320, 240))
    batch = rectify_with_calibration(raw, calibration)
    assert float(batch.focal_px[0]) == pytest.approx(calibration.focal_px / 2, rel=1e-6)
    assert float(batch.baseline_m[0]) == pytest.approx(calibration.baseline_m)
    assert np.median(_row_error_found_again(batch)) < 0.3
    # Unscaled maps would put the rectified board elsewhere: its corners are where the full-size ones are, halved.
    full = rectify_with_calibration(load_image_pair(samples / "left03.jpg", samples / "right03.jpg"), calibration)
    found = [find_board_corners((b.left[0, 0].numpy() * 255).round().astype(np.uint8), BOARD) for b in (batch, full)]
    assert np.abs((found[0] + 0.5) * 2 - 0.5 - found[1]).max() < 0.5
    # Q at the new size gives the same 3-D point for the same pixel and disparity, halved.
    half = calibration.scaled_to((320, 240))
    old_point, new_point = calibration.Q @ [100.0, 50.0, 20.0, 1.0], half.Q @ [49.75, 24.75, 10.0, 1.0]
    np.testing.assert_allclose(new_point[:3] / new_point[3], old_point[:3] / old_point[3], rtol=1e-9)
    # ... in the form OpenCV writes it for P1 and P2, so a file of the scaled rig reads back.
    write_calibration(tmp_path / "half.json", half)
    np.testing.assert_array_equal(read_calibration(tmp_path / "half.json").Q, half.Q)
    with pytest.raises(InputError, match="--calibration: made at 640x480, the pair is 320x320"):
        rectify_with_calibration(resize_stereo_batch(raw, (320, 320)), calibration)


def test_file_round_trips(rig, tmp_path):
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    again = read_calibration(path)
    for name in ("K_left", "dist_left", "K_right", "dist_right", "R", "T", "R1", "R2", "P1", "P2", "Q"):
        np.testing.assert_array_equal(getattr(again, name), getattr(calibration, name))
    assert again.image_wh == (640, 480) and again.rms_stereo_px == calibration.rms_stereo_px
    record = json.loads(path.read_text())
    assert record["board"] == {"inner_corners": [9, 6], "square_m": SQUARE_M} and record["num_pairs"] == 13
    # Saved again by Notepad or Windows PowerShell (a UTF-8 or UTF-16 BOM): refused as not JSON before (an audit).
    for encoding in ("utf-8-sig", "utf-16"):
        (tmp_path / "saved.json").write_text(path.read_text(), encoding=encoding)
        np.testing.assert_array_equal(read_calibration(tmp_path / "saved.json").P2, calibration.P2)
    assert record["baseline_m"] == pytest.approx(calibration.baseline_m) and record["created_utc"]


def _in_millimetres(record: dict, factor: float = 1000) -> dict:
    """The rig's file as an older calibrate wrote it for a square given in millimetres: T, P2's baseline term and
    Q's in mm (one rig, consistent); another ``factor``, in other units."""
    P2 = [list(row) for row in record["P2"]]
    P2[0][3] *= factor
    Q = [list(row) for row in record["Q"]]
    Q[3][2], Q[3][3] = Q[3][2] / factor, Q[3][3] / factor
    return {**record, "T_m": [v * factor for v in record["T_m"]], "P2": P2, "Q": Q, "baseline_m": None}


def _rectified_focal(record: dict, focal_px: float) -> dict:
    """The rig's file with P1, P2 and Q of another rectified focal length (the baseline kept): one rig, consistent,
    whose rectified views magnify the raw image's centre."""
    from svs_torch.geometry.calibration import _implied_q

    P1, P2 = np.array(record["P1"]), np.array(record["P2"])
    baseline_m = -P2[0, 3] / P2[0, 0]
    P1[0, 0] = P1[1, 1] = P2[0, 0] = P2[1, 1] = focal_px
    P2[0, 3] = -focal_px * baseline_m
    summary = {key: None for key in ("focal_px", "baseline_m", "doffs_px")}
    return {**record, **summary, "P1": P1.tolist(), "P2": P2.tolist(), "Q": _implied_q(P1, P2).tolist()}


def test_a_huge_number_in_a_summary_value_is_read_as_unknown(rig, tmp_path):
    """A 400-digit RMS (nothing reads it to rectify) ended in 'internal error: OverflowError'."""
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    path.write_text(json.dumps({**json.loads(path.read_text()), "rms_left_px": 10 ** 400}))
    assert math.isnan(read_calibration(path).rms_left_px)


@pytest.mark.parametrize("change, message", [
    (lambda r: "not json {", "expected a JSON calibration file"),
    (lambda r: {**r, "format": "other"}, "expected a JSON object with \"format\""),
    (lambda r: {k: v for k, v in r.items() if k != "K_left"}, "expected 'K_left' as 3x3 finite numbers"),
    (lambda r: {**r, "P2": [[1, 2], [3, 4]]}, "expected 'P2' as 3x4 finite numbers"),
    (lambda r: {**r, "image_size_wh": [640]}, "expected 'image_size_wh' as \\[width, height\\]"),
    (lambda r: {**r, "dist_left": [0, 1]}, "expected 'dist_left' as 4, 5, 8"),
    (lambda r: {**r, "P2": [[500, 0, 320, 40], [0, 500, 240, 0], [0, 0, 1, 0]]}, "expected P1, P2 of a left-right rig"),
    # Hand edits of one part of the rig alone: refused, not half applied (the part the rectification reads wins).
    (lambda r: {**r, "pairs": None}, "expected 'pairs' as a list"),
    (lambda r: {**r, "R1": [[0, 0, 0]] * 3}, "expected 'R1' as a rotation"),
    (lambda r: {**r, "P1": [[100, *r["P1"][0][1:]], *r["P1"][1:]]}, "expected P1 and P2 with one focal length"),
    (lambda r: {**r, "T_m": [0, 0, 0]}, r"expected \|T_m\| = the baseline of P2"),
    (lambda r: {**r, "Q": [*r["Q"][:2], [0, 0, 0, 1e308], r["Q"][3]]}, "expected 'Q' as the reprojection matrix"),
    (lambda r: {**r, "baseline_m": 0.09}, "'baseline_m' 0.09 is not the 0.0831805 its P1 and P2 give"),
    (lambda r: {**r, "format_version": 99}, "expected 'format_version' 1 to 1"),
    (lambda r: {**r, "K_left": [[str(v) for v in row] for row in r["K_left"]]}, "expected 'K_left' as 3x3 finite"),
    # Found by an audit of the rig file: each gave wrong distances in silence, an internal error or a crash.
    (lambda r: _in_millimetres(r), "expected a baseline of 1 mm to 2 m, got 83.1805 m: a calibration in millimetres"),
    # ... and one whose baseline is under 1 mm was called one in millimetres too.
    (lambda r: _in_millimetres(r, 0.01), "expected a baseline of 1 mm to 2 m, got 0.000831805 m: a calibration of a "
                                         "square given too small"),
    (lambda r: {**r, "K_left": [[r["K_left"][0][0], 10 ** 400, r["K_left"][0][2]], *r["K_left"][1:]]},
     "expected 'K_left' as 3x3 finite"),
    (lambda r: {**r, "image_size_wh": [6400000, 4800000]},
     r"expected 'image_size_wh' as \[width, height\], two positive integers of at most 8192 px"),
    (lambda r: "[" * 100000 + "]" * 100000, r"expected a JSON calibration file \(nested too deep to be one\)"),
    (lambda r: "%YAML:1.0\n---\nK1: !!opencv-matrix\n", r"an OpenCV FileStorage file \(YAML/XML\) is not read"),
    (lambda r: " " * (1 << 20) + json.dumps(r), "expected a calibration file of at most 1 MB"),
    # Hand edits of K, the distortion or the image size, which no other part checks: wrong distances in silence.
    (lambda r: {**r, "image_size_wh": [1280, 960]}, "its left camera's K, distortion and image_size_wh rectify only "
                                                    "68 % of the view from inside the image"),
    (lambda r: {**r, "dist_left": [2.0, *r["dist_left"][1:]]}, "its left camera's .* rectify only 49 %"),
    (lambda r: {**r, "dist_right": [1e30, *r["dist_right"][1:]]}, "its right camera's .* rectify only 0 %"),
    (lambda r: {**r, "image_size_wh": [320, 240]}, r"'K_left' puts the lens centre at \(342, 234\) px, far from"),
    # An audit of numbers read from files: rectified views of a raw pixel or two each (NO_OBJECTS, a clear path)
    # and a focal of 1e30 px in the reports; now the bound of --focal-px.
    (lambda r: _rectified_focal(r, 1e7),
     r"expected P1, P2 of a left-right rig \(P1\[0\]\[0\] a focal length in pixels from 1 to 1,000,000, "
     r"baseline -P2\[0\]\[3\]/P2\[0\]\[0\] over 0\), got 1e\+07 px, 0.0831805 m"),
    (lambda r: _rectified_focal(r, 1e30), r"expected P1, P2 of a left-right rig .*got 1e\+30 px"),
    # P1 and P2 not in stereoRectify's form, whose maps OpenCV cannot make: an internal error (an audit).
    (lambda r: {**r, "P1": [*r["P1"][:2], [0, 0, 0, 0]]}, r"expected P1 and P2 with one focal length and one row "
                                                          r"centre \(rectified views: \[\[f, 0, cx, 0 or -f"),
    (lambda r: {**r, "P1": [r["P1"][0], [0, 0, *r["P1"][1][2:]], r["P1"][2]],
                "P2": [r["P2"][0], [0, 0, *r["P2"][1][2:]], r["P2"][2]]}, "expected P1 and P2 with one focal length"),
    # A 400-digit summary value, which is no float: an internal error (OverflowError), and not 400 digits said.
    (lambda r: {**r, "focal_px": 10 ** 400}, r"'focal_px' 10{29} is not the 516.2"),
    (lambda r: {**r, "doffs_px": "0"}, r"'doffs_px' '0' is not the 0 its P1 and P2 give"),
])
def test_bad_files_give_one_line_errors(rig, tmp_path, change, message):
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    changed = change(json.loads(path.read_text()))
    path.write_text(changed if isinstance(changed, str) else json.dumps(changed))
    with pytest.raises(InputError, match=f"--calibration: .*rig.json: {message}") as raised:
        read_calibration(path)
    assert "\n" not in str(raised.value)
    with pytest.raises(InputError, match="no such file"):
        read_calibration(tmp_path / "missing.json")


def test_calibrate_command(capsys, samples, tmp_path):
    out, figure = tmp_path / "rig.json", tmp_path / "rig.png"
    code, stdout, _ = run_cli(capsys, "calibrate", str(samples / "left*.jpg"), "--square-m", "0.025", "--out",
                              str(out), "--figure", str(figure))
    assert code == 0
    assert "reprojection RMS: left 0.177 px, right 0.181 px, stereo 0.196 px" in stdout
    assert "rectified row error on the chessboards: mean 0.102 px, max 0.629 px" in stdout
    assert ("right camera: its view rolled 0.2° anticlockwise, turned +0.2° about y, +0.4° about x; 83.2 mm right, "
            "0.7 mm higher, 0.1 mm ahead of the left") in stdout
    assert read_calibration(out).pairs[0].endswith("left01.jpg")
    assert f"wrote {out}; figure written to {figure}" in stdout  # said as other commands say it (an audit)
    image = cv2.imread(str(figure))
    assert image is not None and image.shape[1] > 2 * 400
    code, stdout, _ = run_cli(capsys, "calibrate", str(samples / "left0[1-4].jpg"), "--square-m", "0.025",
                              "--out", str(out), "--json")
    assert code == 0 and json.loads(stdout)["num_pairs"] == 4
    # The right camera's pose against the left's, what a developer remounts a loose board by (an addition):
    # R = Rz(roll)·Ry(y)·Rx(x) recomposed from what is said, and its centre as far from the left's as the baseline.
    said, written = json.loads(stdout), read_calibration(out)
    roll, about_y, about_x = (math.radians(v) for v in (said["right_camera_roll_deg"], *said["right_camera_turn_deg"]))
    turns = [cv2.Rodrigues(np.array(axis, dtype=np.float64) * angle)[0]
             for axis, angle in (([0, 0, 1], roll), ([0, 1, 0], about_y), ([1, 0, 0], about_x))]
    assert np.abs(turns[0] @ turns[1] @ turns[2] - written.R).max() < 1e-4
    assert np.linalg.norm(said["right_camera_offset_m"]) == pytest.approx(written.baseline_m, abs=1e-4)
    assert said["right_camera_offset_m"][0] > 0.08  # the right camera is to the right
    listed = tmp_path / "boards.txt"
    listed.write_text("".join(f"{samples / f'left0{n}.jpg'} {samples / f'right0{n}.jpg'}\n" for n in (5, 6, 7)))
    code, stdout, _ = run_cli(capsys, "calibrate", "--pairs", str(listed), "--square-m", "0.025", "--out", str(out),
                              "--json")
    assert code == 0 and [Path(p).name for p in json.loads(stdout)["pairs"]] == ["left05.jpg", "left06.jpg",
                                                                                "left07.jpg"]


def test_calibrate_shows_its_progress_over_the_pairs(capsys, samples, tmp_path, monkeypatch):
    """Was: calibrate decoded every image, then searched each for the board, without a word: 20 pairs of a 12-MP
    camera took minutes of silence (an audit of calibrate). Now a progress bar (plain lines into a log) counts the
    pairs as their boards are looked for, each pair decoded only then."""
    from svs_torch.cli import progress

    counted = []
    real_update = progress.Progress.update
    monkeypatch.setattr(progress.Progress, "update",
                        lambda self, count=1: (real_update(self, count), counted.append((self.desc, self.done))))
    code, _, stderr = run_cli(capsys, "calibrate", str(samples / "left0[1-5].jpg"), "--square-m", "0.025",
                              "--out", str(tmp_path / "rig.json"))
    assert code == 0 and counted == [("calibrate", n) for n in range(1, 6)]
    assert "calibrate: 5/5" not in stderr  # no summary line: the report says how many pairs were used


@pytest.mark.parametrize("argv, message", [
    (["--board", "9"], "--board: expected inner corners as COLSxROWS"),
    (["--board", "2x6"], "--board: expected inner corners as COLSxROWS, each 3 to 100"),  # OpenCV's own limit
    (["--board", "7x5"], "left: the 7x5 board was found in both views of 0 of 2 pairs"),
])
def test_calibrate_bad_input(capsys, samples, tmp_path, argv, message):
    code, _, stderr = run_cli(capsys, "calibrate", str(samples / "left0[12].jpg"), "--square-m", "0.025",
                              "--out", str(tmp_path / "rig.json"), *argv)
    assert code == 2 and message in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "rig.json").exists()


def test_calibrate_finds_the_right_images_in_a_right_folder(capsys, samples, tmp_path):
    """Found by an audit: a rig's views kept as left/01.jpg and right/01.jpg (names without 'left') were refused,
    'has no 'left' in its name', and the folder itself was answered with a pattern that matched none of them."""
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for number in ("01", "02", "03", "04"):
            (tmp_path / side / f"{number}.jpg").write_bytes((samples / f"{side}{number}.jpg").read_bytes())
    out = tmp_path / "rig.json"
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left" / "*.jpg"), "--square-m", "0.025", "--out",
                              str(out))
    assert code == 0 and read_calibration(out).pairs == tuple(str(tmp_path / "left" / f"0{n}.jpg") for n in "1234")
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left"), "--square-m", "0.025", "--out", str(out))
    assert code == 2 and f"e.g. '{tmp_path / 'left' / '*.jpg'}' (quoted)" in stderr


def test_calibrate_counts_each_pair_once_and_refuses_listed_calibrations(capsys, samples, tmp_path):
    listed = tmp_path / "boards.txt"
    listed.write_text(f"{samples / 'left01.jpg'} {samples / 'right01.jpg'}\n" * 3)  # one view, not three
    code, _, stderr = run_cli(capsys, "calibrate", "--pairs", str(listed), "--square-m", "0.025", "--out",
                              str(tmp_path / "rig.json"))
    assert code == 2 and "--pairs: the 9x6 board was found in both views of 1 of 1 pairs" in stderr
    listed.write_text(f"{samples / 'left01.jpg'} {samples / 'right01.jpg'} 500 0.1\n")
    code, _, stderr = run_cli(capsys, "calibrate", "--pairs", str(listed), "--square-m", "0.025", "--out",
                              str(tmp_path / "rig.json"))
    assert code == 2 and "expected 'LEFT RIGHT' lines of chessboard images, got line 1 of" in stderr
    # A line of one field: the message offered a calibration line or a scene folder, which calibrate refuses.
    listed.write_text(f"{samples / 'left01.jpg'}\n")
    code, _, stderr = run_cli(capsys, "calibrate", "--pairs", str(listed), "--square-m", "0.025", "--out",
                              str(tmp_path / "rig.json"))
    assert code == 2 and "expected 'LEFT RIGHT' (two chessboard images), got 1 field" in stderr
    assert "scene folder" not in stderr and "FOCAL_PX" not in stderr
    # A missing image is named with its list line (a long list's "file not found" said neither before).
    listed.write_text(f"{samples / 'left01.jpg'} {samples / 'right01.jpg'}\n{tmp_path / 'gone.jpg'} "
                      f"{samples / 'right02.jpg'}\n")
    code, _, stderr = run_cli(capsys, "calibrate", "--pairs", str(listed), "--square-m", "0.025", "--out",
                              str(tmp_path / "rig.json"))
    assert code == 2 and f"--pairs, line 2 of {listed}: file not found: " in stderr
    (tmp_path / "afile").write_text("")  # an --out below a file: it was said not to exist
    code, _, stderr = run_cli(capsys, "calibrate", str(samples / "left0[1-4].jpg"), "--square-m", "0.025", "--out",
                              str(tmp_path / "afile" / "rig.json"))
    assert code == 2 and "--out: " in stderr and "afile' is not a folder (it is a file)" in stderr


def test_calibrate_names_copies_of_one_pose_one_image_twice_and_a_square_in_millimetres(capsys, samples, tmp_path):
    """Found by an audit: four copies of one pair under other names, or each left image given as its own right,
    ended with "are LEFT and RIGHT swapped?"; --square-m 25 (millimetres typed as metres) wrote an 83 m baseline."""
    import shutil

    copies = tmp_path / "copies"
    copies.mkdir()
    for number in range(1, 5):
        for view in ("left", "right"):
            shutil.copy(samples / f"{view}01.jpg", copies / f"{view}0{number}.jpg")
    out = tmp_path / "rig.json"
    code, _, stderr = run_cli(capsys, "calibrate", str(copies / "left*.jpg"), "--square-m", "0.025", "--out", str(out))
    assert code == 2 and "left: the board is in 1 pose(s) over 4 pairs (copies of one pair?); expected at least 3" in stderr
    listed = tmp_path / "boards.txt"
    listed.write_text("".join(f"{samples / f'left0{n}.jpg'} {samples / f'left0{n}.jpg'}\n" for n in (1, 2, 3, 4)))
    code, _, stderr = run_cli(capsys, "calibrate", "--pairs", str(listed), "--square-m", "0.025", "--out", str(out))
    assert code == 2 and "--pairs: the left and right views show the board at the same pixels in every pair" in stderr
    code, _, stderr = run_cli(capsys, "calibrate", str(samples / "left0[1-4].jpg"), "--square-m", "25", "--out",
                              str(out))
    assert code == 2 and "--square-m: expected the side of one square in metres, at most 1 (25 mm is 0.025)" in stderr
    assert not out.exists()
    # refused as it is parsed, before a single chessboard is read (the folder here does not exist)
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "none" / "left*.jpg"), "--square-m", "25",
                              "--out", str(out))
    assert code == 2 and "--square-m" in stderr and "none" not in stderr
    with pytest.raises(InputError, match="--square-m: expected the side of one square in metres, 0.001 to 1"):
        calibrate_stereo_rig(None, 25.0, (9, 6), "test", "left")
    # A square the option takes can still make a baseline no file may hold (1 m squares: 3.3 m): refused, not written.
    code, _, stderr = run_cli(capsys, "calibrate", str(samples / "left0[1-4].jpg"), "--square-m", "1", "--out", str(out))
    assert code == 2 and "--square-m: expected a baseline of 1 mm to 2 m, got 3.3" in stderr and not out.exists()
    # Squares under 1 mm are refused as they are parsed: 1e-20 ended in an OpenCV assertion ('internal error').
    for tiny in ("1e-20", "0.0005"):
        code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "none" / "left*.jpg"), "--square-m", tiny,
                                  "--out", str(out))
        assert code == 2 and "--square-m: expected the side of one square in metres, at least 0.001 (1 mm" in stderr


def test_calibrate_counts_poses_not_pairs_when_it_warns_of_too_few(capsys, samples, tmp_path):
    """Found by an audit of a rig set up with capture: 13 pairs captured from the emulator showing the 13 shared
    boards were 7 poses, each board held still for two grabs, and calibrate said nothing (it warns under 10 pairs).
    Each of 6 poses here is grabbed twice, the second time with its own sensor noise: the warning says 12 pairs but
    6 poses; the file is the one it wrote before."""
    rng = np.random.default_rng(0)
    boards = tmp_path / "boards"
    boards.mkdir()
    for number in range(1, 7):
        for view in ("left", "right"):
            image = cv2.imread(str(samples / f"{view}0{number}.jpg"), cv2.IMREAD_GRAYSCALE)
            for grab, noise in ((2 * number - 1, 0.0), (2 * number, 2.0)):
                noisy = np.clip(image + rng.normal(0.0, noise, image.shape), 0, 255).astype(np.uint8)
                cv2.imwrite(str(boards / f"{view}{grab:02d}.png"), noisy)
    code, stdout, stderr = run_cli(capsys, "calibrate", str(boards / "left*.png"), "--square-m", "0.025", "--out",
                                   str(tmp_path / "rig.json"), "--json")
    report = json.loads(stdout)
    assert code == 0 and len(report["pairs"]) == 12
    assert report["warnings"] == ["calibrated from 12 pairs but 6 poses of the board (the others show it where "
                                  "another pair does, within 1 px: held still between grabs): 10-20 poses of the "
                                  "board across the field give a steadier focal length and baseline"]
    assert report["warnings"][0] in " ".join(stderr.split())


def test_calibrate_leaves_out_a_pair_whose_views_do_not_fit_and_warns_of_a_poor_fit(capsys, samples, tmp_path):
    """Found by an audit: six good pairs and a seventh holding the same right image twice wrote a stereo RMS of
    13.6 px, a row error of 9 px and a 0.19 m baseline (0.083 m), exit 0 and no word; guide then said "Stop" at
    0.9 m. Now that pair is left out and named, and the rig is the six pairs' alone."""
    import shutil

    boards = tmp_path / "boards"
    boards.mkdir()
    for number in range(1, 7):
        for view in ("left", "right"):
            shutil.copy(samples / f"{view}0{number}.jpg", boards / f"{view}0{number}.jpg")
    shutil.copy(samples / "right01.jpg", boards / "left07.jpg")
    shutil.copy(samples / "right01.jpg", boards / "right07.jpg")
    out = tmp_path / "rig.json"
    code, stdout, stderr = run_cli(capsys, "calibrate", str(boards / "left*.jpg"), "--square-m", "0.025", "--out",
                                   str(out), "--json")
    report = json.loads(stdout)
    assert code == 0 and "reprojection" not in stderr and not any("reprojection" in w for w in report["warnings"])
    # six pairs used: fewer than the 10-20 the help asks for (three gave a focal length 12 % off, an audit)
    assert report["warnings"] == ["calibrated from 6 pairs: 10-20 poses of the board across the field give a "
                                  "steadier focal length and baseline"] and report["warnings"][0] in stderr
    assert len(report["misfits"]) == 1 and report["misfits"][0].startswith(f"{boards / 'left07.jpg'} (its views do not")
    assert report["rms_stereo_px"] < 0.3 and read_calibration(out).baseline_m == pytest.approx(0.0831, abs=0.001)
    assert str(boards / "left07.jpg") not in report["pairs"] and len(report["pairs"]) == 6
    # Each right view of another pose: no one pair explains the poor fit (52.6 px), and its file would rectify none
    # of a view (every command refused it as edited): refused, the poor fit named.
    poor = tmp_path / "poor"
    poor.mkdir()
    for number in range(1, 5):
        shutil.copy(samples / f"left0{number}.jpg", poor / f"left0{number}.jpg")
        shutil.copy(samples / f"right0{number % 4 + 1}.jpg", poor / f"right0{number}.jpg")
    code, stdout, stderr = run_cli(capsys, "calibrate", str(poor / "left*.jpg"), "--square-m", "0.025", "--out",
                                   str(tmp_path / "poor.json"))
    assert code == 2 and "left: the fit does not rectify its own views" in stderr
    assert "the fit is poor (stereo RMS 52.6 px): check that each pair's two images were taken" in stderr
    assert not (tmp_path / "poor.json").exists()
    # Right views 3 px up or down by turns: a poor fit (1.5 px) that still rectifies is written with a warning.
    for number in range(1, 7):
        image = cv2.imread(str(samples / f"right0{number}.jpg"), 0)
        move = np.float32([[1, 0, 0], [0, 1, 3 * (-1) ** number]])
        cv2.imwrite(str(boards / f"right0{number}.jpg"), cv2.warpAffine(image, move, (640, 480),
                                                                         borderMode=cv2.BORDER_REPLICATE))
    (boards / "left07.jpg").unlink()
    code, stdout, stderr = run_cli(capsys, "calibrate", str(boards / "left*.jpg"), "--square-m", "0.025", "--out",
                                   str(tmp_path / "poor.json"))
    assert code == 0 and "svs-depth calibrate: warning: the stereo reprojection RMS is" in stderr
    assert "no one pair explains it" in stderr and (tmp_path / "poor.json").is_file()


def test_a_right_camera_behind_the_left_is_said_in_english():
    """calibrate's pose line said "0.5 mm behind of the left" (the shared set's first four pairs calibrate to such
    a pose)."""
    from svs_torch.cli.calibrate import _pose_line

    line = _pose_line({"right_camera_roll_deg": 0.2, "right_camera_turn_deg": [0.1, 0.3],
                       "right_camera_offset_m": [0.0832, -0.0006, -0.0005]})
    assert line.endswith("83.2 mm right, 0.6 mm higher, 0.5 mm behind the left"), line


@pytest.mark.parametrize("turn, message", [
    # Found by an audit: a good fit (0.19 px) of a right camera mounted upside down, 83 mm right of the left, and of
    # a rig mounted on its side (the right camera 83 mm below the left) were both blamed on swapped cameras.
    ({"right": cv2.ROTATE_180}, "the right camera's view is rolled 180° against the left's (mounted upside down?)"),
    ({"left": cv2.ROTATE_90_CLOCKWISE, "right": cv2.ROTATE_90_CLOCKWISE},
     "the right camera sits 83 mm below the left, 1 mm beside it: expected the cameras side by side (is the rig "
     "mounted on its side?)"),
])
def test_a_rig_that_is_not_left_right_is_not_called_swapped(capsys, samples, tmp_path, turn, message):
    for number in range(1, 7):
        for view in ("left", "right"):
            image = cv2.imread(str(samples / f"{view}0{number}.jpg"))
            cv2.imwrite(str(tmp_path / f"{view}0{number}.png"), cv2.rotate(image, turn[view]) if view in turn
                        else image)
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left*.png"), "--square-m", "0.025", "--out",
                              str(tmp_path / "rig.json"))
    assert code == 2 and f"left: {message}" in stderr and "swapped" not in stderr, stderr
    assert not (tmp_path / "rig.json").exists()


def test_two_pairs_of_mismatched_views_are_left_out_together_or_named_as_a_poor_fit(capsys, samples, tmp_path):
    """An audit: two pairs of 13 whose right views were another pose's wrote a 0.23 m baseline for 0.083 (stereo RMS
    24.6 px, rows 42 px apart) with exit 0, no one pair halving the RMS; two such of five were blamed on swapped
    cameras. Each pair's own error in the fit now singles out both, left out together; where too many are
    mismatched to tell, the error says the fit is poor."""
    import shutil

    names = sorted(path.name for path in samples.glob("left*.jpg"))
    for folder, chosen in (("many", names), ("few", names[:5])):
        (tmp_path / folder).mkdir()
        for name in chosen:
            for view in ("left", "right"):
                shutil.copy(samples / name.replace("left", view), tmp_path / folder / name.replace("left", view))
        shutil.copy(samples / "right04.jpg", tmp_path / folder / "right02.jpg")
        shutil.copy(samples / "right05.jpg", tmp_path / folder / "right03.jpg")
    out = tmp_path / "rig.json"
    code, stdout, _ = run_cli(capsys, "calibrate", str(tmp_path / "many" / "left*.jpg"), "--square-m", "0.025",
                              "--out", str(out), "--json")
    report = json.loads(stdout)
    assert code == 0 and [m.split(" (")[0] for m in report["misfits"]] == [
        str(tmp_path / "many" / f"left0{n}.jpg") for n in (2, 3)]
    assert report["rms_stereo_px"] < 0.3 and read_calibration(out).baseline_m == pytest.approx(0.0831, abs=0.001)
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "few" / "left*.jpg"), "--square-m", "0.025",
                              "--out", str(tmp_path / "few.json"))
    assert code == 2 and "are LEFT and RIGHT swapped? Or, the fit being poor (stereo RMS" in stderr
    assert not (tmp_path / "few.json").exists()


def test_calibrate_draws_16_bit_boards_and_takes_a_long_figure_name(capsys, samples, tmp_path):
    for view in ("left", "right"):
        for number in (1, 2, 3, 4):
            image = cv2.imread(str(samples / f"{view}0{number}.jpg"), 0).astype(np.uint16) * 257
            cv2.imwrite(str(tmp_path / f"{view}0{number}.png"), image)
    out, figure = tmp_path / "rig.json", tmp_path / "rig.png"
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left*.png"), "--square-m", "0.025", "--out",
                              str(out), "--figure", str(figure))
    assert code == 0, stderr
    assert cv2.imread(str(figure)).mean() > 20  # the rectified boards, not a black picture
    out.unlink()
    long_name = tmp_path / ("é" * 120 + ".png")  # 245 bytes, a name a folder takes: its temporary must fit too
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left*.png"), "--square-m", "0.025", "--out",
                              str(out), "--figure", str(long_name))
    assert code == 0 and long_name.is_file() and out.is_file(), stderr


def test_calibrate_draws_float_boards(capsys, samples, tmp_path):
    # Float captures (a TIFF in [0, 1]) are found as the corner finder sees them, and drawn the same way.
    for view in ("left", "right"):
        for number in (1, 2, 3, 4):
            image = cv2.imread(str(samples / f"{view}0{number}.jpg"), 0).astype(np.float32) / 255
            cv2.imwrite(str(tmp_path / f"{view}0{number}.tif"), image)
    figure = tmp_path / "rig.png"
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left*.tif"), "--square-m", "0.025", "--out",
                              str(tmp_path / "rig.json"), "--figure", str(figure))
    assert code == 0 and cv2.imread(str(figure)).mean() > 20, stderr


def test_a_calibration_of_a_poor_fit_is_warned_of_once_where_it_is_read(capsys, rig, samples, tmp_path):
    """A file written before calibrate left out the pairs that spoil a fit (13.6 px) was read in silence."""
    from dataclasses import replace

    poor = tmp_path / "poor.json"
    write_calibration(poor, replace(rig[0], rms_stereo_px=13.6))
    code, _, stderr = run_cli(capsys, "estimate", str(samples / "left01.jpg"), str(samples / "right01.jpg"),
                              "--calibration", str(poor), "--json")
    assert code == 0 and stderr.count("stereo reprojection RMS is 13.60 px") == 1
    write_calibration(poor, rig[0])
    code, _, stderr = run_cli(capsys, "estimate", str(samples / "left01.jpg"), str(samples / "right01.jpg"),
                              "--calibration", str(poor), "--json")
    assert code == 0 and "reprojection" not in stderr


def test_an_empty_calibration_path_is_refused(capsys, samples):
    # `--calibration "$RIG"` with RIG unset must not range in the SVS model's metres.
    with pytest.raises(SystemExit) as exited:
        main(["estimate", str(samples / "left01.jpg"), str(samples / "right01.jpg"), "--calibration", ""])
    assert exited.value.code == 2 and "--calibration: expected a calibration file" in capsys.readouterr().err


def test_calibrate_names_the_view_of_another_size_and_neither_source(capsys, tmp_path):
    small, large = np.zeros((240, 320), np.uint8), np.zeros((480, 640), np.uint8)
    with pytest.raises(InputError, match="got 320x240 in the right view of b"):
        collect_board_views([("a", large, large), ("b", large, small)], (9, 6))
    code, _, stderr = run_cli(capsys, "calibrate", "--square-m", "0.025", "--out", str(tmp_path / "rig.json"))
    assert code == 2 and "give left images (files or patterns) or --pairs LIST.txt, got neither" in stderr


def test_boards_moved_but_never_tilted_are_refused_not_written(capsys, samples, tmp_path):
    """Found by an audit: four pairs of one pose moved across the field (no tilt) wrote a file at 0.34 px stereo RMS
    with focal 3868 px (516) and a 0.14 m baseline (0.083), exit 0, which every command then refused as edited."""
    for number, shift in enumerate((0, 15, 30, 45)):
        move = np.float32([[1, 0, shift], [0, 1, shift / 3]])
        for view in ("left", "right"):
            image = cv2.imread(str(samples / f"{view}01.jpg"), 0)
            cv2.imwrite(str(tmp_path / f"{view}0{number}.png"),
                        cv2.warpAffine(image, move, (640, 480), borderMode=cv2.BORDER_REPLICATE))
    out = tmp_path / "rig.json"
    code, _, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left*.png"), "--square-m", "0.025", "--out", str(out))
    assert code == 2 and "left: the fit does not rectify its own views (focal " in stderr and "tilt it" in stderr
    assert stderr.count("\n") == 1 and not out.exists()
    # A tilted pose moved alone: focal 877 px (516), a 0.092 m baseline, rows 0.95 px apart: written as before,
    # but no longer with the few pairs as the one warning.
    for number, (dx, dy) in enumerate(((0, 0), (20, -10), (-25, 12), (10, 25), (-15, -20))):
        for view in ("left", "right"):
            image = cv2.imread(str(samples / f"{view}03.jpg"), 0)
            cv2.imwrite(str(tmp_path / f"{view}0{number}.png"), cv2.warpAffine(
                image, np.float32([[1, 0, dx], [0, 1, dy]]), (640, 480), borderMode=cv2.BORDER_REPLICATE))
    code, stdout, stderr = run_cli(capsys, "calibrate", str(tmp_path / "left*.png"), "--square-m", "0.025", "--out",
                                   str(out), "--json")
    assert code == 0 and out.is_file() and "the chessboards' rows lie 0.95 px apart after rectification" in stderr
    assert "tilt the board toward and away" in json.loads(stdout)["warnings"][0]


def test_boards_seen_by_one_camera_alone_name_the_other_camera_not_the_board_size(samples):
    """Found by an audit: with the right camera covered (the board in every left view, in no right one) the error
    said "check --board", though the board size was right."""
    blank = np.full((480, 640), 128, np.uint8)
    pairs = [(f"pair{n}", cv2.imread(str(samples / f"left0{n}.jpg"), 0), blank) for n in (1, 2, 3, 4)]
    with pytest.raises(InputError, match="found in both views of 0 of 4 pairs; expected at least 3: it is in 4 left "
                                         "and 0 right views, and both cameras must see the whole board") as raised:
        collect_board_views(pairs, BOARD, "left")
    assert "--board" not in str(raised.value)


def test_estimate_and_eval_take_the_calibration(capsys, rig, samples, tmp_path):
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    left, right, figure = str(samples / "left01.jpg"), str(samples / "right01.jpg"), tmp_path / "fig.png"
    code, stdout, _ = run_cli(capsys, "estimate", left, right, "--calibration", str(path), "--size", "320x240",
                              "--json", "--figure", str(figure))
    report = json.loads(stdout)
    assert code == 0 and report["status"] == "OK" and report["rectified"] is False  # the rig's, not F's
    assert report["calibration_rectified"] is True
    # The calibration the metres used, for the input images (640x480), and where it came from.
    record = report["calibration"]
    assert record["source"] == f"--calibration {path} (the pair rectified by it)" and record["measured"] is True
    assert record["focal_px"] == pytest.approx(calibration.focal_px, abs=1e-3)
    assert record["baseline_m"] == pytest.approx(calibration.baseline_m, abs=1e-6)
    # The board, 0.25-0.5 m away by its own corners (f·B / corner disparity), is the nearest obstacle.
    assert 0.3 < report["nearest_m"] < 0.5
    # d_max in the input's pixels, as the focal and doffs beside it: R_min = f·B / (d_max + doffs) holds.
    assert report["r_min_m"] == pytest.approx(record["focal_px"] * record["baseline_m"]
                                              / (report["d_max_px"] + record["doffs_px"]), rel=1e-3)
    assert cv2.imread(str(figure)).shape[0] > 1000  # the rectified pair with epipolar lines below the pipeline's
    code, _, stderr = run_cli(capsys, "estimate", left, right, "--calibration", str(path), "--focal-px", "500")
    assert code == 2 and "--calibration: the file gives focal" in stderr
    (tmp_path / "bad.json").write_text("{}")
    code, _, stderr = run_cli(capsys, "estimate", left, right, "--calibration", str(tmp_path / "bad.json"))
    assert code == 2 and "--calibration:" in stderr and stderr.count("\n") == 1
    (tmp_path / "list.txt").write_text(f"{left} {right}\n")
    code, stdout, _ = run_cli(capsys, "eval", str(tmp_path / "list.txt"), "--calibration", str(path), "--json")
    row = json.loads(stdout.splitlines()[0])
    assert code == 0 and row["calibrated"] is True and row["status"] == "OK"
    # Found by an audit: eval named the rig's metres "the SVS model assumed".
    assert row["calibration"]["source"] == f"--calibration {path} (the pair rectified by it)"


def test_a_calibration_scaled_to_a_pair_of_another_size_says_so(capsys, rig, samples, tmp_path):
    """Found by an audit: a rig calibrated at 640x480 ranged a 320x240 pair (and a 480x360 crop, 0.30 m for 0.39 m)
    with its matrices scaled, and the calibration line named only the file."""
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    names = []
    for side in ("left", "right"):
        names.append(str(tmp_path / f"{side}_small.png"))
        image = cv2.imread(str(samples / f"{side}01.jpg"), 0)
        cv2.imwrite(names[-1], cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA))
    code, stdout, _ = run_cli(capsys, "estimate", *names, "--calibration", str(path), "--json")
    record = json.loads(stdout)["calibration"]
    assert code == 0 and record["focal_px"] == pytest.approx(calibration.focal_px / 2, rel=1e-3)
    assert record["source"] == (f"--calibration {path} (the pair rectified by it), made at 640x480 and scaled to "
                                "this 320x240 pair")
    code, stdout, _ = run_cli(capsys, "estimate", *names, "--calibration", str(path))
    assert code == 0 and "made at 640x480 and scaled to this 320x240 pair)" in stdout
    (tmp_path / "list.txt").write_text(" ".join(names) + "\n")
    code, stdout, _ = run_cli(capsys, "eval", str(tmp_path / "list.txt"), "--calibration", str(path), "--json")
    assert code == 0 and json.loads(stdout.splitlines()[0])["calibration"]["source"] == record["source"]


def test_a_pair_an_exif_orientation_turned_off_the_rigs_aspect_names_the_turn(capsys, rig, samples, tmp_path):
    """Found by an audit: the rig's own 640x480 frames tagged with a phone's portrait Orientation were refused as
    "the pair is 480x640", a size neither file's header nor an image tool's listing shows."""
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    names = []
    for side in ("left", "right"):
        jpeg = (samples / f"{side}01.jpg").read_bytes()
        entry = b"\x01\x12\x00\x03\x00\x00\x00\x01\x00\x06\x00\x00"  # Orientation 6: turn 90° clockwise
        exif = b"Exif\x00\x00MM\x00\x2a\x00\x00\x00\x08\x00\x01" + entry + b"\x00\x00\x00\x00"
        names.append(str(tmp_path / f"{side}.jpg"))
        Path(names[-1]).write_bytes(jpeg[:2] + b"\xff\xe1" + (len(exif) + 2).to_bytes(2, "big") + exif + jpeg[2:])
    code, _, stderr = run_cli(capsys, "estimate", *names, "--calibration", str(path))
    assert code == 2 and stderr.rstrip().endswith(
        "--calibration: made at 640x480, the pair is 480x640: expected the same aspect ratio (the same view at "
        "another resolution); the left image is turned upright by its EXIF orientation from the 640x480 it stores")


@pytest.mark.parametrize("command", ["estimate", "eval"])
def test_a_listed_pairs_calibration_that_is_no_file_is_named_by_its_option(capsys, samples, tmp_path, command):
    """Found by an audit: with a pair list, a missing --calibration said "error: No such file or directory" (no
    option named), a folder "Is a directory", and a FIFO hung: the file was read for another check first."""
    listed = tmp_path / "list.txt"
    listed.write_text(f"{samples / 'left01.jpg'} {samples / 'right01.jpg'}\n")
    pairs = ["--pairs", str(listed)] if command == "estimate" else [str(listed)]
    for given, kind in ((tmp_path / "missing.json", "no such file"), (tmp_path, "a folder")):
        code, _, stderr = run_cli(capsys, command, *pairs, "--calibration", str(given))
        assert code == 2 and f"--calibration: {given}: expected a calibration file, got {kind}" in stderr


def test_a_listed_pair_with_its_own_calibration_is_not_ranged_by_the_rigs_settings(capsys, rig, samples, tmp_path):
    """Found by an audit: a list line with its own FOCAL_PX BASELINE_M is another camera's pair, yet under
    --calibration it ran with the rig's settings (no rectification from F, a 2 px row band): unrectified, 0.90 m for
    the board at 0.33 m, and nothing said. Now BAD_INPUT with the reason, in estimate --pairs and eval alike; the
    rig's own pairs of the same list are ranged."""
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    left, right = str(samples / "left01.jpg"), str(samples / "right01.jpg")
    listed = tmp_path / "list.txt"
    listed.write_text(f"{left} {right} {calibration.focal_px} {calibration.baseline_m}\n{left} {right}\n")
    for command in ("estimate", "eval"):
        argv = ["--pairs", str(listed)] if command == "estimate" else [str(listed)]
        code, stdout, stderr = run_cli(capsys, command, *argv, "--calibration", str(path), "--size", "320x240",
                                       "--json")
        own, rigs = (json.loads(line) for line in stdout.splitlines()[:2])
        assert own["status"] == "BAD_INPUT" and rigs["status"] == "OK", command
        # estimate --pairs ends a list with a bad entry as an error (every line printed first); eval scores it 0 %
        assert code == (2 if command == "estimate" else 0) and ("1 of 2 pairs are BAD_INPUT" in stderr) == (code == 2)
        assert own["reason"].startswith("--calibration: the line gives its own FOCAL_PX BASELINE_M"), command
    # Without --calibration the same line is rectified from its F, as before.
    code, stdout, _ = run_cli(capsys, "estimate", "--pairs", str(listed), "--size", "320x240", "--json")
    assert code == 0 and json.loads(stdout.splitlines()[0])["status"] == "OK"


@pytest.mark.parametrize("workers", ["1", "2"])
def test_scene_folders_under_a_rig_calibration_are_said_to_keep_their_own(capsys, rig, samples, data_dir, tmp_path,
                                                                          workers):
    """Found by an audit of calibration use: eval and estimate --pairs of scene folders with --calibration rig.json
    ranged them with their own calibration, or the SVS model where a scene ships none (Cones), and nothing said the
    file given was not used. Now one warning names them; the rig's own pairs of the same list are not named."""
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    scenes = data_dir / "middlebury_2003_quarter"
    listed = tmp_path / "list.txt"
    listed.write_text(f"{scenes / 'Cones'}\n{samples / 'left01.jpg'} {samples / 'right01.jpg'}\n{scenes / 'Teddy'}\n")
    for argv in (["estimate", "--pairs", str(listed), "--workers", workers], ["eval", str(listed)]):
        code, stdout, stderr = run_cli(capsys, *argv, "--calibration", str(path), "--size", "320x240", "--json")
        warned = [line for line in stderr.splitlines() if "not applied to" in line]
        assert code == 0 and len(warned) == 1, (argv, stderr)
        assert f"--calibration {path}: not applied to 2 scene folders (" in warned[0]
        assert "Cones" in warned[0] and "Teddy" in warned[0] and "left01" not in warned[0]
        rows = [json.loads(line) for line in stdout.splitlines()[:3]]
        assert [row["status"] for row in rows] == ["OK"] * 3
    code, _, stderr = run_cli(capsys, "eval", str(scenes / "Teddy"), "--size", "320x240")  # no file, no warning
    assert code == 0 and "not applied" not in stderr


def test_epipolar_lines_are_spread_over_the_rows():
    y = np.array([5.0, 100.0, 6.0, 50.0, 7.0])
    assert spread_rows(y, 3).tolist() == [0, 4, 1]  # rows 5, 7, 100: lowest, middle, highest rank
    assert spread_rows(y, 10).size == 5 and spread_rows(np.zeros(0), 4).size == 0


def test_rectify_refuses_ground_truth_and_padding(rig, data_dir):
    from svs_torch.data import load_stereo_pair

    calibration, _ = rig
    scene = load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy")
    with pytest.raises(InputError, match="without ground truth"):
        rectify_with_calibration(scene, calibration)
    padded = replace(scene, disparity_px=None, disparity_valid=None, disparity_nonoccluded=None,
                     image_hw=torch.tensor([[100, 100]]))
    with pytest.raises(InputError, match="fill the batch"):
        rectify_with_calibration(padded, calibration)


def test_capture_keeps_the_calibration_and_guide_uses_it(capsys, rig, tmp_path):
    calibration, _ = rig
    path = tmp_path / "rig.json"
    write_calibration(path, calibration)
    out = tmp_path / "pairs"
    code, _, err = run_cli(capsys, "capture", "--emulator", "--count", "1", "--size", "160x120", "--out-dir",
                           str(out), "--calibration", str(path))  # the rig's aspect ratio at a quarter of its size
    assert code == 0 and "--calibration" in err
    # Found by an audit: the emulator's ideal rig warped by a real rig's maps lost its obstacle, unsaid.
    warning = "warning: --calibration with --emulator: the emulator renders an ideal SVS rig"
    assert err.count(warning) == 1
    np.testing.assert_array_equal(read_calibration(out / "calibration.json").P2, calibration.P2)
    # Ranged again without --calibration, the folder's pairs take the copy kept beside them (found by an audit: they
    # were ranged in the SVS model's metres, unrectified, without a word); one captured without it is not mixed in.
    for command in (["estimate", "--pairs", str(out / "index.jsonl")], ["eval", str(out / "index.jsonl")]):
        code, stdout, err = run_cli(capsys, *command, "--json")
        line = json.loads(stdout.splitlines()[0])
        assert line["calibration"]["source"] == (f"--calibration {out / 'calibration.json'} (the pair rectified by "
                                                 "it), made at 640x480 and scaled to this 160x120 pair")
        assert f"rectified with {out / 'calibration.json'}" in err and line["calibration"]["measured"] is True
    # Another file named replaces the kept one, now said (an audit: it was used without a word); the same rig's
    # copy is not.
    other = tmp_path / "other_rig.json"
    other.write_text(path.read_text().replace('"created_utc": "', '"created_utc": "edited '))
    for given, said in ((other, True), (path, False)):
        code, _, err = run_cli(capsys, "estimate", "--pairs", str(out / "index.jsonl"), "--calibration", str(given))
        assert code == 0 and (f"the pairs were captured with the rig calibration {out / 'calibration.json'}, which "
                              "differs" in err) == said, err
    code, _, err = run_cli(capsys, "capture", "--emulator", "--count", "1", "--out-dir", str(tmp_path / "other"),
                           "--size", "1280x1024", "--calibration", str(path))
    assert code == 2 and "--calibration: made at 640x480, the pair is 1280x1024" in err
    code, _, err = run_cli(capsys, "capture", "--emulator", "--count", "1", "--size", "160x120", "--out-dir",
                           str(tmp_path / "plain"))
    code, _, err = run_cli(capsys, "eval", str(out / "index.jsonl"), str(tmp_path / "plain" / "index.jsonl"))
    assert code == 2 and f"and {tmp_path / 'plain' / 'index.jsonl'} without one: range them apart" in err
    # guide's JSON lines say the rig rectified each pair, as estimate's do.
    code, stdout, err = run_cli(capsys, "guide", "--emulator", "--count", "1", "--no-speech", "--size", "160x120",
                                "--json", "--calibration", str(path))
    line = json.loads(stdout.splitlines()[0])
    assert code == 0 and line["calibration_rectified"] is True and line["calibration"]["measured"] is True, err
    assert err.count(warning) == 1
    # --record keeps the rig's calibration beside the pairs, as capture does, and the replay command names that
    # copy (found by an audit: the folder held only the pairs, the command the original's relative path).
    record = tmp_path / "walk"
    code, _, err = run_cli(capsys, "guide", "--emulator", "--count", "1", "--no-speech", "--size", "160x120",
                           "--record", str(record), "--calibration", str(path))
    assert code == 0 and (record / "calibration.json").read_text() == path.read_text(), err
    assert f"--calibration {record / 'calibration.json'}" in err
    # guide checks the rig against its frame size before it opens the camera (test_cli runs it live).
    code, _, err = run_cli(capsys, "guide", "--emulator", "--count", "1", "--no-speech", "--size", "1280x1024",
                           "--calibration", str(path))
    assert code == 2 and "--calibration: made at 640x480, the pair is 1280x1024" in err


def _rig_file_and_capture(capsys, rig, tmp_path, folder: str) -> tuple[Path, Path]:
    """The rig's calibration written to ``rig.json`` and one emulated pair captured with it into ``folder``."""
    path = tmp_path / "rig.json"
    write_calibration(path, rig[0])
    out = tmp_path / folder
    code, _, err = run_cli(capsys, "capture", "--emulator", "--count", "1", "--size", "160x120", "--out-dir",
                           str(out), "--calibration", str(path))
    assert code == 0, err
    return path, out


def test_the_rig_capture_kept_given_in_another_layout_is_not_said_to_differ(capsys, rig, tmp_path):
    """Found by an audit: capture keeps the file it read written anew, and the warning compared bytes; the same rig's
    file with other line ends or indentation (a Windows checkout, an editor's format on save, a script's json.dump)
    given to estimate over the capture was said to be a calibration 'which differs'."""
    path, out = _rig_file_and_capture(capsys, rig, tmp_path, "pairs")
    compact, crlf = tmp_path / "compact.json", tmp_path / "crlf.json"
    compact.write_text(json.dumps(json.loads(path.read_text())))
    crlf.write_bytes(path.read_bytes().replace(b"\n", b"\r\n"))
    for given in (compact, crlf):
        code, _, err = run_cli(capsys, "estimate", "--pairs", str(out / "index.jsonl"), "--calibration", str(given))
        assert code == 0 and "which differs" not in err, err


def test_estimate_figure_shows_the_pair_as_rectified(monkeypatch):
    """The rectified views and the inliers mapped by the pipeline's homographies; nothing for an unrectified pair."""
    from types import SimpleNamespace

    import svs_torch.plotting.rectified as rectified_figure
    from svs_torch.core.types import StereoBatch

    generator = torch.Generator().manual_seed(0)
    left = torch.rand(1, 1, 60, 80, generator=generator)
    angle = np.deg2rad(2.0)
    turn = torch.tensor([[np.cos(angle), -np.sin(angle), 3.0], [np.sin(angle), np.cos(angle), -2.0], [0, 0, 1]],
                        dtype=torch.float32)
    points_left = torch.rand(1, 6, 2, generator=generator) * 50 + 5
    shifted = points_left - torch.tensor([4.0, 0.0])  # a disparity of 4 px, then the right view turned
    points_right = shifted @ turn[:2, :2].T + turn[:2, 2]
    back = torch.linalg.inv(turn).unsqueeze(0)  # H_right: the right view turned back onto the left's rows
    result = SimpleNamespace(
        rectified=torch.tensor([True]), fundamental=SimpleNamespace(inliers=torch.tensor([[1, 1, 1, 1, 1, 0]]).bool()),
        points=SimpleNamespace(left=points_left, right=points_right, valid=torch.ones(1, 6, dtype=torch.bool)),
        rectification=SimpleNamespace(H_left=torch.eye(3).unsqueeze(0), H_right=back),
        H_left=torch.eye(3).unsqueeze(0), H_right=back, row_aligned=torch.tensor([False]))  # F's, as the pipeline
    batch = StereoBatch.from_images(left, left, 100.0, 0.1)
    shown = {}
    monkeypatch.setattr(rectified_figure, "rectified_pair_figure",
                        lambda *args, **kwargs: shown.update(args=args) or np.zeros((2, 2, 3), np.uint8))
    assert rectified_figure.pipeline_rectified_figure(batch, result, 0) is not None
    _, _, mapped_left, mapped_right, title = shown["args"]
    assert mapped_left.shape == (5, 2) and "rectified from F" in title
    np.testing.assert_allclose(mapped_left[:, 1], mapped_right[:, 1], atol=1e-3)  # the same rows after H
    unrectified = SimpleNamespace(**{**vars(result), "rectified": torch.tensor([False])})
    assert rectified_figure.pipeline_rectified_figure(batch, unrectified, 0) is None
    assert rectified_figure.pipeline_rectified_figure(batch, unrectified, 0, "rig.json") is not None
    assert "by the calibration rig.json" in shown["args"][4]
    # Was: a pair the row alignment rectified (a loose rig) was drawn after F's homographies, which the pipeline had
    # not used. Now the ones it measured its disparities after (H_left / H_right), and the title says which.
    wrong = SimpleNamespace(H_left=torch.eye(3).unsqueeze(0), H_right=torch.eye(3).unsqueeze(0))
    aligned = SimpleNamespace(**{**vars(result), "rectification": wrong, "H_left": torch.eye(3).unsqueeze(0),
                                 "H_right": back, "row_aligned": torch.tensor([True])})
    assert rectified_figure.pipeline_rectified_figure(batch, aligned, 0) is not None
    _, _, mapped_left, mapped_right, title = shown["args"]
    assert "rows aligned to the left view's" in title and "from F" not in title
    np.testing.assert_allclose(mapped_left[:, 1], mapped_right[:, 1], atol=1e-3)
    by_f = SimpleNamespace(**{**vars(aligned), "row_aligned": torch.tensor([False])})
    rectified_figure.pipeline_rectified_figure(batch, by_f, 0)
    assert "rectified from F" in shown["args"][4]


def test_calibrated_pairs_are_not_rectified_again_and_match_along_rows():
    from argparse import Namespace

    from svs_torch.cli.rig import CALIBRATED_BAND_PX, with_calibrated_rectification
    from svs_torch.pipeline import PipelineConfig

    config = with_calibrated_rectification(PipelineConfig(), Namespace(calibration="rig.json"))
    assert config.rectify == "off" and config.epipolar_band_px == CALIBRATED_BAND_PX
    own = with_calibrated_rectification(PipelineConfig(epipolar_band_px=5.0), Namespace(calibration="rig.json"))
    assert own.epipolar_band_px == 5.0
    assert with_calibrated_rectification(PipelineConfig(), Namespace(calibration=None)) == PipelineConfig()


def test_a_loose_rig_with_its_calibration_ranges_as_a_perfect_rig():
    """Synthetic SVS scenes (exact truth) seen by a rig whose right camera is turned 1.5 deg (roll), 0.7 deg (tilt)
    and -0.5 deg (pan): its raw right view is the perfect one warped by K R K^-1, and its calibration is what
    OpenCV's stereoRectify makes of that R and T. Rectified by it, every object's distance is the perfect rig's
    (measured: within 0.003 m; the uncalibrated path on the same raw pairs was off by up to 0.38 m)."""
    from argparse import Namespace

    from svs_torch.geometry.calibration import StereoCalibration
    from svs_torch.cli.rig import with_calibrated_rectification
    from svs_torch.data.synthetic import random_obstacle_scenes
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    scenes = random_obstacle_scenes(1, 2, generator=torch.Generator().manual_seed(5))
    perfect = scenes.batch
    width, height = 320, 240
    K = np.array([[float(perfect.focal_px[0]), 0, (width - 1) / 2], [0, float(perfect.focal_px[0]), (height - 1) / 2],
                  [0, 0, 1.0]])
    turn, _ = cv2.Rodrigues(np.deg2rad(np.array([0.7, -0.5, 1.5])))
    T = turn @ np.array([-float(perfect.baseline_m[0]), 0, 0])  # x_right = R x_left + T
    warp = K @ turn @ np.linalg.inv(K)
    right = torch.stack([torch.from_numpy(cv2.warpPerspective(image[0].numpy(), warp, (width, height),
                                                              borderMode=cv2.BORDER_REPLICATE))
                         for image in perfect.right]).unsqueeze(1)
    raw = replace(perfect, right=right, disparity_px=None, disparity_valid=None,
                  focal_px=torch.full((1,), 500.0), baseline_m=torch.full((1,), 1.0))  # the rig's must replace these
    no_distortion = np.zeros(5)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K, no_distortion, K, no_distortion, (width, height), turn,
                                                T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    rig = StereoCalibration((width, height), K, no_distortion, K, no_distortion, turn, T, R1, R2, P1, P2, Q)
    with torch.no_grad():
        # Otsu's regions, one per view whatever the warp's borders (this measures the rectification, not which
        # regions the nearness segmenter ranks first on the two pairs).
        base = PipelineConfig(segmentation=SegmentationConfig())
        expected = estimate_obstacle_depth(perfect, base).depth.objects
        config = with_calibrated_rectification(base, Namespace(calibration="rig.json"))
        found = estimate_obstacle_depth(rectify_with_calibration(raw, rig), config).depth.objects
    assert bool(expected.valid.all()) and bool(found.valid.all())
    torch.testing.assert_close(found.depth_median_m, expected.depth_median_m, atol=0.01, rtol=0)
    true_depth = scenes.object_depth_m.sort(dim=1).values
    torch.testing.assert_close(found.depth_median_m.sort(dim=1).values, true_depth, atol=0.02, rtol=0)


@pytest.mark.parametrize("earlier_figure", [False, True], ids=["new-figure", "earlier-figure"])
@pytest.mark.parametrize("failing", ["figure", "out"])
def test_calibrate_writes_both_files_or_neither_on_a_full_disk(capsys, samples, tmp_path, monkeypatch, failing,
                                                               earlier_figure):
    """Was (an audit of interrupts and full disks): the calibration was written first, so a --figure the disk
    refused exited 1 without a report, yet had replaced the rig's earlier calibration. Now the figure comes first
    and a calibration that cannot be written takes its new figure with it: the earlier calibration stays. Was
    (later): the new figure had replaced an earlier one before the calibration failed, and was then removed, so
    the earlier figure was lost too; it is kept."""
    import svs_torch.core.files as files
    import svs_torch.geometry.calibration as calibration_module
    from svs_torch.plotting import figures

    out, figure = tmp_path / "rig.json", tmp_path / "rig.png"
    out.write_text("an earlier calibration")
    if earlier_figure:
        figure.write_bytes(b"an earlier figure")
    real = files.atomic_output

    def full_disk_for(name):
        def output(path, *args, **kwargs):
            if Path(path).name == name:
                raise OSError(28, "No space left on device")
            return real(path, *args, **kwargs)
        return output

    if failing == "figure":
        monkeypatch.setattr(figures, "atomic_output", full_disk_for("rig.png"))
    else:
        def refused(path, calibration):
            raise OSError(28, "No space left on device")
        monkeypatch.setattr(calibration_module, "write_calibration", refused)
    code, _, err = run_cli(capsys, "calibrate", str(samples / "left0[1-4].jpg"), "--square-m", "0.025", "--out",
                           str(out), "--figure", str(figure))
    assert code == 1 and "No space left on device" in err
    assert out.read_text() == "an earlier calibration"
    assert figure.read_bytes() == b"an earlier figure" if earlier_figure else not figure.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.json"] + ["rig.png"] * earlier_figure


@pytest.mark.parametrize("convert", [lambda u8: u8.astype(np.float32) / 255, lambda u8: u8.astype(np.uint16) * 257,
                                     lambda u8: np.stack([u8] * 3, -1), torch.from_numpy],
                         ids=["float32", "uint16", "bgr", "tensor"])
def test_find_board_corners_names_an_image_it_cannot_read(data_dir, convert):
    # Each raised OpenCV's "Only 8-bit grayscale" / "src.channels() == 1" / overload error, naming no argument.
    image = cv2.imread(str(data_dir / "opencv_samples" / "left01.jpg"), cv2.IMREAD_GRAYSCALE)
    expected = find_board_corners(image, BOARD)
    with pytest.raises(InputError, match="image: expected a 2-D uint8 gray numpy array .*, got "):
        find_board_corners(convert(image), BOARD)
    if convert is not torch.from_numpy:
        found = find_board_corners(board_image_u8(convert(image)), BOARD)
        assert found is not None and np.abs(found - expected).max() < 0.5


def test_a_left_image_whose_name_holds_brackets_is_read_as_that_file(tmp_path):
    """Found by an audit of calibrate: 'left[1].jpg' was read as a pattern (a set of characters), matched nothing
    and was refused as "no file matches", though the file was there. A pattern still expands as before."""
    import argparse

    from svs_torch.cli.calibrate import pair_paths

    for name in ("left[1].jpg", "right[1].jpg", "left2.jpg", "right2.jpg"):
        (tmp_path / name).write_bytes(b"")
    literal = str(tmp_path / "left[1].jpg")
    assert pair_paths(argparse.Namespace(left=[literal], pairs=None)) == [
        (literal, str(tmp_path / "right[1].jpg"), "left")]
    assert [p[0] for p in pair_paths(argparse.Namespace(left=[str(tmp_path / "left[2].jpg")], pairs=None))] == [
        str(tmp_path / "left2.jpg")]


def test_folders_kept_with_one_rig_in_two_layouts_are_ranged_together(capsys, rig, tmp_path):
    """Found on re-reading the kept-calibration lookup: two capture folders listed together were compared by their
    kept files' bytes, so the same rig's file written with other indentation refused the pair of folders as
    captured with two rigs. They are compared by what the calibration holds; another rig is still refused."""
    import shutil

    _, first = _rig_file_and_capture(capsys, rig, tmp_path, "first")
    second = tmp_path / "second"
    shutil.copytree(first, second)
    (second / "index.jsonl").write_text((first / "index.jsonl").read_text().replace(str(first), str(second)))
    kept = second / "calibration.json"
    kept.write_text(json.dumps(json.loads(kept.read_text()), indent=7) + "\n")
    assert kept.read_bytes() != (first / "calibration.json").read_bytes()
    code, _, err = run_cli(capsys, "eval", str(first / "index.jsonl"), str(second / "index.jsonl"))
    assert code == 0 and f"rectified with {first / 'calibration.json'}" in err, err
    kept.write_text(kept.read_text().replace('"created_utc": "', '"created_utc": "another rig '))
    code, _, err = run_cli(capsys, "eval", str(first / "index.jsonl"), str(second / "index.jsonl"))
    assert code == 2 and "and another with a different one: range them apart" in err


@pytest.mark.parametrize("name", ["left01.jpg", "right06.jpg"])
def test_the_board_is_found_in_a_phone_sized_view(samples, name):
    """Found by an audit: in the shared views enlarged to a phone's 4000x3000 OpenCV's finder found the board in 5 of
    12 (1.2-1.8 s a miss), and calibrate refused them; it is now looked for at 1280 px and refined in the full view,
    where it lands on the corners found at 640x480, scaled (x' = (x + 0.5) s - 0.5)."""
    image = cv2.imread(str(samples / name), cv2.IMREAD_GRAYSCALE)
    large = cv2.resize(image, (4000, 3000), interpolation=cv2.INTER_CUBIC)
    found, expected = find_board_corners(large, BOARD), find_board_corners(image, BOARD)
    assert found is not None and np.abs(found - ((expected + 0.5) * 6.25 - 0.5)).max() < 2.0


def test_a_fits_reprojection_error_is_judged_per_640_px_of_width(rig):
    """Found by an audit: the shared pairs enlarged to a phone's 4000x3000 fit to 1.47 px (0.24 px per 640, as at
    640x480) and were written, and read by every --calibration, with "distances from this file may be far off"."""
    calibration, _ = rig
    assert fit_doubts(replace(calibration.scaled_to((4000, 3000)), rms_stereo_px=1.47)) == []
    assert fit_doubts(replace(calibration.scaled_to((4000, 3000)), rms_stereo_px=7.0)) == [
        "the stereo reprojection RMS is 7.00 px (a rig calibrates under 6.25 px)"]
    assert fit_doubts(replace(calibration, rms_stereo_px=1.47)) == [
        "the stereo reprojection RMS is 1.47 px (a rig calibrates under 1 px)"]
