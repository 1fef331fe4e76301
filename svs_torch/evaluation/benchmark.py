"""``svs-depth bench``: svs_torch against its rivals as a user meets them, on the same inputs, in one run.

What is measured (all on this machine, the thread count recorded):

- **whole process from the command line**: ``svs-depth estimate --pairs LIST --json`` (and the same with the
  paper's ``--segmenter otsu``, to show what the default nearness segmenter costs; start-up, imports, image
  decoding, the default configuration) against the same work as plain OpenCV loops in their own processes
  (:mod:`svs_torch.evaluation.bench_rivals`: decode, Otsu + opening + two largest regions, SIFT or ORB, ratio matching,
  ``findFundamentalMat`` RANSAC, ``StereoBM`` median over the kept regions), run as a plain script that imports
  only OpenCV and numpy, as a user's own loop does (:data:`RIVAL_COMMAND`). Runs are interleaved (svs, SIFT,
  ORB, svs, …) so a busy moment of the machine hits every rival alike; the median of ``repeats`` is reported.
- **in-process** (glibc's allocator kept to freed memory, as the command line runs): the pipeline's stage
  times at B = 32, the per-pair time from B = 1 to 128 (the same 128 synthetic pairs in batches of B, after a
  warm-up batch at each size; batches over 32 pairs of 320×240 run in chunks of 32), the peak resident
  memory per pair of the batch (a child process per B), the latency of one pair at B = 1 (what ``guide``
  pays per frame; also with the paper's Otsu segmenter, and both on the first 16 pairs as the board's default
  camera frames, :func:`svs_torch.data.camera_frame_pairs`, the nearness segmenter's then with guide's floor
  rule on and each call under ``torch.inference_mode``, as guide runs it, and once more with a walker's floor
  under the obstacles, which guide's floor rule finds), with the data folder guide's latency frame by frame on
  the shared real pairs as camera frames (its median, 90th percentile and maximum: :mod:`.frame_latency`), and
  kornia's own composition (``SIFTFeature`` + ``match_snn`` + ``RANSAC('fundamental')``) beside svs_torch's whole
  pipeline on the same 8 pairs at B = 1, with the ratio kornia time / svs_torch time (the whole-process rows'
  ``svs_speedup``).
- ``svs-depth --help`` start-up.
- **comparable work**: per rival, the mean keypoints, matches, inliers and the median R_min over the pairs, so
  a win by doing less shows.

Inputs are written to a temporary folder as PNG files: synthetic SVS scenes (320×240) and the shared real pairs
(when the data folder is there) resampled to 320×240 and 640×480.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

from ..core.checkout import short_commit
from .bench_inputs import _write_list, write_inputs
from .bench_processes import run_child
from .frame_latency import GOAL_MS, real_frame_latency

__all__ = ["run_benchmark", "format_tables"]

#: The OpenCV rivals run as a plain script, by its path: ``python -m svs_torch.evaluation.bench_rivals`` would
#: import the ``svs_torch.evaluation`` package, and with it torch (1.1-1.5 s), in the rival's process and again
#: in each worker its pool spawns, which a user's own OpenCV loop never pays (512 real 320x240 pairs, ORB on a
#: pool of 2: 8.0-8.7 s through the package, 4.0-4.7 s as a script).
RIVAL_COMMAND = (sys.executable, str(Path(__file__).with_name("bench_rivals.py")))

SCALING_BATCHES = (1, 8, 32, 128)
#: guide's latency is also timed on camera frames: the board's default JPEG digit, with sensor noise of σ 4 levels
#: (experiments/real_rig.py's condition at that digit).
CAMERA_DIGIT, CAMERA_SIGMA_LEVELS = 4, 4.0
#: ... and on a walker's view, the same obstacles over a floor 1.5 m below a camera pitched down 20°, where guide's
#: floor rule fits and finds the floor on every frame (the synthetic scenes above have none, and a frame with no
#: floor sample stops the fit early: svs_torch.segmentation.ground_plane).
WALKER_FLOOR_HEIGHT_M, WALKER_PITCH_DEG = 1.5, 20.0


def _run_process(command: list[str], env: dict[str, str]) -> tuple[float, list[dict]]:
    started = time.perf_counter()
    done = run_child(command, env)
    elapsed = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command[:4])} …: exit {done.returncode}: {done.stderr.strip()[-300:]}")
    rows = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    return elapsed, rows


def _work_summary(rows: list[dict]) -> dict:
    """Mean keypoints / matches / inliers and the median R_min of one rival's per-pair lines."""
    def mean(values):
        values = [v for v in values if v is not None]
        return round(statistics.fmean(values), 1) if values else None

    keypoints = [sum(r.get("num_keypoints") or r.get("keypoints") or [0]) / 2 for r in rows]
    r_min = [r["r_min_m"] for r in rows if r.get("r_min_m") is not None]
    # ranged: pairs given an R_min. "ok" is not comparable: the OpenCV loop says OK for a pair it could not range.
    return {"pairs": len(rows), "ok": sum(r.get("status") == "OK" for r in rows), "ranged": len(r_min),
            "keypoints": mean(keypoints),
            "matches": mean([r.get("num_matches", r.get("matches")) for r in rows]),
            "inliers": mean([r.get("num_inliers", r.get("inliers")) for r in rows]),
            "median_r_min_m": round(statistics.median(r_min), 3) if r_min else None}


