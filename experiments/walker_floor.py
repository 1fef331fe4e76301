"""Is the floor a walker's camera sees taken for the nearest obstacle (issue 32: "for a walker the floor or the road
is not an obstacle")?

Rendered scenes at the SVS's 320×240 (:func:`svs_torch.data.synthetic.render_obstacle_scenes` with its floor, the
SVS camera: 276 px focal length, 10.75 cm baseline), a camera worn at ``H`` metres pitched down ``θ``: a box 0.5 m
wide and 0.8 m tall standing on the floor ``F`` metres ahead, ``X`` metres to one side, a second box 0.8 m wide
2.6 m ahead on the other side, the wall at 4 m. H ∈ {1.2, 1.5}, θ ∈ {10°, 20°, 30°}, F ∈ {1.2, 1.6, 2.0},
X ∈ {−0.4, 0.4}: 36 pairs. The boxes face the camera (the renderer's boxes are upright in the camera's frame), at
the depth of their middle, their foot on the floor. Each pair clean and as the board's camera frames (JPEG digit
4 with sensor noise σ 4, the board's default, and digit 8 with σ 8), seeded.

Per pair

- **nearest**: ``estimate``'s nearest obstacle (the kept object with the smallest median depth) lies within 10 %
  of the near box's true median depth;
- **warned**: ``guide``'s warning distance (that obstacle's 10th depth percentile,
  :attr:`~svs_torch.depth.depth_types.NearestObstacle.surface_m`) does; a warning nearer than 90 % of the box's
  distance is a **false warning** (the floor in front of the box, the nearest surface in view);
- **floor kept**: the share of the kept mask that is floor.

The control: the same scenes without the near box, where any warning nearer than 90 % of the far box's distance is
a false one (the floor, or nothing).

The rival: OpenCV StereoSGBM's disparity through the truth's own procedure (Otsu of the disparity, 5×5 opening, the
two largest regions; its nearest obstacle the smaller median depth of the two: ``eval_segmentation.sgbm_rival``).

``--set KEY=VALUE`` (repeatable) changes the pipeline, e.g. ``--set segmentation.ground=true`` (the floor left out,
:mod:`svs_torch.segmentation.ground_plane`; the default keeps it). Tuning data only (our own renderings). About a
minute with the rival on a 2-core machine.

    python experiments/walker_floor.py [--set KEY=VALUE ...] [--no-rival] [--json F] [--markdown F]
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

from svs_torch.data.synthetic import render_obstacle_scenes  # noqa: E402
from svs_torch.pipeline import PipelineStatus, estimate_obstacle_depth  # noqa: E402

#: The camera's heights (m) and pitches (degrees down); the near box's distances ahead and offsets (m).
HEIGHTS_M, PITCHES_DEG, AHEAD_M, OFFSETS_M = (1.2, 1.5), (10.0, 20.0, 30.0), (1.2, 1.6, 2.0), (-0.4, 0.4)
#: The boxes' widths and heights (near, far) and the far box's distance ahead, metres.
NEAR_BOX_M, FAR_BOX_M, FAR_AHEAD_M = (0.5, 0.8), (0.8, 0.8), 2.6
#: A distance within this share of the truth counts as it.
TOLERANCE = 0.10
SEED = 5


def walker_cases() -> list[tuple[float, float, float, float]]:
    """Every (camera height, pitch, near box ahead, offset)."""
    return [(h, p, f, x) for h in HEIGHTS_M for p in PITCHES_DEG for f in AHEAD_M for x in OFFSETS_M]


def upright_box(height_m: float, pitch_deg: float, ahead_m: float, offset_m: float, size_m: tuple[float, float]):
    """A box standing on the floor ``ahead_m`` ahead, in the pitched camera's frame: the depth and the centre (x, y)
    of its middle and its size, as the renderer's camera-facing rectangle (its foot on the floor)."""
    theta = math.radians(pitch_deg)
    below = height_m - size_m[1] / 2  # its middle's drop below the camera, along the world's vertical
    depth = below * math.sin(theta) + ahead_m * math.cos(theta)
    centre_y = below * math.cos(theta) - ahead_m * math.sin(theta)
    return depth, (offset_m, centre_y), (size_m[0], size_m[1] * math.cos(theta))


def walker_scenes(cases, with_near_box: bool = True):
    """The rendered pairs of ``cases`` (module docstring): a :class:`~svs_torch.data.synthetic.SyntheticScenes`
    per camera (height, pitch), each with its cases' indices."""
    groups = {}
    for i, (h, p, f, x) in enumerate(cases):
        groups.setdefault((h, p), []).append(i)
    out = []
    for (h, p), index in groups.items():
        boxes = [[upright_box(h, p, cases[i][2], cases[i][3], NEAR_BOX_M),
                  upright_box(h, p, FAR_AHEAD_M, -0.6 if cases[i][3] > 0 else 0.6, FAR_BOX_M)] for i in index]
        depth = torch.tensor([[b[0] for b in pair] for pair in boxes])
        centre = torch.tensor([[b[1] for b in pair] for pair in boxes])
        size = torch.tensor([[b[2] for b in pair] for pair in boxes])
        valid = torch.tensor([[with_near_box, True]] * len(index))
        scenes = render_obstacle_scenes(depth, centre, size, valid, floor_height_m=h, camera_pitch_deg=p,
                                        generator=torch.Generator().manual_seed(SEED), texture_contrast=0.5)
        out.append((index, scenes))
    return out


