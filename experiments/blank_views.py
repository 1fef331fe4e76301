"""Is a blank view told from a repeated pattern? (the periodicity test's floors; guide's "Cannot see ahead")

A covered lens, the dark or a plain grey wall gives two flat views; as the board's camera frames, each carries its
sensor's noise through JPEG. Segmentation still keeps two noise regions, and the row autocorrelation of such a small
region (:mod:`svs_torch.depth.periodicity`) can peak by chance over the few dozen pixel pairs it has at a lag: the
pair was then reported as a repeated pattern left unranged, 0.4-0.6 m away by its aliases, guide said "Repeated
pattern ahead. Distance unknown." and, as a pattern counts as something seen, never "Cannot see ahead" (an audit).

Two floors could keep such regions out: a peak counted over 64 pixel pairs or more
(:data:`~svs_torch.depth.periodicity.MIN_PERIOD_PAIRS`, off by default), and only where the image spreads
:data:`~svs_torch.depth.periodicity.MIN_PATTERN_SPREAD` or more over the region (the default). This script measures
each floor alone and both against none, on

- **blank pairs**: flat views at levels 60, 128 and 200, sensor noise σ 2, 4 and 8 (8-bit levels) in each view,
  raw and as camera frames at digits 1, 4 and 8 (:func:`svs_torch.data.camera_frame_pairs`), 4 pairs each, 144
  in all, seeded: pairs reported as a repeated pattern (any would be said aloud in the band, or keep guide from
  saying it cannot see);
- **rendered panels**: the 36 bars, checkers and grates of ``experiments/repeated_patterns.py`` in its eight
  conditions (as rendered, misaligned, camera frames, a loose rig's frames): ranged / wrong / unranged, as that
  script counts them, so that the floors cost no real pattern its alias check.

Rendered data only; no shared scene is read. About 6 minutes on a 2-core machine.

    python experiments/blank_views.py [--seed N] [--json F] [--markdown F]
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import repeated_patterns  # noqa: E402
from run_metadata import command_line, rendered_experiment_setup, report_rows, run_script  # noqa: E402

from svs_torch.core.types import StereoBatch  # noqa: E402
from svs_torch.data import camera_frame_pairs  # noqa: E402
from svs_torch.depth import periodicity  # noqa: E402
from svs_torch.pipeline import estimate_obstacle_depth  # noqa: E402

LEVELS, SIGMAS, DIGITS, PAIRS_EACH = (60, 128, 200), (2.0, 4.0, 8.0), (0, 1, 4, 8), 4
#: The floors measured: (name, fewest pixel pairs, least spread in [0, 1] levels).
FLOORS = (("none (before)", 0, 0.0), ("pairs only", 64, 0.0),
          ("spread only (the default)", periodicity.MIN_PERIOD_PAIRS, periodicity.MIN_PATTERN_SPREAD),
          ("twice the pairs", 128, periodicity.MIN_PATTERN_SPREAD), ("both", 64, periodicity.MIN_PATTERN_SPREAD))
HEIGHT, WIDTH = repeated_patterns.HEIGHT, repeated_patterns.WIDTH


def blank_batches(seed: int) -> list[tuple[str, StereoBatch]]:
    """``(name, batch)`` of every blank condition: ``PAIRS_EACH`` flat pairs, noisy in each view (module
    docstring), each drawn from its own generator seeded from ``seed`` and its place."""
    n, focal = PAIRS_EACH, repeated_patterns.focal_px()
    out = []
    for number, (level, sigma, digit) in enumerate((a, b, c) for a in LEVELS for b in SIGMAS for c in DIGITS):
        generator = torch.Generator().manual_seed(1000 * seed + number)
        flat = torch.full((n, 1, HEIGHT, WIDTH), level / 255)
        batch = StereoBatch(flat, flat.clone(), torch.full((n,), focal), torch.full((n,), repeated_patterns.BASELINE_M),
                            torch.zeros(n), torch.ones(n, dtype=torch.bool), torch.tensor([[HEIGHT, WIDTH]] * n))
        if digit:
            batch = camera_frame_pairs(batch, digit, sigma, generator)
        else:  # raw frames: the sensor's noise alone, as a PNG-grabbing rig would give them
            noisy = [(flat + sigma / 255 * torch.randn(flat.shape, generator=generator)).clamp(0, 1) for _ in "lr"]
            batch = StereoBatch(*noisy, batch.focal_px, batch.baseline_m, batch.doffs_px, batch.calibrated,
                                batch.image_hw)
        out.append((f"level {level}, σ {sigma:g}, " + (f"digit {digit}" if digit else "raw"), batch))
    return out


def blank_rows(floor: str, batches: list[tuple[str, StereoBatch]], config) -> list[dict]:
    rows = []
    for name, batch in batches:
        nearest = estimate_obstacle_depth(batch, config).nearest_unranged_alias_m
        said = [False] * PAIRS_EACH if nearest is None else (~torch.isnan(nearest)).tolist()
        rows += [{"floor": floor, "set": "blank", "condition": name, "said_repeated": s} for s in said]
    return rows


def markdown(rows: list[dict], command: str) -> str:
    lines = [f"`{command}`", "",
             "| floor | blank pairs said to repeat (of 144) | panels ranged / wrong / unranged (of 288) | "
             "camera frames (digit 4, σ 4) | loose rig's camera frames (digit 4) |", "|---|---|---|---|---|"]
    for floor, *_ in FLOORS:
        blank = [r for r in rows if r["floor"] == floor and r["set"] == "blank"]
        panels = [r for r in rows if r["floor"] == floor and r["set"] == "panels"]

        def counts(group: list[dict]) -> str:
            return " / ".join(str(sum(r[k] for r in group)) for k in ("ranged", "wrong", "unranged"))

        frames = [counts([r for r in panels if r["condition"] == c]) for c in (repeated_patterns.CONDITIONS[6][0],
                                                                            repeated_patterns.CONDITIONS[7][0])]
        lines.append(f"| {floor} | {sum(r['said_repeated'] for r in blank)} | {counts(panels)} | {frames[0]} | "
                     f"{frames[1]} |")
    return "\n".join(lines) + "\n"


def _options(parser) -> None:
    parser.add_argument("--seed", type=int, default=0, help="the blank pairs' noise draw (default 0)")


def main(argv: list[str] | None = None) -> dict:
    args, config, _, started = rendered_experiment_setup(__doc__, argv, _options)
    blanks = blank_batches(args.seed)
    lefts, rights, *_ = repeated_patterns.render_pairs()
    panels = [(c[0], repeated_patterns.condition_batch(lefts, rights, *c[1:])) for c in repeated_patterns.CONDITIONS]
    rows, kept = [], (periodicity.MIN_PERIOD_PAIRS, periodicity.MIN_PATTERN_SPREAD)
    try:
        with torch.inference_mode():
            for floor, pairs, spread in FLOORS:
                periodicity.MIN_PERIOD_PAIRS, periodicity.MIN_PATTERN_SPREAD = pairs, spread
                rows += blank_rows(floor, blanks, config)
                for condition, batch in panels:
                    rows += [dict(r, floor=floor, set="panels") for r in
                             repeated_patterns.pipeline_rows(batch, config, floor, condition)]
    finally:
        periodicity.MIN_PERIOD_PAIRS, periodicity.MIN_PATTERN_SPREAD = kept
    command = command_line("experiments/blank_views.py", argv)
    return report_rows(markdown(rows, command), rows, command, args.set, started, args.json, args.markdown)


if __name__ == "__main__":
    run_script(main)
