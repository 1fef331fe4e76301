"""Stereo pairs per second through the capture driver against the emulator over loopback TCP.

The emulator runs in its own process (as the device would), started as ``python -m hw.emulator --json`` on free
ports; the driver (:class:`svs_torch.capture.SVSStereoCamera`, default link settings) grabs, checks and decodes
pairs. Reported per size: the median and spread of ``--runs`` runs of ``--pairs`` pairs each, the mean JPEG size,
and for context the bound a real 2,304,000-baud UART would put on the rate (one frame per board per
``jpeg_bytes / 230,400`` s, both boards in parallel). JSON on stdout, with its metadata (commit, versions,
threads, the settings), and with ``--json FILE`` in FILE too, as the other benchmarks write theirs.

Run: ``python experiments/bench_capture.py [--sizes 320x240,640x480] [--runs 5] [--pairs 50] [--frames torch]
[--json out.json]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import serial
import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from svs_torch.core.camera import parse_size  # noqa: E402
from svs_torch.capture import LinkConfig, SVSStereoCamera  # noqa: E402

from svs_torch.cli.common import positive_int  # noqa: E402
from svs_torch.core.camera import SVS_RESOLUTIONS  # noqa: E402
from run_metadata import command_line, output_path, run_metadata, run_script, write_text_whole  # noqa: E402

#: The sizes a board sends, as ``--sizes`` takes them.
BOARD_SIZES = tuple(f"{width}x{height}" for width, height in SVS_RESOLUTIONS.values())


def board_sizes(text: str) -> str:
    """An ``argparse`` type for ``--sizes``: comma-separated sizes a board sends (:data:`BOARD_SIZES`). An audit:
    ``native`` (which the help offered) and ``100x100`` were taken, then ended in a traceback once the emulator had
    started (with ``--frames torch``: "emulator did not start", a RuntimeError)."""
    odd = [size for size in text.split(",") if size not in BOARD_SIZES]
    if odd:
        raise argparse.ArgumentTypeError(f"expected comma-separated sizes a board sends ({', '.join(BOARD_SIZES)}), "
                                         f"got {text!r}")
    return text


def start_emulator(frames: str, sizes: list[str]) -> tuple[subprocess.Popen, dict[str, str]]:
    """Start the emulator process; wait for its JSON line with the URLs (after any keyframe preparation). Ended
    again if this fails or is interrupted: a Ctrl-C as its line came left it serving, unseen, for good (an orphan
    holding this process's stderr), since only the benchmark's runs were in main's ``finally``."""
    cmd = [sys.executable, "-m", "hw.emulator", "--left-port", "0", "--right-port", "0", "--json"]
    cmd += ["--simple-frames"] if frames == "simple" else ["--prepare", ",".join(sizes)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"emulator did not start: {' '.join(cmd)}")
        return proc, json.loads(line)["urls"]
    except BaseException:
        proc.kill()
        proc.wait()
        raise


def bench_size(urls: dict[str, str], size: str, runs: int, pairs: int) -> dict:
    width, height = parse_size(size, "--sizes")
    rates, jpeg_bytes, gaps = [], [], []
    with SVSStereoCamera(urls["left"], urls["right"], (width, height), config=LinkConfig()) as cam:
        cam.grab_pairs(5)  # warm-up: connections, caches
        for _ in range(runs):
            start = time.perf_counter()
            grabbed = cam.grab_pairs(pairs)
            rates.append(pairs / (time.perf_counter() - start))
            jpeg_bytes += [len(f.jpeg) for p in grabbed for f in (p.left, p.right)]
            gaps += [abs(p.time_between_frames_s) * 1e3 for p in grabbed]
        retries = sum(link.stats.retries for link in cam.links.values())
    mean_bytes = statistics.fmean(jpeg_bytes)
    return {
        "size": size, "pairs_per_run": pairs, "runs": runs,
        "pairs_per_s_median": round(statistics.median(rates), 1),
        "pairs_per_s_min": round(min(rates), 1), "pairs_per_s_max": round(max(rates), 1),
        "pairs_per_s_all": [round(r, 1) for r in rates],
        "mean_jpeg_bytes": round(mean_bytes), "retries": retries,
        "time_between_frames_ms_median": round(statistics.median(gaps), 3),
        "uart_2304000_bound_pairs_per_s": round(LinkConfig().bytes_per_s / mean_bytes, 1),
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="320x240,640x480", type=board_sizes,
                        help=f"comma-separated sizes a board sends, of {', '.join(BOARD_SIZES)} (default: %(default)s)")
    parser.add_argument("--runs", type=positive_int, default=5, help="timed runs (default: %(default)s)")
    parser.add_argument("--pairs", type=positive_int, default=50,
                        help="frame pairs read per run (default: %(default)s)")
    parser.add_argument("--frames", choices=("torch", "simple"), default="torch",
                        help="emulator frames: svs_torch's synthetic renderer (keyframes prepared first) or the "
                             "fast stand-in")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads in this process")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE too")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    sizes = args.sizes.split(",")
    proc, urls = start_emulator(args.frames, sizes)
    try:
        results = [bench_size(urls, size, args.runs, args.pairs) for size in sizes]
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    settings = {**vars(args), "json": args.json and str(args.json)}
    report = {"metadata": run_metadata(torch.get_num_threads(), pyserial=serial.__version__, frames=args.frames,
                                       config=settings, link="loopback TCP, emulator in its own process",
                                       command=command_line("experiments/bench_capture.py", argv)),
              "results": results}
    print(json.dumps(report, indent=1))
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    run_script(main)  # a refused input or a Ctrl-C: one line, exit 2 or 130 (a Ctrl-C was a traceback: an audit)