def whole_process(sets: dict[str, list], workdir: Path, repeats: int, threads: int,
                  progress=None) -> list[dict]:
    """Interleaved whole-process runs of the CLI and the OpenCV loops on every input set."""
    # The user's environment, threads pinned. No OMP_WAIT_POLICY: PASSIVE made `svs-depth estimate --pairs` 1.5x
    # slower (64 synthetic pairs: 8.3 s against 5.7 s), and a user does not set it.
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    env.pop("OMP_WAIT_POLICY", None)
    rows = []
    for name, pairs in sets.items():
        listing = _write_list(pairs, workdir / f"{name.replace(' ', '_')}.txt")
        commands = {
            "svs-depth estimate --pairs": [sys.executable, "-m", "svs_torch.cli", "estimate", "--pairs", str(listing),
                                           "--json"],
            # The paper's segmenter beside the default (issue 32 item 4: what the nearness segmenter costs).
            "svs-depth estimate --pairs --segmenter otsu": [sys.executable, "-m", "svs_torch.cli", "estimate",
                                                            "--pairs", str(listing), "--json", "--segmenter", "otsu"],
            "OpenCV SIFT loop": [*RIVAL_COMMAND, "sift", str(listing), "--threads", str(threads)],
            "OpenCV ORB loop": [*RIVAL_COMMAND, "orb", str(listing), "--threads", str(threads)],
            # The strongest loop a user writes for throughput: one process per core, one OpenCV thread each.
            f"OpenCV SIFT pool ({threads} proc)": [*RIVAL_COMMAND, "sift", str(listing), "--workers", str(threads)],
            f"OpenCV ORB pool ({threads} proc)": [*RIVAL_COMMAND, "orb", str(listing), "--workers", str(threads)],
        }
        times: dict[str, list[float]] = {key: [] for key in commands}
        work: dict[str, dict] = {}
        for _ in range(repeats):
            for key, command in commands.items():
                elapsed, lines = _run_process(command, env)
                if len(lines) != len(pairs):  # its pairs a second would count pairs it did not do
                    raise RuntimeError(f"{key}: {len(lines)} result lines for {len(pairs)} pairs ({name})")
                times[key].append(elapsed)
                work[key] = _work_summary(lines)
                if progress:
                    progress(f"{name}: {key} {len(pairs) / elapsed:.1f} pairs/s")
        svs = statistics.median(times["svs-depth estimate --pairs"])
        for key in commands:
            median = statistics.median(times[key])
            rows.append({"inputs": name, "rival": key, "pairs": len(pairs), "median_s": round(median, 3),
                         "pairs_per_s": round(len(pairs) / median, 2), "svs_speedup": round(median / svs, 3),
                         "runs_s": [round(t, 3) for t in times[key]], **{f"work_{k}": v for k, v in
                                                                          work[key].items()}})
    return rows


