"""Every experiment refuses a bad option value when its arguments are parsed: one line naming the option and exit
status 2, never a traceback, a run of minutes, or a record of a run with a value it could not have meant."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
from conftest import REPO_ROOT

# Each experiment is called as its command (run_script) in a fresh process whose parse_args stops the run once the
# arguments are parsed (the value taken shows as "parsed"), so a value taken by mistake never starts the experiment;
# unless the case asks to run on, for a refusal made after the parse, before any work. One fresh process for all
# (conftest.experiment_calls, with test_experiment_commands.py's calls): a process cost about 2.5 s of imports.
RUNNER = r"""
import argparse, contextlib, io, json, sys
sys.path.insert(0, sys.argv[1] + "/experiments")
original = argparse.ArgumentParser.parse_args

class Parsed(Exception):
    pass

def parse_args(self, args=None, namespace=None):
    result = original(self, args, namespace)
    raise Parsed()

from run_metadata import run_script
results = []
for script, argv, stop in json.loads(sys.argv[2]):
    argparse.ArgumentParser.parse_args = parse_args if stop else original
    module = __import__(script)
    err = io.StringIO()
    sys.argv = [script + ".py", *argv]
    try:
        with contextlib.redirect_stderr(err):
            run_script(lambda: module.main(argv) if "argv" in module.main.__code__.co_varnames else module.main())
        outcome = "ran"
    except Parsed:
        outcome = "parsed"
    except SystemExit as stop:
        outcome = stop.code
    except Exception as error:
        outcome = type(error).__name__
    results.append([outcome, err.getvalue().strip().splitlines()[-1:] or [""]])
print(json.dumps(results))
"""


def _assert_refused(cases: list[tuple[str, list[str]]], ended: list[tuple[object, str]]) -> None:
    """Each of ``cases`` ended (``ended``, in order) in exit status 2 with a line naming its first option."""
    for (script, argv), (code, line) in zip(cases, ended, strict=True):
        assert code == 2 and f"argument {argv[0]}" in line, (script, argv, code, line)


def case_table(data_dir: Path, folder: Path) -> dict[str, list[tuple[str, list[str], bool]]]:
    """Every test's experiment calls, ``(script, argv, stop once parsed)``, by test; files under ``folder``."""
    shipped = REPO_ROOT / "svs_torch" / "segmentation" / "weights"
    for name, weights in (("cut_learned.pt", "obstacle_net.pt"), ("cut_nearness.pt", "nearness_net.pt")):
        (folder / name).write_bytes((shipped / weights).read_bytes()[:1000])  # a weights file cut short
    (folder / "empty").mkdir()
    (folder / "both").mkdir()
    validate = ["--data", str(data_dir), "--limit", "2", "--folds", "9"]
    both = ["--json", str(folder / "both" / "t.md"), "--markdown", str(folder / "both" / "." / "t.md")]
    bad_set = ["--set", "segmentation.ground.min_camera_height_m=-1"]
    later = {"camera_frames_gate": ["--splits", "bogus"], "eval_segmentation": ["--methods", "bogus"],
             "guide_confirm": ["--splits", "bogus"], "guide_nearer": ["--splits", "bogus"],
             "paper_table1": ["--splits", "bogus"], "real_rig": ["--splits", "bogus"], "validate_nearness": validate,
             "thin_obstacles": ["--min-area", "1.5"], "walker_floor": bad_set, "walker_heaps": bad_set,
             "floor_distance": bad_set}
    weights, data = str(folder / "net.pt"), ["--data", str(data_dir), "--limit", "1"]
    not_data = [folder / "empty", data_dir / "kitti"]  # (an empty folder; one data set's own)
    stop = {"data_folders": [(script, ["--data", str(path)]) for script in DATA_SCRIPTS for path in not_data],
            "counts": COUNTS, "lists": LISTS + LISTS_PARSED, "kernel_parity": KERNELS + KERNELS_PARSED,
            "conditions": CONDITIONS + CONDITIONS_PARSED, "sizes": SIZES + SIZES_PARSED,
            "train_segmentation": [("train_segmentation", ["--init", "nearness"]),
                                   ("train_segmentation", ["--init", f"learned:{folder / 'cut_learned.pt'}"]),
                                   ("train_segmentation", ["--size", "320"]),
                                   ("train_segmentation", ["--size", "0x240"]),
                                   ("train_segmentation", ["--init", "learned", "--size", "160x120"])]}
    run_on = {  # refused after the parse, before any work: run on until then
        "after_parse": [("eval_segmentation", ["--methods", "bogus"]), ("real_rig", ["--splits", "bogus"]),
                        ("camera_frames_gate", ["--splits", "bogus"]),
                        ("select_nearness_setting", ["--variants", "a=1"]),
                        ("guide_second_passes", ["--data", str(folder / "empty")]), ("validate_nearness", validate)],
        "json_and_markdown": [(script, both + argv) for script, argv in later.items()],
        "report_over_weights": [
            ("eval_segmentation", ["--weights", weights, "--json", weights, "--methods", "bogus"]),
            ("eval_segmentation", ["--nearness", f"n={weights}", "--markdown", weights, "--methods", "bogus"])],
        "weights_read_first": [
            ("eval_segmentation", [*data, "--weights", str(folder / "cut_learned.pt"), "--methods", "learned"]),
            ("eval_segmentation", [*data, "--nearness", f"n={folder / 'cut_nearness.pt'}", "--methods", "default,n"])]}
    return {**{name: [(*case, True) for case in cases] for name, cases in stop.items()},
            **{name: [(*case, False) for case in cases] for name, cases in run_on.items()}}


