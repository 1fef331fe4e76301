"""The OpenCV rivals of ``svs-depth bench``: the paper's pipeline as a plain OpenCV loop, run as its own process
so that its whole-process time (start-up, decoding) is measured the way ``svs-depth estimate --pairs`` is.

Per pair, the paper's steps, as the svs_torch default takes them but for its segmentation (the default keeps
what is near in a whole-frame disparity map; the rival keeps Otsu's regions): decode both images, Otsu + 5×5
opening + the two largest regions (the paper's segmentation), SIFT or ORB on the masked images, brute-force
matching with the ratio test 0.8, ``findFundamentalMat`` RANSAC (1 px, 0.99), and ``StereoBM`` (SAD, 9×9
window) over the frame with each kept region's median disparity as its depth; R_min / R_max are the nearest /
farthest region. One JSON line per pair (keypoints, matches, inliers, depths), so the benchmark can check that
the rivals did comparable work.

    python svs_torch/evaluation/bench_rivals.py sift LIST.txt [--focal-px F] [--baseline-m B] [--workers N]

Run it by its path, as the benchmark does: it imports only the standard library, OpenCV and numpy, as a user's
own loop would. Through ``python -m svs_torch.evaluation.bench_rivals`` the ``svs_torch.evaluation`` package, and
so torch, is imported first, in this process and in every worker the pool spawns (which re-imports the main
module): 1.1-1.5 s each that a user's loop does not pay.

``--workers N`` runs the loop on a pool of N processes with one OpenCV thread each, the pairs split into N
contiguous chunks and printed in list order: the strongest loop a user who wants throughput writes (2 processes
on this 2-core machine ran 1.6× the single process for both detectors). The pool uses the ``spawn`` start
method: a ``fork`` after OpenCV has started its thread pool deadlocked every worker here.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

#: The SVS camera at 320×240 (3.6 mm lens on a 4.17 mm wide sensor), scaled with the width like svs_torch does.
SVS_FOCAL_PX_AT_320 = 276.26
SVS_BASELINE_M = 0.1075


def _segment(cv2, np, gray, kernel):
    _, binary = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    opened = cv2.dilate(cv2.erode(binary, kernel), kernel)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    keep = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable")[:2]
    return labels, keep


def run_pair(cv2, np, left_path: str, right_path: str, detector, matcher, stereo, kernel, baseline_m: float,
             focal_px: float | None) -> dict:
    left = cv2.imread(left_path, cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(right_path, cv2.IMREAD_GRAYSCALE)
    if left is None or right is None or left.shape != right.shape:
        return {"status": "BAD_INPUT"}
    focal = focal_px if focal_px else SVS_FOCAL_PX_AT_320 * left.shape[1] / 320
    labels_left, keep_left = _segment(cv2, np, left, kernel)
    labels_right, keep_right = _segment(cv2, np, right, kernel)
    masked_left = np.where(np.isin(labels_left, keep_left), left, 0).astype(np.uint8)
    masked_right = np.where(np.isin(labels_right, keep_right), right, 0).astype(np.uint8)
    kl, dl = detector.detectAndCompute(masked_left, None)
    kr, dr = detector.detectAndCompute(masked_right, None)
    report = {"status": "OK", "keypoints": [len(kl), len(kr)], "matches": 0, "inliers": 0}
    if dl is not None and dr is not None and len(kr) >= 2:
        good = [m[0] for m in matcher.knnMatch(dl, dr, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        report["matches"] = len(good)
        if len(good) >= 8:
            pl = np.float32([kl[m.queryIdx].pt for m in good])
            pr = np.float32([kr[m.trainIdx].pt for m in good])
            _, mask = cv2.findFundamentalMat(pl, pr, cv2.FM_RANSAC, 1.0, 0.99)
            report["inliers"] = 0 if mask is None else int(mask.sum())
    disparity = stereo.compute(left, right).astype(np.float32) / 16.0
    depths = []
    for label in keep_left:
        values = disparity[(labels_left == label) & (disparity > 0)]
        if values.size:
            depths.append(float(focal * baseline_m / np.median(values)))
    report["objects_m"] = depths
    report["r_min_m"] = min(depths) if depths else None
    report["r_max_m"] = max(depths) if depths else None
    return report


def _make_tools(detector_name: str, threads: int):
    import cv2
    import numpy as np

    if threads:
        cv2.setNumThreads(threads)
    detector = cv2.SIFT_create() if detector_name == "sift" else cv2.ORB_create(nfeatures=500)
    matcher = cv2.BFMatcher(cv2.NORM_L2 if detector_name == "sift" else cv2.NORM_HAMMING)
    stereo = cv2.StereoBM_create(numDisparities=64, blockSize=9)
    return cv2, np, detector, matcher, stereo, np.ones((5, 5), np.uint8)


def _run_lines(lines: list[str], detector_name: str, threads: int, baseline_m: float,
               focal_px: float | None) -> list[str]:
    """The JSON lines of the listed pairs, in order (one worker's chunk, or the whole list)."""
    cv2, np, detector, matcher, stereo, kernel = _make_tools(detector_name, threads)
    out = []
    for line in lines:
        parts = line.split()
        if len(parts) < 2:
            continue
        report = run_pair(cv2, np, parts[0], parts[1], detector, matcher, stereo, kernel, baseline_m, focal_px)
        out.append(json.dumps({"left": parts[0], "right": parts[1], **report}) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m svs_torch.evaluation.bench_rivals", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("detector", choices=("sift", "orb"))
    parser.add_argument("pairs", help="a file with one 'LEFT RIGHT' per line")
    parser.add_argument("--focal-px", type=float, help="focal length in pixels (default: the SVS model)")
    parser.add_argument("--baseline-m", type=float, default=SVS_BASELINE_M)
    parser.add_argument("--threads", type=int, default=0, help="cv2.setNumThreads (default 0: OpenCV's choice)")
    parser.add_argument("--workers", type=int, default=0,
                        help="a pool of this many processes, one OpenCV thread each (default 0: this process)")
    args = parser.parse_args(argv)
    with open(args.pairs, encoding="utf-8") as handle:
        lines = handle.read().splitlines()
    os.chdir(os.path.dirname(os.path.abspath(args.pairs)))  # relative paths are the list's, as svs-depth reads them
    if args.workers <= 0:
        sys.stdout.writelines(_run_lines(lines, args.detector, args.threads, args.baseline_m, args.focal_px))
        return 0
    import concurrent.futures
    import multiprocessing

    size = -(-len(lines) // args.workers)
    chunks = [lines[i:i + size] for i in range(0, len(lines), size)] or [[]]
    with concurrent.futures.ProcessPoolExecutor(len(chunks), mp_context=multiprocessing.get_context("spawn")) as pool:
        for out in pool.map(_run_lines, chunks, [args.detector] * len(chunks), [1] * len(chunks),
                            [args.baseline_m] * len(chunks), [args.focal_px] * len(chunks)):
            sys.stdout.writelines(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