def _child_peak_memory(batch_size: int, threads: int) -> dict:
    """Peak resident memory of a child process running the default pipeline on B synthetic pairs with ``threads``
    torch threads, above the child's peak once torch is imported and the input batch is loaded (written by this
    process, so rendering the scenes does not set the peak)."""
    import torch

    from ..data.synthetic import random_obstacle_scenes

    scenes = random_obstacle_scenes(batch_size, 2, generator=torch.Generator().manual_seed(0))
    with tempfile.TemporaryDirectory(prefix="svs_bench_mem_") as tmp:
        path = Path(tmp) / "batch.pt"
        torch.save({"left": scenes.batch.left, "right": scenes.batch.right}, path)
        # VmHWM, not ru_maxrss: Linux carries ru_maxrss across execve, so a child would start at its parent's
        # peak; VmHWM belongs to the child's own address space.
        code = (
            "import torch, json\n"
            "from svs_torch.core.workers import keep_freed_memory\n"
            "keep_freed_memory()  # as the command line does\n"
            "def peak_mb():\n"
            "    for line in open('/proc/self/status'):\n"
            "        if line.startswith('VmHWM:'):\n"
            "            return int(line.split()[1]) / 1024\n"
            "from svs_torch.pipeline import estimate_obstacle_depth\n"
            "from svs_torch.core.types import StereoBatch\n"
            f"images = torch.load({str(path)!r})\n"
            "batch = StereoBatch.from_images(images['left'], images['right'], 276.26, 0.1075)\n"
            "base = peak_mb()\n"
            "estimate_obstacle_depth(batch)\n"
            "print(json.dumps({'base_mb': base, 'peak_mb': peak_mb()}))\n")
        # The report's thread count, not the caller's OMP_NUM_THREADS (or every core) as the child found them.
        done = run_child([sys.executable, "-c", code], {**os.environ, "OMP_NUM_THREADS": str(threads)}, check=True)
    values = json.loads(done.stdout.strip().splitlines()[-1])
    return {"B": batch_size, "peak_mb": round(values["peak_mb"], 1),
            "per_pair_mb": round((values["peak_mb"] - values["base_mb"]) / batch_size, 2)}