@pytest.fixture(scope="module")
def ended(data_dir, experiment_calls) -> dict[str, list[tuple[object, str]]]:
    """How each test's experiment calls ended (:func:`case_table`), all run in one process (conftest.experiment_calls):
    one process a test cost about 2.5 s each of imports; ``"folder"``: where their files are."""
    folder, table, results = experiment_calls["options"]
    outcomes = iter([(code, line[0]) for code, line in results])
    return {"folder": folder, **{name: [next(outcomes) for _ in cases] for name, cases in table.items()}}


COUNTS = [
    ("bench_capture", ["--runs", "0"]), ("bench_capture", ["--pairs", "-1"]), ("bench_capture", ["--threads", "0"]),
    ("bench_dense", ["--batch", "0"]), ("bench_dense", ["--threads", "0"]), ("bench_dense", ["--repeats", "0"]),
    ("bench_differentiable", ["--batch", "-2"]),
    ("bench_features", ["--max-keypoints", "0"]), ("bench_features", ["--repeats", "0"]),
    ("bench_features", ["--threads", "0"]),
    ("bench_pipeline", ["--threads", "-1"]), ("bench_pipeline", ["--repeats", "0"]),
    ("bench_ransac", ["--pairs", "0"]), ("bench_ransac", ["--matches", "0"]), ("bench_ransac", ["--noise-px", "nan"]),
    ("bench_ransac", ["--matches", "6"]), ("paper_table1", ["--threads", "0"]),  # (an audit: an OpenCV assertion, a
    # RuntimeError of set_num_threads, each after the run started)
    ("bench_ransac", ["--seed", "-1"]), ("bench_ransac", ["--threads", "0"]), ("bench_ransac", ["--repeats", "0"]),
    ("bench_segmentation", ["--threads", "0"]), ("bench_segmentation", ["--repeats", "0"]),
    ("calibrated_rectify", ["--scenes", "0"]), ("calibrated_rectify", ["--turn-deg", "nan", "0", "0"]),
    ("differentiable_agreement", ["--threads", "0"]), ("eval_segmentation", ["--threads", "0"]),
    ("fundamental_vs_opencv", ["--max-keypoints", "0"]), ("fundamental_vs_opencv", ["--threads", "0"]),
    ("fundamental_vs_opencv", ["--seed", "-1"]), ("fundamental_vs_opencv", ["--chessboard-seeds", "0"]),
    ("guide_confirm", ["--walks", "0"]), ("guide_confirm", ["--frames", "-1"]), ("guide_confirm", ["--seed", "-1"]),
    ("guide_nearer", ["--streams", "0"]), ("guide_nearer", ["--walks", "-1"]), ("guide_nearer", ["--frames", "0"]),
    ("guide_nearer", ["--seed", "-5"]), ("guide_second_passes", ["--repeats", "0"]),
    ("kernel_parity", ["--workers", "0"]),
    ("surf_vs_sift", ["--max-keypoints", "0"]), ("surf_vs_sift", ["--threads", "0"]),
    ("surf_vs_sift", ["--ratios", "nan"]),
    ("validate_nearness", ["--folds", "1"]), ("validate_nearness", ["--val-crops", "0"]),
    ("validate_nearness", ["--threads", "0"]),
    ("verify_views", ["--threads", "0"]), ("verify_views", ["--synthetic", "-1"]),
]


