"""When does the sparse stage vouch that both views show one scene? Real pairs against pairs of unrelated views.

Under the dense rule an object is ranged on at least ``DepthConfig.min_object_valid_fraction`` (0.1) of its region
with valid dense disparities where the pair's geometry is *verified*, and on the stricter
``min_object_valid_fraction_unverified`` (0.4) otherwise: views that do not show the same scene (a swapped, frozen
or misconnected camera) still leave up to about a third of a region "consistent" by chance. RANSAC's F alone
vouches badly: 7-point RANSAC fits some F to a dozen chance matches. This script measures the candidate rules on

- **positives**: every shared real pair (at native size, 320 px wide, and squeezed to the SVS's 320×240 as the
  benchmark's real pairs are) and 64 synthetic SVS scenes;
- **negatives**: the left view of one scene with the right view of another (every ordered pair of distinct
  scenes, both at 320×240; duplicates of one scene under another name, such as ArtL / Art or Piano / PianoL,
  are not paired), and each synthetic scene's left view with the next scene's right view.

For every pair it records RANSAC's status and inliers, the matches, the inliers whose disparity the dense map
confirms within one working pixel (:func:`svs_torch.depth.dense_objects.count_agreeing_inliers`) and those at a
pixel it measured at all; each rule's verdict and the objects it lets through are then recomputed from the same run
(the dense map does not depend on the rule). A rule is ``(verify_min_inliers, verify_min_inlier_share,
verify_min_agreeing_inliers, DepthConfig.min_object_valid_fraction_unverified, (verify_many_inliers,
verify_many_inliers_min_agreeing), (verify_unanimous_min_inliers, verify_unanimous_min_agreeing))`` of
:class:`~svs_torch.pipeline.PipelineConfig`;
the first row is the earlier default, and the defaults are one of the rows (``tests/test_experiments.py`` checks).
The fifth: so many RANSAC inliers vouch with only so many confirmed by the dense map (a clipped or noisy view's
dense map confirms few of them; the negatives' most inliers, in the first table, bound it). The last: so many
inliers vouch where the dense map confirms at least so many and every one it measured (a noisy frame's map
measures few windows; None: never).

Choosing the default: positives and negatives from the scenes outside ``paper_table1.py``'s held-out split
(MiddEval3, Middlebury 2001, KITTI, the OpenCV sample, synthetic) decide; the held-out split's are reported
beside them.

    python experiments/verify_views.py [--data DIR] [--json out.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see bench_ransac.py

import argparse
import json
import sys
from pathlib import Path

import torch

from svs_torch.core.camera import SVS_CAMERA
from svs_torch.data import list_shared_pairs, load_stereo_pair, resize_stereo_batch
from svs_torch.data.synthetic import random_obstacle_scenes
from svs_torch.evaluation import with_nominal_calibration
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth
from svs_torch.core.types import StereoBatch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import is_held_out  # noqa: E402
from svs_torch.cli.common import positive_int  # noqa: E402
from run_metadata import (add_data_option, command_line, output_path, run_metadata, run_script,  # noqa: E402
                          scene_limit, write_text_whole)

#: The rules compared: (verify_min_inliers, verify_min_inlier_share, verify_min_agreeing_inliers,
#: DepthConfig.min_object_valid_fraction_unverified, (verify_many_inliers, verify_many_inliers_min_agreeing) or None,
#: (verify_unanimous_min_inliers, verify_unanimous_min_agreeing) or None).
RULES = [(15, 0.5, 0, 0.3, None, None), (10, 0.5, 0, 0.3, None, None), (0, 0.5, 6, 0.3, None, None),
         (0, 0.0, 6, 0.3, None, None), (15, 0.5, 6, 0.3, None, None), (0, 0.5, 4, 0.3, None, None),
         (0, 0.5, 8, 0.3, None, None), (0, 0.5, 6, 0.4, None, None), (0, 0.5, 6, 0.5, None, None),
         (0, 0.5, 6, 1.0, None, None), (0, 0.5, 6, 0.4, (20, 0), None), (0, 0.5, 6, 0.4, (60, 0), None),
         (0, 0.5, 6, 0.4, (40, 1), None), (0, 0.5, 6, 0.4, (60, 1), None), (0, 0.5, 4, 0.4, (60, 1), None),
         (0, 0.5, 5, 0.4, (60, 1), None), (0, 0.5, 5, 0.4, (60, 1), (1, 3)), (0, 0.5, 5, 0.4, (60, 1), (20, 3)),
         (0, 0.5, 5, 0.4, (60, 1), (20, 2))]
#: The same scene under two names (MiddEval3's ArtL is 2005's Art, OpenCV's sample pair is Aloe, ...): never
#: paired as unrelated.
SAME_SCENE = {"ArtL": "Art", "MotorcycleE": "Motorcycle", "PianoL": "Piano", "opencv_samples": "Aloe"}
NEGATIVE_SIZE_WH = (320, 240)
BATCH = 32


def group(path: Path) -> str:
    """``held-out`` for paper_table1.py's held-out split, else ``tuning``."""
    return "held-out" if is_held_out(path) else "tuning"


