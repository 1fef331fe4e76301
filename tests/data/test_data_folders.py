"""Scene folders as users have them, not only as the shared copies are: other sizes of a data set, a calib.txt kept
beside resized views, a scene without its ground truth, scenes beside the data sets, two scenes of one name, damaged
or hand-edited files. Each test builds its folder from the shared data in ``tmp_path``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path, PureWindowsPath

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.data import (load_middlebury_2005_2006, load_middlebury_eval3, load_opencv_aloe, load_stereo_pair,
                            read_gray_image, read_middlebury_calib, read_pair_list, read_pair_sources,
                            write_pfm)
from svs_torch.data.datasets import load_kitti, scene_calibration_source
from svs_torch.data.pair_list import load_pair_source
from svs_torch.data.pair_names import _telling_folders
from svs_torch.evaluation.export import export_name


def _median_depth_m(batch) -> float:
    valid = batch.disparity_valid[0, 0]
    disparity = batch.disparity_px[0, 0][valid]
    return float((batch.focal_px[0] * batch.baseline_m[0] / (disparity + batch.doffs_px[0])).median())


def test_a_full_size_2005_2006_scene_is_read_at_its_own_scale(tmp_path: Path, data_dir: Path) -> None:
    # OpenCV's Aloe is Middlebury 2006 Aloe at full size: as a 2005/2006 folder its disp1.png is d itself, not 3·d.
    samples, scene = data_dir / "opencv_samples", tmp_path / "Aloe"
    scene.mkdir()
    for view, name in (("aloeL.jpg", "view1.png"), ("aloeR.jpg", "view5.png")):
        cv2.imwrite(str(scene / name), cv2.imread(str(samples / view)))
    shutil.copy(samples / "aloeGT.png", scene / "disp1.png")
    full, reference = load_middlebury_2005_2006(scene), load_opencv_aloe(samples)
    assert float(full.disparity_px.max()) == 211.0 and float(full.focal_px[0]) == 3740.0
    assert (full.disparity_px == reference.disparity_px).all()
    third = load_middlebury_2005_2006(data_dir / "middlebury_2005_2006_third" / "Aloe")
    assert float(third.focal_px[0]) == pytest.approx(3740.0 / 3)
    assert _median_depth_m(full) == pytest.approx(_median_depth_m(third), rel=0.02)  # one scene, one depth
    small = tmp_path / "Small"
    small.mkdir()
    for name in ("view1.png", "view5.png", "disp1.png"):  # 320 px: no size of the data set, so no known scale
        cv2.imwrite(str(small / name), cv2.resize(cv2.imread(str(scene / name), cv2.IMREAD_UNCHANGED), (320, 277)))
    with pytest.raises(InputError, match=r"left: expected a Middlebury 2005/2006 view of full .* got 320 px"):
        load_middlebury_2005_2006(small)


@pytest.mark.parametrize("width, focal_px", [(1396, 3740.0), (698, 1870.0)])  # Midd1, the widest: full and half
def test_the_widest_2005_2006_scene_loads_at_full_and_half_size(tmp_path: Path, data_dir: Path, width,
                                                               focal_px) -> None:
    third = data_dir / "middlebury_2005_2006_third" / "Midd1"
    for name in ("view1.png", "view5.png", "disp1.png"):  # disp1.png holds full-size disparities at every size
        image = cv2.imread(str(third / name), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(tmp_path / name), cv2.resize(image, (width, 370 * width // 465),
                                                     interpolation=cv2.INTER_NEAREST))
    assert float(load_middlebury_2005_2006(tmp_path).focal_px[0]) == focal_px


def test_a_calib_txt_kept_beside_resized_views_is_scaled_to_them(tmp_path: Path, data_dir: Path) -> None:
    original = data_dir / "middlebury_eval3_Q" / "Teddy"
    scene = tmp_path / "Teddy225"
    shutil.copytree(original, scene)
    for name in ("im0.png", "im1.png"):
        cv2.imwrite(str(scene / name), cv2.resize(cv2.imread(str(original / name)), (225, 188),
                                                  interpolation=cv2.INTER_AREA))
    truth = load_middlebury_eval3(original)
    gt = np.where(truth.disparity_valid[0, 0].numpy(), truth.disparity_px[0, 0].numpy(), np.inf)
    write_pfm(scene / "disp0GT.pfm", cv2.resize(gt, (225, 188), interpolation=cv2.INTER_NEAREST) * 0.5)
    (scene / "mask0nocc.png").unlink()
    batch = load_middlebury_eval3(scene)
    assert float(batch.focal_px[0]) == pytest.approx(750.0) and float(batch.doffs_px[0]) == pytest.approx(26.0)
    assert _median_depth_m(batch) == pytest.approx(_median_depth_m(truth), rel=0.01)
    assert scene_calibration_source(scene) == "Teddy225/calib.txt, scaled from its 450 px wide to the views' 225"
    assert scene_calibration_source(original) == "Teddy/calib.txt"


def test_a_2003_teddy_of_another_width_scales_its_calibration(tmp_path: Path, data_dir: Path) -> None:
    # Teddy's 2003 calibration is MiddEval3's calib.txt for 450 px: a copy resized to 225 px (disp2.png still 4·d)
    # kept f 1500 px and doffs 52 px, and its median true depth read 1.78 m for 1.45 m (an audit).
    original = data_dir / "middlebury_2003_quarter" / "Teddy"
    scene = tmp_path / "Teddy"
    scene.mkdir()
    for name in ("imL.png", "imR.png"):
        cv2.imwrite(str(scene / name), cv2.resize(cv2.imread(str(original / name)), (225, 188),
                                                  interpolation=cv2.INTER_AREA))
    stored = cv2.resize(cv2.imread(str(original / "disp2.png"), cv2.IMREAD_UNCHANGED), (225, 188),
                        interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(scene / "disp2.png"), np.where(stored > 0, np.maximum(1, np.rint(stored / 2)), 0).astype(np.uint8))
    truth, batch = load_stereo_pair(original), load_stereo_pair(scene)
    assert float(batch.focal_px[0]) == pytest.approx(750.0) and float(batch.doffs_px[0]) == pytest.approx(26.0)
    assert _median_depth_m(batch) == pytest.approx(_median_depth_m(truth), rel=0.01)
    assert scene_calibration_source(scene).endswith(", scaled from its 450 px wide to the views' 225")
    assert float(truth.focal_px[0]) == 1500.0 and float(truth.doffs_px[0]) == 52.0
    assert scene_calibration_source(original) == "MiddEval3 trainingQ/Teddy/calib.txt, the same scene and view"


def test_a_middlebury_2014_scene_reads_its_disp0_pfm_as_truth(tmp_path: Path, data_dir: Path) -> None:
    # Middlebury 2014's data sets ship calib.txt, im0/im1.png and disp0.pfm (MiddEval3's GT archive: disp0GT.pfm).
    # It loaded without truth, and eval scored none of its pairs (an audit).
    original = data_dir / "middlebury_eval3_Q" / "Teddy"
    scene = tmp_path / "Teddy-perfect"
    scene.mkdir()
    for name in ("im0.png", "im1.png", "calib.txt"):
        shutil.copy(original / name, scene / name)
    shutil.copy(original / "disp0GT.pfm", scene / "disp0.pfm")
    truth, batch = load_middlebury_eval3(original), load_stereo_pair(scene)
    assert batch.disparity_px is not None and batch.disparity_nonoccluded is None
    assert torch.equal(batch.disparity_valid, truth.disparity_valid)
    assert torch.equal(batch.disparity_px, truth.disparity_px)
    assert _median_depth_m(batch) == pytest.approx(_median_depth_m(truth))


def test_scenes_without_ground_truth_load_without_it(tmp_path: Path, data_dir: Path) -> None:
    scene = tmp_path / "TeddyTest"
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", scene)
    (scene / "disp0GT.pfm").unlink()
    batch = load_stereo_pair(scene)
    assert batch.disparity_px is None and float(batch.focal_px[0]) == 1500.0
    kitti = tmp_path / "kitti"
    shutil.copytree(data_dir / "kitti" / "stereo2015_training", kitti)
    shutil.rmtree(kitti / "disp_occ_0")
    assert load_stereo_pair(kitti / "image_2" / "000000_10.png").disparity_px is None
    # A KITTI testing folder (no truth at all) stands for every frame, as a training folder for its scored ones.
    assert [source.name for source in read_pair_sources([kitti])] == ["kitti/000000_10", "kitti/000001_10"]


def test_a_half_size_kitti_copy_keeps_its_distances(tmp_path: Path, data_dir: Path) -> None:
    """A KITTI frame resized by its user (views and truth halved, the truth's values too) reads the same metres as
    the native frame: its focal is the listed width's scaled by the width, not the native 721.5 px kept (which read
    every distance twice too far)."""
    native = load_kitti(data_dir / "kitti" / "stereo2015_training")
    half = tmp_path / "kitti"
    for folder in ("image_2", "image_3", "disp_occ_0"):
        (half / folder).mkdir(parents=True)
        image = cv2.imread(str(data_dir / "kitti" / "stereo2015_training" / folder / "000000_10.png"),
                           cv2.IMREAD_UNCHANGED)
        size = (image.shape[1] // 2, image.shape[0] // 2)
        if folder == "disp_occ_0":  # nearest keeps the 0 = unknown pixels; the disparity halves with the width
            image = (cv2.resize(image, size, interpolation=cv2.INTER_NEAREST) // 2).astype(np.uint16)
        else:
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(half / folder / "000000_10.png"), image)
    batch = load_kitti(half)
    # the 2012 and 2015 listed cameras differ by under 1 % in focal per pixel of width
    assert float(batch.focal_px[0]) == pytest.approx(float(native.focal_px[0]) * 621 / 1242, rel=0.01)
    assert _median_depth_m(batch) == pytest.approx(_median_depth_m(native), rel=0.02)
    assert float(native.focal_px[0]) == pytest.approx(721.5377)  # the native width keeps its listed values


def test_kitti_truth_must_be_16_bit(tmp_path: Path, data_dir: Path) -> None:
    kitti = tmp_path / "kitti"
    shutil.copytree(data_dir / "kitti" / "stereo2015_training", kitti)
    truth = kitti / "disp_occ_0" / "000000_10.png"
    cv2.imwrite(str(truth), (cv2.imread(str(truth), cv2.IMREAD_UNCHANGED) // 256).astype(np.uint8))
    with pytest.raises(InputError, match="disparity: expected a uint16 KITTI disparity PNG, got uint8"):
        load_kitti(kitti)


def test_a_three_channel_pfm_truth_is_named(tmp_path: Path, data_dir: Path) -> None:
    scene = tmp_path / "Teddy"
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", scene)
    (scene / "disp0GT.pfm").write_bytes(b"PF\n450 375\n-1\n" + np.zeros((375, 450, 3), "<f4").tobytes())
    with pytest.raises(InputError, match=r"disparity: expected a 1-channel PFM \('Pf'\), got 3 channels"):
        load_middlebury_eval3(scene)


@pytest.mark.parametrize("edit, message", [
    (("baseline=", "baseline= -80\n#"), r"calib: expected a finite positive number for 'baseline', got -80: "),
    (("doffs=", "doffs= nan\n#"), r"calib: expected a finite number for 'doffs', got nan: "),
    (("doffs=", "doffs=\n#"), r"calib: expected a number for 'doffs', got '': "),
    (("width=", "width= 450\nwidth="), r"calib: 'width' given twice: "),
    (("cam0=", "cam0=[0 0 225; 0 0 187; 0 0 1]\n#"), r"calib: expected cam0 finite with a positive focal length"),
])
def test_bad_calib_values_name_the_key_and_the_file(tmp_path: Path, data_dir: Path, edit, message) -> None:
    text = (data_dir / "middlebury_eval3_Q" / "Teddy" / "calib.txt").read_text()
    key, replacement = edit
    path = tmp_path / "calib.txt"
    path.write_text("\n".join(replacement + line.split("=", 1)[1] if line.strip().startswith(key) else line
                              for line in text.splitlines()))
    with pytest.raises(InputError, match=message + r".*calib\.txt"):
        read_middlebury_calib(path, "calib")


def test_a_damaged_jpeg_is_refused_and_an_intact_one_read(tmp_path: Path, data_dir: Path) -> None:
    data = bytearray((data_dir / "opencv_samples" / "aloeL.jpg").read_bytes())
    data[len(data) // 2:len(data) // 2 + 2000] = bytes(2000)  # libjpeg would fill the rest of the image with gray
    (tmp_path / "damaged.jpg").write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"left: a damaged JPEG \(libjpeg: Corrupt JPEG data"):
        read_gray_image(tmp_path / "damaged.jpg", "left")
    expected = cv2.imread(str(data_dir / "opencv_samples" / "aloeL.jpg"), cv2.IMREAD_GRAYSCALE)
    assert (read_gray_image(data_dir / "opencv_samples" / "aloeL.jpg")[0, 0].mul(255).round().numpy()
            == expected).all()
    # An audit: a JPEG whole but for its end marker (imread reads it) and one cut short were both "not a readable
    # image file", with no reason. The first is read as imread reads it; the second is damaged, libjpeg's words.
    whole = (data_dir / "opencv_samples" / "aloeL.jpg").read_bytes()
    assert whole.endswith(b"\xff\xd9")
    (tmp_path / "no_end.jpg").write_bytes(whole[:-2])
    assert (read_gray_image(tmp_path / "no_end.jpg")[0, 0].mul(255).round().numpy() == expected).all()
    (tmp_path / "cut.jpg").write_bytes(whole[:len(whole) // 2])
    with pytest.raises(InputError, match=r"left: a damaged JPEG \(libjpeg: Corrupt JPEG data: premature end"):
        read_gray_image(tmp_path / "cut.jpg", "left")


def test_scenes_beside_the_data_sets_are_listed_too(tmp_path: Path, data_dir: Path) -> None:
    (tmp_path / "middlebury_2001").mkdir()
    shutil.copytree(data_dir / "middlebury_2001" / "Venus", tmp_path / "middlebury_2001" / "Venus")
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", tmp_path / "MyTeddy")
    assert [source.name for source in read_pair_sources([tmp_path])] == ["middlebury_2001/Venus",
                                                                         f"{tmp_path.name}/MyTeddy"]


def test_a_scene_folder_lacking_a_file_is_a_bad_entry_not_left_out(tmp_path: Path, data_dir: Path) -> None:
    """Found by an audit: a folder of scenes left out a scene without calib.txt, or with IM0.PNG, without a word."""
    shared = tmp_path / "shared"
    (shared / "middlebury_eval3_Q").mkdir(parents=True)
    for name, drop, rename in (("Whole", None, None), ("NoCalib", "calib.txt", None), ("Upper", None, "im0.png")):
        for target in (tmp_path / "scenes" / name, shared / "middlebury_eval3_Q" / name):
            shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", target)
            if drop:
                (target / drop).unlink()
            if rename:
                (target / rename).rename(target / rename.upper())
    (tmp_path / "scenes" / "plots").mkdir()  # a folder with no scene's file in it is no scene, and not one bad
    for folder in (tmp_path / "scenes", shared):
        sources = read_pair_sources([folder])
        assert sorted((Path(source.left).name, source.problem is None) for source in sources) == [
            ("NoCalib", False), ("Upper", False), ("Whole", True)]
        problems = sorted(source.problem for source in sources if source.problem)
        assert problems[0].endswith("NoCalib: a MiddEval3 scene folder without calib.txt")
        assert problems[1].endswith("Upper: a MiddEval3 scene folder without im0.png (IM0.PNG is there: file names "
                                    "are case-sensitive)")
    # One such folder named alone is a bad entry too; loading it names what it lacks.
    assert [source.problem is None for source in read_pair_sources([tmp_path / "scenes" / "NoCalib"])] == [False]
    with pytest.raises(InputError, match=r"in \S+NoCalib: a MiddEval3 scene folder without calib.txt$"):
        load_stereo_pair(tmp_path / "scenes" / "NoCalib")
    # A list's line naming a folder that is not there says so, not "expected 'LEFT RIGHT' ..., got 1 field".
    (tmp_path / "pairs.txt").write_text("scenes/Whole\nscenes/Gone\n")
    assert read_pair_list(tmp_path / "pairs.txt")[1].problem.startswith(
        f"pairs: line 2 of {tmp_path / 'pairs.txt'}: no such file or folder (one field names a scene folder): ")


@pytest.mark.parametrize("scene", ["middlebury_eval3_Q/Teddy", "middlebury_2005_2006_third/Art",
                                   "middlebury_2003_quarter/Teddy", "middlebury_2001/Venus", "middlebury_2001/Tsukuba",
                                   "opencv_samples", "kitti/stereo2015_training"])
def test_every_layout_loads_its_views_and_calibration_without_its_truth(data_dir: Path, scene: str) -> None:
    """truth=False (estimate of a scene whose truth file is damaged): the same views and camera, no truth read."""
    whole, alone = (load_stereo_pair(data_dir / scene, truth=truth) for truth in (True, False))
    assert whole.disparity_px is not None and alone.disparity_px is None and alone.disparity_valid is None
    assert torch.equal(whole.left, alone.left) and torch.equal(whole.right, alone.right)
    assert (whole.focal_px, whole.baseline_m, whole.doffs_px, whole.names) == (
        alone.focal_px, alone.baseline_m, alone.doffs_px, alone.names)


def test_a_nonoccluded_mask_of_other_levels_is_refused_not_read_as_empty(tmp_path: Path, data_dir: Path) -> None:
    """Found by an audit: a mask0nocc.png of 0 and 1 read as no pixel non-occluded, its metrics left out unsaid."""
    scene = tmp_path / "Teddy"
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", scene)
    mask = cv2.imread(str(scene / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE)
    assert bool(load_stereo_pair(scene).disparity_nonoccluded.any())
    cv2.imwrite(str(scene / "mask0nocc.png"), (mask == 255).astype(np.uint8))
    with pytest.raises(InputError, match=r"^mask0nocc: expected MiddEval3's levels 255 \(non-occluded\), 128 "
                                         r"\(occluded\) and 0 \(unknown\), got 0, 1: "):
        load_stereo_pair(scene)


def test_two_scenes_of_one_name_are_told_apart(tmp_path: Path, data_dir: Path) -> None:
    for folder, scene in (("a", "Teddy"), ("b", "Piano")):
        shutil.copytree(data_dir / "middlebury_eval3_Q" / scene, tmp_path / folder / "Teddy")
    sources = read_pair_sources([tmp_path / "a" / "Teddy", tmp_path / "b" / "Teddy", tmp_path / "a" / "Teddy"])
    assert [source.name for source in sources] == ["eval3/Teddy (a)", "eval3/Teddy (b)", "eval3/Teddy (a)"]
    assert [load_pair_source(source).names[0] for source in sources[:2]] == ["eval3/Teddy (a)", "eval3/Teddy (b)"]
    listed = tmp_path / "pairs.txt"  # file pairs too: both would be Teddy/im0.png
    listed.write_text("a/Teddy/im0.png a/Teddy/im1.png\nb/Teddy/im0.png b/Teddy/im1.png\n")
    assert [source.name for source in read_pair_list(listed)] == ["Teddy/im0.png (a)", "Teddy/im0.png (b)"]
    alone = read_pair_sources([data_dir / "middlebury_eval3_Q" / "Teddy", data_dir / "middlebury_2003_quarter"])
    assert [source.name for source in alone][0] == "middlebury_eval3_Q/Teddy"  # no other eval3/Teddy: no label
    (tmp_path / "link").symlink_to(tmp_path / "a")  # one scene reached twice: the same pair, not two to tell apart
    assert read_pair_sources([tmp_path / "a" / "Teddy", tmp_path / "link" / "Teddy"])[1].label is None
    # Labels of two folders keep both in an exported map's name; a root or drive is no folder to tell them by.
    deeper = [tmp_path / f"{x}/{a}/Teddy" for x, a in (("x", "a"), ("y", "a"), ("x", "b"))]
    for path in deeper:
        shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", path)
    names = [source.name for source in read_pair_sources(deeper)]
    assert names == ["eval3/Teddy (x/a)", "eval3/Teddy (y/a)", "eval3/Teddy (x/b)"]
    assert [export_name(name) for name in names] == ["Teddy_x_a", "Teddy_y_a", "Teddy_x_b"]
    assert _telling_folders([PureWindowsPath("C:/data/Teddy"), PureWindowsPath("D:/data/Teddy")]) == ["1", "2"]


def test_a_pair_listed_again_through_a_link_keeps_the_name_it_runs_under(tmp_path: Path, data_dir: Path) -> None:
    # Two Teddy/im0.png pairs told apart by their folders, then the first listed again through a link to its folder:
    # eval runs the first spelling and drops the repeat, but the repeat's folder renamed it ("Teddy/im0.png (link)"
    # in the JSON, the store and the --disparity-out folder) where the list without the repeat said "(a)".
    for folder, scene in (("a", "Teddy"), ("b", "Piano")):
        (tmp_path / folder / "Teddy").mkdir(parents=True)
        for view in ("im0.png", "im1.png"):
            shutil.copy(data_dir / "middlebury_eval3_Q" / scene / view, tmp_path / folder / "Teddy" / view)
    (tmp_path / "link").symlink_to(tmp_path / "a")
    lines = "a/Teddy/im0.png a/Teddy/im1.png\nb/Teddy/im0.png b/Teddy/im1.png\n"
    (tmp_path / "pairs.txt").write_text(lines)
    (tmp_path / "again.txt").write_text(lines + "link/Teddy/im0.png link/Teddy/im1.png\n")
    once = [source.name for source in read_pair_sources([tmp_path / "pairs.txt"])]
    again = [source.name for source in read_pair_sources([tmp_path / "again.txt"])]
    assert once == ["Teddy/im0.png (a)", "Teddy/im0.png (b)"]
    assert again == [*once, "Teddy/im0.png (a)"]
    assert [source.name for source in read_pair_list(tmp_path / "again.txt")] == again


def test_a_pair_list_saved_with_a_byte_order_mark_reads(tmp_path: Path, data_dir: Path) -> None:
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listed = tmp_path / "pairs.txt"
    listed.write_bytes(f"\ufeff# my pairs\r\n{teddy / 'im0.png'} {teddy / 'im1.png'}\r\n".encode("utf-8"))
    assert [source.problem for source in read_pair_list(listed)] == [None]


def test_an_empty_file_name_is_that_lines_problem_not_the_lists_folder(tmp_path: Path) -> None:
    """An audit of hand-edited lists: a quoted empty name ('"" R.png') or an index line's "right": "" was read as the
    list's own folder, and the pair failed as "expected a file, got a directory: <the folder>" (a line '""' alone
    stood for every scene in that folder)."""
    import json

    listed, index = tmp_path / "pairs.txt", tmp_path / "index.jsonl"
    listed.write_text('"" R.png\nL.png ""\n""\n')
    index.write_text(json.dumps({"left": "L.png", "right": ""}) + "\n")
    problems = [source.problem for source in read_pair_list(listed) + read_pair_list(index)]
    assert len(problems) == 4 and all(problem and "got a directory" not in problem for problem in problems)
    assert all("got an empty file name" in problem for problem in problems[:3])
    assert "expected a JSON object with 'left' and 'right' file names" in problems[3]


def _unlistable(monkeypatch, *folders: Path) -> None:
    """List ``folders`` as a non-root user lists a folder it may not read (as root, a mode of 000 does not stop us)."""
    import errno
    import os

    refused = {str(folder) for folder in folders}
    real_scandir, real_listdir = os.scandir, os.listdir

    def check(path):
        if os.fspath(path) in refused:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))

    monkeypatch.setattr(os, "scandir", lambda path=".": check(path) or real_scandir(path))
    monkeypatch.setattr(os, "listdir", lambda path=".": check(path) or real_listdir(path))


def test_a_scene_folder_that_cannot_be_read_is_warned_of(tmp_path: Path, data_dir: Path, monkeypatch) -> None:
    """A scene folder of a data set the user may not read was skipped without a word (eval: "1 pairs, 0 failed",
    exit 0); a PATH folder itself that cannot be read was "error: Permission denied: PATH/middlebury_eval3_Q"."""
    for scene in ("Art", "Books"):
        shutil.copytree(data_dir / "middlebury_2005_2006_third" / scene, tmp_path / "sets" / scene)
    _unlistable(monkeypatch, tmp_path / "sets" / "Books")
    with pytest.warns(RuntimeWarning, match=r"Books: a folder that cannot be read \(Permission denied\): skipped"):
        assert [Path(source.left).name for source in read_pair_sources([tmp_path / "sets"])] == ["Art"]
    _unlistable(monkeypatch, tmp_path / "sets")
    with pytest.raises(InputError, match=r"^path: cannot read the folder .*sets \(Permission denied\)$"):
        read_pair_sources([tmp_path / "sets"])


def test_a_capture_index_line_whose_frame_fails_to_load_is_named(tmp_path):
    """Found by an audit of the bulk commands: a list file's pair that failed to load named its line, an
    ``index.jsonl``'s did not ("left: file not found: gone.png" alone, in an index of thousands of frames)."""
    from svs_torch.data.pair_list import load_pair_source

    cv2.imwrite(str(tmp_path / "a.png"), np.full((24, 32), 90, np.uint8))
    index = tmp_path / "index.jsonl"
    index.write_text('{"left": "a.png", "right": "a.png"}\n{"left": "gone.png", "right": "a.png"}\n')
    present, missing = read_pair_list(index)
    assert load_pair_source(present, 500.0, 0.1).left.shape == (1, 1, 24, 32)
    with pytest.raises(InputError, match=rf"file not found: .*gone\.png \(line 2 of {index}\)$"):
        load_pair_source(missing, 500.0, 0.1)


