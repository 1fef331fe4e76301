"""Is a heap on the floor (a pile of rocks or rubble: one continuous rough surface) still warned of when the floor is
left out (``--floor on``, guide's default)? The held-out Middlebury heaps seen from above read as a floor
(experiments/walker_floor.md); the renderer's boxes could not reproduce that, these heaps are its tuning data.

Rendered SVS pairs at 320×240 (:func:`svs_torch.data.synthetic.render_obstacle_scenes` with ``heaps``), a camera
worn at ``H`` metres pitched down ``θ`` over a textured floor:

- **walker**: a heap of radius 0.45 m and 0.35 m high, rocks of 5 cm on it, ``F`` metres ahead and ``X`` to one
  side, an 0.8 m box 2.6 m ahead on the other side, the wall at 4 m. H ∈ {1.2, 1.5}, θ ∈ {10°, 20°, 30°},
  F ∈ {1.2, 1.6, 2.0}, X ∈ {−0.3, 0.3}: 36 pairs.
- **filling**: a heap of radius 1 m and 0.5 m high right ahead (F ∈ {1.2, 1.5}), under a camera pitched 30° or 35°
  at H ∈ {1.0, 1.3}, X ∈ {−0.2, 0.2}: 16 pairs whose lower view is mostly heap, the held-out scenes' case.
- **bed**: a low wide mound, 1.4 m in radius and 0.15 m high (rubble the walker stands at), F ∈ {1.4, 1.8}, under the
  same cameras: 16 pairs whose lower view is a rough surface nearly flat, which a plane holds in part.

Each pair clean and as the board's camera frames (JPEG digit 4 with noise σ 4, digit 8 with σ 8), seeded. Per pair:
**nearest**: ``estimate``'s nearest obstacle (smallest median depth) lies within 10 % of the heap's true median
depth; **warned**: ``guide``'s warning distance (that obstacle's 10th depth percentile) within 10 % of the heap's
true 10th percentile; a warning nearer than 90 % of it is a **false warning** (the floor in front); **kept**: the
share of the heap's pixels in the kept mask. The rival: OpenCV StereoSGBM through the truth procedure
(``eval_segmentation.sgbm_rival``), its nearest obstacle the warning too.

``--set KEY=VALUE`` changes the pipeline (``--set segmentation.ground=true``: the floor left out). Tuning data only
(our own renderings). About three minutes with the rival on a 2-core machine.

    python experiments/walker_heaps.py [--set KEY=VALUE ...] [--no-rival] [--json F] [--markdown F]
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_segmentation import sgbm_rival  # noqa: E402
from run_metadata import command_line, rendered_experiment_setup, report_rows, run_script  # noqa: E402
from thin_obstacles import FRAMES, as_frames  # noqa: E402
from walker_floor import FAR_AHEAD_M, FAR_BOX_M, upright_box  # noqa: E402

from svs_torch.data.heap_rendering import WALKER_HEAP_HEIGHT_M, WALKER_HEAP_RADIUS_M  # noqa: E402
from svs_torch.data.synthetic import render_obstacle_scenes  # noqa: E402
from svs_torch.pipeline import PipelineStatus, estimate_obstacle_depth  # noqa: E402

#: (kind, camera height m, pitch degrees, heap ahead m, offset m, radius m, height m) of every pair.
WALKER = [("walker", h, p, f, x, WALKER_HEAP_RADIUS_M, WALKER_HEAP_HEIGHT_M) for h in (1.2, 1.5)
          for p in (10.0, 20.0, 30.0) for f in (1.2, 1.6, 2.0) for x in (-0.3, 0.3)]
FILLING = [("filling", h, p, f, x, 1.0, 0.5) for h in (1.0, 1.3) for p in (30.0, 35.0) for f in (1.2, 1.5)
           for x in (-0.2, 0.2)]
BED = [("bed", h, p, f, x, 1.4, 0.15) for h in (1.0, 1.3) for p in (30.0, 35.0) for f in (1.4, 1.8)
       for x in (-0.2, 0.2)]
ROCKS_M = 0.05
TOLERANCE = 0.10
SEED = 7
#: A heap counts where it covers at least this share of the left view.
IN_VIEW = 0.005


def heap_scenes(cases):
    """The rendered pairs of ``cases``: a :class:`~svs_torch.data.synthetic.SyntheticScenes` per camera (height,
    pitch), each with its cases' indices."""
    groups = {}
    for i, case in enumerate(cases):
        groups.setdefault(case[1:3], []).append(i)
    out = []
    for (h, p), index in groups.items():
        boxes = [upright_box(h, p, FAR_AHEAD_M, -0.6 if cases[i][4] > 0 else 0.6, FAR_BOX_M) for i in index]
        heaps = torch.tensor([[cases[i][4], cases[i][3], cases[i][5], cases[i][6]] for i in index])
        scenes = render_obstacle_scenes(torch.tensor([[b[0]] for b in boxes]), torch.tensor([[b[1]] for b in boxes]),
                                        torch.tensor([[b[2]] for b in boxes]), floor_height_m=h, camera_pitch_deg=p,
                                        heaps=heaps, heap_roughness_m=ROCKS_M, texture_contrast=0.5,
                                        generator=torch.Generator().manual_seed(SEED))
        out.append((index, scenes))
    return out