def in_process(repeats: int, threads: int, data_dir: Path | None = None) -> dict:
    """Stage times at B = 32, per-pair time against B, latency at B = 1, kornia's composition; with ``data_dir``,
    guide's latency frame by frame on the shared real pairs as camera frames (:mod:`.frame_latency`)."""
    import torch

    from ..data import camera_frame_pairs
    from ..data.synthetic import random_obstacle_scenes
    from ..core.workers import keep_freed_memory
    from ..pipeline import PipelineConfig

    torch.set_num_threads(threads)
    keep_freed_memory()  # glibc kept to freed memory, as the command line and its workers run
    config = PipelineConfig()
    scenes = random_obstacle_scenes(max(SCALING_BATCHES), 2, generator=torch.Generator().manual_seed(1))
    scaling, stages = [], {}
    # Every batch size runs the same pairs (all of them, in batches of B), so that the time a pair compares batch
    # sizes, not the scenes each size happened to take.
    for b in SCALING_BATCHES:
        runs = repeats if b <= 32 else max(1, repeats // 2)  # (a B = 128 pass is the slowest; its runs are said)
        ms, last = _ms_per_pair(scenes.batch, b, config, runs)
        scaling.append({"B": b, "ms_per_pair": ms, "runs": runs})
        if b == 32:
            stages = {k: round(v / b * 1e3, 2) for k, v in last.timings_s.items()}
    latency = next(row["ms_per_pair"] for row in scaling if row["B"] == 1)
    # The one-pair latency with the paper's segmenter (Otsu, the two largest regions) over the first 16 pairs.
    otsu = dataclasses.replace(config, segmentation=dataclasses.replace(config.segmentation, segmenter="otsu",
                                                                        keep="largest"))
    first = scenes.batch.select(list(range(16)))
    # guide's own input: a real SVS sends noisy JPEG frames, on which the pipeline takes more passes than on
    # clean ones (a noisy map matched wider, the dense stage's coarse retry).
    frames = camera_frame_pairs(first, CAMERA_DIGIT, CAMERA_SIGMA_LEVELS, torch.Generator().manual_seed(0))
    # ... and guide's own configuration (PipelineConfig.for_guide: a camera's frames, the floor left out).
    walker = config.for_guide()
    floor = random_obstacle_scenes(16, 2, generator=torch.Generator().manual_seed(1),
                                   floor_height_m=WALKER_FLOOR_HEIGHT_M, camera_pitch_deg=WALKER_PITCH_DEG)
    floor_frames = camera_frame_pairs(floor.batch, CAMERA_DIGIT, CAMERA_SIGMA_LEVELS, torch.Generator().manual_seed(0))
    # The camera frames are timed as guide's loop runs them: under inference mode, which reads each result and
    # drops it, so the pipeline hands out its tensors uncopied (svs_torch.core.inference).
    # guide --second-passes off beside the default: what a walker's slowest frames wait for.
    guide_rows = {"nearness": walker, "nearness, --second-passes off": config.for_guide(second_passes=False),
                  "otsu": otsu}
    real = {} if data_dir is None else real_frame_latency(data_dir, guide_rows, repeats, CAMERA_DIGIT,
                                                          CAMERA_SIGMA_LEVELS)
    return {"stages_ms_per_pair_B32": stages, "scaling": scaling, "latency_ms_B1": latency,
            "latency_real_camera_frames": real,
            "latency_ms_B1_otsu": _ms_per_pair(first, 1, otsu, repeats)[0],
            "latency_ms_B1_camera": _ms_per_pair(frames, 1, walker, repeats, as_guide=True)[0],
            "latency_ms_B1_camera_otsu": _ms_per_pair(frames, 1, otsu, repeats, as_guide=True)[0],
            "latency_ms_B1_camera_floor": _ms_per_pair(floor_frames, 1, walker, repeats, as_guide=True)[0],
            **_kornia_rival(scenes.batch.select(list(range(8))), config, repeats)}


def _ms_per_pair(pairs, b: int, config, repeats: int, as_guide: bool = False) -> tuple[float, object]:
    """The pipeline's time a pair over all of ``pairs`` in batches of ``b``, after a warm-up batch at that size
    (a user's first batch pays for it once): the median of ``repeats`` passes, in ms, and the last batch's result.
    ``as_guide``: each call under ``torch.inference_mode``, as ``svs-depth guide`` makes it."""
    import torch

    from ..pipeline import estimate_obstacle_depth

    def estimate(batch):
        with torch.inference_mode() if as_guide else contextlib.nullcontext():
            return estimate_obstacle_depth(batch, config)

    total = pairs.batch_size
    batches = [pairs.select(list(range(start, min(start + b, total)))) for start in range(0, total, b)]
    estimate(batches[0])
    runs, last = [], None
    for _ in range(repeats):
        started = time.perf_counter()
        for batch in batches:
            last = estimate(batch)
        runs.append(time.perf_counter() - started)
    return round(statistics.median(runs) / total * 1e3, 2), last


def _kornia_rival(pairs, config, repeats: int) -> dict:
    """kornia's composition and svs_torch's pipeline per pair on the same ``pairs`` at B = 1 (kornia's takes one image
    at a time), and the ratio kornia time / svs_torch time: kornia's time was reported alone (an audit)."""
    kornia_ms, svs_ms = _kornia_composition(pairs, repeats), _ms_per_pair(pairs, 1, config, repeats)[0]
    return {"kornia_ms_per_pair": kornia_ms, "svs_ms_per_pair_kornia_pairs": svs_ms,
            "kornia_svs_speedup": round(kornia_ms / svs_ms, 3)}


def _kornia_composition(batch, repeats: int) -> float:
    """kornia's own sparse pipeline per pair: SIFTFeature on both images, match_snn 0.8, RANSAC fundamental."""
    import torch
    from kornia.feature import SIFTFeature, match_snn
    from kornia.geometry.ransac import RANSAC

    sift = SIFTFeature(num_features=500, upright=True)
    ransac = RANSAC("fundamental", inl_th=1.0, max_iter=10, seed=0)

    def run():
        # kornia's SIFTFeature takes one image at a time (its input must be (1, C, H, W)).
        for i in range(batch.batch_size):
            with torch.no_grad():
                lafs_l, _, desc_l = sift(batch.left[i:i + 1])
                lafs_r, _, desc_r = sift(batch.right[i:i + 1])
                _, idx = match_snn(desc_l[0], desc_r[0], 0.8)
                if len(idx) >= 8:
                    ransac(lafs_l[0, idx[:, 0], :, 2], lafs_r[0, idx[:, 1], :, 2])

    run()
    runs = []
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        runs.append(time.perf_counter() - started)
    return round(statistics.median(runs) / batch.batch_size * 1e3, 2)


def help_time(repeats: int) -> float:
    runs = []
    for _ in range(repeats):
        started = time.perf_counter()
        run_child([sys.executable, "-m", "svs_torch.cli", "--help"], check=True)
        runs.append(time.perf_counter() - started)
    return round(statistics.median(runs), 3)


def _metadata(threads: int, commit: str, **extra) -> dict:
    import cv2
    import kornia
    import numpy
    import torch

    from ..core.workers import available_cores

    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"commit": commit, "torch": torch.__version__, "kornia": kornia.__version__, "opencv": cv2.__version__,
            "numpy": numpy.__version__, "python": sys.version.split()[0], "cpu": cpu, "cpus": os.cpu_count(),
            # the cores this run could use (a container's or taskset's share), which "cpus" (the machine's) is not
            "cores_available": available_cores(), "threads": threads,
            # The in-process part runs under this process's OpenMP wait policy (a shell's PASSIVE made guide's
            # latency about half again as long) on these vector instructions (AVX-512 or AVX2): as the experiments
            # record them (experiments/run_metadata.py), which this report did not (an audit).
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None, **extra}