def record(result, index: int) -> dict:
    """What the rules need of one pair of a pipeline result, and the pipeline's own verdicts under the run's
    configuration (``verified``, ``ranged``: its objects with a depth), which the recomputed rules must give
    for that configuration."""
    objects = result.depth.objects
    # Whether the pair reached the object depths: its status then depends only on which objects are ranged.
    status = int(result.status[index])
    return {"ok": status in (PipelineStatus.OK, PipelineStatus.NO_DENSE_DEPTH),
            "fundamental_ok": int(result.fundamental.status[index]) == 0,
            "inliers": int(result.num_inliers[index]), "matches": int(result.num_matches[index]),
            "agreeing": int(result.num_agreeing_inliers[index]), "measured": int(result.num_measured_inliers[index]),
            "verified": bool(result.verified[index]),
            "ranged": int(objects.valid[index].sum()) if status == PipelineStatus.OK else 0,
            "objects": [{"valid_px": int(objects.num_valid_px[index, n]),
                         "in_view_px": int(objects.num_in_view_px[index, n]), "area_px": int(objects.area_px[index, n])}
                        for n in range(objects.label.shape[1]) if int(objects.label[index, n]) > 0]}


def verified(pair: dict, rule: tuple) -> bool:
    min_inliers, share, agreeing, _, many, unanimous = rule
    return (pair["fundamental_ok"] and pair["inliers"] >= min_inliers and pair["inliers"] >= share * pair["matches"]
            and (pair["agreeing"] >= agreeing
                 or (many is not None and pair["inliers"] >= many[0] and pair["agreeing"] >= many[1])
                 or (unanimous is not None and pair["inliers"] >= unanimous[0] and pair["agreeing"] >= unanimous[1]
                     and pair["agreeing"] == pair["measured"])))


def ranged_objects(pair: dict, rule: tuple, config: PipelineConfig) -> int:
    """The objects the pipeline would range under ``rule`` (dense_object_depths' validity, recomputed)."""
    if not pair["ok"]:
        return 0
    depth = config.depth
    fraction = depth.min_object_valid_fraction if verified(pair, rule) else rule[3]
    fraction = torch.tensor(fraction, dtype=torch.float32)  # as the pipeline compares, in float32
    least_px, least_in_view_px = max(depth.min_object_pixels, 1), depth.min_object_pixels_in_view
    return sum(1 for o in pair["objects"] if o["valid_px"] >= least_px and o["in_view_px"] >= least_in_view_px
               and o["valid_px"] >= float(fraction * o["area_px"]))


def run_batches(lefts: torch.Tensor, rights: torch.Tensor, config: PipelineConfig, label: str) -> list[dict]:
    out = []
    for start in range(0, lefts.shape[0], BATCH):
        print(f"\r{label}: {start}/{lefts.shape[0]}        ", end="", file=sys.stderr, flush=True)
        batch = StereoBatch.from_images(lefts[start:start + BATCH], rights[start:start + BATCH],
                                        SVS_CAMERA.focal_px(lefts.shape[-1]), SVS_CAMERA.baseline_m)
        result = estimate_obstacle_depth(batch, config)
        out += [record(result, i) for i in range(batch.batch_size)]
    print(f"\r{label}: {lefts.shape[0]} pairs        ", file=sys.stderr)
    return out


