"""Every result names the calibration its metres use and where it came from; eval keeps nominal scenes apart."""

from __future__ import annotations

import json
import re
import statistics
import sys
from pathlib import Path

import pytest

from svs_torch.data import PairSource, load_stereo_pair, pair_calibration_source, read_pair_list
from svs_torch.data.calibration import calibration_record, format_calibration
from svs_torch.data.datasets import scene_calibration_source
from svs_torch.evaluation import PairEvaluation, summarize

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cli"))  # run alone, pytest has not put it there
from test_cli import run_cli  # noqa: E402

# One scene of each layout and calibration rule (MANIFEST §1).
SCENES = ["middlebury_eval3_Q/Teddy", "middlebury_2005_2006_third/Art", "middlebury_2005_2006_third/Aloe",
          "middlebury_2003_quarter/Teddy", "middlebury_2003_quarter/Cones", "middlebury_2001/Tsukuba",
          "kitti/stereo2015_training/image_2/000000_10.png", "opencv_samples"]


@pytest.mark.parametrize("scene", SCENES)
def test_a_scene_source_says_assumed_exactly_where_the_loader_has_no_measured_calibration(data_dir, scene):
    path = data_dir / scene
    batch = load_stereo_pair(path)
    source = scene_calibration_source(path)
    assert ("assumed" in source) == (not bool(batch.calibrated[0])), source
    if path.parent.name == "middlebury_eval3_Q":
        assert source == "Teddy/calib.txt"


def _read_calib(path) -> dict:
    """calib.txt's focal, baseline and doffs, read here with a regex (independently of the package's reader)."""
    text = path.read_text()
    focal = float(re.search(r"cam0\s*=\s*\[\s*([\d.]+)", text).group(1))
    baseline_mm = float(re.search(r"baseline\s*=\s*([\d.]+)", text).group(1))
    doffs = float(re.search(r"doffs\s*=\s*([\d.]+)", text).group(1))
    return {"focal_px": focal, "baseline_m": baseline_mm / 1000, "doffs_px": doffs}


def test_estimate_names_the_scene_calib_file_and_the_svs_model(data_dir, capsys):
    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    code, out, _ = run_cli(capsys, "estimate", str(scene), "--size", "160x120", "--json")
    record = json.loads(out)["calibration"]
    assert code == 0 and record.pop("source") == "Teddy/calib.txt" and record.pop("measured") is True
    assert record == pytest.approx(_read_calib(scene / "calib.txt"))  # the input size's values, not 160x120's
    code, out, _ = run_cli(capsys, "estimate", str(scene / "im0.png"), str(scene / "im1.png"), "--size", "160x120")
    line = next(line for line in out.splitlines() if "calibration" in line)
    assert line == "  calibration: f 388.5 px, B 0.1075 m, doffs 0.0 px (the SVS model assumed)"  # 3.6/4.17 x 450


def test_a_listed_calibration_names_its_line_and_options_name_themselves(tmp_path):
    listing = tmp_path / "pairs.txt"
    listing.write_text("# two pairs\na.png b.png 700 0.12 3\na.png b.png\n")
    own, plain = read_pair_list(listing)
    assert pair_calibration_source(own) == f"the pair list, line 2 of {listing}"
    assert pair_calibration_source(plain) == "the SVS model assumed"
    assert pair_calibration_source(plain, 700.0, 0.12) == "command-line options"
    assert pair_calibration_source(plain, 700.0).startswith("command-line option --focal-px, the SVS model")


def test_a_doffs_given_alone_is_named_as_the_options_source(data_dir, capsys):
    """``--doffs-px 52`` alone put 52 px into every distance and was reported as "the SVS model assumed"."""
    assert pair_calibration_source(PairSource("a.png", "b.png"), None, None, 52.0) == (
        "command-line option --doffs-px, the SVS model assumed for the rest")
    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    code, out, _ = run_cli(capsys, "estimate", str(scene / "im0.png"), str(scene / "im1.png"), "--size", "160x120",
                           "--focal-px", "1500", "--doffs-px", "52", "--json")
    record = json.loads(out)["calibration"]
    assert code == 0 and record["doffs_px"] == 52.0
    assert record["source"] == "command-line options --focal-px and --doffs-px, the SVS model assumed for the rest"


def test_calibration_record_reports_the_input_size(data_dir):
    from svs_torch.data import resize_stereo_batch

    batch = load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy")  # 450x375
    small = resize_stereo_batch(batch, (225, 188))
    record = calibration_record(small, 0, "Teddy/calib.txt", width_scale=450 / 225)
    assert record["focal_px"] == pytest.approx(1500.0) and record["doffs_px"] == pytest.approx(52.0)
    assert format_calibration(record) == "calibration: f 1500.0 px, B 0.08 m, doffs 52.0 px (Teddy/calib.txt)"


def test_summary_headline_leaves_nominal_scenes_apart():
    own = [PairEvaluation(name=f"own{i}", status="OK", calibrated=True, has_truth=True, acc_r_min_pct=a,
                          acc_r_max_pct=a, acc_objects_pct=a) for i, a in enumerate((90.0, 96.0))]
    failed = PairEvaluation(name="failed", status="NO_OBJECTS", calibrated=True, has_truth=True)
    nominal = PairEvaluation(name="kitti", status="OK", calibrated=False, has_truth=True, acc_r_min_pct=50.0,
                             acc_r_max_pct=60.0, acc_objects_pct=55.0)
    summary = summarize([*own, failed, nominal])
    assert summary["scored"] == 3 and summary["acc_r_min_pct"] == pytest.approx(statistics.fmean([90, 96, 0]))
    assert summary["nominal_calibration"] == {"scored": 1, "names": ["kitti"], "acc_r_min_pct": 50.0,
                                              "acc_r_max_pct": 60.0, "acc_objects_pct": 55.0}


def test_eval_marks_nominal_scenes_and_lists_each_calibration(data_dir, capsys):
    scenes = [data_dir / "middlebury_2003_quarter" / name for name in ("Cones", "Teddy")]
    code, out, _ = run_cli(capsys, "eval", *map(str, scenes), "--size", "160x120")
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith("2003/")}
    assert code == 0 and rows["2003/Cones"].rstrip().endswith("NOMINAL") and rows["2003/Teddy"].rstrip().endswith("own")
    assert ("2003/Cones: calibration: f 1246.7 px, B 0.16 m, doffs 0.0 px (nominal, for scoring only: no calibration "
            "shipped or given)") in out
    assert "mean Acc (Eq. 9) over 1 pair with their own calibration" in out  # (was "1 pairs")
    assert "apart, 1 scored with a NOMINAL calibration" in out
    assert "2 pairs, 0 failed, 1 scored against ground truth with their own calibration and 1 with a NOMINAL one" in out
    code, out, _ = run_cli(capsys, "eval", *map(str, scenes), "--size", "160x120", "--json")
    *rows, summary = [json.loads(line) for line in out.splitlines()]
    assert [r["calibration"]["measured"] for r in rows] == [False, True]
    assert json.loads(json.dumps(summary))["nominal_calibration"]["names"] == ["2003/Cones"]
