"""Benchmark: SURF detect + describe per stereo pair at 320×240, svs_torch vs OpenCV SIFT and ORB and kornia's
SIFTFeature, same run.

svs_torch runs on whole batches (B = 1 and B = 32 pairs, i.e. 2B images), eager and compiled, with MATLAB's
defaults and with the upsampled variant; OpenCV and kornia (whose SIFTFeature takes one image at a time) detect and
describe one image at a time. Median of several
runs, min-max spread, thread count recorded; JSON with metadata.

    python experiments/bench_features.py [--threads 2] [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import os

# Idle OpenMP threads that spin while another process holds the cores slow torch 10-30x on a shared machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import sys
from pathlib import Path

import cv2
import torch
from kornia.feature import SIFTFeature

from svs_torch.features.detector import SurfConfig
from svs_torch.features.surf import extract_surf_features

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svs_torch.cli.common import positive_int  # noqa: E402
from run_metadata import add_data_option, output_path, run_metadata, run_script, write_text_whole  # noqa: E402
from bench_segmentation import load_pairs, timed  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads (default: %(default)s)")
    parser.add_argument("--repeats", type=positive_int, default=5,
                        help="timed runs of each; the median is reported (default: %(default)s)")
    parser.add_argument("--max-keypoints", type=positive_int, default=512,
                        help="keypoints per image (default: %(default)s)")
    parser.add_argument("--json", type=output_path, metavar="FILE", help="write the report as JSON to FILE")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    left, right = load_pairs(Path(args.data), 32)
    images = torch.cat([left, right])  # pairs 0..31 left, then their right images
    grays = list((images[:, 0] * 255).round().to(torch.uint8).numpy())
    sift = cv2.SIFT_create(nfeatures=args.max_keypoints)
    orb = cv2.ORB_create(nfeatures=args.max_keypoints)
    results: dict[str, dict] = {}
    for name, detector in (("opencv_sift", sift), ("opencv_orb", orb)):
        results[name] = timed(lambda: [detector.detectAndCompute(g, None) for g in grays], args.repeats, pairs=32)
    # kornia's own detector + descriptor, the torch rival (it was missing from this run: an audit of the benchmarks).
    kornia_sift = SIFTFeature(num_features=args.max_keypoints, upright=True)
    with torch.no_grad():
        results["kornia_sift"] = timed(lambda: [kornia_sift(images[i:i + 1]) for i in range(images.shape[0])],
                                       args.repeats, pairs=32)
    variants = {
        "surf_matlab": SurfConfig(max_keypoints=args.max_keypoints),
        "surf_x2_thr300": SurfConfig(max_keypoints=args.max_keypoints, metric_threshold=300.0, upsample=True),
    }
    for label, config in variants.items():
        for compiled in (False, True):
            cfg = SurfConfig(**{**config.__dict__, "compiled": compiled})
            for b in (1, 32):  # OpenCV's 32 pairs in batches of B (B = 1 timed the first pair alone: an audit)
                batches = [torch.cat([left[i:i + b], right[i:i + b]]) for i in range(0, 32, b)]
                key = f"{label}{'_compiled' if compiled else ''}_B{b}"
                results[key] = timed(lambda: [extract_surf_features(batch, cfg) for batch in batches], args.repeats,
                                     pairs=32)
    sift_ms = results["opencv_sift"]["ms_per_pair"]
    # The ratios printed are the JSON's too, so a script comparing runs reads them rather than working them out.
    ratios = {key: round(value["ms_per_pair"] / sift_ms, 3) for key, value in results.items()}
    print(f"threads {args.threads}, 320x240, detect + describe, median of {args.repeats} runs, ms per pair "
          f"(two images)")
    for key, value in results.items():
        print(f"  {key:34s} {value['ms_per_pair']:8.2f} ms/pair   x SIFT {ratios[key]:5.2f}   "
              f"(run min {value['min_ms']:.1f}, max {value['max_ms']:.1f} ms)")
    if args.json:
        report = {"metadata": run_metadata(args.threads), "results": results, "time_x_opencv_sift": ratios}
        write_text_whole(args.json, json.dumps(report, indent=2))


if __name__ == "__main__":
    run_script(main)
