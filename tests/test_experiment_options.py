"""Every experiment refuses a bad option value when its arguments are parsed: one line naming the option and exit
status 2, never a traceback, a run of minutes, or a record of a run with a value it could not have meant."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from conftest import REPO_ROOT

# Each experiment is called as its command (run_script) in a fresh process whose parse_args stops the run once the
# arguments are parsed (the value taken shows as "parsed"), so a value taken by mistake never starts the experiment;
# unless the case asks to run on, for a refusal made after the parse, before any work.
_RUNNER = r"""
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


def refusals(cases: list[tuple[str, list[str]]], stop: bool = True) -> list[tuple[object, str]]:
    """How each experiment ``(script, argv)`` ended: its exit status (or "parsed") and its last line on stderr;
    ``stop``: once its arguments are parsed."""
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", _RUNNER, str(REPO_ROOT), json.dumps([[*case, stop] for case in cases])], env=env,
                          capture_output=True, text=True, timeout=300, check=True)
    return [(code, line[0]) for code, line in json.loads(done.stdout)]


def assert_refused(cases: list[tuple[str, list[str]]]) -> None:
    for (script, argv), (code, line) in zip(cases, refusals(cases)):
        assert code == 2 and f"argument {argv[0]}" in line, (script, argv, code, line)


def _assert_refused_then_parsed(refused: list[tuple[str, list[str]]], parsed: list[tuple[str, list[str]]]) -> None:
    """``refused`` each refused as :func:`assert_refused` says and ``parsed`` each parsed, in one process (each
    process costs about 2 s of imports)."""
    ended = refusals(refused + parsed)
    for (script, argv), (code, line) in zip(refused, ended):
        assert code == 2 and f"argument {argv[0]}" in line, (script, argv, code, line)
    assert ended[len(refused):] == [("parsed", "")] * len(parsed)


