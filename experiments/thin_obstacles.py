"""Is a thin near pole warned of (issue 32, item 2: a small near obstacle is never dropped for a large far one)?

Rendered scenes at the SVS's 320×240 (:func:`svs_torch.data.synthetic.render_obstacle_scenes`, the SVS camera:
276 px focal length, 10.75 cm baseline): a pole 1.6 m tall and ``W`` wide at ``Z`` metres, ``X`` metres off the
optical axis, with a 0.8 × 0.8 m box at 2.4 m on the other side and the wall at 4 m; every surface at half the
default texture contrast. W ∈ {2, 3, 5, 8} cm (3.5 to 18 px at 1.6 m), Z ∈ {1.2, 1.6, 2.0} m, X ∈ {−0.3, −0.1,
0.1, 0.3} m: 48 pairs, the pole at X = 0.1 m standing just in front of the box's edge in the image. Each pair
clean and as the board's camera frames (:func:`svs_torch.data.camera_frames`: JPEG digit 4 with sensor noise σ 4,
the board's default, and digit 8 with σ 8), seeded.

Per pair the pole counts as

- **nearest** where ``estimate``'s nearest obstacle (the kept object with the smallest median depth) lies within
  10 % of the pole's distance;
- **warned** where ``guide``'s warning distance (that obstacle's nearest visible surface, its 10th depth
  percentile: :attr:`~svs_torch.depth.depth_types.NearestObstacle.surface_m`) does: a pole in front of the box may
  be kept as one region with it, whose median is the box's but whose near surface is the pole's.

The control: the same 48 pairs without the pole (the box, the wall and their textures unchanged), where a warning
nearer than 90 % of the box's distance is a false one: what keeping smaller regions could cost.

The rival: OpenCV StereoSGBM's disparity through the truth's own procedure (Otsu of the disparity, 5×5 opening, the
two largest regions; its nearest obstacle the smaller median depth of the two: ``eval_segmentation.sgbm_rival``).

``--min-area`` runs the default pipeline at each least area (``SegmentationConfig.min_area_fraction``, a share
of the image) in turn: what the default's 0.3 % was checked on (experiments/thin_obstacles.md). Tuning data only
(our own renderings). About 25 s with the rival on a 2-core machine, 15 s more for each further least area.

    python experiments/thin_obstacles.py [--min-area 0.003,0.01] [--set KEY=VALUE ...] [--no-rival]
                                         [--json F] [--markdown F]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_segmentation import sgbm_rival  # noqa: E402
from run_metadata import (add_rendered_experiment_options, check_reports_apart, command_line, report_rows,  # noqa: E402
                          run_script)

from svs_torch.core.errors import InputError  # noqa: E402
from svs_torch.data import camera_frame_pairs  # noqa: E402
from svs_torch.data.synthetic import render_obstacle_scenes  # noqa: E402
from svs_torch.evaluation.overrides import apply_overrides, parse_assignment  # noqa: E402
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth  # noqa: E402

#: The poles (module docstring): widths and distances in metres, offsets from the optical axis in metres.
POLE_WIDTHS_M, POLE_DEPTHS_M, POLE_OFFSETS_M = (0.02, 0.03, 0.05, 0.08), (1.2, 1.6, 2.0), (-0.3, -0.1, 0.1, 0.3)
#: The pole's height, the box's side, distance and centre's offset from the axis (on the pole's other side), metres.
POLE_HEIGHT_M, BOX_SIDE_M, BOX_DEPTH_M, BOX_OFFSET_M = 1.6, 0.8, 2.4, 0.45
#: A distance within this share of the pole's counts as the pole.
TOLERANCE = 0.10
#: The frames: name, JPEG digit (0: the clean pair) and sensor noise in 8-bit levels.
FRAMES = (("clean", 0, 0.0), ("jpeg q4 + noise s4", 4, 4.0), ("jpeg q8 + noise s8", 8, 8.0))
SEED = 3


def pole_cases() -> list[tuple[float, float, float]]:
    """Every (width, distance, offset) of the poles, metres."""
    return [(w, z, x) for w in POLE_WIDTHS_M for z in POLE_DEPTHS_M for x in POLE_OFFSETS_M]


def pole_scenes(cases: list[tuple[float, float, float]], with_pole: bool = True):
    """One rendered pair per case (module docstring), a :class:`~svs_torch.core.types.StereoBatch`; without the
    pole (the control: the same box, wall and textures) where ``with_pole`` is False."""
    depth = torch.tensor([[z, BOX_DEPTH_M] for (_, z, _) in cases])
    centre = torch.tensor([[[x, 0.0], [-BOX_OFFSET_M if x > 0 else BOX_OFFSET_M, 0.1]] for (_, _, x) in cases])
    size = torch.tensor([[[w, POLE_HEIGHT_M], [BOX_SIDE_M, BOX_SIDE_M]] for (w, _, _) in cases])
    valid = torch.tensor([[with_pole, True]] * len(cases))
    return render_obstacle_scenes(depth, centre, size, valid, generator=torch.Generator().manual_seed(SEED),
                                  texture_contrast=0.5).batch


def as_frames(batch, digit: int, sigma_levels: float):
    """``batch`` as the board's frames at JPEG ``digit`` with sensor noise (0: unchanged)."""
    if digit == 0:
        return batch
    return camera_frame_pairs(batch, digit, sigma_levels, torch.Generator().manual_seed(SEED + digit))