def run_benchmark(num_pairs: int = 64, repeats: int = 3, threads: int = 2, data_dir: Path | None = None,
                  progress=None, memory: bool = True) -> dict:
    """Everything above; returns a JSON-ready report (see the module docstring)."""
    # The load before this run adds its own: what says whether other jobs shared the machine (the one taken at the
    # end counts the benchmark's own threads).
    load_at_start = os.getloadavg() if hasattr(os, "getloadavg") else None
    commit = short_commit()  # the code this run imports: a checkout changed during the run was recorded instead
    with tempfile.TemporaryDirectory(prefix="svs_bench_") as tmp:
        workdir = Path(tmp)
        sets = write_inputs(workdir, num_pairs, data_dir)
        report = {"whole_process": whole_process(sets, workdir, repeats, threads, progress)}
    if progress:
        progress("in-process: stages, batch scaling, latency, kornia")
    report["in_process"] = in_process(repeats, threads, data_dir)
    report["help_s"] = help_time(repeats)
    if memory and os.path.isfile("/proc/self/status"):  # the children's peak is read there: not on macOS, Windows
        if progress:
            progress("peak memory per batch size")
        report["memory"] = [_child_peak_memory(b, threads) for b in SCALING_BATCHES]
    try:
        import resource  # (not on Windows)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (1024 * 1024 if sys.platform == "darwin" else 1024)
    except ImportError:
        rss = None
    report["metadata"] = _metadata(threads, commit, num_pairs=num_pairs, repeats=repeats,
                                   load_average_at_start=load_at_start,
                                   max_rss_mb=None if rss is None else round(rss, 1))  # macOS counts bytes, Linux KiB
    return report