def test_a_capture_index_line_naming_a_file_with_a_nul_character_is_a_bad_line(tmp_path, capsys):
    """An audit: an index.jsonl line whose "left" held a NUL ("L.png\\u0000", valid JSON; no file can have the
    name) ended 'svs-depth eval index.jsonl' in "internal error: ValueError: embedded null byte", exit 1 (estimate
    --pairs found it BAD_INPUT only when loading), and a lone surrogate ("\\ud800") in a UnicodeEncodeError. It is a
    bad line, as a list file's NUL is."""
    from svs_torch.cli import main

    cv2.imwrite(str(tmp_path / "a.png"), np.full((24, 32), 90, np.uint8))
    index = tmp_path / "index.jsonl"
    index.write_text('{"left": "a.png\\u0000x", "right": "a.png"}\n{"left": "a.png", "right": "a\\ud800.png"}\n')
    for source in read_pair_sources([index]):
        assert source.problem.endswith(f"of {index}: a NUL or surrogate in a file name")
    assert main(["eval", str(index), "--json"]) == 0
    assert [json.loads(line)["status"] for line in capsys.readouterr().out.splitlines()[:2]] == ["BAD_INPUT"] * 2


def test_a_capture_index_line_nested_too_deep_is_a_bad_line(tmp_path):
    """An audit: an index.jsonl line of 100 000 nested brackets ended 'svs-depth eval index.jsonl' and 'estimate
    --pairs' in "internal error: RecursionError: maximum recursion depth exceeded while decoding a JSON array",
    exit 1, before any pair ran. It is a bad line, as one that is not JSON is, and the other lines are read."""
    cv2.imwrite(str(tmp_path / "a.png"), np.full((24, 32), 90, np.uint8))
    index = tmp_path / "index.jsonl"
    index.write_text("[" * 100_000 + "]" * 100_000 + '\n{"left": "a.png", "right": "a.png"}\n')
    deep, good = read_pair_sources([index])
    assert deep.problem == f"path: line 1 of {index}: expected a JSON object with 'left' and 'right' file names"
    assert good.problem is None