def is_pole(distance_m: float | None, pole_m: float) -> bool:
    return distance_m is not None and abs(distance_m - pole_m) <= TOLERANCE * pole_m


def outcome(setting: str, frame: str, case: tuple[float, float, float], pole: bool, nearest_m: float | None,
            warning_m: float | None) -> dict:
    """One pair's row: with the pole, whether it was found; without it, whether a warning came nearer than the
    box (a false warning)."""
    w, z, x = case
    found = pole and is_pole(warning_m, z)
    false = not pole and warning_m is not None and warning_m < (1 - TOLERANCE) * BOX_DEPTH_M
    return {"setting": setting, "frame": frame, "width_m": w, "depth_m": z, "offset_m": x, "pole": pole,
            "nearest_m": nearest_m, "warning_m": warning_m, "nearest": pole and is_pole(nearest_m, z),
            "warned": found, "false_warning": false}


def pipeline_rows(batch, config: PipelineConfig, cases, frame: str, setting: str, pole: bool) -> list[dict]:
    """Each pair's nearest obstacle and warning distance under ``config``."""
    result = estimate_obstacle_depth(batch, config)
    nearest = result.depth.nearest
    rows = []
    for i, case in enumerate(cases):
        ok = int(result.status[i]) == PipelineStatus.OK and bool(nearest.valid[i])
        median = float(nearest.depth_m[i]) if ok else None
        surface = float(nearest.surface_m[i]) if ok else None
        rows.append(outcome(setting, frame, case, pole, median, surface))
    return rows


def rival_rows(batch, cases, frame: str, pole: bool) -> list[dict]:
    """StereoSGBM's nearest obstacle per pair (module docstring); a loop over pairs, as OpenCV runs."""
    rows = []
    for i, case in enumerate(cases):
        _, nearest, _ = sgbm_rival(batch.select([i]))
        rows.append(outcome("OpenCV SGBM", frame, case, pole, nearest, nearest))
    return rows


def markdown(rows: list[dict], command: str) -> str:
    """One line per setting and frame: poles found nearest and warned of, by width."""
    lines = [f"`{command}`", "",
             "| setting | frames | nearest (of 48) | warned (of 48) | "
             + " | ".join(f"warned, {100 * w:.0f} cm (of 12)" for w in POLE_WIDTHS_M)
             + " | without the pole: warned nearer than the box (of 48) |",
             "|---|---|---|---|---|" + "---|" * len(POLE_WIDTHS_M)]
    keys = list(dict.fromkeys((r["setting"], r["frame"]) for r in rows))
    for setting, frame in keys:
        group = [r for r in rows if (r["setting"], r["frame"]) == (setting, frame)]
        widths = [sum(r["warned"] for r in group if r["width_m"] == w) for w in POLE_WIDTHS_M]
        lines.append(f"| {setting} | {frame} | {sum(r['nearest'] for r in group)} | "
                     f"{sum(r['warned'] for r in group)} | " + " | ".join(str(n) for n in widths)
                     + f" | {sum(r['false_warning'] for r in group)} |")
    return "\n".join(lines) + "\n"


def pipeline_settings(assignments: list[str], min_areas: str | None) -> dict[str, PipelineConfig]:
    """The configurations to run by name: the default with ``--set``'s ``assignments``, or one per least area of
    ``min_areas`` (comma-separated shares of the image) over it."""
    base = apply_overrides(PipelineConfig(), dict(parse_assignment(text) for text in assignments))
    if min_areas is None:
        return {"default": base}
    try:
        areas = [float(a) for a in min_areas.split(",")]
    except ValueError:
        raise ValueError(f"--min-area: expected comma-separated shares of the image, got {min_areas!r}") from None
    return {f"least area {a:g}": apply_overrides(base, {"segmentation.min_area_fraction": a}, "--min-area")
            for a in areas}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--min-area", default=None,
                        help="comma-separated least areas (shares of the image) to run in turn (default: the "
                             "pipeline's)")
    add_rendered_experiment_options(parser)
    args = parser.parse_args(argv)
    check_reports_apart(parser, args)
    try:
        settings = pipeline_settings(args.set, args.min_area)
    except (InputError, ValueError) as error:
        parser.error(str(error))
    started = time.perf_counter()
    cases = pole_cases()
    rows = []
    for pole in (True, False):
        scenes = pole_scenes(cases, with_pole=pole)
        for frame, digit, sigma in FRAMES:
            batch = as_frames(scenes, digit, sigma)
            for setting, config in settings.items():
                rows += pipeline_rows(batch, config, cases, frame, setting, pole)
            if not args.no_rival:
                rows += rival_rows(batch, cases, frame, pole)
    command = command_line("experiments/thin_obstacles.py", argv)
    table = markdown(sorted(rows, key=lambda r: (r["setting"], [f[0] for f in FRAMES].index(r["frame"]))), command)
    return report_rows(table, rows, command, args.set, started, args.json, args.markdown)


if __name__ == "__main__":
    run_script(main)
