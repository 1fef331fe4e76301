"""``svs-depth features``: its JSON fields and own defaults, and its matches on a real pair against the ground truth
and a plain OpenCV SIFT loop (issue 33, item 4; the full table: ``experiments/features_cli_vs_sift.py``)."""

from __future__ import annotations

import argparse
import json
import sys

import cv2
import numpy as np
from conftest import REPO_ROOT

from svs_torch.cli import build_parser, main
from svs_torch.cli.features import COMMAND_MAX_KEYPOINTS, COMMAND_UPSAMPLE_MAX_PIXELS, command_config
from svs_torch.features.detector import MAX_KEYPOINTS

sys.path.insert(0, str(REPO_ROOT / "experiments"))

import features_cli_vs_sift  # noqa: E402

TEDDY_2003 = "middlebury_2003_quarter/Teddy"  # held-out split, 450 x 375


def features_json(capsys, *argv: str) -> dict:
    assert main(["features", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_command_defaults_are_its_own_and_options_win():
    def namespace(*options: str) -> argparse.Namespace:
        return build_parser().parse_args(["features", "left.png", "right.png", *options])

    assert COMMAND_MAX_KEYPOINTS == MAX_KEYPOINTS  # "every keypoint": the detector's own limit
    config = command_config(namespace(), (375, 450))
    assert config.surf.max_keypoints == MAX_KEYPOINTS and config.surf.upsample
    side = int(COMMAND_UPSAMPLE_MAX_PIXELS**0.5)
    assert not command_config(namespace(), (side + 1, side + 1)).surf.upsample  # large frames: no x2 scale space
    given = command_config(namespace("--max-keypoints", "300", "--no-upsample"), (375, 450))
    assert given.surf.max_keypoints == 300 and not given.surf.upsample
    paper = command_config(namespace("--preset", "paper"), (375, 450))
    assert paper.surf.max_keypoints == 512 and not paper.surf.upsample and paper.max_ratio == 0.6


def test_json_fields_and_settings(data_dir, capsys):
    scene = data_dir / TEDDY_2003
    report = features_json(capsys, str(scene / "imL.png"), str(scene / "imR.png"), "--no-segment")
    assert set(report) == {"status", "left", "right", "matches", "matched_xy_px", "refined", "segmented", "segmenter",
                           "settings", "time_s"}
    assert report["status"] == "OK" and report["refined"] and not report["segmented"] and report["time_s"] > 0
    assert report["segmenter"] is None
    assert report["settings"] == {"max_keypoints": MAX_KEYPOINTS, "metric_threshold": 100.0, "upsample": True,
                                  "max_ratio": 0.8, "mutual": False, "laplacian_gate": True}
    assert 512 < len(report["left"]) <= MAX_KEYPOINTS  # more than the pipeline's cap: no cap in practice
    assert len(report["matched_xy_px"]) == len(report["matches"])
    for (i, j), row in zip(report["matches"], report["matched_xy_px"]):
        assert 0 <= i < len(report["left"]) and 0 <= j < len(report["right"]) and len(row) == 4
    capped = features_json(capsys, str(scene / "imL.png"), str(scene / "imR.png"), "--no-segment",
                           "--max-keypoints", "200", "--no-upsample")
    assert capped["settings"]["max_keypoints"] == 200 and not capped["settings"]["upsample"]
    assert len(capped["left"]) <= 200


def test_a_too_small_answer_has_the_fields_of_an_ok_one(capsys, tmp_path):
    """Was: a pair under 5x5 pixels answered without "refined" and "settings", which every other answer has, so a
    script reading them met a KeyError on it (an audit). Now both answers have the same fields."""
    path = tmp_path / "thin.png"
    cv2.imwrite(str(path), np.full((3, 160), 90, np.uint8))
    report = features_json(capsys, str(path), str(path))
    assert report["status"] == "TOO_SMALL"
    assert set(report) == {"status", "reason", "left", "right", "matches", "matched_xy_px", "refined", "segmented",
                           "segmenter", "settings", "time_s"}
    assert report["refined"] and report["settings"]["max_keypoints"] == MAX_KEYPOINTS


def ground_truth_precision(matched: np.ndarray, disparity: np.ndarray) -> tuple[float, int]:
    """Share (and count) of matches within 1 px of the GT disparity in x and 1 px in y, among those with GT."""
    rows = np.clip(np.round(matched[:, 1]).astype(int), 0, disparity.shape[0] - 1)
    cols = np.clip(np.round(matched[:, 0]).astype(int), 0, disparity.shape[1] - 1)
    truth = disparity[rows, cols]
    has_gt = truth > 0
    error_x, error_y = np.abs(matched[:, 0] - matched[:, 2] - truth), np.abs(matched[:, 1] - matched[:, 3])
    correct = has_gt & (error_x <= 1) & (error_y <= 1)
    return float(correct.sum() / has_gt.sum()), int(correct.sum())


def test_precision_on_a_real_pair_at_least_sift(data_dir, capsys):
    """Teddy (2003, native 450 x 375): GT read here with OpenCV (disp2.png / 4, 0 = unknown), not by svs_torch."""
    scene = data_dir / TEDDY_2003
    left, right = str(scene / "imL.png"), str(scene / "imR.png")
    disparity = cv2.imread(str(scene / "disp2.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / 4
    report = features_json(capsys, left, right, "--no-segment")
    precision, correct = ground_truth_precision(np.asarray(report["matched_xy_px"], np.float64), disparity)
    sift = cv2.SIFT_create()
    kl, dl = sift.detectAndCompute(cv2.imread(left, cv2.IMREAD_GRAYSCALE), None)
    kr, dr = sift.detectAndCompute(cv2.imread(right, cv2.IMREAD_GRAYSCALE), None)
    sift_rows = [kl[m.queryIdx].pt + kr[m.trainIdx].pt for m, n in cv2.BFMatcher().knnMatch(dl, dr, k=2)
                 if m.distance < 0.8 * n.distance]
    sift_precision, sift_correct = ground_truth_precision(np.asarray(sift_rows, np.float64), disparity)
    # Measured: 0.871 of 1756 (1530 correct) against SIFT's 0.802 of 353 (283).
    assert precision >= sift_precision and precision > 0.8
    assert correct >= sift_correct / 2 and correct > 1000
    # The keypoints' own (unrefined) positions are less precise: score matched_xy_px.
    keypoints = np.asarray([report["left"][i]["xy_px"] + report["right"][j]["xy_px"] for i, j in report["matches"]])
    assert ground_truth_precision(keypoints, disparity)[0] < precision


def test_experiment_on_one_scene(data_dir, tmp_path):
    """features_cli_vs_sift.py on the first tuned scene (ArtL): both methods scored, the command ahead."""
    out = tmp_path / "features.json"
    report = features_cli_vs_sift.main(["--data", str(data_dir), "--split", "tuned", "--limit", "1",
                                        "--json", str(out)])
    result = report["results"]["tuned"]
    assert [p["scene"] for p in result["pairs"]] == ["middlebury_eval3_Q/ArtL"]
    command, sift = result["command"], result["sift"]
    assert command["pairs"] == sift["pairs"] == 1 and 0 < sift["correct"] <= sift["with_gt"] <= sift["matches"]
    # Measured: 0.776 of 541 (420 correct) against SIFT's 0.656 of 186 (122).
    assert command["precision"] >= sift["precision"] and command["correct"] >= sift["correct"] / 2
    saved = json.loads(out.read_text())
    assert saved["metadata"]["command"].startswith("python experiments/features_cli_vs_sift.py")


def test_segmented_features_lie_on_the_regions_segment_shows(data_dir, capsys):
    """Was: the segmented path masked the views by Otsu's regions whatever the preset, while ``segment`` and
    ``estimate`` keep the nearness segmenter's. Now the keypoints lie on the preset's own kept regions: the
    nearness segmenter's by default, Otsu's two largest under ``--preset paper``. A keypoint's box filter reaches
    past a region's edge by half its size, 9 · scale / 1.2 / 2 (a masked edge is a strong blob there)."""
    from svs_torch.data import load_image_pair
    from svs_torch.pipeline import PipelineConfig, segment_pair

    scene = data_dir / TEDDY_2003
    left, right = str(scene / "imL.png"), str(scene / "imR.png")
    batch = load_image_pair(left, right)

    def distance_px(config: PipelineConfig, xy: np.ndarray) -> np.ndarray:
        kept = segment_pair(batch, config.segmentation).left.kept_mask[0, 0].numpy().astype(np.uint8)
        return cv2.distanceTransform(1 - kept, cv2.DIST_L2, 5)[xy[:, 1], xy[:, 0]]

    for preset, own, other in (("default", PipelineConfig(), PipelineConfig.paper()),
                               ("paper", PipelineConfig.paper(), PipelineConfig())):
        report = features_json(capsys, left, right, "--preset", preset)
        assert report["segmented"] and report["segmenter"] == own.segmentation.segmenter and len(report["left"]) > 100
        xy = np.array([point["xy_px"] for point in report["left"]]).round().astype(int)
        scale = np.array([point["scale_px"] for point in report["left"]])
        assert (distance_px(own, xy) <= 3.75 * scale + 1).all(), preset
        assert (distance_px(other, xy) > 3.75 * scale + 1).any(), preset  # the presets' regions differ on Teddy


def test_features_text_says_its_matches_come_before_ransac(data_dir, capsys):
    """Found by an audit: the text listed matches tens of pixels off their row first, with nothing saying they are
    the SAD matches before RANSAC's epipolar check."""
    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    code = main(["features", str(scene / "im0.png"), str(scene / "im1.png"), "--size", "320x267"])
    head = capsys.readouterr().out.splitlines()[0]
    assert code == 0 and "SAD matches before RANSAC" in head and "svs-depth fundamental" in head


def test_a_pair_whose_segmentation_keeps_nothing_is_not_ok(capsys, tmp_path):
    """Was: where the segmentation kept no region (here Otsu on noise: no foreground survives the opening), features
    answered "status OK" and "0 keypoints" without a word of why, as if SURF found nothing on a textured pair
    (estimate says NO_OBJECTS; an audit). Now the status is estimate's, with the reason and the way out."""
    noise = np.random.default_rng(0).integers(0, 256, (120, 160), dtype=np.uint8)
    left, right = tmp_path / "left.png", tmp_path / "right.png"
    cv2.imwrite(str(left), noise)
    cv2.imwrite(str(right), np.roll(noise, -5, axis=1))
    report = features_json(capsys, str(left), str(right), "--preset", "paper")
    assert report["status"] == "NO_OBJECTS" and report["left"] == [] and report["matches"] == []
    why = ("the otsu segmenter kept no region in either view (left NO_FOREGROUND, right NO_FOREGROUND); "
           "--no-segment detects on the whole images")
    assert report["reason"] == why
    assert main(["features", str(left), str(right), "--preset", "paper"]) == 0
    assert capsys.readouterr().out.startswith(f"status NO_OBJECTS: {why}\nleft: 0 keypoints")
    blank, square = tmp_path / "blank.png", np.zeros((120, 160), np.uint8)  # one view without a region: no match
    cv2.imwrite(str(blank), square)  # either (estimate: NO_OBJECTS)
    square[30:90, 40:120] = noise[30:90, 40:120] // 2 + 128  # a bright textured object, kept by Otsu
    cv2.imwrite(str(right), square)
    one = features_json(capsys, str(blank), str(right), "--preset", "paper")
    assert one["status"] == "NO_OBJECTS" and one["reason"].startswith("the otsu segmenter kept no region in the left "
                                                                      "view (left UNIFORM_IMAGE, right OK)")
    cv2.imwrite(str(right), np.roll(noise, -5, axis=1))
    whole = features_json(capsys, str(left), str(right), "--preset", "paper", "--no-segment")
    assert whole["status"] == "OK" and "reason" not in whole and len(whole["matches"]) > 50


def test_the_help_names_the_options_that_show_what_estimate_counts(data_dir, capsys):
    """features --help says --no-segment --max-keypoints 512 --no-upsample shows estimate's keypoints and matches,
    and --preset paper estimate --preset paper's (both held on the shared pairs by an audit of the stage commands)."""
    scene = data_dir / TEDDY_2003
    pair = [str(scene / "imL.png"), str(scene / "imR.png")]
    for options, preset in ((["--no-segment", "--max-keypoints", "512", "--no-upsample"], []),
                            (["--preset", "paper"], ["--preset", "paper"])):
        report = features_json(capsys, *pair, *options)
        assert main(["estimate", *pair, "--json", *preset]) == 0
        estimated = json.loads(capsys.readouterr().out)
        assert estimated["num_keypoints"] == [len(report["left"]), len(report["right"])]
        assert estimated["num_matches"] == len(report["matches"]) > 50