def test_a_scene_given_as_dot_is_named_after_its_folder(data_dir, tmp_path, monkeypatch, capsys):
    """An audit: 'cd Teddy && svs-depth estimate . --disparity-out maps' named the scene "eval3/" (Path('.').name is
    empty): the calibration line read "(/calib.txt)", eval's row "eval3/", and the map went to maps/eval3/, not
    maps/Teddy/ where the MiddEval3 SDK looks; 'cd Art && estimate .' lost Art's dmin (looked up by the folder's
    name) and ranged it at 3.49 m, not 1.61 m. '.' and '..' are named after the folder they are."""
    from svs_torch.cli import main
    from svs_torch.data import load_stereo_pair

    scene = tmp_path / "Teddy"
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", scene)
    monkeypatch.chdir(scene)
    assert load_stereo_pair(".").names == ("eval3/Teddy",)
    (source,) = read_pair_sources(["."])
    assert source.loaded_name == "eval3/Teddy"
    assert main(["estimate", ".", "--size", "160x133", "--disparity-out", str(tmp_path / "maps")]) == 0
    assert "(Teddy/calib.txt)" in capsys.readouterr().out
    assert (tmp_path / "maps" / "Teddy" / "disp0SVSTorch.pfm").is_file()
    monkeypatch.chdir(data_dir / "middlebury_2005_2006_third" / "Art")
    art = load_stereo_pair(".")
    assert art.names == ("2005_2006/Art",) and float(art.doffs_px[0]) == pytest.approx(200 / 3)


