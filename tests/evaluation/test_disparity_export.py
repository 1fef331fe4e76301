"""Disparity maps out (svs_torch.evaluation.export, the PFM and KITTI PNG writers of svs_torch.data.formats):
exact round trips, the official layouts, and maps that read back to the depths the JSON reports."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.cli import main
from svs_torch.data import (load_stereo_pair, read_kitti_disparity, read_middlebury_calib, read_pfm,
                            write_kitti_disparity, write_pfm)
from svs_torch.evaluation.export import DisparityExport, export_name
from svs_torch.pipeline import estimate_obstacle_depth


@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (375, 450)])
def test_pfm_round_trip_is_bit_exact(tmp_path, generator, shape):
    values = (torch.randn(shape, generator=generator, dtype=torch.float64) * 100).numpy().astype(np.float32)
    values.flat[::5] = np.inf  # Middlebury's unknown
    values.flat[1::7] = -0.0
    write_pfm(tmp_path / "d.pfm", values)
    back = read_pfm(tmp_path / "d.pfm")
    assert back.dtype == np.float32 and back.view(np.uint32).tolist() == values.view(np.uint32).tolist()
    # The layout itself, read by hand (MANIFEST §2): header, little-endian scale, rows bottom to top.
    raw = (tmp_path / "d.pfm").read_bytes()
    header = f"Pf\n{shape[1]} {shape[0]}\n-1\n".encode()
    assert raw.startswith(header)
    assert np.array_equal(np.frombuffer(raw[len(header):], "<f4").reshape(shape)[::-1], values)


def test_kitti_png_round_trip_is_exact(tmp_path, generator):
    steps = torch.randint(1, 65536, (37, 53), generator=generator).numpy()
    disparity = (steps / 256.0).astype(np.float32)  # every value the format holds as known
    valid = torch.rand(37, 53, generator=generator).numpy() > 0.3
    write_kitti_disparity(tmp_path / "d.png", disparity, valid)
    back, back_valid = read_kitti_disparity(tmp_path / "d.png")
    assert np.array_equal(back_valid, valid) and np.array_equal(back[valid], disparity[valid])
    assert not back[~valid].any()
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)  # OpenCV's own decoding: uint16, d x 256
    assert raw.dtype == np.uint16 and np.array_equal(raw, np.where(valid, steps, 0))


def test_kitti_png_clips_what_it_cannot_hold(tmp_path):
    disparity = np.array([[0.0, 0.001, 300.0, -2.0, np.nan, 12.3456]], dtype=np.float32)
    write_kitti_disparity(tmp_path / "d.png", disparity, np.ones_like(disparity, dtype=bool))
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    # A known 0 or tiny disparity stays known (1/256); above 255.996 is clipped; negative and NaN are unknown.
    assert raw[0].tolist() == [1, 1, 65535, 0, 0, round(12.3456 * 256)]


def test_writers_and_reader_name_bad_input(tmp_path):
    with pytest.raises(InputError, match="array: expected a non-empty"):
        write_pfm(tmp_path / "d.pfm", np.zeros((2, 2, 3), np.float32))
    with pytest.raises(InputError, match="disparity_px, valid"):
        write_kitti_disparity(tmp_path / "d.png", np.zeros((2, 3)), np.zeros((3, 2), bool))
    cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(InputError, match="expected a uint16 KITTI disparity PNG"):
        read_kitti_disparity(tmp_path / "eight.png")
    # a library call is told its argument's name, a command's user the option (the class is both's)
    with pytest.raises(InputError, match=r"^format \(--disparity-format\): expected one of"):
        DisparityExport(tmp_path, "png")
    with pytest.raises(InputError, match=r"^method \(--method-name\): expected 1-64"):
        DisparityExport(tmp_path, "middlebury", "my method")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="--disparity-out: expected a folder"):
        DisparityExport(tmp_path / "file").prepare()
    with pytest.raises(InputError, match="does not exist"):
        DisparityExport(tmp_path / "no" / "maps").prepare()


def test_export_names():
    assert [export_name(n) for n in ("eval3/Teddy", "kitti2012/000000_10", "captured/left 01.png", "..")] == \
        ["Teddy", "000000_10", "left_01", "pair"]
    # A view's generic name is its folder's, as a plain line's pair is named (data.datasets.pair_name).
    assert [export_name(n) for n in ("Piano/im0.png", "rig/L.jpg", "im0.png", "captures/pair0007_left.png")] == \
        ["Piano", "rig", "im0", "pair0007_left"]


def test_listed_pairs_with_their_calibration_keep_a_map_each(data_dir, tmp_path, capsys):
    """Found by an audit of the documented examples: every MiddEval3 line 'LEFT RIGHT FOCAL_PX BASELINE_M DOFFS_PX'
    was exported as 'im0', so one map was kept and the others skipped with a warning, exit 0."""
    listed = tmp_path / "cal.txt"
    lines = []
    for scene in ("Teddy", "Piano"):
        calib = read_middlebury_calib(data_dir / "middlebury_eval3_Q" / scene / "calib.txt", "calib")
        folder = data_dir / "middlebury_eval3_Q" / scene
        lines.append(f"{folder / 'im0.png'} {folder / 'im1.png'} {calib['cam0'][0, 0]} "
                     f"{calib['baseline'] / 1000} {calib['doffs']}\n")
    listed.write_text("".join(lines))
    out = tmp_path / "maps"
    for command in (["estimate", "--pairs", str(listed)], ["eval", str(listed)]):
        code = main([*command, "--size", "160x120", "--json", "--disparity-out", str(out), "--disparity-format",
                     "kitti"])
        err = capsys.readouterr().err
        assert code == 0 and "not written" not in err, (command, err)
        assert sorted(p.name for p in out.iterdir()) == ["Piano.png", "Teddy.png"], command


def test_written_maps_equal_the_dense_map(data_dir, tmp_path):
    batch = load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy")
    with torch.no_grad():
        result = estimate_obstacle_depth(batch)
    assert not bool(result.rectified[0])
    DisparityExport(tmp_path / "m").prepare()
    DisparityExport(tmp_path / "m").write(batch, result, 0.25)
    DisparityExport(tmp_path / "k", "kitti").prepare()
    DisparityExport(tmp_path / "k", "kitti").write(batch, result, 0.25)
    dense, valid = result.dense.disparity_px[0, 0].numpy(), result.dense.valid[0, 0].numpy()
    pfm = read_pfm(tmp_path / "m" / "Teddy" / "disp0SVSTorch.pfm")
    assert np.array_equal(np.isfinite(pfm), valid) and np.array_equal(pfm[valid], dense[valid])
    assert (tmp_path / "m" / "Teddy" / "timeSVSTorch.txt").read_text() == "0.250000\n"
    png, png_valid = read_kitti_disparity(tmp_path / "k" / "Teddy.png")
    assert np.array_equal(png_valid, valid) and np.abs(png[valid] - dense[valid]).max() <= 1 / 512
    export = DisparityExport(tmp_path / "m")
    export.write(batch, result, 0.25)
    pfm_file = tmp_path / "m" / "Teddy" / "disp0SVSTorch.pfm"
    before = pfm_file.read_bytes()
    other = dataclasses.replace(batch, names=("2003/Teddy",))
    with pytest.warns(RuntimeWarning, match="'2003/Teddy' not written: it would overwrite 'eval3/Teddy'"):
        assert export.write(other, result, 0.25) == []  # another pair of the same name in this export: skipped
    assert pfm_file.read_bytes() == before


def _fill_rows(d: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The documented fill (``DenseConfig.fill_invalid``): an unknown pixel takes its row's nearest known
    neighbours' mean where they agree within 1 px, else the smaller (background); one side if only one."""
    out, reach = d.copy(), ok.copy()
    for y in range(d.shape[0]):
        known = np.flatnonzero(ok[y])
        if known.size == 0:
            continue
        for x in np.flatnonzero(~ok[y]):
            right = known[np.searchsorted(known, x):]
            left = known[:np.searchsorted(known, x)]
            a = d[y, left[-1]] if left.size else None
            b = d[y, right[0]] if right.size else None
            out[y, x] = (b if a is None else a if b is None else (a + b) / 2 if abs(a - b) <= 1 else min(a, b))
            reach[y, x] = True
    return out, reach