COUNTS = [
    ("bench_capture", ["--runs", "0"]), ("bench_capture", ["--pairs", "-1"]), ("bench_capture", ["--threads", "0"]),
    ("bench_dense", ["--batch", "0"]), ("bench_dense", ["--threads", "0"]), ("bench_dense", ["--repeats", "0"]),
    ("bench_differentiable", ["--batch", "-2"]),
    ("bench_features", ["--max-keypoints", "0"]), ("bench_features", ["--repeats", "0"]),
    ("bench_features", ["--threads", "0"]),
    ("bench_pipeline", ["--threads", "-1"]), ("bench_pipeline", ["--repeats", "0"]),
    ("bench_ransac", ["--pairs", "0"]), ("bench_ransac", ["--matches", "0"]), ("bench_ransac", ["--noise-px", "nan"]),
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


def test_counts_threads_seeds_and_numbers_are_refused_when_parsed():
    """Found by an audit: ``--threads 0`` was a RuntimeError traceback, ``--repeats 0`` a StatisticsError after the
    data was loaded, ``bench_ransac.py --pairs 0`` a traceback and ``--seed -1`` a run recording seed -1,
    ``calibrated_rectify.py --scenes 0`` a refusal after the chessboard calibration had run."""
    assert_refused(COUNTS)


LISTS = [
    ("guide_confirm", ["--digits", "4,x"]), ("guide_confirm", ["--digits", "9"]),
    ("guide_confirm", ["--confirm", "0,2"]), ("guide_nearer", ["--digits", "9"]),
    ("guide_nearer", ["--margins", "nan"]), ("guide_nearer", ["--margins", "0.1,-1"]),
    ("coarse_retry", ["--shares", "nan"]), ("coarse_retry", ["--contrasts", "0"]),
    ("camera_frames_gate", ["--contrasts", "x"]), ("select_nearness_setting", ["--contrasts", "nan"]),
    ("validate_nearness", ["--checkpoints", "x,-3"]),
]


def test_comma_separated_values_are_refused_when_parsed():
    """Found by an audit: ``guide_confirm.py --digits 9`` was a KeyError traceback after the first walks, ``--digits
    4,x`` a ValueError one; ``guide_nearer.py --margins nan`` and ``coarse_retry.py --shares nan`` ran on;
    ``coarse_retry.py --contrasts 0`` was a StatisticsError after a run, ``--checkpoints x`` a ValueError."""
    _assert_refused_then_parsed(LISTS, [("guide_nearer", ["--margins", "inf,0"]), ("coarse_retry", ["--shares", "1"])])


def test_kernel_parity_refuses_a_kernel_name_no_stage_has_when_parsed():
    """Found by an audit: ``kernel_parity.py --torch NAME`` turned off only the names it found in the stages' kernels
    modules and passed over the others, so a typo or a renamed kernel (the docstring's own ``--torch
    lk_refine,usurf_describe``) ran a parity of every kernel reported as "kernels (but NAME)"."""
    refused = [("kernel_parity", ["--torch", "lk_refined"]), ("kernel_parity", ["--torch", "lk_refine,bogus"]),
               ("kernel_parity", ["--torch", "check_border"])]
    _assert_refused_then_parsed(refused, [("kernel_parity", ["--torch", "lk_refine,usurf_describe"]),
                                          ("kernel_parity", [])])


def test_a_condition_no_prefix_names_is_refused_when_parsed():
    """Found by an audit: ``select_nearness_setting.py --conditions jpg`` scored its first variant (35 s) before
    real_rig.py, which it calls, refused the prefix under its own usage; real_rig.py refused it after its parse."""
    _assert_refused_then_parsed(
        [("real_rig", ["--conditions", "jpg"]),
         ("select_nearness_setting", ["--conditions", "clean,jpg", "--variants", "min_near_share=0"])],
        [("real_rig", ["--conditions", "jpeg q4,roll"]),
         ("select_nearness_setting", ["--conditions", "clean,jpeg", "--variants", "min_near_share=0"])])


def test_option_values_refused_after_the_parse_are_exit_status_2(data_dir, tmp_path):
    """Found by an audit: these refusals, one line and before any work, were exit status 1 (a SystemExit with the
    message) where every other bad option is 2; a caller telling a usage error from a failed run could not."""
    cases = [("eval_segmentation", ["--methods", "bogus"]), ("real_rig", ["--splits", "bogus"]),
             ("camera_frames_gate", ["--splits", "bogus"]), ("select_nearness_setting", ["--variants", "a=1"]),
             ("guide_second_passes", ["--data", str(tmp_path)]),
             ("validate_nearness", ["--data", str(data_dir), "--limit", "2", "--folds", "9"])]
    for (script, argv), (code, line) in zip(cases, refusals(cases, stop=False)):
        option = "--data" if script == "guide_second_passes" else argv[-2]
        assert code == 2 and line.startswith(f"{script}.py: error: {option}"), (script, argv, code, line)


def test_json_and_markdown_at_one_file_are_refused_before_the_run(data_dir, tmp_path):
    """Found by an audit: ``paper_table1.py --json t.md --markdown t.md`` (and every experiment with both) ran in
    full, then wrote the table over the report, exit 0. (Each case also has a value refused later, before any work,
    so that the code before the fix ends at once rather than running.)"""
    both = ["--json", str(tmp_path / "t.md"), "--markdown", str(tmp_path / "." / "t.md")]
    bad_set = ["--set", "segmentation.ground.min_camera_height_m=-1"]
    later = {"camera_frames_gate": ["--splits", "bogus"], "eval_segmentation": ["--methods", "bogus"],
             "guide_confirm": ["--splits", "bogus"], "guide_nearer": ["--splits", "bogus"],
             "paper_table1": ["--splits", "bogus"], "real_rig": ["--splits", "bogus"],
             "validate_nearness": ["--data", str(data_dir), "--limit", "2", "--folds", "9"],
             "thin_obstacles": ["--min-area", "1.5"], "walker_floor": bad_set, "walker_heaps": bad_set,
             "floor_distance": bad_set}
    cases = [(script, both + argv) for script, argv in later.items()]
    for (script, _), (code, line) in zip(cases, refusals(cases, stop=False)):
        assert code == 2 and "argument --markdown: the file of --json" in line, (script, code, line)
    assert not list(tmp_path.iterdir())


def test_fixed_list_check_refuses_a_record_it_cannot_write_or_read_before_the_run(tmp_path, monkeypatch, capsys):
    """Found by an audit: ``fixed_list_check.py record FOLDER`` (or under a missing folder) and ``compare`` with a
    missing record ran every pair of the list first, then ended in a traceback."""
    import pytest

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


def test_sizes_without_a_side_of_0_or_beyond_the_largest_are_taken():
    """Found by an audit: ``--sizes 0`` and ``0x0`` were taken: ``bench_capture.py`` ended in a RuntimeError
    traceback, ``paper_table1.py`` in a refusal naming a library field once the run began, ``kernel_parity.py
    --size 0x0`` in "58 of 58 pairs were not read" after its runs, exit 1."""
    cases = [("paper_table1", ["--sizes", "0"]), ("paper_table1", ["--sizes", "320,99999"]),
             ("bench_capture", ["--sizes", "0x0"]), ("real_rig", ["--sizes", "320x240,320x0"]),
             ("kernel_parity", ["--size", "0x0"]), ("kernel_parity", ["--size", "native"])]
    _assert_refused_then_parsed(cases, [("paper_table1", ["--sizes", "320,native"]),
                                        ("kernel_parity", ["--size", "640x480"])])


def test_eval_segmentation_refuses_a_report_over_the_weights_it_evaluates(tmp_path):
    """Found by an audit: ``eval_segmentation.py --weights W --json W`` (or ``--nearness NAME=W --markdown W``)
    evaluated W and then wrote the report over it, exit 0. (``--methods bogus``: refused later, before any work.)"""
    weights = str(tmp_path / "net.pt")
    cases = [("eval_segmentation", ["--weights", weights, "--json", weights, "--methods", "bogus"]),
             ("eval_segmentation", ["--nearness", f"n={weights}", "--markdown", weights, "--methods", "bogus"])]
    assert [(code, line.split(" reads")[0]) for code, line in refusals(cases, stop=False)] == [
        (2, "eval_segmentation.py: error: argument --json: the file --weights"),
        (2, "eval_segmentation.py: error: argument --markdown: the file --nearness")]


def test_train_segmentation_checks_its_starting_weights_and_size_when_parsed(tmp_path):
    """Found by an audit: ``train_segmentation.py --through-pipeline --init nearness`` failed once the pairs were read
    with "network: expected an ObstacleNet for segmenter 'learned'", a truncated ``--init learned:FILE`` with a line
    naming "segmenter" and not --init, and ``--size 320`` was a ValueError traceback."""
    cut = tmp_path / "cut.pt"
    cut.write_bytes((REPO_ROOT / "svs_torch" / "segmentation" / "weights" / "obstacle_net.pt").read_bytes()[:1000])
    cases = [("train_segmentation", ["--init", "nearness"]), ("train_segmentation", ["--init", f"learned:{cut}"]),
             ("train_segmentation", ["--size", "320"]), ("train_segmentation", ["--size", "0x240"])]
    ended = refusals([*cases, ("train_segmentation", ["--init", "learned", "--size", "160x120"])])
    for (script, argv), (code, line) in zip(cases, ended):
        assert code == 2 and f"argument {argv[0]}" in line, (script, argv, code, line)
    lines = [line for _, line in ended[:2]]
    assert "nearness weights are trained by train_nearness.py" in lines[0] and f"'{cut}' is not a weights" in lines[1]
    assert ended[-1] == ("parsed", "")


def test_eval_segmentation_reads_its_weights_files_before_any_scene(data_dir, tmp_path):
    """Found by an audit: a truncated ``--weights`` or ``--nearness NAME=FILE`` was refused only after the first
    scene's work, in a line naming "segmenter", not the option."""
    cut = tmp_path / "cut.pt"
    cut.write_bytes((REPO_ROOT / "svs_torch" / "segmentation" / "weights" / "nearness_net.pt").read_bytes()[:1000])
    data = ["--data", str(data_dir), "--limit", "1"]
    cases = [("eval_segmentation", [*data, "--weights", str(cut), "--methods", "learned"]),
             ("eval_segmentation", [*data, "--nearness", f"n={cut}", "--methods", "default,n"])]
    assert [(code, line.split(" is not")[0]) for code, line in refusals(cases, stop=False)] == [
        (2, f"eval_segmentation.py: error: --weights: '{cut}'"), (2, f"eval_segmentation.py: error: --nearness: '{cut}'")]


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
