"""The saved-pairs folder of ``capture --out-dir`` and ``guide --record`` (svs_torch.cli.pairs_folder): a pair is
kept whole or not at all, and every refusal or failure names the option and the file. Found by an audit of the
device-side commands."""

from __future__ import annotations

import json
import shlex
from types import SimpleNamespace

import pytest

import svs_torch.cli.pairs_folder as pairs_folder
from svs_torch.cli import main
from svs_torch.cli.pairs_folder import PairsIndex, new_pairs_folder, save_pair
from svs_torch.core.errors import InputError


def _pair(index: int) -> SimpleNamespace:
    frame = SimpleNamespace(jpeg=b"\xff\xd8 a jpeg", size_wh=(320, 240), request_monotonic_s=1.0,
                            header_monotonic_s=1.05, arrival_monotonic_s=1.1, arrival_wall_s=2.0, attempts=1)
    return SimpleNamespace(index=index, left=frame, right=frame, time_between_frames_s=0.01)


def test_a_folder_below_a_file_is_refused_before_the_camera_opens(tmp_path):
    """Was: "[Errno 20] Not a directory: 'afile/sub'", exit 1, after the emulator had started."""
    (tmp_path / "afile").write_text("")
    with pytest.raises(InputError, match=r"--out-dir: expected a folder, but .*afile on its path is not a folder"):
        new_pairs_folder(str(tmp_path / "afile" / "sub" / "deeper"), "--out-dir")
    assert new_pairs_folder(str(tmp_path / "new" / "sub"), "--out-dir") == tmp_path / "new" / "sub"
    with pytest.raises(InputError, match="--record: expected a folder, got a device or socket"):
        new_pairs_folder("/dev/null", "--record")  # was "got a other"


def test_a_folder_holding_pair_images_is_refused_without_an_index(tmp_path):
    """Was: a folder of pairs whose index.jsonl had been removed was written over without a word."""
    (tmp_path / "pair000001_right.jpg").write_bytes(b"mine")
    with pytest.raises(InputError, match=r"--out-dir: .*pair000001_right\.jpg already exists; choose a new folder"):
        new_pairs_folder(str(tmp_path), "--out-dir")
    (tmp_path / "pair000001_right.jpg").rename(tmp_path / "notes.jpg")  # another name: not a saved pair
    assert new_pairs_folder(str(tmp_path), "--out-dir") == tmp_path


def test_a_folder_holding_a_calibration_is_refused(tmp_path):
    """An audit: capture --calibration wrote over another run's calibration.json in silence; without --calibration,
    estimate --pairs would read that file as the new pairs' rig."""
    (tmp_path / "calibration.json").write_text("{}")
    with pytest.raises(InputError, match=r"--record: .*calibration\.json already exists; choose a new folder"):
        new_pairs_folder(str(tmp_path), "--record")
    assert (tmp_path / "calibration.json").read_text() == "{}"


def test_a_pair_whose_right_image_cannot_be_written_leaves_no_left_image(monkeypatch, tmp_path):
    written = []

    def full_after_one(path, data):
        if written:
            raise OSError(28, "No space left on device")
        written.append(path)
        path.write_bytes(data)

    monkeypatch.setattr(pairs_folder, "write_bytes_atomic", full_after_one)
    with pytest.raises(OSError, match=r"--record: cannot write '.*pair000007_right\.jpg': No space left on device"):
        save_pair(tmp_path, _pair(7), "--record")
    assert written and list(tmp_path.iterdir()) == []


