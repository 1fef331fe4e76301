"""Does ``guide`` say how far ahead an obstacle stands, or how far along the camera's tilted axis
(:mod:`svs_torch.depth.floor_distance`)?

A walker's camera is pitched down; depth along its axis puts a point ``g`` metres ahead and ``z`` below the camera
at ``g·cos θ + z·sin θ``. ``guide`` said that depth (the nearest obstacle's 10th depth percentile); it now says the
distance ahead along the floor where its floor rule found the floor. Rendered SVS pairs at 320×240, guide's
configuration (``PipelineConfig.for_guide``: the floor left out, camera frames), each clean and as the board's
camera frames (JPEG digit 4 with noise σ 4, digit 8 with σ 8):

- **boxes**: ``experiments/walker_floor.py``'s 36 scenes: a camera at H ∈ {1.2, 1.5} m pitched θ ∈ {10°, 20°,
  30°}, a box 0.5 × 0.8 m standing F ∈ {1.2, 1.6, 2.0} m ahead, X = ±0.4 m aside, a far box at 2.6 m;
- **heaps**: ``experiments/walker_heaps.py``'s 36 "walker" scenes: a heap of rocks 0.45 m in radius and 0.35 m
  high, its centre F ∈ {1.2, 1.6, 2.0} m ahead (its front 0.45 m nearer), under the same cameras;
- **walks**: a camera 1.3 m up pitched 20° walking at 1.4 m/s (20 pairs a second) toward such a heap, its centre
  from 3.0 to 0.8 m ahead, 0.3 m to either side, as digit 4 frames: each pair's distance ranged alone (its own
  floor, or the camera's axis where the rule found none) and as ``guide`` ranges the stream (the floor found
  last remembered for ``FLOOR_MEMORY_S`` seconds, :class:`~svs_torch.cli.guide_loop.FloorMemory`).

Truth: the true nearest obstacle (the near box, or the heap) and, over its visible pixels, the 10th percentile
of each pixel's true distance ahead along the floor (the renderer's ``depth · (cos θ − sin θ · (y − cy) / f)``),
the part of it a walker reaches first. Per pair, the distance ``guide`` would say (before: the axis depth of the
nearest obstacle's nearest part; now: its distance ahead where the floor was found, else the axis depth) is
scored by Eq. (9) against that truth, and its class (``stop`` under 1 m, ``warn`` to 2 m, else ``clear``:
``WarningPolicy``'s default band) against the truth's class. Also the floor's camera height and pitch against
the rendered ones, and what ``guide --camera-pitch-deg`` gives where the pair is ranged along a level floor under
the camera's pitch as worn (given exactly, and 5° too steep) once no floor is seen. No rival: OpenCV's matchers
give depth along the axis and no floor.

``--set KEY=VALUE`` changes the pipeline. Tuning data only (our own renderings). About four minutes on a 2-core
machine.

    python experiments/floor_distance.py [--set KEY=VALUE ...] [--json F] [--markdown F]
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_metadata import command_line, rendered_experiment_setup, report_rows, run_script  # noqa: E402
from thin_obstacles import FRAMES, as_frames  # noqa: E402
from walker_floor import walker_cases, walker_scenes  # noqa: E402
from walker_heaps import WALKER, heap_scenes  # noqa: E402

from svs_torch.capture.guide import WarningPolicy  # noqa: E402
from svs_torch.cli.guide_loop import FLOOR_MEMORY_S, FloorMemory  # noqa: E402
from svs_torch.data.heap_rendering import WALKER_HEAP_HEIGHT_M, WALKER_HEAP_RADIUS_M  # noqa: E402
from svs_torch.data.synthetic import render_obstacle_scenes  # noqa: E402
from svs_torch.pipeline import PipelineStatus, estimate_obstacle_depth  # noqa: E402

POLICY = WarningPolicy()
#: The walks: a camera at 1.3 m pitched 20° (``hw.frames.WALKER_PITCH_DEG``) walking at 1.4 m/s, 20 pairs a second,
#: toward a heap whose centre comes from 3.0 to 0.8 m ahead, 0.3 m to either side.
WALK_HEIGHT_M, WALK_PITCH_DEG, WALK_SPEED_M_S, PAIRS_PER_S = 1.3, 20.0, 1.4, 20.0
WALK_FROM_M, WALK_TO_M, WALK_OFFSETS_M = 3.0, 0.8, (-0.3, 0.3)


def ahead_truth(scenes, on: torch.Tensor, pitch_deg: float) -> list[float]:
    """Each pair's 10th percentile of the true distance ahead along the floor over the pixels ``on``
    ``(B, 1, H, W)`` (NaN where none is visible)."""
    theta = math.radians(pitch_deg)
    h = scenes.depth_m.shape[-2]
    focal = scenes.batch.focal_px.view(-1, 1, 1, 1)
    rows = torch.arange(h, dtype=scenes.depth_m.dtype).view(1, 1, h, 1)
    ahead = scenes.depth_m * (math.cos(theta) - math.sin(theta) * (rows - (h - 1) / 2) / focal)
    return torch.where(on, ahead, math.nan).flatten(1).nanquantile(0.1, dim=1).tolist()


def accuracy(said: float | None, truth: float) -> float:
    """Eq. (9), 0 where nothing was said."""
    return 0.0 if said is None else max(0.0, 100.0 * (1 - abs(said - truth) / truth))


def pair_rows(kind: str, scenes, index, cases, on: torch.Tensor, config, frame: str, setting: str) -> list[dict]:
    """One row per pair of ``scenes`` (module docstring); ``on``: the true nearest obstacle's pixels."""
    batch = as_frames(scenes.batch, *[(d, s) for name, d, s in FRAMES if name == frame][0])
    result = estimate_obstacle_depth(batch, config)
    truths = ahead_truth(scenes, on, cases[index[0]][1])  # (one camera's pairs)
    rows = []
    for j, i in enumerate(index):
        height_m, pitch_deg, truth = cases[i][0], cases[i][1], truths[j]
        if math.isnan(truth):
            continue
        one = _one_pair(result, j)
        ok = int(result.status[j]) == PipelineStatus.OK
        axis = float(result.depth.nearest.surface_m[j]) if ok and bool(result.depth.nearest.valid[j]) else None
        nearest, along, _ = FloorMemory().nearest(one, 0.0)  # each pair alone: its own floor or the camera's axis
        now = float(nearest.surface_m[0]) if ok and bool(nearest.valid[0]) else None
        # with guide --camera-pitch-deg: the rig's pitch as worn, given exactly and 5° too steep
        worn = [FloorMemory(worn_pitch_deg=pitch_deg + error).nearest(one, 0.0)[0] for error in (0.0, 5.0)]
        worn = [float(n.surface_m[0]) if ok and bool(n.valid[0]) else None for n in worn]
        floor = result.floor.floor
        found = bool(floor.found[j])
        rows.append({"setting": setting, "frame": frame, "kind": kind, "height_m": height_m, "pitch_deg": pitch_deg,
                     "case": list(cases[i]), "truth_ahead_m": truth, "axis_m": axis, "said_m": now,
                     "along_floor": along != "axis", "floor_found": found,
                     "floor_height_m": float(floor.camera_height_m[j]) if found else None,
                     "floor_pitch_deg": float(floor.pitch_deg[j]) if found else None,
                     "axis_acc": accuracy(axis, truth), "said_acc": accuracy(now, truth),
                     "truth_class": POLICY.classify(truth), "axis_class": POLICY.classify(axis),
                     "said_class": POLICY.classify(now), "worn_m": worn[0], "worn_acc": accuracy(worn[0], truth),
                     "worn_class": POLICY.classify(worn[0]), "worn5_m": worn[1],
                     "worn5_acc": accuracy(worn[1], truth), "worn5_class": POLICY.classify(worn[1])})
    return rows