def _kornia_ratio(inside: dict) -> str:
    """The table's words for kornia's ratio to svs_torch ("" in a report from before it was measured)."""
    if inside.get("kornia_svs_speedup") is None:
        return ""
    return (f" (its sparse stages alone) against svs_torch's whole pipeline's {inside['svs_ms_per_pair_kornia_pairs']}"
            f" ms on the same pairs at B = 1: svs_torch speed-up (kornia time / svs_torch time) "
            f"{inside['kornia_svs_speedup']}")


def format_tables(report: dict) -> str:
    """The report as Markdown tables."""
    lines = ["| inputs | rival | pairs/s | svs_torch speed-up | pairs ranged | keypoints | matches | inliers | "
             "median R_min m |", "|---|---|---|---|---|---|---|---|---|"]
    for row in report["whole_process"]:  # (ranged: a rival that ranges fewer pairs shows it, as one doing less)
        lines.append(f"| {row['inputs']} | {row['rival']} | {row['pairs_per_s']} | {row['svs_speedup']} | "
                     f"{row.get('work_ranged', '-')} of {row.get('pairs', '-')} | "
                     f"{row['work_keypoints']} | {row['work_matches']} | {row['work_inliers']} | "
                     f"{row['work_median_r_min_m']} |")
    inside = report["in_process"]
    lines += ["", "| stage (B = 32, 320x240 synthetic) | ms per pair |", "|---|---|"]
    lines += [f"| {stage} | {ms} |" for stage, ms in inside["stages_ms_per_pair_B32"].items()]
    lines += ["", "| B | ms per pair | median of runs | peak MB per pair |", "|---|---|---|---|"]
    memory = {row["B"]: row for row in report.get("memory", [])}
    for row in inside["scaling"]:
        lines.append(f"| {row['B']} | {row['ms_per_pair']} | {row.get('runs', '-')} | "
                     f"{memory.get(row['B'], {}).get('per_pair_mb', '-')} |")
    lines += ["", f"latency of one pair (B = 1): {inside['latency_ms_B1']} ms (with the paper's Otsu "
              f"segmenter: {inside.get('latency_ms_B1_otsu', '-')} ms); as camera frames the way guide runs them "
              f"(JPEG digit {CAMERA_DIGIT}, noise σ {CAMERA_SIGMA_LEVELS:g}, guide's floor rule on, inference mode): "
              f"{inside.get('latency_ms_B1_camera', '-')} ms (Otsu: {inside.get('latency_ms_B1_camera_otsu', '-')} "
              f"ms), over a walker's floor ({WALKER_FLOOR_HEIGHT_M:g} m below a camera pitched "
              f"{WALKER_PITCH_DEG:g}°): {inside.get('latency_ms_B1_camera_floor', '-')} ms; kornia SIFTFeature + "
              f"match_snn + RANSAC: {inside['kornia_ms_per_pair']} ms per pair{_kornia_ratio(inside)}; "
              f"`svs-depth --help`: "
              f"{report['help_s']} s; threads {report['metadata']['threads']}, commit {report['metadata']['commit']}"]
    real = inside.get("latency_real_camera_frames") or {}
    if real:
        lines += ["", f"guide frame by frame on the shared real pairs as camera frames (320x240, JPEG digit "
                  f"{CAMERA_DIGIT}, noise σ {CAMERA_SIGMA_LEVELS:g}, B = 1, inference mode; goal {GOAL_MS:g} ms):",
                  "", "| segmenter | frames | median ms | 90th percentile ms | max ms | frames over the goal |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {name} | {row['frames']} | {row['median_ms']} | {row['p90_ms']} | {row['max_ms']} | "
                  f"{row['over_goal']} |" for name, row in real.items()]
    return "\n".join(lines)