def test_exported_pfm_reads_back_to_the_json_depths(data_dir, tmp_path, capsys):
    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    code = main(["estimate", str(scene), "--json", "--masks-out", str(tmp_path / "labels.png"),
                 "--disparity-out", str(tmp_path / "maps")])
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["status"] == "OK" and not report["rectified"]
    pfm = read_pfm(tmp_path / "maps" / "Teddy" / "disp0SVSTorch.pfm")
    labels = cv2.imread(str(tmp_path / "labels.png"), cv2.IMREAD_UNCHANGED)
    calib = read_middlebury_calib(scene / "calib.txt")
    focal, baseline_m, doffs = calib["cam0"][0, 0], calib["baseline"] / 1000, calib["doffs"]
    filled, reach = _fill_rows(pfm.astype(np.float64), np.isfinite(pfm))
    x0, y0, width, height = report["dense_box_xywh"]  # the statistics are over the searched box
    box = np.zeros(pfm.shape, dtype=bool)
    box[y0:y0 + height, x0:x0 + width] = True
    reach &= box
    checked = 0
    for obj in report["objects"]:
        if obj["depth_m"] is None:
            continue
        region = (labels == obj["label"]) & reach & (filled + doffs > 0)
        depth = focal * baseline_m / (filled[region] + doffs)
        assert np.median(depth) == pytest.approx(obj["depth_m"], abs=6e-5)  # the JSON rounds to 0.1 mm
        assert np.percentile(depth, 10) == pytest.approx(obj["depth_p10_m"], abs=6e-5)
        checked += 1
    assert checked == len(report["objects"]) >= 1  # every kept object ranged and read back