def test_counts_threads_seeds_and_numbers_are_refused_when_parsed(ended):
    """Found by an audit: ``--threads 0`` was a RuntimeError traceback, ``--repeats 0`` a StatisticsError after the
    data was loaded, ``bench_ransac.py --pairs 0`` a traceback and ``--seed -1`` a run recording seed -1,
    ``calibrated_rectify.py --scenes 0`` a refusal after the chessboard calibration had run."""
    _assert_refused(COUNTS, ended["counts"])


LISTS = [
    ("guide_confirm", ["--digits", "4,x"]), ("guide_confirm", ["--digits", "9"]),
    ("guide_confirm", ["--confirm", "0,2"]), ("guide_nearer", ["--digits", "9"]),
    ("guide_nearer", ["--margins", "nan"]), ("guide_nearer", ["--margins", "0.1,-1"]),
    ("coarse_retry", ["--shares", "nan"]), ("coarse_retry", ["--contrasts", "0"]),
    ("camera_frames_gate", ["--contrasts", "x"]), ("select_nearness_setting", ["--contrasts", "nan"]),
    ("validate_nearness", ["--checkpoints", "x,-3"]),
]


LISTS_PARSED = [("guide_nearer", ["--margins", "inf,0"]), ("coarse_retry", ["--shares", "1"])]


def test_comma_separated_values_are_refused_when_parsed(ended):
    """Found by an audit: ``guide_confirm.py --digits 9`` was a KeyError traceback after the first walks, ``--digits
    4,x`` a ValueError one; ``guide_nearer.py --margins nan`` and ``coarse_retry.py --shares nan`` ran on;
    ``coarse_retry.py --contrasts 0`` was a StatisticsError after a run, ``--checkpoints x`` a ValueError."""
    _assert_refused(LISTS, ended["lists"][:len(LISTS)])
    assert ended["lists"][len(LISTS):] == [("parsed", "")] * len(LISTS_PARSED)


KERNELS = [("kernel_parity", ["--torch", "lk_refined"]), ("kernel_parity", ["--torch", "lk_refine,bogus"]),
           ("kernel_parity", ["--torch", "check_border"])]
KERNELS_PARSED = [("kernel_parity", ["--torch", "lk_refine,usurf_describe"]), ("kernel_parity", [])]


def test_kernel_parity_refuses_a_kernel_name_no_stage_has_when_parsed(ended):
    """Found by an audit: ``kernel_parity.py --torch NAME`` turned off only the names it found in the stages' kernels
    modules and passed over the others, so a typo or a renamed kernel (the docstring's own ``--torch
    lk_refine,usurf_describe``) ran a parity of every kernel reported as "kernels (but NAME)"."""
    _assert_refused(KERNELS, ended["kernel_parity"][:len(KERNELS)])
    assert ended["kernel_parity"][len(KERNELS):] == [("parsed", "")] * len(KERNELS_PARSED)