def truth_m(scenes, slot: int) -> torch.Tensor:
    """``(B,)`` the median true depth over box ``slot``'s visible pixels (NaN where unseen)."""
    on = scenes.object_ids == slot + 1
    depth = torch.where(on, scenes.depth_m, math.nan).flatten(1)
    return depth.nanmedian(1).values


def outcome(setting: str, frame: str, case, near_box: bool, truth: float, nearest_m, warning_m,
            floor_kept: float | None) -> dict:
    """One pair's row (module docstring): ``truth`` the near box's distance, or the far box's in the control."""
    h, p, f, x = case
    false = warning_m is not None and warning_m < (1 - TOLERANCE) * truth
    close = (lambda d: d is not None and abs(d - truth) <= TOLERANCE * truth)
    return {"setting": setting, "frame": frame, "height_m": h, "pitch_deg": p, "ahead_m": f, "offset_m": x,
            "near_box": near_box, "truth_m": truth, "nearest_m": nearest_m, "warning_m": warning_m,
            "nearest": near_box and close(nearest_m), "warned": near_box and close(warning_m),
            "false_warning": false, "floor_kept_share": floor_kept}


def pipeline_rows(scenes, index, cases, config, frame: str, setting: str, near_box: bool, batch) -> list[dict]:
    """Each pair's nearest obstacle, warning distance and the floor's share of its kept mask under ``config``."""
    result = estimate_obstacle_depth(batch, config)
    nearest = result.depth.nearest
    kept = result.segmentation.left.kept_mask
    floor_share = (kept & scenes.floor_mask).flatten(1).sum(1) / kept.flatten(1).sum(1).clamp_min(1)
    truth = truth_m(scenes, 0 if near_box else 1)
    rows = []
    for j, i in enumerate(index):
        ok = int(result.status[j]) == PipelineStatus.OK and bool(nearest.valid[j])
        rows.append(outcome(setting, frame, cases[i], near_box, float(truth[j]),
                            float(nearest.depth_m[j]) if ok else None, float(nearest.surface_m[j]) if ok else None,
                            float(floor_share[j])))
    return rows


def rival_rows(scenes, index, cases, frame: str, near_box: bool, batch) -> list[dict]:
    """StereoSGBM's nearest obstacle per pair (module docstring); a loop over pairs, as OpenCV runs."""
    truth = truth_m(scenes, 0 if near_box else 1)
    rows = []
    for j, i in enumerate(index):
        mask, nearest, _ = sgbm_rival(batch.select([j]))
        floor = float((mask & scenes.floor_mask[j:j + 1]).sum() / mask.sum().clamp_min(1))
        rows.append(outcome("OpenCV SGBM", frame, cases[i], near_box, float(truth[j]), nearest, nearest, floor))
    return rows


def markdown(rows: list[dict], command: str) -> str:
    """One line per setting and frame."""
    n = len(walker_cases())
    lines = [f"`{command}`", "",
             f"| setting | frames | nearest is the box (of {n}) | warned of the box (of {n}) | false warnings, box "
             f"there (of {n}) | floor share of the kept mask | without the near box: false warnings (of {n}) |",
             "|---|---|---|---|---|---|---|"]
    for setting, frame in dict.fromkeys((r["setting"], r["frame"]) for r in rows):
        group = [r for r in rows if (r["setting"], r["frame"]) == (setting, frame)]
        there = [r for r in group if r["near_box"]]
        control = [r for r in group if not r["near_box"]]
        shares = [r["floor_kept_share"] for r in there if r["floor_kept_share"] is not None]
        lines.append(f"| {setting} | {frame} | {sum(r['nearest'] for r in there)} | {sum(r['warned'] for r in there)}"
                     f" | {sum(r['false_warning'] for r in there)} | {sum(shares) / max(1, len(shares)):.2f} | "
                     f"{sum(r['false_warning'] for r in control)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    args, config, setting, started = rendered_experiment_setup(__doc__, argv)
    cases = walker_cases()
    rows = []
    for near_box in (True, False):
        for index, scenes in walker_scenes(cases, near_box):
            for frame, digit, sigma in FRAMES:
                batch = as_frames(scenes.batch, digit, sigma)
                rows += pipeline_rows(scenes, index, cases, config, frame, setting, near_box, batch)
                if not args.no_rival:
                    rows += rival_rows(scenes, index, cases, frame, near_box, batch)
    command = command_line("experiments/walker_floor.py", argv)
    order = [f[0] for f in FRAMES]
    table = markdown(sorted(rows, key=lambda r: (r["setting"] == "OpenCV SGBM", order.index(r["frame"]))), command)
    return report_rows(table, rows, command, args.set, started, args.json, args.markdown)


if __name__ == "__main__":
    run_script(main)