def collect(data_dir: Path, config: PipelineConfig, limit: int = 0, synthetic: int = 64) -> dict[str, list[dict]]:
    """Pair records by set: ``positive/<group>``, ``negative/<group>`` and the synthetic ones (``limit``: only
    the first shared scenes, 0 all; ``synthetic``: how many synthetic scenes)."""
    paths = list_shared_pairs(data_dir)
    paths = paths[:limit] if limit else paths
    sets: dict[str, list[dict]] = {}
    for number, path in enumerate(paths, start=1):
        print(f"\rpositives: {number}/{len(paths)}        ", end="", file=sys.stderr, flush=True)
        native = with_nominal_calibration(load_stereo_pair(path))
        height, width = native.size_hw
        for batch in (native, resize_stereo_batch(native, (320, round(height * 320 / width))),
                      resize_stereo_batch(native, NEGATIVE_SIZE_WH)):
            result = estimate_obstacle_depth(batch, config)
            sets.setdefault(f"positive/{group(path)}", []).append(record(result, 0))
    print(file=sys.stderr)
    small = [resize_stereo_batch(load_stereo_pair(path), NEGATIVE_SIZE_WH) for path in paths]
    names = [SAME_SCENE.get(path.name, path.name) for path in paths]
    for kind in ("tuning", "held-out"):
        # A negative belongs to the held-out set when either of its views comes from a held-out scene.
        pairs = [(i, j) for i in range(len(paths)) for j in range(len(paths))
                 if names[i] != names[j] and (kind == "held-out") == (group(paths[i]) == "held-out"
                                                                      or group(paths[j]) == "held-out")]
        if not pairs:
            continue
        lefts = torch.cat([small[i].left for i, _ in pairs])
        rights = torch.cat([small[j].right for _, j in pairs])
        sets[f"negative/{kind}"] = run_batches(lefts, rights, config, f"negatives ({kind})")
    scenes = random_obstacle_scenes(synthetic, 2, generator=torch.Generator().manual_seed(2026))
    sets["positive/synthetic"] = run_batches(scenes.batch.left, scenes.batch.right, config, "synthetic positives")
    sets["negative/synthetic"] = run_batches(scenes.batch.left, scenes.batch.right.roll(1, dims=0), config,
                                             "synthetic negatives")
    return sets


def report(sets: dict[str, list[dict]], config: PipelineConfig) -> str:
    lines = ["| set | pairs | agreeing inliers: min / 5th pct / median / 95th pct / max | RANSAC inliers: max |",
             "|---|---|---|---|"]
    for name, pairs in sets.items():
        values = sorted(p["agreeing"] for p in pairs if p["fundamental_ok"]) or [0]
        pct = [values[min(len(values) - 1, int(q * (len(values) - 1)))] for q in (0.0, 0.05, 0.5, 0.95, 1.0)]
        most = max((p["inliers"] for p in pairs if p["fundamental_ok"]), default=0)
        lines.append(f"| {name} | {len(pairs)} (F found: {sum(p['fundamental_ok'] for p in pairs)}) | "
                     + " / ".join(map(str, pct)) + f" | {most} |")
    lines += ["", "| rule (min inliers, share, min agreeing, unverified fraction, (many inliers, min agreeing), "
              "(unanimous inliers, min agreeing)) | " + " | ".join(sets) + " |",
              "|---|" + "---|" * len(sets)]
    for rule in RULES:
        cells = []
        for name, pairs in sets.items():
            v = sum(verified(p, rule) for p in pairs)
            ranged = sum(ranged_objects(p, rule, config) for p in pairs)
            cells.append(f"{v} verified, {ranged} objects ranged")
        lines.append(f"| {rule} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser)
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads (default: %(default)s)")
    parser.add_argument("--limit", type=scene_limit, help="only the first N shared scenes (0: all)")
    parser.add_argument("--synthetic", type=positive_int, default=64,
                        help="synthetic scenes (each a positive and, with the "
                        "next one's right view, a negative)")
    parser.add_argument("--json", type=output_path, metavar="FILE",
                        help="write every pair's record and the run metadata as JSON")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = PipelineConfig()
    sets = collect(Path(args.data), config, args.limit, args.synthetic)
    text = report(sets, config)
    print(text)
    out = {"metadata": run_metadata(args.threads, command=command_line("experiments/verify_views.py", argv),
                                    limit=args.limit, synthetic=args.synthetic), "sets": sets,
           "report": text}
    if args.json:
        write_text_whole(args.json, json.dumps(out))
    return out


if __name__ == "__main__":
    run_script(main)
