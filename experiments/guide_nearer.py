"""``guide``'s warning of a nearer obstacle on another side while ``--repeat-s`` runs
(``WarningPolicy.nearer_elsewhere_m``, ``guide --nearer-elsewhere-m``; issue 32: warn about what is nearest).

Within ``repeat_s`` guide says a warning again only when its class turns more urgent; a person stepping in 0.5 m
nearer, beside an obstacle already warned of, in the same class, was said only when ``repeat_s`` ran out. The rule
tried: say it at once when the confirmed nearest obstacle is on another side than the one last said and at least
``nearer_elsewhere_m`` nearer. Each margin M (``inf``: the rule before) is replayed through guide's own
:class:`svs_torch.capture.guide.WarningPolicy` with each pair's side, on streams ranged as guide ranges them
(``PipelineConfig().for_guide()``, the board's JPEG frames at digit D with their sensor noise, 20 pairs/s):

- **stepping in** (rendered, tuning data): the walker walks at 1.4 m/s toward a box on one side until it is
  ``STAND_M`` away (said on entering the band) and stands; ``STEP_IN_S`` later a second box steps in on the other
  side ``STEP_IN_NEARER_M`` nearer and stays. Scored: the delay from its step to the first message saying its side
  (none within the stream's ``STAND_S``: missed), and the messages (two are due: each box once).
- **chatter** (what the rule may add): ``experiments/guide_confirm.py``'s walks toward one box (tuning data; its
  side may cross a third's edge as it nears) and the shared real scenes held still with the band around their
  distance, where noisy frames may range another of the kept objects nearest: every message after the one due.
  The tuned split chooses; the held-out split is reported.

Run: ``python experiments/guide_nearer.py --markdown experiments/guide_nearer.md`` (about 15 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

from svs_torch.capture.guide import CONFIRM_FRAMES
from svs_torch.cli.progress import Progress
from svs_torch.data import camera_frame_pairs
from svs_torch.data.synthetic import render_obstacle_scenes
from svs_torch.pipeline import PipelineConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from guide_confirm import (PAIRS_PER_S, WALK_FROM_M, WALK_SPEED_M_S, WALL_M, ranged, replay,  # noqa: E402
                           still_rows, walk)
from paper_table1 import split_scenes  # noqa: E402
from real_rig import JPEG_NOISE, jpeg_digit  # noqa: E402
from svs_torch.cli.common import positive_int, seed_int  # noqa: E402
from run_metadata import (add_data_option, check_reports_apart, comma_list, command_line, output_path,  # noqa: E402
                          run_metadata, run_script, write_report)

STAND_M = 1.8  # the first box's distance where the walker stops, metres
STAND_S = 3.0  # seconds of the stream after the walker stops (guide's default repeat_s)
STEP_IN_S = 0.5  # the second box steps in this long after the walker stops, seconds
STEP_IN_NEARER_M = 0.5  # and this much nearer than the first, metres
SIDE_X_M = 0.55  # the boxes' centres this far left or right of the camera's axis, metres (outer thirds of the view)


def step_in(index: int, digit: int, seed: int, config: PipelineConfig) -> dict:
    """One rendered stream (module docstring): the step-in pair's index, the second box's side and guide's view."""
    g = torch.Generator().manual_seed(seed * 10_007 + index + 500_000)
    walking = torch.arange(WALK_FROM_M, STAND_M - 1e-6, -WALK_SPEED_M_S / PAIRS_PER_S)
    standing = int(round(STAND_S * PAIRS_PER_S))
    n, stepped = len(walking) + standing, len(walking) + int(round(STEP_IN_S * PAIRS_PER_S))
    first = torch.cat([walking, torch.full((standing,), STAND_M)])
    depth = torch.stack([first, torch.full((n,), STAND_M - STEP_IN_NEARER_M)], dim=1)
    sign = 1.0 if index % 2 else -1.0  # the first box left, then right, in turn
    centre = torch.tensor([[sign * SIDE_X_M, 0.1], [-sign * SIDE_X_M, 0.1]]).expand(n, 2, 2)
    size = (torch.rand(2, 2, generator=g) * torch.tensor([0.1, 0.6]) + torch.tensor([0.4, 0.6])).expand(n, 2, 2)
    valid = torch.stack([torch.ones(n, dtype=torch.bool), torch.arange(n) >= stepped], dim=1)
    scenes = render_obstacle_scenes(depth, centre, size, valid, background_depth_m=WALL_M,
                                    texture_contrast=(1.0, 0.5)[(index // 2) % 2], generator=g)
    frames = camera_frame_pairs(scenes.batch, digit, dict(JPEG_NOISE)[digit], g)
    seen, sides = ranged(frames, config)
    return {"stepped": stepped, "second_side": "left" if sign > 0 else "right", "seen_m": seen, "seen_side": sides}


def margin_m(text: str) -> float:
    """An ``argparse`` type for a margin M of ``--margins``: metres, 0 or more, or inf."""
    import math

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected metres >= 0 or inf, got {text!r}")
    return value


def score_step_in(streams: list[dict], margin_m: float) -> dict:
    """Delays from the second box's step to a message saying its side, misses, and messages (two are due)."""
    delays, missed, messages = [], 0, 0
    for s in streams:
        steps = replay(s["seen_m"], CONFIRM_FRAMES, seen_side=s["seen_side"], nearer_elsewhere_m=margin_m)
        said = [i for i, (_, message, _) in enumerate(steps) if message is not None]
        messages += len(said)
        side_words = f"on the {s['second_side']}"
        told = next((i for i in said if i >= s["stepped"] and side_words in steps[i][1]), None)
        missed += told is None
        if told is not None:
            delays.append((told - s["stepped"]) * 1000 / PAIRS_PER_S)
    return {"delay_ms_median": statistics.median(delays) if delays else None,
            "delay_ms_max": max(delays, default=None), "missed": missed, "streams": len(streams),
            "messages": messages, "due": 2 * len(streams)}


def chatter_walks(walks: list[dict], margin_m: float) -> dict:
    """Messages said on ``guide_confirm``'s walks toward one box (two are due: entering the band, and "Stop")."""
    said = sum(message is not None for w in walks
               for _, message, _ in replay(w["seen_m"], CONFIRM_FRAMES, seen_side=w["seen_side"],
                                           nearer_elsewhere_m=margin_m))
    return {"messages": said, "due": 2 * len(walks)}


def chatter_still(streams: list[dict], margin_m: float) -> dict:
    """Messages beyond the one due on real scenes held still, the band around each clean distance (as
    ``guide_confirm.score_still``: its far edge 1.25 × the distance, its near edge half that)."""
    extra = said = 0
    for s in streams:
        if s["clean_m"] is None:
            continue
        far_m = s["clean_m"] * 1.25
        steps = replay(s["seen_m"], CONFIRM_FRAMES, near_m=far_m / 2, far_m=far_m, seen_side=s["seen_side"],
                       nearer_elsewhere_m=margin_m)
        count = sum(message is not None for _, message, _ in steps)
        said, extra = said + count, extra + max(0, count - 1)
    return {"messages": said, "messages_after_first": extra}


def markdown(report: dict, command: str) -> str:
    lines = ["# guide's warning of a nearer obstacle on another side (`experiments/guide_nearer.py`)", "",
             f"Made by `{command}`; the module docstring says what is scored. M: `nearer_elsewhere_m`, metres "
             "(inf: the rule before, said again only when `repeat_s` runs out).", "",
             "## A second box steps in 0.5 m nearer on the other side (rendered, tuning data)", "",
             "| digit | M | delay to its side said, ms (median / max) | missed | streams | messages | due |",
             "|---|---|---|---|---|---|---|"]
    for r in report["step_in"]:
        delay = "–" if r["delay_ms_median"] is None else f"{r['delay_ms_median']:.0f} / {r['delay_ms_max']:.0f}"
        lines.append(f"| {r['digit']} | {r['margin_m']} | {delay} | {r['missed']} | {r['streams']} | "
                     f"{r['messages']} | {r['due']} |")
    lines += ["", "## Chatter: walks toward one box (rendered, tuning data)", "",
              "| digit | M | messages | due |", "|---|---|---|---|"]
    lines += [f"| {r['digit']} | {r['margin_m']} | {r['messages']} | {r['due']} |" for r in report["walks"]]
    lines += ["", "## Chatter: real scenes held still at 320×240, the band around their distance", "",
              "| split | digit | M | messages | messages after the first |", "|---|---|---|---|---|"]
    lines += [f"| {r['split']} | {r['digit']} | {r['margin_m']} | {r['messages']} | {r['messages_after_first']} |"
              for r in report["still"]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_option(parser)
    parser.add_argument("--streams", type=positive_int, default=12, help="step-in streams per digit")
    parser.add_argument("--walks", type=positive_int, default=24, help="walks toward one box per digit")
    parser.add_argument("--digits", default="4,6,8", type=comma_list(jpeg_digit, "JPEG digits"),
                        help="the board's JPEG digits (with their sensor noise)")
    parser.add_argument("--frames", type=positive_int, default=24, help="frames of each real scene held still")
    parser.add_argument("--splits", default="tuned,held-out", help="shared splits held still (default: %(default)s)")
    parser.add_argument("--margins", default="inf,0.1,0.2,0.3,0.5", type=comma_list(margin_m, "margins"),
                        help="the M compared, metres")
    parser.add_argument("--seed", type=seed_int, default=0, help="seed of the rendered streams (default: %(default)s)")
    parser.add_argument("--json", type=output_path, help="write the report as JSON to FILE")
    parser.add_argument("--markdown", type=output_path, help="write the tables as Markdown to FILE")
    args = parser.parse_args(argv)
    check_reports_apart(parser, args)
    known = list(split_scenes(Path(args.data)))
    splits = [s for s in args.splits.split(",") if s]
    if set(splits) - set(known):
        parser.error(f"--splits: expected among {', '.join(known)}, got {args.splits}")
    config = PipelineConfig().for_guide()
    digits, margins = [int(d) for d in args.digits.split(",")], [float(m) for m in args.margins.split(",")]
    command = command_line("experiments/guide_nearer.py", argv or None)
    report = {"metadata": run_metadata(torch.get_num_threads(), command=command, seed=args.seed, streams=args.streams,
                                       walks=args.walks, frames=args.frames), "step_in": [], "walks": [], "still": []}
    with Progress(len(digits) * (args.streams + args.walks + len(splits)), "guide_nearer", unit="stream") as progress:
        for digit in digits:
            streams = [step_in(i, digit, args.seed, config) for i in range(args.streams)]
            progress.update(args.streams)
            walks = [walk(i, digit, args.seed, config) for i in range(args.walks)]
            progress.update(args.walks)
            for m in margins:
                report["step_in"].append(dict(digit=digit, margin_m=m, **score_step_in(streams, m)))
                report["walks"].append(dict(digit=digit, margin_m=m, **chatter_walks(walks, m)))
            for split in splits:
                report["still"] += still_rows(split, digit, args.frames, config, Path(args.data), "margin_m",
                                              margins, chatter_still)
                progress.update()
    text = markdown(report, command_line("experiments/guide_nearer.py", argv or None))
    print(text)
    write_report(report, text, args.json, args.markdown)
    return report


if __name__ == "__main__":
    run_script(main)
