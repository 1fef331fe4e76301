"""A calibration read from a file (a pair list's line, capture's ``index.jsonl``, a scene's ``calib.txt``) is held to
the ranges of the options ``--focal-px``, ``--baseline-m`` and ``--doffs-px`` (one definition:
:data:`svs_torch.core.camera.CALIBRATION_RANGES`). An audit of numbers read from files: a list line's baseline of
1e9 ranged Teddy at 4.5e10 m and a focal of 1e30 at 2e27 m, status OK; a calib.txt's baseline of 1e9 mm, focal or
doffs of 1e30 and width of 0.0001 were ranged and scored, status OK."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from svs_torch import InputError
from svs_torch.cli import main
from svs_torch.core.camera import CALIBRATION_RANGES, MAX_BASELINE_M, MAX_FOCAL_PX, MIN_BASELINE_M, MIN_FOCAL_PX
from svs_torch.data.formats import read_middlebury_calib
from svs_torch.data.middlebury import load_middlebury_eval3
from svs_torch.data.pair_list import read_pair_list

FOCAL = "a focal length in pixels from 1 to 1,000,000"
BASELINE = "a baseline in metres from 0.001 to 2 (millimetres / 1000)"
DOFFS = "pixels from -1,000,000 to 1,000,000"


@pytest.mark.parametrize("numbers, message", [
    ("1e30 0.08", f"FOCAL_PX: expected {FOCAL}, got '1e30'"),
    ("1e300 0.08", f"FOCAL_PX: expected {FOCAL}, got '1e300'"),  # was "focal_px: ... got inf", naming no line
    ("1500 1e9", f"BASELINE_M: expected {BASELINE}, got '1e9'"),
    ("1500 0.08 1e30", f"DOFFS_PX: expected {DOFFS}, got '1e30'"),
    ("1500 0.08 -1e30", f"DOFFS_PX: expected {DOFFS}, got '-1e30'"),  # NO_DENSE_DEPTH, blaming the doffs' sign
    ("1e-30 0.08", f"FOCAL_PX: expected {FOCAL}, got '1e-30'"),  # every object at 0.000 m, status OK
    ("1500 1e-30", f"BASELINE_M: expected {BASELINE}, got '1e-30'"),  # likewise
])
def test_a_list_lines_calibration_out_of_any_rig_is_that_lines_problem(tmp_path, numbers, message):
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"l.png r.png 1500 0.08 52\nl.png r.png {numbers}\n")
    good, bad = read_pair_list(listing, "--pairs")
    assert good.problem is None and bad.problem == f"--pairs: line 2 of {listing}: {message}"
    index = tmp_path / "index.jsonl"
    focal, baseline, *doffs = (float(v) for v in numbers.split())
    index.write_text(json.dumps({"left": "l.png", "right": "r.png", "focal_px": focal, "baseline_m": baseline,
                                 **({"doffs_px": doffs[0]} if doffs else {})}) + "\n")
    (entry,) = read_pair_list(index, "--pairs")
    key, expected = message.split(": ", 1)  # named by its JSON key there ('focal_px'), not a list's column
    assert entry.problem.startswith(f"--pairs: line 1 of {index}: {key.lower()}: {expected.split(', got')[0]}")


@pytest.mark.parametrize("value", ['"500"', "true", "[500]", '{"px": 500}'])
def test_an_index_lines_calibration_that_is_no_json_number_is_that_lines_problem(tmp_path, value):
    """A string "500" was taken as 500 (a calibration file refuses it); true and [500] were refused as 'FOCAL_PX:
    expected a finite positive number, got 'True'', naming a column an index line does not have."""
    index = tmp_path / "index.jsonl"
    index.write_text(f'{{"left": "l.png", "right": "r.png", "focal_px": {value}, "baseline_m": 0.1}}\n'
                     '{"left": "l.png", "right": "r.png", "focal_px": 500, "baseline_m": 0.1}\n')
    bad, good = read_pair_list(index, "--pairs")
    assert bad.problem == f"--pairs: line 1 of {index}: focal_px: expected a JSON number, got {value}"
    assert (good.problem, good.focal_px, good.baseline_m) == (None, 500.0, 0.1)


def test_the_bounds_themselves_are_taken_from_a_list_as_from_the_options(tmp_path):
    from svs_torch.cli.rig import baseline_m_value, doffs_px_value, focal_px_value

    listing = tmp_path / "pairs.txt"
    listing.write_text(f"l.png r.png {MAX_FOCAL_PX:g} {MAX_BASELINE_M:g} {-MAX_FOCAL_PX:g}\n"
                       f"l.png r.png {MIN_FOCAL_PX:g} {MIN_BASELINE_M:g} {MAX_FOCAL_PX:g}\n")
    highest, lowest = read_pair_list(listing)
    assert (highest.problem, highest.focal_px, highest.baseline_m, highest.doffs_px) == (None, 1e6, 2.0, -1e6)
    assert (lowest.problem, lowest.focal_px, lowest.baseline_m, lowest.doffs_px) == (None, 1.0, 0.001, 1e6)
    assert (focal_px_value("1e6"), baseline_m_value("2"), doffs_px_value("-1e6")) == (1e6, 2.0, -1e6)
    assert CALIBRATION_RANGES["focal_px"][1] == MAX_FOCAL_PX


def test_one_bad_lines_calibration_fails_that_pair_and_the_others_are_ranged(capsys, data_dir, tmp_path):
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{teddy / 'im0.png'} {teddy / 'im1.png'} 1500 1e9 52\n"
                       f"{teddy / 'im0.png'} {teddy / 'im1.png'} 1500 0.08 52\n")
    main(["estimate", "--pairs", str(listing), "--size", "225x188"])
    out = capsys.readouterr().out
    assert f"status BAD_INPUT: --pairs: line 1 of {listing}: BASELINE_M: expected {BASELINE}, got '1e9'" in out
    assert out.count("status OK") == 1 and "e+09 m" not in out and "B 1e+09" not in out