def test_an_index_line_cut_short_is_cut_off_again_with_its_images(tmp_path):
    """A full disk in the middle of a line left half a line, and ``estimate --pairs`` stops at a line it cannot
    read; the pair's images went unlisted."""
    index = PairsIndex(tmp_path, "--out-dir")
    index.append(save_pair(tmp_path, _pair(0)))

    class HalfThenFull:
        def __init__(self, real):
            self.real, self.calls = real, 0

        def write(self, data):
            self.calls += 1
            if self.calls > 1:
                raise OSError(28, "No space left on device")
            return self.real.write(data[:len(data) // 2])

        def __getattr__(self, name):
            return getattr(self.real, name)

    index._file = HalfThenFull(index._file)
    record = save_pair(tmp_path, _pair(1))
    with pytest.raises(OSError, match=r"--out-dir: cannot write '.*index\.jsonl': No space left on device"):
        index.append(record)
    index.close()
    lines = (tmp_path / "index.jsonl").read_text().splitlines()
    assert [json.loads(line)["index"] for line in lines] == [0]
    assert sorted(p.name for p in tmp_path.glob("*.jpg")) == ["pair000000_left.jpg", "pair000000_right.jpg"]


def test_capture_on_a_full_disk_keeps_whole_pairs_and_names_the_option_and_file(monkeypatch, capsys, tmp_path):
    """Was: "[Errno 28] No space left on device (1 of 10 pairs saved …)", and a left image without its right."""
    calls = []
    real_write = pairs_folder.write_bytes_atomic

    def full_at_the_second_right_image(path, data):
        calls.append(path.name)
        if len(calls) == 4:
            raise OSError(28, "No space left on device")
        real_write(path, data)

    monkeypatch.setattr(pairs_folder, "write_bytes_atomic", full_at_the_second_right_image)
    out = tmp_path / "pairs"
    code = main(["capture", "--emulator", "--count", "3", "--out-dir", str(out)])
    err = capsys.readouterr().err
    # the option first, as the pairs_folder docstring promises: it read "error: [Errno 28] --out-dir: cannot write"
    assert code == 1 and "capture: error: --out-dir: cannot write" in err and "pair000001_right.jpg" in err
    assert "1 of 3 pairs saved" in err
    # the pair kept is ranged by the command printed, as after a whole capture
    argv = shlex.split(err.split("range the pairs kept with: ")[1].strip())
    assert main([*argv[1:], "--workers", "1"]) == 0 and len(capsys.readouterr().out.splitlines()) == 1
    assert sorted(p.name for p in out.iterdir()) == ["index.jsonl", "pair000000_left.jpg", "pair000000_right.jpg"]
    assert len((out / "index.jsonl").read_text().splitlines()) == 1


def test_a_second_capture_into_one_folder_leaves_the_first_ones_index_and_folder(monkeypatch, capsys, tmp_path):
    """Found by an audit of two processes at once: two captures started together into one new folder both found it
    free; the second, refused at the index ("[Errno 17] ... File exists"), removed the first's still empty index and
    the folder in its clean-up, and the first then failed too ("No such file or directory"), nothing saved. Now the
    refused one says why in one line and touches nothing of the other's."""
    import svs_torch.cli.capture as capture

    out = tmp_path / "pairs"
    real_open = capture.open_stereo_camera

    def another_capture_starts(*args, **kwargs):
        camera = real_open(*args, **kwargs)
        out.mkdir()  # the other capture: its folder and its index, no pair yet
        PairsIndex(out, "--out-dir").close()
        return camera

    monkeypatch.setattr(capture, "open_stereo_camera", another_capture_starts)
    assert main(["capture", "--emulator", "--count", "1", "--size", "160x120", "--out-dir", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"error: --out-dir: {out / 'index.jsonl'} was made by another run since this one started" in err
    assert [p.name for p in out.iterdir()] == ["index.jsonl"]


def test_the_printed_estimate_command_names_a_long_folder_whole(capsys, tmp_path):
    """Found by an audit of replays: a folder path past 120 characters was shortened in the printed command as in a
    message ('.../walk_record…ay_morning/...'), and that command then read no file. Now it ranges the pairs."""
    out = tmp_path / ("a_rather_long_folder_name_for_a_walk_recorded_on_a_tuesday_morning_" * 2) / "walk"
    assert main(["capture", "--emulator", "--count", "1", "--size", "160x120", "--out-dir", str(out)]) == 0
    command = capsys.readouterr().err.split("range them with: ")[1].strip()
    argv = shlex.split(command)
    assert argv[argv.index("--pairs") + 1] == str(out / "index.jsonl")
    assert main([*argv[1:], "--workers", "1"]) == 0
    assert json.loads(capsys.readouterr().out)["left"] == str(out / "pair000000_left.jpg")


def test_the_printed_estimate_command_takes_a_folder_named_with_a_dash(capsys, tmp_path, monkeypatch):
    """Found by an audit of replays: ``capture --out=-walk`` (or ``guide --record=-walk``) printed
    ``estimate --pairs -walk/index.jsonl``, which estimate refused as an option without its value."""
    monkeypatch.chdir(tmp_path)
    assert main(["capture", "--emulator", "--count", "1", "--size", "160x120", "--out=-walk"]) == 0
    argv = shlex.split(capsys.readouterr().err.split("range them with: ")[1].strip())
    assert "--pairs=-walk/index.jsonl" in argv
    assert main([*argv[1:], "--workers", "1"]) == 0
    assert json.loads(capsys.readouterr().out)["status"]


def _strict_json(text: str) -> dict:
    """``text`` as JSON that strict readers (jq, JavaScript's JSON.parse) take: NaN and Infinity refused."""
    def refuse(token: str):
        raise ValueError(f"not strict JSON: {token}")
    return json.loads(text, parse_constant=refuse)


def test_index_and_guide_json_lines_are_strict_json(tmp_path):
    """Found by an audit of JSON writers: capture's and guide's index.jsonl and guide's --json lines were written by
    json.dumps, which turns a NaN or inf into the tokens NaN / Infinity that strict readers refuse; every other JSON
    line of svs-depth (estimate, eval, bench, sweep: dumps_strict) writes null there."""
    import io

    from svs_torch.cli.guide_log import GuideLog

    record = {"index": 0, "nearest_m": float("nan"), "warning": {"confirmed_m": float("inf")}}
    with PairsIndex(tmp_path, "--record") as index:
        index.append(record)
    line = _strict_json((tmp_path / "index.jsonl").read_text())
    assert line["nearest_m"] is None and line["warning"]["confirmed_m"] is None
    stream = io.StringIO()
    GuideLog(stream, None).event("camera_back", lost_s=float("-inf"))
    assert _strict_json(stream.getvalue())["lost_s"] is None


def test_a_capture_folder_given_for_its_index_is_told_to_give_the_index(capsys, tmp_path):
    """Found by an audit of recordings: ``estimate DIR``, ``estimate --pairs DIR`` and ``eval DIR`` of a capture's
    (or guide --record's) folder said only "no stereo scene (MiddEval3, ...) in the folder DIR", naming no way to
    range its pairs; now each says it is a capture folder and names its index.jsonl. A folder without one is told
    as before."""
    folder, plain = tmp_path / "walk", tmp_path / "plain"
    folder.mkdir(), plain.mkdir()
    (folder / "index.jsonl").write_text('{"index": 0, "left": "pair000000_left.jpg", "right": "x.jpg"}\n')
    (tmp_path / "list.txt").write_text("walk\n")
    hint = f"(a capture folder: give its index, {folder / 'index.jsonl'})"
    for argv in (["estimate", str(folder)], ["estimate", "--pairs", str(folder)], ["eval", str(folder)],
                 ["estimate", "--pairs", str(tmp_path / "list.txt"), "--workers", "1"]):
        assert main(argv) == 2, argv
        assert f"no stereo scene in the folder {folder} {hint}" in capsys.readouterr().err.replace(
            " (MiddEval3, Middlebury 2001–2006, KITTI, OpenCV aloe)", ""), argv
    assert main(["estimate", "--pairs", str(plain)]) == 2
    assert capsys.readouterr().err.rstrip().endswith(f"in the folder {plain}")


def test_a_recording_of_the_emulator_says_so_and_its_scene(capsys, tmp_path):
    """Found by an audit of recordings: a folder of ``capture --emulator --emulator-noise 4`` frames (the help's "the
    frames a real board sends") could not be told, read later, from a real board's, nor its noise from another
    run's. Now each index line (capture's, guide --record's, and guide's --json lines) says the emulator's scene;
    null from boards."""
    def lines(folder):
        return [json.loads(line) for line in (folder / "index.jsonl").read_text().splitlines()]

    assert main(["capture", "--emulator", "--emulator-noise", "3.5", "--emulator-loose-rig", "--count", "2", "--size",
                 "160x120", "--out-dir", str(tmp_path / "noisy")]) == 0
    scene = {"noise_sigma": 3.5, "loose_rig": True, "floor_m": None, "heap_m": None}
    assert [line["emulator"] for line in lines(tmp_path / "noisy")] == [scene, scene]
    assert main(["guide", "--emulator", "--emulator-floor-m", "1.3", "--count", "1", "--no-speech", "--size",
                 "160x120", "--json", "--record", str(tmp_path / "walk")]) == 0
    scene = {"noise_sigma": 0.0, "loose_rig": False, "floor_m": 1.3, "heap_m": None}
    assert json.loads(capsys.readouterr().out.splitlines()[0])["emulator"] == scene
    assert [line["emulator"] for line in lines(tmp_path / "walk")] == [scene]
    from svs_torch.cli.link_options import emulator_record

    assert emulator_record(SimpleNamespace(emulator=False, emulator_noise=0.0)) is None  # boards at --left/--right


def test_capture_help_names_every_file_that_refuses_its_folder(capsys):
    """Found by an audit of recordings: capture --help said the folder 'must not hold an index.jsonl', and a folder
    with a calibration.json or pair images but no index was then refused (test_a_folder_holding_*); guide --help's
    --record named all three. Now capture's names them too."""
    with pytest.raises(SystemExit):
        main(["capture", "--help"])
    said = " ".join(capsys.readouterr().out.split())
    assert "it must not hold another run's index.jsonl, calibration.json or pair images" in said


def test_capture_help_says_what_its_index_marks_and_how_to_check_which_board_is_left(capsys):
    """Found by an audit of a rig set up with capture: its --help said only "an index.jsonl of timestamps", nothing
    of the pairs it marks and warns of, nor of boards answering in each other's roles (the URLs the other way round,
    which it now marks as cameras_swapped) or of the covered lens that tells which camera is which (hw/README)."""
    with pytest.raises(SystemExit):
        main(["capture", "--help"])
    said = " ".join(capsys.readouterr().out.split())
    for words in ("the index marks, and the end warns of, pairs guide would not range", "--left not the stereo "
                  "master (cameras_swapped", "cover the left lens, and its image must be the dark one"):
        assert words in said


def test_a_recording_whose_kept_calibration_is_gone_is_refused_not_ranged_in_the_svs_model(capsys, data_dir,
                                                                                             tmp_path):
    """Found by an audit of recordings: a capture --calibration folder copied without its calibration.json (the
    images and index.jsonl only) was ranged by estimate --pairs and eval in the SVS model's metres, unrectified (the
    baseline 0.1075 m for the rig's 0.0832), said only as "the SVS model assumed". Now capture's index lines name
    the kept copy (rig_calibration), and a folder without it is refused until it is back or --calibration names it;
    a capture without --calibration is ranged as before."""
    rig, out, plain = tmp_path / "rig.json", tmp_path / "pairs", tmp_path / "plain"
    assert main(["calibrate", str(data_dir / "opencv_samples" / "left*.jpg"), "--square-m", "0.025", "--out",
                 str(rig)]) == 0
    for folder, calibration in ((out, ["--calibration", str(rig)]), (plain, [])):
        assert main(["capture", "--emulator", "--count", "1", "--size", "160x120", "--out-dir", str(folder),
                     *calibration]) == 0
    assert json.loads((out / "index.jsonl").read_text())["rig_calibration"] == "calibration.json"
    assert json.loads((plain / "index.jsonl").read_text())["rig_calibration"] is None
    (out / "calibration.json").unlink()
    capsys.readouterr()
    for command in (["estimate", "--pairs"], ["eval"]):
        assert main([*command, str(out / "index.jsonl")]) == 2, command
        assert (f"--calibration: {out / 'index.jsonl'} lists pairs captured with a rig calibration, and no "
                "calibration.json is beside it" in capsys.readouterr().err), command
    assert main(["estimate", "--pairs", str(out / "index.jsonl"), "--calibration", str(rig), "--workers", "1"]) == 0
    assert main(["estimate", "--pairs", str(plain / "index.jsonl"), "--workers", "1"]) == 0
    # guide --record's lines say it as calibration_rectified
    walk = tmp_path / "walk"
    assert main(["guide", "--emulator", "--count", "1", "--no-speech", "--size", "160x120", "--calibration", str(rig),
                 "--record", str(walk)]) == 0
    (walk / "calibration.json").unlink()
    capsys.readouterr()
    assert main(["estimate", "--pairs", str(walk / "index.jsonl")]) == 2
    assert "lists pairs captured with a rig calibration, and no calibration.json" in capsys.readouterr().err
