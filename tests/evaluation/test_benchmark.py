"""The benchmark's pieces: the OpenCV rival loop does the stated work, the whole-process runner reports every
rival on the same pairs, and the tables render. Speed itself is never asserted."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from svs_torch.evaluation.benchmark import RIVAL_COMMAND, _work_summary, format_tables, whole_process, write_inputs


def test_rival_loop_and_whole_process_on_the_same_pairs(tmp_path):
    sets = write_inputs(tmp_path, 3, None, seed=2)
    assert list(sets) == ["synthetic 320x240"] and len(sets["synthetic 320x240"]) == 3
    listing = tmp_path / "list.txt"
    listing.write_text("".join(f"{l} {r}\n" for l, r in sets["synthetic 320x240"]) + "missing.png also.png\n")
    out = subprocess.run([*RIVAL_COMMAND, "sift", str(listing)], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    rows = [json.loads(line) for line in out]
    assert [r["status"] for r in rows] == ["OK", "OK", "OK", "BAD_INPUT"]
    # Synthetic obstacles lie 1-2 m away: StereoBM medians over the kept regions must land there.
    assert all(0.7 < r["r_min_m"] <= r["r_max_m"] < 3.0 for r in rows[:3])
    assert all(r["inliers"] <= r["matches"] and min(r["keypoints"]) > 0 for r in rows[:3])
    # The pooled loop (the strongest a user writes for throughput) does the same work, in list order.
    command = [*RIVAL_COMMAND, "sift", str(listing), "--workers", "2"]
    pooled = subprocess.run(command, capture_output=True, text=True, check=True).stdout.splitlines()
    assert [json.loads(line) for line in pooled] == rows
    report_rows = whole_process({"synthetic 320x240": sets["synthetic 320x240"][:2]}, tmp_path, 1, 1)
    assert [r["rival"] for r in report_rows] == ["svs-depth estimate --pairs", "svs-depth estimate --pairs --segmenter "
                                                 "otsu", "OpenCV SIFT loop", "OpenCV ORB loop",
                                                 "OpenCV SIFT pool (1 proc)", "OpenCV ORB pool (1 proc)"]
    assert all(r["work_pairs"] == 2 and r["pairs_per_s"] > 0 for r in report_rows)
    for svs in report_rows[:2]:  # both segmenters range the synthetic obstacles
        assert svs["work_ok"] == 2 and 0.7 < svs["work_median_r_min_m"] < 3.0
    assert report_rows[0]["svs_speedup"] == 1.0


def test_rival_script_imports_no_torch():
    """The rival is a user's own OpenCV loop: its process (and so every worker its pool spawns, which imports the
    same script) never pays for torch's import, which the benchmark's svs_torch command does pay."""
    probe = ("import runpy, sys; sys.argv = [sys.argv[1], '--help']\n"
             "try:\n    runpy.run_path(sys.argv[0], run_name='__main__')\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in ('torch', 'svs_torch', 'kornia') if m in sys.modules))")
    out = subprocess.run([RIVAL_COMMAND[0], "-c", probe, RIVAL_COMMAND[1]], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"


def test_work_summary_and_tables():
    rows = [{"status": "OK", "num_keypoints": [10, 20], "num_matches": 8, "num_inliers": 6, "r_min_m": 1.5},
            {"status": "NO_OBJECTS", "num_keypoints": [0, 0], "num_matches": 0, "num_inliers": 0, "r_min_m": None}]
    summary = _work_summary(rows)
    assert summary == {"pairs": 2, "ok": 1, "ranged": 1, "keypoints": 7.5, "matches": 4.0, "inliers": 3.0,
                       "median_r_min_m": 1.5}
    # The OpenCV loop says OK for a pair it could not range: 'ranged' counts the pairs given an R_min.
    assert _work_summary([{"status": "OK", "keypoints": [3, 5], "matches": 0, "inliers": 0, "r_min_m": None}])[
        "ranged"] == 0
    report = {"whole_process": [{"inputs": "x", "rival": "y", "pairs": 2, "pairs_per_s": 1.0, "svs_speedup": 1.0,
                                 **{f"work_{k}": v for k, v in summary.items()}}],
              "in_process": {"stages_ms_per_pair_B32": {"features": 1.0}, "scaling": [{"B": 1, "ms_per_pair": 2.0, "runs": 3}],
                             "latency_ms_B1": 2.0, "kornia_ms_per_pair": 3.0},
              "memory": [{"B": 1, "per_pair_mb": 4.0}], "help_s": 0.1, "metadata": {"threads": 2, "commit": "abc"}}
    text = format_tables(report)
    assert "| x | y | 1.0 | 1.0 | 1 of 2 | 7.5 | 4.0 | 3.0 | 1.5 |" in text and "| 1 | 2.0 | 3 | 4.0 |" in text


def test_bench_help_and_bad_data(capsys):
    from svs_torch.cli import main

    try:
        main(["bench", "--help"])
    except SystemExit as exit_:
        assert exit_.code == 0
    assert "OpenCV" in capsys.readouterr().out
    assert main(["bench", "--data", "/no/such/folder"]) == 2
    assert "--data: expected a folder" in capsys.readouterr().err


def test_guides_latency_is_also_timed_on_camera_frames():
    """The in-process report's camera-frame latency: the pairs as the board's default frames (each view noisy
    and JPEG-encoded, the two views' noise independent, seeded), and the table line that reports it."""
    import torch

    from svs_torch.data import camera_frame_pairs, random_obstacle_scenes
    from svs_torch.evaluation.benchmark import CAMERA_DIGIT, CAMERA_SIGMA_LEVELS

    def camera_pairs(batch):  # as the benchmark makes them
        return camera_frame_pairs(batch, CAMERA_DIGIT, CAMERA_SIGMA_LEVELS, torch.Generator().manual_seed(0))

    batch = random_obstacle_scenes(2, 2, generator=torch.Generator().manual_seed(1)).batch
    frames = camera_pairs(batch)
    assert frames.left.shape == batch.left.shape and not torch.equal(frames.left, batch.left)
    assert not torch.equal(frames.left - batch.left, frames.right - batch.right)
    assert torch.equal(camera_pairs(batch).right, frames.right)
    report = {"whole_process": [], "in_process": {
        "stages_ms_per_pair_B32": {}, "scaling": [], "latency_ms_B1": 2.0, "latency_ms_B1_otsu": 1.0,
        "latency_ms_B1_camera": 3.5, "latency_ms_B1_camera_otsu": 1.5, "latency_ms_B1_camera_floor": 4.5,
        "kornia_ms_per_pair": 3.0},
        "help_s": 0.1, "metadata": {"threads": 2, "commit": "abc"}}
    assert (f"as camera frames the way guide runs them (JPEG digit {CAMERA_DIGIT}, noise σ 4, guide's floor rule on, "
            "inference mode): 3.5 ms (Otsu: 1.5 ms), over a walker's floor (1.5 m below a camera pitched 20°): 4.5 ms"
            in format_tables(report))


def test_the_walker_frames_have_a_floor_that_guide_finds(monkeypatch):
    """The walker latency's frames are what their name says: guide's floor rule finds the floor in them (and the
    obstacles are still ranged), where the plain synthetic scenes have none to find."""
    import dataclasses

    import torch

    import svs_torch.segmentation.nearness as nearness
    from svs_torch.data import camera_frame_pairs, random_obstacle_scenes
    from svs_torch.evaluation.benchmark import (CAMERA_DIGIT, CAMERA_SIGMA_LEVELS, WALKER_FLOOR_HEIGHT_M,
                                                WALKER_PITCH_DEG)
    from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth

    found, fit = [], nearness.fit_ground_plane

    def recorded(*args, **kwargs):
        plane = fit(*args, **kwargs)
        found.append(plane.found)
        return plane

    monkeypatch.setattr(nearness, "fit_ground_plane", recorded)
    config = PipelineConfig()
    guide = dataclasses.replace(config, segmentation=config.segmentation.for_guide())
    for floor in (True, False):
        extra = {"floor_height_m": WALKER_FLOOR_HEIGHT_M, "camera_pitch_deg": WALKER_PITCH_DEG} if floor else {}
        scenes = random_obstacle_scenes(2, 2, generator=torch.Generator().manual_seed(1), **extra)
        frames = camera_frame_pairs(scenes.batch, CAMERA_DIGIT, CAMERA_SIGMA_LEVELS, torch.Generator().manual_seed(0))
        found.clear()
        result = estimate_obstacle_depth(frames, guide)
        assert found and all(f.tolist() == [floor, floor] for f in found)
        assert (result.status == PipelineStatus.OK).all() and result.depth.nearest.valid.all()


def test_guides_latency_is_timed_the_way_guide_calls_the_pipeline(monkeypatch):
    """guide's loop calls the pipeline under inference mode (its result read and dropped, so not copied); the
    camera-frame latency is timed the same way, the other latencies as a library caller makes the call."""
    import torch

    import svs_torch.pipeline
    from svs_torch.data import random_obstacle_scenes
    from svs_torch.evaluation import benchmark

    modes = []
    monkeypatch.setattr(svs_torch.pipeline, "estimate_obstacle_depth",
                        lambda batch, config: modes.append(torch.is_inference_mode_enabled()) or batch.batch_size)
    pairs = random_obstacle_scenes(2, 1, generator=torch.Generator().manual_seed(1)).batch
    ms, last = benchmark._ms_per_pair(pairs, 1, None, 2, as_guide=True)
    assert modes == [True] * 5 and last == 1 and ms >= 0  # a warm-up call, then 2 passes over 2 pairs
    modes.clear()
    benchmark._ms_per_pair(pairs, 2, None, 1)
    assert modes == [False, False]


def test_guides_latency_on_real_frames_is_reported_frame_by_frame(data_dir):
    """With the data folder the benchmark also times guide on the shared real pairs as camera frames, one frame at
    a time, and reports their distribution (the frames that take the pipeline's second passes are the slow ones
    a mean hides): the median, the 90th percentile by nearest rank, the maximum and the frames over the goal."""
    import dataclasses

    from svs_torch.evaluation.frame_latency import GOAL_MS, latency_summary, real_frame_latency
    from svs_torch.pipeline import PipelineConfig

    assert latency_summary([10, 20, 30, 40, 60, 70, 80, 90, 100, 5]) == {
        "frames": 10, "median_ms": 50.0, "p90_ms": 90, "max_ms": 100, "over_goal": 5}
    assert GOAL_MS == 50.0
    config = PipelineConfig()
    otsu = dataclasses.replace(config, segmentation=dataclasses.replace(config.segmentation, segmenter="otsu",
                                                                        keep="largest"))
    report = real_frame_latency(data_dir, {"otsu": otsu}, 1, 4, 4.0, limit=2)
    row = report["otsu"]
    assert row["frames"] == 2 and 0 < row["median_ms"] <= row["p90_ms"] <= row["max_ms"]
    text = format_tables({"whole_process": [], "in_process": {
        "stages_ms_per_pair_B32": {}, "scaling": [], "latency_ms_B1": 2.0, "kornia_ms_per_pair": 3.0,
        "latency_real_camera_frames": {"nearness": {"frames": 45, "median_ms": 38.2, "p90_ms": 71.0,
                                                    "max_ms": 104.5, "over_goal": 9}}},
        "help_s": 0.1, "metadata": {"threads": 2, "commit": "abc"}})
    assert "guide frame by frame on the shared real pairs as camera frames" in text
    assert "| nearness | 45 | 38.2 | 71.0 | 104.5 | 9 |" in text


def test_bench_finishes_without_linux_only_features(monkeypatch, tmp_path):
    """On Windows (no ``resource``, no ``os.getloadavg``) ``svs-depth bench`` was an internal error at once, and on
    macOS (no ``/proc/self/status`` for the memory children) one after minutes of timing. Now those parts are left
    out there, as --no-memory leaves the children out; macOS's peak resident memory, counted in bytes, is in MB."""
    import os
    from types import SimpleNamespace

    import svs_torch.evaluation.benchmark as benchmark

    for name, stub in [("write_inputs", lambda *a: {}), ("whole_process", lambda *a: []),
                       ("in_process", lambda *a: {}), ("help_time", lambda *a: 0.1),
                       ("_child_peak_memory", lambda *a: pytest.fail("/proc/self/status is not there to read"))]:
        monkeypatch.setattr(benchmark, name, stub)
    real_isfile = os.path.isfile
    monkeypatch.setattr(os.path, "isfile", lambda path: not str(path).startswith("/proc") and real_isfile(path))
    monkeypatch.delattr(os, "getloadavg")
    monkeypatch.setitem(sys.modules, "resource", None)
    metadata = benchmark.run_benchmark(1, 1, memory=True)["metadata"]
    assert metadata["max_rss_mb"] is None and metadata["load_average"] is None
    assert metadata["load_average_at_start"] is None
    monkeypatch.setattr(sys, "platform", "darwin")
    usage = SimpleNamespace(ru_maxrss=300 * 1024 * 1024)
    monkeypatch.setitem(sys.modules, "resource", SimpleNamespace(RUSAGE_SELF=0, getrusage=lambda who: usage))
    assert benchmark.run_benchmark(1, 1, memory=True)["metadata"]["max_rss_mb"] == 300.0


def test_whole_process_lists_survive_a_space_in_the_temporary_folder(tmp_path):
    """bench writes its inputs under the temporary folder, whose path may hold a space (Windows' ``C:\\Users\\Jo Li
    \\AppData\\Local\\Temp``, a TMPDIR): each list line was split in four, and svs-depth and the OpenCV loops ranged
    no pair (every one BAD_INPUT). The lists now name the files relative to themselves, as both read them."""
    from svs_torch.data.pair_list import read_pair_list
    from svs_torch.evaluation.benchmark import _write_list

    workdir = tmp_path / "Jo Li é"
    pairs = write_inputs(workdir, 2, None, seed=2)["synthetic 320x240"]
    listing = _write_list(pairs, workdir / "synthetic_320x240.txt")
    assert [(s.problem, s.left) for s in read_pair_list(listing)] == [(None, left) for left, _ in pairs]
    out = subprocess.run([*RIVAL_COMMAND, "orb", str(listing)], capture_output=True, text=True, check=True,
                         cwd=tmp_path).stdout.splitlines()
    assert [json.loads(line)["status"] for line in out] == ["OK", "OK"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_an_interrupted_rival_leaves_no_process_of_its_own_behind(tmp_path):
    """A SIGINT sent to the benchmark alone (``timeout -s INT``, ``kill -INT PID``) while the OpenCV pool ran:
    ``svs-depth bench`` said "interrupted" and exited 130, and the pool's spawned workers and their resource
    tracker went on running as orphans (an audit). The rival's whole process group is now ended."""
    import os
    import signal
    import threading
    import time

    from svs_torch.evaluation import benchmark

    pid_file = tmp_path / "grandchild.pid"
    code = ("import subprocess, sys, time\n"
            "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
            f"open({str(pid_file)!r}, 'w').write(str(child.pid))\n"
            "time.sleep(60)\n")
    main = threading.main_thread().ident

    def interrupt():
        while not pid_file.exists() or not pid_file.read_text():
            time.sleep(0.05)
        signal.pthread_kill(main, signal.SIGINT)

    threading.Thread(target=interrupt, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        benchmark._run_process([sys.executable, "-c", code], dict(os.environ))
    grandchild = int(pid_file.read_text())

    def running(pid):
        try:
            with open(f"/proc/{pid}/stat") as handle:
                return handle.read().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    deadline = time.monotonic() + 10
    while running(grandchild) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = running(grandchild)
    if alive:
        os.kill(grandchild, signal.SIGKILL)
    assert not alive


def test_threads_above_the_cores_are_refused_before_any_work(capsys, monkeypatch):
    """``--threads 999`` on 2 cores was taken: svs-depth estimate ran on its 2 cores, the OpenCV loop asked for 999
    threads, its pool spawned up to 999 processes, and the report said 'threads 999' for all of them."""
    from svs_torch.cli import main
    from svs_torch.core import workers
    from svs_torch.evaluation import benchmark

    monkeypatch.setattr(workers, "available_cores", lambda: 2)
    monkeypatch.setattr(benchmark, "run_benchmark", lambda *a, **k: pytest.fail("work started"))
    assert main(["bench", "--threads", "999"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--threads: expected 1 to 2 (the cores this process may run on), got 999" in err
    from svs_torch.cli.bench import checked_threads

    assert (checked_threads(None), checked_threads(1)) == (2, 1)
    monkeypatch.setattr(workers, "available_cores", lambda: 1)
    assert checked_threads(None) == 1  # the default on a 1-core machine: what svs-depth estimate takes there


def test_the_memory_children_run_the_reported_thread_count(monkeypatch):
    """The peak-memory children inherited the caller's OMP_NUM_THREADS (or ran a thread per core), not --threads,
    which the report records as the thread count of every part."""
    import subprocess

    from svs_torch.evaluation import bench_processes, benchmark

    seen = []

    def child(command, env=None, check=False):
        seen.append((env or {}).get("OMP_NUM_THREADS"))
        return subprocess.CompletedProcess(command, 0, '{"base_mb": 100.0, "peak_mb": 108.0}\n', "")

    monkeypatch.setattr(benchmark, "run_child", child)
    monkeypatch.setattr(bench_processes, "run_child", child)
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    row = benchmark._child_peak_memory(2, 1)
    assert seen == ["1"] and row == {"B": 2, "peak_mb": 108.0, "per_pair_mb": 4.0}


def test_bench_pairs_beyond_the_cap_are_refused_before_any_work(capsys, monkeypatch):
    """``--pairs 1000000000`` was taken: after the imports, an internal error trying to allocate 40 GB at once."""
    from svs_torch.cli import main
    from svs_torch.evaluation import benchmark

    monkeypatch.setattr(benchmark, "run_benchmark", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "--pairs", "1000000000"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1
    assert "argument --pairs: expected 1 to 4096 pairs, got '1000000000'" in err
    # --repeats had no cap: each repeat runs every rival's whole processes again (minutes each).
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "--repeats", "300"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1
    assert "argument --repeats: expected 1 to 100 runs, got '300'" in err


def test_inputs_are_rendered_a_chunk_at_a_time(tmp_path, monkeypatch):
    """All of --pairs' synthetic scenes were rendered at once, about 20 MB each while rendered: --pairs 512 (the
    README's run) peaked near 10 GB. Now a chunk at a time, from one generator, so the first chunk (the whole
    default run) is the scenes it was, and every pair still gets a file of its own."""
    import cv2

    import svs_torch.data.synthetic as synthetic
    from svs_torch.evaluation import bench_inputs

    sizes, render = [], synthetic.random_obstacle_scenes
    monkeypatch.setattr(synthetic, "random_obstacle_scenes", lambda n, *a, **k: sizes.append(n) or render(n, *a, **k))
    monkeypatch.setattr(bench_inputs, "CHUNK_PAIRS", 2, raising=False)
    pairs = bench_inputs.write_inputs(tmp_path / "chunked", 5, None)["synthetic 320x240"]
    assert sizes == [2, 2, 1] and len({left for left, _ in pairs}) == 5
    whole = bench_inputs.write_inputs(tmp_path / "whole", 2, None)["synthetic 320x240"]
    for (left, right), (left_0, right_0) in zip(pairs[:2], whole):
        assert (cv2.imread(left) == cv2.imread(left_0)).all() and (cv2.imread(right) == cv2.imread(right_0)).all()


def test_the_recorded_commit_says_when_the_code_that_ran_was_not_committed(monkeypatch):
    """The report's commit was ``git rev-parse --short HEAD`` alone: a run of edited code was recorded, and its rows
    quoted, as that commit's. Uncommitted changes to tracked files now show as ``-dirty``, as sweeps record them."""
    import subprocess

    from svs_torch.core import checkout

    def git(command, **kwargs):
        out = "abc1234\n" if "rev-parse" in command else " M svs_torch/pipeline/core.py\n"
        return subprocess.CompletedProcess(command, 0, out, "")

    monkeypatch.setattr(checkout.subprocess, "run", git)
    assert checkout.short_commit() == "abc1234-dirty"


def test_the_load_before_the_run_is_recorded_beside_the_load_after_it(monkeypatch):
    """The report's load average was taken at the end, when the benchmark's own threads had raised it: it could not
    say whether other jobs shared the machine. The load before the run is now recorded too."""
    import os

    from svs_torch.evaluation import benchmark

    for name, stub in [("write_inputs", lambda *a: {}), ("whole_process", lambda *a: []),
                       ("in_process", lambda *a: {}), ("help_time", lambda *a: 0.1)]:
        monkeypatch.setattr(benchmark, name, stub)
    loads = iter([(0.5, 0.4, 0.3), (2.0, 1.0, 0.5)])
    monkeypatch.setattr(os, "getloadavg", lambda: next(loads))
    metadata = benchmark.run_benchmark(1, 1, memory=False)["metadata"]
    assert metadata["load_average_at_start"] == (0.5, 0.4, 0.3) and metadata["load_average"] == (2.0, 1.0, 0.5)


def test_a_rival_that_answers_for_fewer_pairs_than_listed_is_not_timed_as_if_it_did_them_all(tmp_path, monkeypatch):
    """pairs/s is the listed pairs over the run's time: a rival that printed results for fewer pairs (a list line it
    skipped) was credited with every listed pair, unsaid."""
    from svs_torch.evaluation import benchmark

    row = {"status": "OK", "keypoints": [1, 1], "matches": 0, "inliers": 0, "r_min_m": 1.0}
    monkeypatch.setattr(benchmark, "_run_process", lambda command, env: (1.0, [row]))
    with pytest.raises(RuntimeError, match=r"svs-depth estimate --pairs: 1 result lines for 2 pairs"):
        benchmark.whole_process({"s": [("a.png", "b.png"), ("c.png", "d.png")]}, tmp_path, 1, 1)


def test_the_recorded_commit_is_the_one_checked_out_when_the_run_started(monkeypatch):
    """The commit was read after minutes of timing: a checkout changed meanwhile (another branch, a pull) was
    recorded as the code that ran, though the run had imported the code of the start."""
    from svs_torch.evaluation import benchmark

    commits = iter(["aaaaaaa", "bbbbbbb"])
    monkeypatch.setattr(benchmark, "short_commit", lambda: next(commits))
    for name, stub in [("write_inputs", lambda *a: {}), ("whole_process", lambda *a: []),
                       ("in_process", lambda *a: {}), ("help_time", lambda *a: 0.1)]:
        monkeypatch.setattr(benchmark, name, stub)
    assert benchmark.run_benchmark(1, 1, memory=False)["metadata"]["commit"] == "aaaaaaa"


def test_the_metadata_records_the_cores_this_run_could_use():
    """Found by an audit: only ``os.cpu_count()`` (the machine's) was recorded, not the cores a container or
    ``taskset`` left this run, which is what its times and its ``--threads`` cap rest on."""
    from svs_torch.core.workers import available_cores
    from svs_torch.evaluation.benchmark import _metadata

    assert _metadata(1, "abc1234")["cores_available"] == available_cores()
    from conftest import REPO_ROOT

    sys.path.insert(0, str(REPO_ROOT / "experiments"))
    from run_metadata import run_metadata

    assert run_metadata(1)["cores_available"] == available_cores()


def test_each_batch_size_says_the_runs_its_median_is_of(monkeypatch):
    """Found by an audit: the in-process B = 128 time was the median of repeats // 2 runs (one at --repeats 3), the
    JSON's metadata saying 'repeats': 3 and nothing saying otherwise. Each batch size's row now records its runs, and
    the table shows them."""
    from types import SimpleNamespace

    import svs_torch.data
    import svs_torch.data.synthetic
    from svs_torch.evaluation import benchmark

    asked = []
    batch = SimpleNamespace(select=lambda indices: batch)
    monkeypatch.setattr(svs_torch.data.synthetic, "random_obstacle_scenes",
                        lambda *args, **kwargs: SimpleNamespace(batch=batch))
    monkeypatch.setattr(svs_torch.data, "camera_frame_pairs", lambda *args: batch)
    monkeypatch.setattr(benchmark, "_kornia_composition", lambda *args: 1.0)
    monkeypatch.setattr(benchmark, "_ms_per_pair", lambda pairs, b, config, repeats, as_guide=False: (
        asked.append((b, repeats)) or 1.0, SimpleNamespace(timings_s={})))
    inside = benchmark.in_process(3, 1)
    assert asked[:4] == [(1, 3), (8, 3), (32, 3), (128, 1)]
    assert [(row["B"], row["runs"]) for row in inside["scaling"]] == asked[:4]


def test_the_metadata_records_the_openmp_wait_policy_and_the_vector_instructions(monkeypatch):
    """Found by an audit: the experiments record OMP_WAIT_POLICY and torch's CPU capability beside their times, the
    benchmark did not, though its in-process part runs under the policy its shell exported (PASSIVE made guide's
    frame time half again as long: README, "Speed today") and the README sets AVX-512 machines apart from AVX2 ones."""
    import torch

    from svs_torch.evaluation.benchmark import _metadata

    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")
    metadata = _metadata(1, "abc1234")
    assert metadata["omp_wait_policy"] == "PASSIVE"
    assert metadata["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    monkeypatch.delenv("OMP_WAIT_POLICY")
    assert _metadata(1, "abc1234")["omp_wait_policy"] is None


def test_kornias_composition_is_set_against_svs_torch_on_its_own_pairs(monkeypatch):
    """Found by a look at the benchmarks against the house rule (rivals in the same run, ratios printed): `svs-depth
    bench` reported kornia's composition as its time a pair alone, beside no svs_torch time of the same pairs. The
    pipeline now runs kornia's pairs at B = 1 as well, and the JSON and the table give the ratio kornia time /
    svs_torch time (the whole-process rows' svs_speedup), the table saying which way it is."""
    from types import SimpleNamespace

    import svs_torch.data
    import svs_torch.data.synthetic
    from svs_torch.evaluation import benchmark

    def select(indices):  # each selection its own object, so that the pairs each timing ran on are told apart
        return SimpleNamespace(indices=tuple(indices), select=select)

    batch = SimpleNamespace(select=select)
    timed, kornia_pairs = [], []
    monkeypatch.setattr(svs_torch.data.synthetic, "random_obstacle_scenes",
                        lambda *args, **kwargs: SimpleNamespace(batch=batch))
    monkeypatch.setattr(svs_torch.data, "camera_frame_pairs", lambda *args: batch)
    monkeypatch.setattr(benchmark, "_kornia_composition", lambda pairs, repeats: kornia_pairs.append(pairs) or 10.0)
    monkeypatch.setattr(benchmark, "_ms_per_pair", lambda pairs, b, config, repeats, as_guide=False: (
        timed.append((pairs, b)) or 4.0, SimpleNamespace(timings_s={})))
    inside = benchmark.in_process(3, 1)
    assert [getattr(pairs, "indices", None) for pairs in kornia_pairs] == [tuple(range(8))]
    assert [b for pairs, b in timed if getattr(pairs, "indices", None) == tuple(range(8))] == [1]
    assert inside["kornia_ms_per_pair"] == 10.0 and inside["svs_ms_per_pair_kornia_pairs"] == 4.0
    assert inside["kornia_svs_speedup"] == 2.5
    report = {"whole_process": [], "in_process": {**inside, "stages_ms_per_pair_B32": {}, "scaling": []},
              "help_s": 0.1, "metadata": {"threads": 1, "commit": "abc"}}
    assert ("kornia SIFTFeature + match_snn + RANSAC: 10.0 ms per pair (its sparse stages alone) against svs_torch's "
            "whole pipeline's 4.0 ms on the same pairs at B = 1: svs_torch speed-up (kornia time / svs_torch time) "
            "2.5" in format_tables(report))