CONDITIONS = [("real_rig", ["--conditions", "jpg"]),
              ("select_nearness_setting", ["--conditions", "clean,jpg", "--variants", "min_near_share=0"])]
CONDITIONS_PARSED = [("real_rig", ["--conditions", "jpeg q4,roll"]),
                     ("select_nearness_setting", ["--conditions", "clean,jpeg", "--variants", "min_near_share=0"])]


def test_a_condition_no_prefix_names_is_refused_when_parsed(ended):
    """Found by an audit: ``select_nearness_setting.py --conditions jpg`` scored its first variant (35 s) before
    real_rig.py, which it calls, refused the prefix under its own usage; real_rig.py refused it after its parse."""
    _assert_refused(CONDITIONS, ended["conditions"][:len(CONDITIONS)])
    assert ended["conditions"][len(CONDITIONS):] == [("parsed", "")] * len(CONDITIONS_PARSED)


#: The experiments that read the shared data folder (``--data``).
DATA_SCRIPTS = sorted(path.stem for path in (REPO_ROOT / "experiments").glob("*.py") if path.stem != "run_metadata"
                      and ("add_data_option(" in path.read_text() or "add_common_options(" in path.read_text()))


def test_every_data_option_refuses_a_folder_that_is_not_the_shared_data(ended):
    """Found by an audit: an empty folder, or shared/data/kitti, ran to empty or partial tables, written, exit 0
    (paper_table1, real_rig, eval_segmentation, ...), or to a traceback (the benchmarks: torch.cat of no tensors)."""
    assert len(DATA_SCRIPTS) > 20
    assert not [path.name for path in (REPO_ROOT / "experiments").glob("*.py")
                if 'add_argument("--data"' in path.read_text() and path.stem != "run_metadata"]  # (all checked)
    _assert_refused([(script, ["--data"]) for script in DATA_SCRIPTS for _ in range(2)], ended["data_folders"])
    assert all("expected the shared data folder" in line for _, line in ended["data_folders"])


def test_option_values_refused_after_the_parse_are_exit_status_2(ended):
    """Found by an audit: these refusals, one line and before any work, were exit status 1 (a SystemExit with the
    message) where every other bad option is 2; a caller telling a usage error from a failed run could not."""
    scripts = ["eval_segmentation", "real_rig", "camera_frames_gate", "select_nearness_setting", "guide_second_passes",
               "validate_nearness"]
    options = ["--methods", "--splits", "--splits", "--variants", "argument --data", "--folds"]  # (--data: when parsed)
    for script, option, (code, line) in zip(scripts, options, ended["after_parse"], strict=True):
        assert code == 2 and line.startswith(f"{script}.py: error: {option}"), (script, code, line)


def test_json_and_markdown_at_one_file_are_refused_before_the_run(ended):
    """Found by an audit: ``paper_table1.py --json t.md --markdown t.md`` (and every experiment with both) ran in
    full, then wrote the table over the report, exit 0. (Each case also has a value refused later, before any work,
    so that the code before the fix ends at once rather than running.)"""
    assert len(ended["json_and_markdown"]) == 11
    for code, line in ended["json_and_markdown"]:
        assert code == 2 and "argument --markdown: the file of --json" in line, (code, line)
    assert not list((ended["folder"] / "both").iterdir())


def test_fixed_list_check_refuses_a_record_it_cannot_write_or_read_before_the_run(tmp_path, monkeypatch, capsys):
    """Found by an audit: ``fixed_list_check.py record FOLDER`` (or under a missing folder) and ``compare`` with a
    missing record ran every pair of the list first, then ended in a traceback."""
    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    import fixed_list_check

    def ran(workdir):
        raise AssertionError("the list was run")

    monkeypatch.setattr(fixed_list_check, "run_all", ran)
    (tmp_path / "broken.json").write_text("{")
    for argv in (["record", str(tmp_path)], ["record", str(tmp_path / "nodir" / "r.json")],
                 ["compare", str(tmp_path / "none.json")], ["compare", str(tmp_path / "broken.json")]):
        with pytest.raises(SystemExit) as stop:
            fixed_list_check.main([*argv, "--workdir", str(tmp_path / "work")])
        assert stop.value.code == 2 and "error: argument json: " in capsys.readouterr().err, argv