def _teddy_with(tmp_path: Path, data_dir: Path, key: str, value: str) -> Path:
    scene = tmp_path / "Teddy"
    if not scene.exists():
        scene.mkdir()
        for name in ("im0.png", "im1.png", "disp0GT.pfm"):
            (scene / name).write_bytes((data_dir / "middlebury_eval3_Q" / "Teddy" / name).read_bytes())
    text = (data_dir / "middlebury_eval3_Q" / "Teddy" / "calib.txt").read_text()
    lines = [f"{key}={value}" if line.strip().startswith(f"{key}=") else line for line in text.splitlines()]
    (scene / "calib.txt").write_text("\n".join(lines) + "\n")
    return scene


@pytest.mark.parametrize("key, value, message", [
    ("baseline", "1e9", f"'baseline' 1e+09 mm: expected {BASELINE}"),
    ("baseline", "1e-27", f"'baseline' 1e-27 mm: expected {BASELINE}"),
    ("cam0", "[1e-30 0 199; 0 1e-30 187; 0 0 1]", f"'cam0's focal' 1e-30 px: expected {FOCAL}"),
    ("doffs", "1e30", f"'doffs' 1e+30 px: expected {DOFFS}"),
    ("cam0", "[1e30 0 199; 0 1e30 187; 0 0 1]", f"'cam0's focal' 1e+30 px: expected {FOCAL}"),
    ("cam1", "[-5 0 251; 0 1500 187; 0 0 1]", "expected cam1 finite with a positive focal length"),  # (already)
    ("width", "0.0001", "expected a whole number of pixels from 1 to 8192 for 'width', got 0.0001"),
    ("height", "1e9", "expected a whole number of pixels from 1 to 8192 for 'height', got 1e+09"),
])
def test_a_calib_txt_out_of_any_rig_is_refused_naming_the_key_and_the_file(tmp_path, data_dir, key, value, message):
    scene = _teddy_with(tmp_path, data_dir, key, value)
    with pytest.raises(InputError) as raised:
        read_middlebury_calib(scene / "calib.txt", "calib")
    assert str(raised.value).startswith("calib: ") and message in str(raised.value)
    assert str(raised.value).endswith(str(scene / "calib.txt"))
    with pytest.raises(InputError):
        load_middlebury_eval3(scene)


def test_a_calib_txt_focal_scaled_out_of_range_is_refused(tmp_path, data_dir):
    """Each value in range, but the width it was written for (1 px) scales the focal of 1e6 px by 450."""
    scene = _teddy_with(tmp_path, data_dir, "width", "1")
    (scene / "calib.txt").write_text((scene / "calib.txt").read_text().replace("1500", "1e6"))  # (both cams)
    with pytest.raises(InputError, match=rf"calib: focal_px 4.5e\+08 once scaled .*: expected {FOCAL}"):
        load_middlebury_eval3(scene)


def test_eval_of_a_scene_whose_calib_txt_is_out_of_range_gives_it_bad_input(capsys, tmp_path, data_dir):
    scene = _teddy_with(tmp_path, data_dir, "baseline", "1e9")
    main(["eval", str(scene)])
    out = capsys.readouterr().out
    assert "BAD_INPUT: calib: 'baseline' 1e+09 mm: expected" in out and "Traceback" not in out


@pytest.mark.parametrize("key, value", [("doffs", "[1 2; 3 4]"), ("baseline", "[80 1]"), ("width", "[450]")])
def test_a_calib_txt_number_given_as_a_matrix_is_that_scenes_bad_input(capsys, tmp_path, data_dir, key, value):
    """'doffs=[1 2; 3 4]' stopped the whole eval run: 'internal error: TypeError: only 0-dimensional arrays can be
    converted to Python scalars'."""
    scene = _teddy_with(tmp_path, data_dir, key, value)
    with pytest.raises(InputError, match=f"^calib: expected a number for '{key}', got a matrix: .*calib.txt$"):
        read_middlebury_calib(scene / "calib.txt", "calib")
    listing = tmp_path / "scenes.txt"
    listing.write_text(f"{scene}\n{data_dir / 'middlebury_eval3_Q' / 'ArtL'}\n")
    main(["eval", str(listing), "--size", "174x139"])
    out = capsys.readouterr().out
    assert f"BAD_INPUT: calib: expected a number for '{key}', got a matrix" in out and "statuses: BAD_INPUT 1, OK 1" in out


@pytest.mark.parametrize("key, value, message", [
    # ranged at 0.225 m for 1.405 m, scored 99.9 % (the truth's depth read the same doffs)
    ("doffs", "500", r"expected 'doffs' = cam1's cx - cam0's cx \(52 px, the format's definition\), got 500"),
    ("cam1", "[3000 0 251; 0 3000 187; 0 0 1]", "expected cam0 and cam1 with one focal length .*, got 1500 and 3000"),
])
def test_a_calib_txt_that_contradicts_itself_is_refused(tmp_path, data_dir, key, value, message):
    scene = _teddy_with(tmp_path, data_dir, key, value)
    with pytest.raises(InputError, match=f"^calib: {message}") as raised:
        load_middlebury_eval3(scene)
    assert str(raised.value).endswith(str(scene / "calib.txt"))


def test_every_shared_calib_txt_agrees_with_itself(data_dir):
    for path in sorted((data_dir / "middlebury_eval3_Q").glob("*/calib.txt")):
        read_middlebury_calib(path, "calib")
