"""``guide``'s warnings on a stream of camera frames: each pair's own distance against the median of the last N
(``WarningPolicy.confirm_frames``, ``guide --confirm-frames``; issue 33: the board sends noisy JPEG frames).

Every stream is ranged as guide ranges it (``PipelineConfig().for_guide()``: the camera's frames, the floor left
out, both second passes; one pair's result does not depend on its batch, so a stream is ranged as one batch) and
its per-pair distances (the nearest object's nearest visible surface, ``surface_m``) are replayed through guide's
own rule (:class:`svs_torch.capture.guide.WarningPolicy`) for each N, at 20 pairs/s:

- **walks** (rendered, tuning data): the camera walks at 1.4 m/s toward a 0.4–0.7 × 0.6–1.2 m box from 3.3 m to
  0.7 m (7 cm a pair), a wall 4.5 m away behind it; texture contrast 1 and 0.5 in turn; each pair the board's
  camera frames at JPEG digit D with its sensor noise, drawn anew for every pair and view. Scored over the walks:
  the delay from the pair on which the box's front comes within the band's far edge (2 m) to the first on which
  the rule's class is a warning (entering it speaks), and from the near edge (1 m) to "Stop"; false warnings (a
  message while the box is more than 0.2 m beyond the band); messages whose distance is off the box's by more
  than 10 %; pairs silenced (once warned, the box 0.2 m or more inside the band but the class clear).
- **held still** (the shared real scenes): K camera frames of one pair, each with its own noise, the band moved
  so that the clean pair's distance lies 15 % beyond its far edge (near edge at half the far one): every message
  is false; and moved so that the distance lies inside it (far edge 25 % beyond it): one warning is due, and
  every further message (the class left and entered again: chatter) and every pair judged clear after it (a
  warning silenced) is scored. The tuned split chooses; the held-out split is reported.

Run: ``python experiments/guide_confirm.py --markdown experiments/guide_confirm.md`` (about 3.5 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

from svs_torch.capture.guide import NEARER_ELSEWHERE_M, STOP, WARN, WarningPolicy
from svs_torch.cli.progress import Progress
from svs_torch.data import camera_frame_pairs
from svs_torch.data.synthetic import render_obstacle_scenes
from svs_torch.depth import ObstacleSide
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_table1 import load_scene, resample, split_scenes  # noqa: E402
from real_rig import JPEG_NOISE, jpeg_digit  # noqa: E402
from svs_torch.cli.common import positive_int, seed_int  # noqa: E402
from run_metadata import (add_data_option, check_reports_apart, comma_list, command_line, output_path,  # noqa: E402
                          run_metadata, run_script, write_report)

PAIRS_PER_S = 20.0
WALK_SPEED_M_S = 1.4
WALK_FROM_M, WALK_TO_M, WALL_M = 3.3, 0.7, 4.5
FALSE_MARGIN_M = 0.2  # a message while the box is farther than the band's far edge plus this is false
WRONG_SHARE = 0.1  # a message whose distance is off the box's by more than this share is wrong
SILENCED_MARGIN_M = 0.2  # a pair whose box is this far inside the band but judged clear silences the warning
STILL_BEYOND = 1.15  # held still: the clean pair's distance lies this factor beyond the band's far edge
STILL_INSIDE = 1.25  # held still, in the band: its far edge lies this factor beyond the clean pair's distance


def distances(batch, config: PipelineConfig) -> list[float | None]:
    """guide's distance of each pair of ``batch`` (None: no obstacle ranged)."""
    return ranged(batch, config)[0]


def ranged(batch, config: PipelineConfig) -> tuple[list[float | None], list[str | None]]:
    """guide's distance of each pair of ``batch`` (None: no obstacle ranged) and the side guide says with it."""
    with torch.inference_mode():
        nearest = estimate_obstacle_depth(batch, config).depth.nearest
    seen = [float(nearest.surface_m[i]) if bool(nearest.valid[i]) else None for i in range(batch.batch_size)]
    sides = [ObstacleSide(int(nearest.side[i])).name.lower() if seen[i] is not None else None
             for i in range(batch.batch_size)]
    return seen, sides


def walk(index: int, digit: int, seed: int, config: PipelineConfig) -> dict:
    """One rendered walk (module docstring) as the board's frames at ``digit``: the box's distance and guide's."""
    g = torch.Generator().manual_seed(seed * 10_007 + index)
    n = int(round((WALK_FROM_M - WALK_TO_M) / (WALK_SPEED_M_S / PAIRS_PER_S))) + 1
    depth = torch.linspace(WALK_FROM_M, WALK_TO_M, n).view(n, 1)
    x_m, width_m, height_m = (float(v) for v in (torch.rand(3, generator=g) * torch.tensor([0.6, 0.3, 0.6])
                                                + torch.tensor([-0.3, 0.4, 0.6])))
    scenes = render_obstacle_scenes(depth, torch.tensor([x_m, 0.1]).expand(n, 1, 2),
                                    torch.tensor([width_m, height_m]).expand(n, 1, 2), background_depth_m=WALL_M,
                                    texture_contrast=(1.0, 0.5)[index % 2], generator=g)
    frames = camera_frame_pairs(scenes.batch, digit, dict(JPEG_NOISE)[digit], g)
    seen, sides = ranged(frames, config)
    return {"truth_m": depth.flatten().tolist(), "seen_m": seen, "seen_side": sides}