def test_fixed_list_check_refuses_a_workdir_it_cannot_write_before_the_run(tmp_path, monkeypatch, capsys):
    """Found by an audit: ``fixed_list_check.py record R.json --workdir /proc`` (or a file) ended in a traceback
    from mkdir; now one line naming --workdir and the path that failed, exit status 2, before any pair runs."""
    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    import fixed_list_check

    def ran(workdir):
        raise AssertionError("the list was run")

    monkeypatch.setattr(fixed_list_check, "run_all", ran)
    (tmp_path / "a_file").write_text("")
    workdirs = [tmp_path / "a_file", *([Path("/proc")] if Path("/proc/self").is_dir() else [])]
    for workdir in workdirs:
        with pytest.raises(SystemExit) as stop:
            fixed_list_check.main(["record", str(tmp_path / "r.json"), "--workdir", str(workdir)])
        err = capsys.readouterr().err
        assert stop.value.code == 2 and "error: argument --workdir: cannot write" in err, err
        assert f"{workdir}/synthetic" in err, err


SIZES = [("paper_table1", ["--sizes", "0"]), ("paper_table1", ["--sizes", "320,99999"]),
         ("bench_capture", ["--sizes", "0x0"]), ("real_rig", ["--sizes", "320x240,320x0"]),
         ("kernel_parity", ["--size", "0x0"]), ("kernel_parity", ["--size", "native"])]
SIZES_PARSED = [("paper_table1", ["--sizes", "320,native"]), ("kernel_parity", ["--size", "640x480"])]


def test_sizes_without_a_side_of_0_or_beyond_the_largest_are_taken(ended):
    """Found by an audit: ``--sizes 0`` and ``0x0`` were taken: ``bench_capture.py`` ended in a RuntimeError
    traceback, ``paper_table1.py`` in a refusal naming a library field once the run began, ``kernel_parity.py
    --size 0x0`` in "58 of 58 pairs were not read" after its runs, exit 1."""
    _assert_refused(SIZES, ended["sizes"][:len(SIZES)])
    assert ended["sizes"][len(SIZES):] == [("parsed", "")] * len(SIZES_PARSED)


def test_eval_segmentation_refuses_a_report_over_the_weights_it_evaluates(ended):
    """Found by an audit: ``eval_segmentation.py --weights W --json W`` (or ``--nearness NAME=W --markdown W``)
    evaluated W and then wrote the report over it, exit 0. (``--methods bogus``: refused later, before any work.)"""
    assert [(code, line.split(" reads")[0]) for code, line in ended["report_over_weights"]] == [
        (2, "eval_segmentation.py: error: argument --json: the file --weights"),
        (2, "eval_segmentation.py: error: argument --markdown: the file --nearness")]


def test_train_segmentation_checks_its_starting_weights_and_size_when_parsed(ended):
    """Found by an audit: ``train_segmentation.py --through-pipeline --init nearness`` failed once the pairs were read
    with "network: expected an ObstacleNet for segmenter 'learned'", a truncated ``--init learned:FILE`` with a line
    naming "segmenter" and not --init, and ``--size 320`` was a ValueError traceback."""
    *refused, parsed = ended["train_segmentation"]
    for option, (code, line) in zip(["--init", "--init", "--size", "--size"], refused, strict=True):
        assert code == 2 and f"argument {option}" in line, (option, code, line)
    cut = ended["folder"] / "cut_learned.pt"
    assert "nearness weights are trained by train_nearness.py" in refused[0][1] and f"'{cut}' is not a weights" in \
        refused[1][1]
    assert parsed == ("parsed", "")