def _one_pair(result, j: int):
    """Pair ``j`` of ``result`` as a one-pair result (what ``guide`` reads)."""
    from svs_torch.core.pair_trees import take_pairs

    return take_pairs(result, torch.tensor([j]), result.status.shape[0])


def walk_rows(config, setting: str) -> list[dict]:
    """The walks (module docstring): each pair's distance said without and with ``guide``'s floor memory."""
    rows = []
    for offset_m in WALK_OFFSETS_M:
        ahead = [WALK_FROM_M - k * WALK_SPEED_M_S / PAIRS_PER_S
                 for k in range(int((WALK_FROM_M - WALK_TO_M) / (WALK_SPEED_M_S / PAIRS_PER_S)) + 1)]
        heaps = torch.tensor([[offset_m, f, WALKER_HEAP_RADIUS_M, WALKER_HEAP_HEIGHT_M] for f in ahead])
        scenes = render_obstacle_scenes(torch.zeros(len(ahead), 0), torch.zeros(len(ahead), 0, 2),
                                        torch.zeros(len(ahead), 0, 2), floor_height_m=WALK_HEIGHT_M,
                                        camera_pitch_deg=WALK_PITCH_DEG, heaps=heaps, heap_roughness_m=0.05,
                                        texture_contrast=0.5, generator=torch.Generator().manual_seed(11))
        truths = ahead_truth(scenes, scenes.heap_mask, WALK_PITCH_DEG)
        batch = as_frames(scenes.batch, 4, 4.0)
        result = estimate_obstacle_depth(batch, config)
        memory = FloorMemory()
        for j, truth in enumerate(truths):
            one = _one_pair(result, j)
            alone, alone_along, _ = FloorMemory().nearest(one, 0.0)
            kept, kept_along, _ = memory.nearest(one, j / PAIRS_PER_S)
            said = [float(n.surface_m[0]) if bool(n.valid[0]) else None for n in (alone, kept, one.depth.nearest)]
            rows.append({"setting": setting, "frame": "jpeg q4 + noise s4", "kind": "walk", "offset_m": offset_m,
                         "heap_ahead_m": ahead[j], "truth_ahead_m": truth, "alone_m": said[0], "memory_m": said[1],
                         "alone_along_floor": alone_along != "axis", "memory_along_floor": kept_along != "axis",
                         "axis_m": said[2], "axis_along_floor": False, "axis_acc": accuracy(said[2], truth),
                         "axis_class": POLICY.classify(said[2]),
                         "alone_acc": accuracy(said[0], truth), "memory_acc": accuracy(said[1], truth),
                         "truth_class": POLICY.classify(truth), "alone_class": POLICY.classify(said[0]),
                         "memory_class": POLICY.classify(said[1])})
    return rows