def heap_truth(scenes) -> list[tuple[float, float, float]]:
    """Each heap's median and 10th-percentile true depth over its visible pixels (metres), and its share of the
    left view."""
    depth = torch.where(scenes.heap_mask, scenes.depth_m, math.nan).flatten(1)
    seen = scenes.heap_mask.flatten(1).float().mean(1)
    return list(zip(depth.nanmedian(1).values.tolist(), depth.nanquantile(0.1, dim=1).tolist(), seen.tolist()))


def outcome(setting: str, frame: str, case, truth: tuple[float, float, float], nearest_m, warning_m, kept) -> dict:
    """One pair's row (module docstring); ``truth``: the heap's median and low depth, and its share of the view."""
    median_m, low_m, seen = truth
    close = (lambda d, truth: d is not None and abs(d - truth) <= TOLERANCE * truth)
    return {"setting": setting, "frame": frame, "kind": case[0], "height_m": case[1], "pitch_deg": case[2],
            "ahead_m": case[3], "offset_m": case[4], "truth_median_m": median_m, "truth_low_m": low_m,
            "nearest_m": nearest_m, "warning_m": warning_m, "nearest": close(nearest_m, median_m),
            "warned": close(warning_m, low_m),
            "false_warning": warning_m is not None and warning_m < (1 - TOLERANCE) * low_m, "heap_kept": kept,
            "heap_view_share": seen}


def pipeline_rows(scenes, index, cases, config, frame: str, setting: str, batch) -> list[dict]:
    result = estimate_obstacle_depth(batch, config)
    nearest, kept = result.depth.nearest, result.segmentation.left.kept_mask
    share = (kept & scenes.heap_mask).flatten(1).sum(1) / scenes.heap_mask.flatten(1).sum(1).clamp_min(1)
    truth = heap_truth(scenes)
    rows = []
    for j, i in enumerate(index):
        ok = int(result.status[j]) == PipelineStatus.OK and bool(nearest.valid[j])
        rows.append(outcome(setting, frame, cases[i], truth[j],
                            float(nearest.depth_m[j]) if ok else None, float(nearest.surface_m[j]) if ok else None,
                            float(share[j])))
    return rows


def rival_rows(scenes, index, cases, frame: str, batch) -> list[dict]:
    """StereoSGBM's nearest obstacle per pair; a loop over pairs, as OpenCV runs."""
    truth = heap_truth(scenes)
    rows = []
    for j, i in enumerate(index):
        mask, nearest, _ = sgbm_rival(batch.select([j]))
        kept = float((mask & scenes.heap_mask[j:j + 1]).sum() / scenes.heap_mask[j:j + 1].sum().clamp_min(1))
        rows.append(outcome("OpenCV SGBM", frame, cases[i], truth[j], nearest, nearest, kept))
    return rows


def markdown(rows: list[dict], command: str) -> str:
    """One line per setting, frame and kind of heap, over the pairs whose heap is in view."""
    lines = [f"`{command}`", "", f"Pairs whose heap covers at least {IN_VIEW:.1%} of the left view (the others: "
             "below the frame under a camera pitched 10°).", "",
             "| setting | frames | heaps | nearest is the heap | warned of the heap | false warnings | "
             "heap share kept |", "|---|---|---|---|---|---|---|"]
    for setting, frame, kind in dict.fromkeys((r["setting"], r["frame"], r["kind"]) for r in rows):
        group = [r for r in rows if (r["setting"], r["frame"], r["kind"]) == (setting, frame, kind)
                 and r["heap_view_share"] >= IN_VIEW]
        n = len(group)
        lines.append(f"| {setting} | {frame} | {kind} | {sum(r['nearest'] for r in group)} of {n} | "
                     f"{sum(r['warned'] for r in group)} of {n} | {sum(r['false_warning'] for r in group)} | "
                     f"{sum(r['heap_kept'] for r in group) / n:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    args, config, setting, started = rendered_experiment_setup(__doc__, argv)
    cases = WALKER + FILLING + BED
    rows = []
    for index, scenes in heap_scenes(cases):
        for frame, digit, sigma in FRAMES:
            batch = as_frames(scenes.batch, digit, sigma)
            rows += pipeline_rows(scenes, index, cases, config, frame, setting, batch)
            if not args.no_rival:
                rows += rival_rows(scenes, index, cases, frame, batch)
    command = command_line("experiments/walker_heaps.py", argv)
    order = [f[0] for f in FRAMES]
    kinds = ("walker", "filling", "bed")
    key = (lambda r: (r["setting"] == "OpenCV SGBM", order.index(r["frame"]), kinds.index(r["kind"])))
    table = markdown(sorted(rows, key=key), command)
    return report_rows(table, rows, command, args.set, started, args.json, args.markdown)


if __name__ == "__main__":
    run_script(main)