def test_eval_segmentation_reads_its_weights_files_before_any_scene(ended):
    """Found by an audit: a truncated ``--weights`` or ``--nearness NAME=FILE`` was refused only after the first
    scene's work, in a line naming "segmenter", not the option."""
    folder = ended["folder"]
    assert [(code, line.split(" is not")[0]) for code, line in ended["weights_read_first"]] == [
        (2, f"eval_segmentation.py: error: --weights: '{folder / 'cut_learned.pt'}'"),
        (2, f"eval_segmentation.py: error: --nearness: '{folder / 'cut_nearness.pt'}'")]


def test_the_bench_experiments_write_their_json_whole():
    """bench_dense/features/pipeline/ransac/segmentation wrote --json with Path.write_text: a full disk or a
    Ctrl-C while writing left a truncated report where a whole one (or none) was expected; an earlier report at
    that name was lost first. They now write it whole or not at all (write_bytes_atomic), as bench.py does."""
    for path in sorted((REPO_ROOT / "experiments").glob("bench*.py")):
        assert ".write_text(json.dumps" not in path.read_text(), path.name


def test_every_experiment_writes_its_reports_whole(tmp_path):
    """As the bench experiments' --json (the test above): paper_table1, eval_segmentation, validate_nearness and the
    others wrote their --json and --markdown with Path.write_text, which empties an earlier report first and leaves
    a cut one on a full disk or a Ctrl-C; and in the locale's encoding, where a report holds "×" and "±"."""
    import re

    for path in sorted((REPO_ROOT / "experiments").glob("*.py")):
        assert not re.search(r"(Path\(args\.\w+\)|args\.json)\.write_text\(", path.read_text()), path.name
    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    from run_metadata import write_text_whole

    report = tmp_path / "table.md"
    write_text_whole(report, "320×240 ± 0.5 %\n")
    assert report.read_bytes() == "320×240 ± 0.5 %\n".encode("utf-8") and [p.name for p in tmp_path.iterdir()] == [
        "table.md"]


def test_bench_capture_takes_only_the_sizes_a_board_sends():
    """Found by an audit: ``bench_capture.py --sizes native`` (its help offered "WxH sizes or native") and ``--sizes
    100x100`` were taken, then ended in an InputError traceback once the emulator had started and frames were read
    (or, preparing its frames, in "emulator did not start"). They are now refused when parsed, naming the sizes."""
    import subprocess

    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1"}
    for sizes in ("native", "320x240,100x100"):
        run = subprocess.run([sys.executable, str(REPO_ROOT / "experiments" / "bench_capture.py"), "--sizes", sizes,
                              "--runs", "1", "--pairs", "1", "--frames", "simple"], env=env, capture_output=True,
                             text=True, timeout=120)
        assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr[-2000:]
        assert run.stderr.strip().splitlines()[-1] == (
            f"bench_capture.py: error: argument --sizes: expected comma-separated sizes a board sends (160x120, "
            f"320x240, 640x480, 1280x1024), got {sizes!r}")


def test_the_bench_experiments_refuse_a_data_folder_without_middlebury_pairs(data_dir, tmp_path):
    """Found by an audit: bench_segmentation/features/pipeline/dense/differentiable.py read Middlebury pairs only, but
    took any shared data folder: one of KITTI alone ended in "ValueError: torch.cat(): expected a non-empty list of
    Tensors" (bench_dense.py after rendering its scenes), and a missing default folder in a line naming data_dir.
    Both are now a line naming --data, exit 2."""
    import subprocess

    (tmp_path / "kitti").symlink_to(data_dir / "kitti", target_is_directory=True)
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1", "SVS_TORCH_DATA": str(tmp_path / "no")}
    for argv in (["--data", str(tmp_path)], []):
        run = subprocess.run([sys.executable, str(REPO_ROOT / "experiments" / "bench_dense.py"), "--repeats", "1",
                              *argv], env=env, capture_output=True, text=True, timeout=120)
        assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr[-2000:]
        expected = "with Middlebury pairs (middlebury_*/)" if argv else "no such folder"
        assert run.stderr.startswith("bench_dense.py: error: --data: expected the shared data folder") and \
            expected in run.stderr, run.stderr