def walk_markdown(rows: list[dict]) -> str:
    """The walks' pairs whose heap is in view and within the band's far edge plus half a metre."""
    group = [r for r in rows if not math.isnan(r["truth_ahead_m"]) and r["truth_ahead_m"] <= POLICY.far_m + 0.5]
    n = len(group)
    lines = ["", f"Walks toward a heap (camera {WALK_HEIGHT_M} m up, pitched {WALK_PITCH_DEG:.0f}°, "
             f"{WALK_SPEED_M_S} m/s at {PAIRS_PER_S:.0f} pairs/s, digit 4 frames): {n} pairs with the heap in view "
             f"and at most {POLICY.far_m + 0.5} m ahead.", "",
             "| ranged | along the floor | Acc | class right |", "|---|---|---|---|"]
    for name, label in (("axis", "along the camera's axis (before)"), ("alone", "each pair alone"),
                        ("memory", f"the floor remembered {FLOOR_MEMORY_S} s (guide)")):
        lines.append(f"| {label} | {sum(r[name + '_along_floor'] for r in group)} of {n} | "
                     f"{sum(r[name + '_acc'] for r in group) / max(1, n):.1f} % | "
                     f"{sum(r[name + '_class'] == r['truth_class'] for r in group)} of {n} |")
    return "\n".join(lines) + "\n"


def markdown(rows: list[dict], command: str) -> str:
    """One line per frame kind and scene kind."""
    lines = [f"`{command}`", "", "| frames | scenes | pairs | floor found | camera height error, m | pitch error, ° "
             "| said before (axis): Acc / class right | said now: Acc / class right "
             "| with --camera-pitch-deg: exact / 5° too steep |", "|---|---|---|---|---|---|---|---|---|"]
    for frame, kind in dict.fromkeys((r["frame"], r["kind"]) for r in rows):
        group = [r for r in rows if (r["frame"], r["kind"]) == (frame, kind)]
        found = [r for r in group if r["floor_found"]]
        n = len(group)
        height = sum(abs(r["floor_height_m"] - r["height_m"]) for r in found) / max(1, len(found))
        pitch = sum(abs(r["floor_pitch_deg"] - r["pitch_deg"]) for r in found) / max(1, len(found))
        said = [f"{sum(r[name + '_acc'] for r in group) / n:.1f} % / "
                f"{sum(r[name + '_class'] == r['truth_class'] for r in group)}"
                for name in ("axis", "said", "worn", "worn5")]
        lines.append(f"| {frame} | {kind} | {n} | {len(found)} | {height:.3f} | {pitch:.2f} | {said[0]} | {said[1]} "
                     f"| {said[2]}; {said[3]} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    args, config, setting, started = rendered_experiment_setup(__doc__, argv)
    config = config.for_guide(True)
    rows = []
    box_cases = walker_cases()  # (height, pitch, ahead, offset)
    for index, scenes in walker_scenes(box_cases):
        for frame, _, _ in FRAMES:
            rows += pair_rows("boxes", scenes, index, box_cases, scenes.object_ids == 1, config, frame, setting)
    heap_cases = [case[1:] for case in WALKER]  # (height, pitch, ahead, offset, radius, height)
    for index, scenes in heap_scenes(WALKER):
        for frame, _, _ in FRAMES:
            rows += pair_rows("heaps", scenes, index, heap_cases, scenes.heap_mask, config, frame, setting)
    walks = walk_rows(config, setting)
    command = command_line("experiments/floor_distance.py", argv)
    order = [f[0] for f in FRAMES]
    table = markdown(sorted(rows, key=lambda r: (order.index(r["frame"]), r["kind"])), command) + walk_markdown(walks)
    rows += walks
    return report_rows(table, rows, command, args.set, started, args.json, args.markdown)


if __name__ == "__main__":
    run_script(main)
