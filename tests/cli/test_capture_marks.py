"""``estimate --pairs`` and ``eval`` of a capture's index.jsonl say which pairs the index marks as no stereo moment
(svs_torch.cli.capture_marks). Found by an audit: capture warned of a frozen camera's pairs and of frames that came
apart, and ``estimate --pairs DIR/index.jsonl`` then ranged them without a word."""

from __future__ import annotations

import json

import cv2
import torch

from svs_torch.cli import main

#: (time_between_frames_s, frozen_camera) of each index line; None, None: an older index without the keys.
MARKS = [(0.01, None), (0.01, "left"), (0.4, None), (-0.3, "right"), (None, None)]


def _index(tmp_path):
    """A capture-like index.jsonl of small textured pairs (each its own files: eval ranges a pair once)."""
    image = (torch.rand(48, 64, generator=torch.Generator().manual_seed(0)) * 255).to(torch.uint8).numpy()
    lines = []
    for number, (gap_s, frozen) in enumerate(MARKS):
        for side, shift in (("left", 0), ("right", 2)):
            cv2.imwrite(str(tmp_path / f"pair{number:06d}_{side}.png"), cv2.blur(image[:, shift:shift + 60], (3, 3)))
        line = {"index": number, "left": f"pair{number:06d}_left.png", "right": f"pair{number:06d}_right.png"}
        lines.append(json.dumps(line if gap_s is None else {**line, "time_between_frames_s": gap_s,
                                                            "frozen_camera": frozen}))
    (tmp_path / "index.jsonl").write_text("\n".join(lines) + "\n")
    return str(tmp_path / "index.jsonl")


def _said(err: str) -> None:
    assert "1 of 5 listed pairs have the left camera's frame sent again while the right one's changed" in err
    assert "1 of 5 listed pairs have the right camera's frame sent again" in err
    assert "2 of 5 listed pairs' frames came too far apart to be one stereo moment (up to 0.40 s" in err


def test_estimate_pairs_of_an_index_marks_and_warns_of_frozen_and_torn_pairs(tmp_path, capsys):
    index = _index(tmp_path)
    assert main(["estimate", "--pairs", index, "--json", "--workers", "1"]) == 0
    out, err = capsys.readouterr()
    rows = [json.loads(line) for line in out.splitlines()]
    assert [{key: row[key] for key in ("frozen_camera", "frames_apart_s") if key in row} for row in rows] == [
        {}, {"frozen_camera": "left", "frames_apart_s": None}, {"frozen_camera": None, "frames_apart_s": 0.4},
        {"frozen_camera": "right", "frames_apart_s": 0.3}, {}]  # a sound pair's line as before
    _said(err)
    assert main(["estimate", "--pairs", index, "--workers", "1"]) == 0  # text: a line under each such pair
    assert capsys.readouterr().out.count("not one stereo moment") == 3


def test_eval_of_an_index_marks_and_warns_of_frozen_and_torn_pairs(tmp_path, capsys):
    assert main(["eval", _index(tmp_path), "--json"]) == 0
    out, err = capsys.readouterr()
    rows = [json.loads(line) for line in out.splitlines()[:-1]]  # the last line is the summary
    assert [row.get("frozen_camera", "-") for row in rows] == ["-", "left", None, "right", "-"]
    _said(err)


def test_sweep_of_an_index_warns_of_frozen_and_torn_pairs(tmp_path, capsys):
    (tmp_path / "sweep.toml").write_text(f'paths = ["{_index(tmp_path)}"]\n[grid]\n"segmentation.kernel_size" = [5]\n')
    assert main(["sweep", str(tmp_path / "sweep.toml"), "--db", str(tmp_path / "sweep.sqlite"), "--workers", "0"]) == 0
    _said(capsys.readouterr().err)


def test_estimate_and_eval_of_an_index_tell_the_pairs_captured_from_boards_in_each_others_roles(tmp_path, capsys):
    """Found by an audit of a rig set up with capture given the boards' URLs the other way round: capture now marks
    such pairs (cameras_swapped), and estimate --pairs of its index could still only ask "are LEFT and RIGHT
    swapped?". Each such pair's line now says what capture saw, and the end counts them; a pair marked false, or not
    marked, is as it was."""
    index = _index(tmp_path)
    lines = [json.loads(line) for line in (tmp_path / "index.jsonl").read_text().splitlines()]
    for line, swapped in zip(lines, (True, True, False, None, None)):
        if swapped is not None:
            line["cameras_swapped"] = swapped
    (tmp_path / "index.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
    assert main(["estimate", "--pairs", index, "--json", "--workers", "1"]) == 0
    out, err = capsys.readouterr()
    rows = [json.loads(line) for line in out.splitlines()]
    assert [row.get("cameras_swapped", "-") for row in rows] == [True, True, "-", "-", "-"]
    assert rows[1]["frozen_camera"] == "left"  # beside the other marks
    said = "2 of 5 listed pairs were captured from boards answering in each other's roles (cameras_swapped in the " \
           "index and in each --json line): ranged, but each left image is likely the right camera's view; capture " \
           "again with --left and --right the other way round"
    assert said in " ".join(err.split())
    assert main(["estimate", "--pairs", index, "--workers", "1"]) == 0
    assert capsys.readouterr().out.count("captured from boards answering in each other's roles (cameras_swapped in "
                                         "the index): its left image is likely the right camera's view") == 2
    assert main(["eval", index, "--json"]) == 0
    out, err = capsys.readouterr()
    assert [json.loads(line).get("cameras_swapped", "-") for line in out.splitlines()[:-1]] == [True, True, "-", "-",
                                                                                                "-"]
    assert said in " ".join(err.split())