def replay(seen_m: list[float | None], confirm_frames: int, near_m: float = 1.0, far_m: float = 2.0,
           seen_side: list[str | None] | None = None, nearer_elsewhere_m: float = NEARER_ELSEWHERE_M
           ) -> list[tuple[str, str | None, float | None]]:
    """Each pair's (class, message, confirmed distance) under guide's rule, pairs ``1 / PAIRS_PER_S`` apart (with
    each pair's side where ``seen_side`` is given, as guide passes it)."""
    policy = WarningPolicy(near_m=near_m, far_m=far_m, confirm_frames=confirm_frames,
                           nearer_elsewhere_m=nearer_elsewhere_m)
    sides = seen_side or [None] * len(seen_m)
    out = []
    for i, (distance, side) in enumerate(zip(seen_m, sides)):
        message = policy.update(distance, i / PAIRS_PER_S, side)
        out.append((policy.current, message, policy.confirmed_m))
    return out


def score_walks(walks: list[dict], confirm_frames: int) -> dict:
    """The walks' delays, misses, false or wrong messages and silenced pairs under ``confirm_frames`` (module
    docstring)."""
    warn_ms, stop_ms, missed, false, wrong, said, silenced = [], [], 0, 0, 0, 0, 0
    for w in walks:
        truth, steps = w["truth_m"], replay(w["seen_m"], confirm_frames)
        enters = next(i for i, t in enumerate(truth) if t <= 2.0)
        urgent = next(i for i, t in enumerate(truth) if t < 1.0)
        # Warned from the first pair on which the class is warn or stop: entering it always speaks (a warning
        # said just before the box came within the band, and kept, counts as no delay).
        warned = next((i for i in range(enters, len(steps)) if steps[i][0] in (WARN, STOP)), None)
        stopped = next((i for i in range(urgent, len(steps)) if steps[i][0] == STOP), None)
        missed += warned is None or stopped is None
        if warned is not None:
            warn_ms.append((warned - enters) * 1000 / PAIRS_PER_S)
            # Once warned, a pair whose box is well inside the band but judged clear silences the warning.
            silenced += sum(t < 2.0 - SILENCED_MARGIN_M and c not in (WARN, STOP)
                            for t, (c, _, _) in zip(truth[warned:], steps[warned:]))
        if stopped is not None:
            stop_ms.append((stopped - urgent) * 1000 / PAIRS_PER_S)
        for t, (_, message, d) in zip(truth, steps):
            said += message is not None
            false += message is not None and t > 2.0 + FALSE_MARGIN_M
            wrong += message is not None and d is not None and abs(d - t) / t > WRONG_SHARE
    return {"warn_delay_ms_median": statistics.median(warn_ms) if warn_ms else None,
            "warn_delay_ms_max": max(warn_ms, default=None), "stop_delay_ms_median":
            statistics.median(stop_ms) if stop_ms else None, "stop_delay_ms_max": max(stop_ms, default=None),
            "missed": missed, "false_messages": false, "wrong_distance_messages": wrong, "messages": said,
            "silenced_pairs": silenced}


def still_streams(split: str, digit: int, frames: int, config: PipelineConfig, data: Path) -> list[dict]:
    """Each scene of ``split`` at 320×240 held still: the clean pair's distance and ``frames`` camera frames'."""
    out = []
    for index, path in enumerate(split_scenes(data)[split]):
        batch = resample(load_scene(path), "320")
        clean = distances(batch, config)[0]
        stream = camera_frame_pairs(batch.select(torch.zeros(frames, dtype=torch.long)), digit,
                                    dict(JPEG_NOISE)[digit], torch.Generator().manual_seed(1000 * digit + index))
        seen, sides = ranged(stream, config)
        out.append({"scene": path.name, "clean_m": clean, "seen_m": seen, "seen_side": sides})
    return out


def still_rows(split: str, digit: int, frames: int, config: PipelineConfig, data: Path, setting: str,
               values: list, score) -> list[dict]:
    """The rows of ``split``'s scenes held still at ``digit`` (:func:`still_streams`), one per value of ``setting``
    (``score(streams, value)``'s columns)."""
    streams = still_streams(split, digit, frames, config, data)
    return [{"split": split, "digit": digit, setting: value, **score(streams, value)} for value in values]