def test_read_pair_sources_takes_one_path_alone_and_names_a_path_of_the_wrong_type(data_dir):
    """Found by an audit of the Python API: read_pair_sources("…/middlebury_2003_quarter") read the name letter by
    letter, to "no stereo scene ... in the folder /"; None, or None in the list, was a TypeError from os.fspath."""
    folder = data_dir / "middlebury_2003_quarter"
    listed = read_pair_sources([folder])
    assert read_pair_sources(str(folder)) == listed and read_pair_sources(folder) == listed
    for paths in (None, [None], [folder, 3]):
        with pytest.raises(InputError, match=r"path: expected a scene folder, a pair list or index.jsonl \(str or "
                                             r"os.PathLike\), got (NoneType|int)"):
            read_pair_sources(paths)
    with pytest.raises(InputError, match=r"pairs: expected a list file name \(str or os.PathLike\), got NoneType"):
        read_pair_list(None)


def test_load_pair_source_names_a_source_that_is_no_pair_source(data_dir):
    """Found by an audit of the Python API: load_pair_source("…/Teddy") was an AttributeError ('str' object has no
    attribute 'problem')."""
    with pytest.raises(InputError, match="source: expected a PairSource, got str"):
        load_pair_source(str(data_dir / "middlebury_2003_quarter" / "Teddy"))