def test_a_rectified_map_is_brought_back_to_the_left_grid(data_dir):
    from svs_torch.evaluation.export import left_view_disparity

    batch = load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy")
    with torch.no_grad():
        result = estimate_obstacle_depth(batch)
    # As if the left view had been rectified by a shift of 3 px to the left: rectified x = x - 3.
    shift = torch.tensor([[[1.0, 0.0, -3.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    rectified = dataclasses.replace(result, rectified=torch.tensor([True]),
                                    rectification=dataclasses.replace(result.rectification, H_left=shift))
    back, back_valid = left_view_disparity(batch, rectified, 0)
    dense, valid = result.dense.disparity_px[0, 0].numpy(), result.dense.valid[0, 0].numpy()
    assert np.array_equal(back_valid[:, 3:], valid[:, :-3]) and not back_valid[:, :3].any()
    assert np.array_equal(back[:, 3:][valid[:, :-3]], dense[:, :-3][valid[:, :-3]])


def test_disparity_out_needs_the_dense_rule_and_a_folder(data_dir, tmp_path, capsys):
    scene = str(data_dir / "middlebury_eval3_Q" / "Teddy")
    assert main(["eval", scene, "--preset", "paper", "--disparity-out", str(tmp_path / "m")]) == 2
    assert "--disparity-out: expected the dense range rule" in capsys.readouterr().err
    assert main(["estimate", scene, "--range", "paper", "--disparity-out", str(tmp_path / "m")]) == 2
    assert "--disparity-out: expected the dense range rule" in capsys.readouterr().err
    assert main(["estimate", scene, "--disparity-out", str(tmp_path / "no" / "m")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse's own refusal, exit status 2
        main(["estimate", scene, "--method-name", "a b", "--disparity-out", str(tmp_path)])
    assert "--method-name: expected 1-64 letters" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_estimate_pairs_on_workers_writes_the_first_listed_of_a_shared_name(data_dir, tmp_path, capsys):
    """Found by an audit of the bulk commands: with --workers 2 each worker wrote its own Teddy into the one
    export folder, one over the other, the survivor varying from run to run, without a warning; one worker kept
    the first and warned. Every worker claims the names from the whole list now."""
    listing = tmp_path / "teddys.txt"
    listing.write_text(f"{data_dir / 'middlebury_eval3_Q' / 'Teddy'}\n{data_dir / 'middlebury_2003_quarter' / 'Teddy'}\n")
    maps = {}
    for workers in ("1", "2"):
        out = tmp_path / f"maps{workers}"
        # Exit 1 at the end, as for an output that cannot be written (it said 0: a script took every map as
        # written; an audit of the files the commands write).
        assert main(["estimate", "--pairs", str(listing), "--size", "160x120", "--json", "--workers", workers,
                     "--batch-size", "1", "--disparity-out", str(out)]) == 1
        err = capsys.readouterr().err
        assert err.count("'2003/Teddy' not written: ") == 1 and "'eval3/Teddy'" in err, err
        assert err.endswith("svs-depth estimate: error: --disparity-out: 1 map not written (warned above); every "
                            "pair's results stand\n")
        maps[workers] = (out / "Teddy" / "disp0SVSTorch.pfm").read_bytes()
    assert maps["1"] == maps["2"]


def test_estimate_pairs_keeps_the_first_of_two_listed_files_of_one_name(data_dir, tmp_path, capsys):
    """Found by an audit: a/x.png and b/x.png (two scenes' left files copied under one name) were both named 'x' by
    estimate --pairs, so --disparity-out wrote the second's map over the first's without a word (eval warned)."""
    import shutil

    for folder, scene in (("a", "Teddy"), ("b", "Piano")):
        (tmp_path / folder).mkdir()
        for view, name in (("im0", "x"), ("im1", "y")):
            shutil.copy(data_dir / "middlebury_eval3_Q" / scene / f"{view}.png", tmp_path / folder / f"{name}.png")
    listing = tmp_path / "pairs.txt"
    listing.write_text("".join(f"{tmp_path / f / 'x.png'} {tmp_path / f / 'y.png'}\n" for f in ("a", "b")))
    out = tmp_path / "maps"
    assert main(["estimate", "--pairs", str(listing), "--json", "--workers", "1",
                 "--disparity-out", str(out), "--disparity-format", "kitti"]) == 1
    err = capsys.readouterr().err
    assert err.count("not written: ") == 1 and "'b/x.png' not written: its export name belongs to 'a/x.png'" in err
    assert [p.name for p in out.iterdir()] == ["x.png"]
    assert read_kitti_disparity(out / "x.png")[0].shape == (375, 450)  # Teddy's map (Piano's is 481 x 707)


def test_a_full_disk_names_the_file_it_refused_and_leaves_no_map_without_its_time(data_dir, tmp_path, monkeypatch):
    """Was (an audit of full disks): the map was written before its time file, and a disk that refused the time
    file gave 'cannot write .../disp0SVSTorch.pfm' while that map was there, complete, without the time file the
    SDK reads beside it. Now the time file comes first and the error names the file refused; and the scene's folder,
    made for the two files, is not left behind empty (it was, a scene the SDK lists with no map)."""
    import svs_torch.evaluation.export as export_module

    batch = load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy")
    with torch.no_grad():
        result = estimate_obstacle_depth(batch)

    def full_disk(path, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export_module, "write_bytes_atomic", full_disk)
    export = DisparityExport(tmp_path / "m")
    export.prepare()
    with pytest.raises(OSError, match=r"--disparity-out: cannot write .*timeSVSTorch\.txt: No space left on device"):
        export.write(batch, result, 0.25)
    assert list((tmp_path / "m").iterdir()) == []


def test_a_map_refused_for_permission_is_the_runs_failure_not_a_usage_error(data_dir, tmp_path, monkeypatch, capsys):
    """An audit: 'eval SCENE --disparity-out DIR' where a map could not be replaced (EPERM: an immutable file, another
    user's in a sticky folder) stopped with exit 2, a usage error, where a full disk is exit 1, the help's status for
    an output that cannot be written: the error was rebuilt as OSError(1, ...), which Python makes a
    PermissionError."""
    import svs_torch.evaluation.export as export_module
    from svs_torch.cli import main

    def refused(path, data):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(export_module, "write_bytes_atomic", refused)
    assert main(["eval", str(data_dir / "middlebury_eval3_Q" / "Teddy"), "--disparity-out", str(tmp_path / "m")]) == 1
    assert "--disparity-out: cannot write " in capsys.readouterr().err


def _evaldisp_size_ok(map_hw: tuple[int, int], truth_hw: tuple[int, int]) -> bool:
    """The MiddEval3 SDK's evaldisp size rule, read from its source: the GT must be exactly 1, 2 or 4 times the
    map's size ("GT disp size must be exactly 1, 2, or 4 * disp size")."""
    return any(truth_hw == (k * map_hw[0], k * map_hw[1]) for k in (1, 2, 4))


@pytest.mark.parametrize("source", ["eval", "estimate", "estimate --pairs"])
def test_maps_at_a_size_the_official_tools_refuse_are_said(data_dir, tmp_path, capsys, source):
    """Found by an audit of the export: the README's example 'eval middlebury_eval3_Q --size 320x240 --disparity-out
    maps' wrote 320x240 maps that the SDK's evaldisp refuses (Teddy's GT is 450x375) and the KITTI devkit too
    (only its own size), exit 0 and nothing said. The maps stay at the size the pipeline ran at (estimate's boxes
    are in its pixels); eval now says so, once, and at the scene's own size it says nothing. Found again by an audit
    of option gaps: estimate, whose maps are the same files for the same tools (the shared --disparity-out help),
    said nothing; now the same note, once, one pair or a --pairs list alike."""
    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    truth_hw = read_pfm(scene / "disp0GT.pfm").shape
    (tmp_path / "list.txt").write_text(f"{scene}\n")
    command = {"eval": ["eval", str(scene)], "estimate": ["estimate", str(scene)],
               "estimate --pairs": ["estimate", "--pairs", str(tmp_path / "list.txt"), "--workers", "1"]}[source]
    for size, warned in (("160x120", True), (None, False)):
        out = tmp_path / f"maps_{size}"
        argv = [*command, "--json", "--disparity-out", str(out)] + (["--size", size] if size else [])
        assert main(argv) == 0
        err = capsys.readouterr().err
        map_hw = read_pfm(out / "Teddy" / "disp0SVSTorch.pfm").shape
        assert _evaldisp_size_ok(map_hw, truth_hw) is not warned, (size, map_hw)
        assert err.count("the MiddEval3 SDK scores a map only at") == int(warned), err
        if warned:
            assert "--disparity-out: the maps are 160x120, the --size the pipeline ran at" in err
            assert "not written" not in err  # a note, not a map left out: exit 0


def test_a_pair_not_run_again_loses_the_map_an_earlier_run_left(data_dir, tmp_path, capsys):
    """Found by an audit of the export: a scene whose image had become unreadable was BAD_INPUT on the second run
    into the same folder, and its map from the first run stayed beside the second run's maps, where the SDK scored
    it as this run's. Now eval and estimate --pairs remove it, warned; the other scene's map is the new run's."""
    import shutil

    scenes = tmp_path / "scenes"
    for name in ("Teddy", "Other"):
        shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", scenes / name)
    listing = tmp_path / "pairs.txt"
    listing.write_text("".join(f"{scenes / n / 'im0.png'} {scenes / n / 'im1.png'}\n" for n in ("Teddy", "Other")))
    runs = {"eval": ["eval", str(scenes)], "estimate": ["estimate", "--pairs", str(listing)]}
    for command, argv in runs.items():
        out, bad_image = tmp_path / f"maps_{command}", scenes / "Other" / "im1.png"
        shutil.copy(scenes / "Teddy" / "im1.png", bad_image)
        assert main([*argv, "--size", "160x120", "--json", "--disparity-out", str(out)]) == 0
        assert sorted(p.name for p in out.iterdir()) == ["Other", "Teddy"]
        bad_image.write_bytes(b"not an image")
        assert main([*argv, "--size", "160x120", "--json", "--disparity-out", str(out)]) == (0 if command == "eval"
                                                                                             else 2)
        err = capsys.readouterr().err
        assert err.count("not run (BAD_INPUT): the map an earlier run left") == 1, err
        assert f"{out / 'Other' / 'disp0SVSTorch.pfm'}, removed" in err
        assert sorted(p.name for p in (out / "Other").iterdir()) == [], command
        assert sorted(p.name for p in (out / "Teddy").iterdir()) == ["disp0SVSTorch.pfm", "timeSVSTorch.txt"]


def test_forget_unrun_keeps_what_is_not_an_earlier_export(data_dir, tmp_path):
    """:meth:`DisparityExport.forget_unrun` removes only a map an export wrote before: never a ground truth (a PFM
    without its time file), a map this process wrote (a pair scored as ERROR after its map was written), nor the
    map of another pair that has the name."""
    batch = load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy")
    with torch.no_grad():
        result = estimate_obstacle_depth(batch)
    export = DisparityExport(tmp_path / "m")
    export.prepare()
    (map_file,) = export.write(batch, result, 0.25)
    assert export.forget_unrun(batch.names[0], "ERROR") is None and map_file.exists()
    later = DisparityExport(tmp_path / "m")
    later.claim_ahead("2003/Teddy")
    assert later.forget_unrun("eval3/Teddy", "BAD_INPUT") is None and map_file.exists()
    truth = tmp_path / "gt"
    (truth / "Teddy").mkdir(parents=True)
    (truth / "Teddy" / "disp0GT.pfm").write_bytes(map_file.read_bytes())
    assert DisparityExport(truth, method="GT").forget_unrun("Teddy", "BAD_INPUT") is None
    assert (truth / "Teddy" / "disp0GT.pfm").exists()
    with pytest.warns(RuntimeWarning, match="not run \\(BAD_INPUT\\): the map an earlier run left"):
        assert DisparityExport(tmp_path / "m").forget_unrun("eval3/Teddy", "BAD_INPUT") == map_file
    assert not map_file.exists() and not (map_file.parent / "timeSVSTorch.txt").exists()