def score_still(streams: list[dict], confirm_frames: int) -> dict:
    """Over the streams held still: false messages with the band moved just nearer than each clean distance, and
    with it moved around it (far edge ``STILL_INSIDE`` × the distance), the messages beyond the one warning each
    stream needs (its pairs span less than ``repeat_s``) and the pairs judged clear after it."""
    false = frames = extra = silenced = 0
    for s in streams:
        if s["clean_m"] is None:
            continue
        far_m = s["clean_m"] / STILL_BEYOND
        steps = replay(s["seen_m"], confirm_frames, near_m=far_m / 2, far_m=far_m)
        false += sum(message is not None for _, message, _ in steps)
        frames += len(steps)
        far_m = s["clean_m"] * STILL_INSIDE
        steps = replay(s["seen_m"], confirm_frames, near_m=far_m / 2, far_m=far_m)
        spoken = [i for i, (_, message, _) in enumerate(steps) if message is not None]
        extra += max(0, len(spoken) - 1)
        silenced += sum(c not in (WARN, STOP) for c, _, _ in steps[spoken[0]:]) if spoken else len(steps)
    per_minute = PAIRS_PER_S * 60 / max(frames, 1)
    return {"false_messages": false, "frames": frames, "false_per_minute": false * per_minute,
            "extra_messages": extra, "silenced_pairs": silenced}


def _delays(row: dict, kind: str) -> str:
    """A walks row's ``kind`` (warn, stop) delays as "median / max" ms; "–" where no walk was warned (``--walks 0``,
    or every walk missed: the table was lost after the whole run)."""
    median, largest = row[f"{kind}_delay_ms_median"], row[f"{kind}_delay_ms_max"]
    return "–" if median is None else f"{median:.0f} / {largest:.0f}"


def markdown(report: dict, command: str) -> str:
    lines = ["# guide's warnings confirmed over the last N pairs (`experiments/guide_confirm.py`)", "",
             f"Made by `{command}`; the module docstring says what is scored.", "",
             "## Rendered walks toward a box (tuning data)", "",
             "| digit | N | warn delay ms (median / max) | stop delay ms (median / max) | walks missed | false "
             "messages | messages off > 10 % | messages | pairs silenced in the band |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in report["walks"]:
        lines.append(f"| {row['digit']} | {row['confirm_frames']} | {_delays(row, 'warn')} | {_delays(row, 'stop')} | "
                     f"{row['missed']} | {row['false_messages']} | {row['wrong_distance_messages']} | "
                     f"{row['messages']} | {row['silenced_pairs']} |")
    lines += ["", "## Real scenes held still at 320×240", "",
              "| split | digit | N | band nearer: false messages | frames | false per minute at 20 pairs/s | "
              "band around: messages after the first | pairs silenced |", "|---|---|---|---|---|---|---|---|"]
    for row in report["still"]:
        lines.append(f"| {row['split']} | {row['digit']} | {row['confirm_frames']} | {row['false_messages']} | "
                     f"{row['frames']} | {row['false_per_minute']:.1f} | {row['extra_messages']} | "
                     f"{row['silenced_pairs']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_option(parser)
    parser.add_argument("--walks", type=positive_int, default=24, help="rendered walks per digit")
    parser.add_argument("--digits", default="4,6,8", type=comma_list(jpeg_digit, "JPEG digits"),
                        help="the board's JPEG digits (with their sensor noise)")
    parser.add_argument("--frames", type=positive_int, default=24, help="frames of each real scene held still")
    parser.add_argument("--splits", default="tuned,held-out",
                        help="comma-separated shared splits held still: tuned, held-out (default: %(default)s)")
    parser.add_argument("--confirm", default="1,2,3,5", type=comma_list(positive_int, "frame counts"),
                        help="the N compared")
    parser.add_argument("--seed", type=seed_int, default=0, help="seed of the rendered walks (default: %(default)s)")
    parser.add_argument("--json", type=output_path, help="write the report as JSON to FILE")
    parser.add_argument("--markdown", type=output_path, help="write the table as Markdown to FILE")
    args = parser.parse_args(argv)
    check_reports_apart(parser, args)
    known = list(split_scenes(Path(args.data)))
    unknown = sorted({s for s in args.splits.split(",") if s} - set(known))
    if unknown:  # before the walks (a KeyError after minutes of them before)
        parser.error(f"--splits: unknown {', '.join(unknown)}; expected among {', '.join(known)}")
    config = PipelineConfig().for_guide()
    digits, counts = [int(d) for d in args.digits.split(",")], [int(n) for n in args.confirm.split(",")]
    splits = [s for s in args.splits.split(",") if s]
    command = command_line("experiments/guide_confirm.py", argv or None)
    report = {"metadata": run_metadata(torch.get_num_threads(), command=command, seed=args.seed, walks=args.walks,
                                       frames=args.frames), "walks": [], "still": []}
    with Progress(len(digits) * (args.walks + len(splits)), "guide_confirm", unit="stream") as progress:
        for digit in digits:
            walks = []
            for index in range(args.walks):
                walks.append(walk(index, digit, args.seed, config))
                progress.update()
            report["walks"] += [dict(digit=digit, confirm_frames=n, **score_walks(walks, n)) for n in counts]
            for split in splits:
                report["still"] += still_rows(split, digit, args.frames, config, Path(args.data), "confirm_frames",
                                              counts, score_still)
                progress.update()
    text = markdown(report, command_line("experiments/guide_confirm.py", argv or None))
    print(text)
    write_report(report, text, args.json, args.markdown)
    return report


if __name__ == "__main__":
    run_script(main)
