"""Are repeated patterns (a fence, a railing, a grate) ranged right on a real rig's pairs? (issue 33, items 1-2)

A pattern that repeats along the rows gives the block matcher a cost minimum at the true disparity and one a period
away on either side. Rendered here at the SVS's 320×240 (276 px focal length, 10.75 cm baseline): a 0.6 × 0.8 m
panel facing the rig at Z ∈ {1.0, 1.5, 2.0} m, painted with vertical bars, a checkerboard or a grate (crossing
bars) of period P ∈ {8, 12, 16, 24} px (7-17 cm at 1.5 m), with a faint texture of its own (3 % of its contrast),
before a textured wall at 4 m: 36 pairs, seeded, the true disparity fractional (each view sampled from the same
continuous pattern, 4× supersampled). Each pair as rendered, then with the right camera deviating as a loose rig's
does (:class:`svs_torch.data.rig_deviation.RigDeviation`: roll 0.5° and 1.5°, scale +2 %, a shift of 3 % of the
height, 30 % more gain), as the board's camera frames (JPEG digit 4 with sensor noise σ 4), and as a loose rig's
camera frames (:data:`~svs_torch.data.rig_deviation.LOOSE_RIG` at digit 4).

Per pair the panel counts as **ranged** where the nearest obstacle's median depth lies within 5 % of the panel's
distance, **wrong** where a status-OK nearest obstacle lies farther off than that (what a walker is told
wrongly), **unranged** where the pair has no distance; of those, **said to repeat** where a kept object is
reported as a repeated pattern seen but not ranged (``PipelineResult.unranged_repeated``), with the panel's distance
among the distances its aliases give (within 5 %, :func:`svs_torch.depth.alias_choice.alias_depths_m`) in brackets.
Acc is Eq. (9) of the nearest distance (0 where none).
The settings: the default, and the default with every pair allowed onto the coarse grid
(``--set depth.coarse_retry_max_period_peak=none``: :mod:`svs_torch.depth.periodicity` keeps a repeated pattern
off it by default). The rival: OpenCV StereoSGBM's disparity through the truth's own
procedure (``eval_segmentation.sgbm_rival``). Rendered data only: no shared scene is read. About 1 minute on a
2-core machine.

    python experiments/repeated_patterns.py [--set KEY=VALUE ...] [--no-rival] [--json F] [--markdown F]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_segmentation import sgbm_rival  # noqa: E402
from run_metadata import command_line, rendered_experiment_setup, report_rows, run_script  # noqa: E402

from svs_torch.capture.guide import WarningPolicy  # noqa: E402
from svs_torch.core.camera import SVS_CAMERA  # noqa: E402
from svs_torch.core.types import StereoBatch  # noqa: E402
from svs_torch.data import camera_frame_pairs  # noqa: E402
from svs_torch.data.rig_deviation import LOOSE_RIG, RigDeviation, deviate_view  # noqa: E402
from svs_torch.depth.alias_choice import alias_depths_m  # noqa: E402
from svs_torch.evaluation.overrides import apply_overrides  # noqa: E402
from svs_torch.pipeline import PipelineConfig, PipelineStatus, estimate_obstacle_depth  # noqa: E402

HEIGHT, WIDTH = 240, 320
BASELINE_M = 0.1075
KINDS, PERIODS_PX, DEPTHS_M = ("bars", "checker", "grate"), (8, 12, 16, 24), (1.0, 1.5, 2.0)
PANEL_W_M, PANEL_H_M, WALL_M = 0.6, 0.8, 4.0
#: A distance within this share of the panel's counts as the panel.
TOLERANCE = 0.05
#: The rendered set the alias rule was chosen on (``--seed``: the panels' textures and the sensor noise); 8 and 9
#: were only reported (repeated_patterns.md, "The whole object's alias").
SEED = 7
#: guide's default warning band's far edge, metres (a pattern that may lie within it is said aloud).
GUIDE_FAR_M = WarningPolicy().far_m
#: The conditions: name, the right camera's deviation, JPEG digit (0: none) and sensor noise in 8-bit levels.
CONDITIONS = (("as rendered", RigDeviation(), 0, 0.0), ("roll 0.5°", RigDeviation(roll_deg=0.5), 0, 0.0),
              ("roll 1.5°", RigDeviation(roll_deg=1.5), 0, 0.0), ("scale +2 %", RigDeviation(scale=0.02), 0, 0.0),
              ("shift 3 %", RigDeviation(shift_y_fraction=0.03), 0, 0.0),
              ("gain +30 %", RigDeviation(gain=0.3), 0, 0.0),
              ("camera frames (digit 4, σ 4)", RigDeviation(), 4, 4.0),
              ("loose rig's camera frames (digit 4)", LOOSE_RIG, 4, 4.0))


def focal_px() -> float:
    return float(SVS_CAMERA.focal_px(WIDTH))


def pattern(kind: str, period: float, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The panel's paint in [0, 1] at panel coordinates ``u``, ``v`` (left-view pixels at the panel's depth)."""
    bar_u = (np.floor(u / (period / 2)) % 2).astype(np.float32)
    if kind == "bars":
        return bar_u
    bar_v = (np.floor(v / (period / 2)) % 2).astype(np.float32)
    if kind == "checker":
        return (bar_u + bar_v) % 2
    return np.maximum((u % period < period / 3), (v % period < period / 3)).astype(np.float32)


def smooth_texture(rng: np.random.Generator, height: int, width: int, sigma: float) -> np.ndarray:
    import cv2

    noise = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), sigma)
    return (noise - noise.min()) / max(float(noise.max() - noise.min()), 1e-6)


def render_view(kind: str, period: int, disparity: float, wall_d: float, textures: tuple, shift: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """One view (``shift`` 0: the left; 1: the right, every surface moved left by its disparity) and the panel's
    mask, 4× supersampled along the rows."""
    wall, own = textures
    columns = (np.arange(WIDTH * 4) + 0.5) / 4 - 0.5
    xs, ys = np.meshgrid(columns, np.arange(HEIGHT, dtype=np.float64))
    f = focal_px()
    z = f * BASELINE_M / disparity
    pw, ph = PANEL_W_M * f / z, PANEL_H_M * f / z  # the panel's size in pixels at its depth
    u = xs + shift * disparity - (WIDTH - 1) / 2 + pw / 2
    v = ys - (HEIGHT - 1) / 2 + ph / 2
    inside = (u >= 0) & (u < pw) & (v >= 0) & (v < ph)
    # The wall's texture at half-pixel steps, so that its fractional disparity moves it too.
    wall_x = np.clip(np.round((xs + shift * wall_d) * 2).astype(int) + 40, 0, wall.shape[1] - 1)
    background = 0.25 + 0.5 * wall[ys.astype(int), wall_x]
    own_x = np.clip(np.round(u * 2).astype(int), 0, own.shape[1] - 1)
    own_y = np.clip(np.round(v).astype(int), 0, own.shape[0] - 1)
    paint = 0.15 + 0.7 * pattern(kind, period, u, v) + 0.03 * own[own_y, own_x]
    image = np.where(inside, paint, background).reshape(HEIGHT, WIDTH, 4).mean(-1)
    return image.astype(np.float32), inside.reshape(HEIGHT, WIDTH, 4).any(-1)


def cases(periods: tuple[int, ...] = PERIODS_PX) -> list[tuple[str, int, float]]:
    return [(k, p, z) for k in KINDS for p in periods for z in DEPTHS_M]


def render_pairs(seed: int = SEED, periods: tuple[int, ...] = PERIODS_PX
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Left and right views ``(N, H, W)`` float32 in [0, 1] of every case (of ``periods``), the panels' disparities
    ``(N,)`` and their masks in the left view ``(N, H, W)`` bool; ``seed`` draws the wall's and the panels'
    textures."""
    rng = np.random.default_rng(seed)
    f = focal_px()
    lefts, rights, disparities, masks = [], [], [], []
    for kind, period, z in cases(periods):
        textures = (smooth_texture(rng, HEIGHT, WIDTH * 2 + 160, 3.0), smooth_texture(rng, HEIGHT, WIDTH * 2, 0.7))
        d, wall_d = f * BASELINE_M / z, f * BASELINE_M / WALL_M
        left, mask = render_view(kind, period, d, wall_d, textures, 0.0)
        lefts.append(left)
        masks.append(mask)
        rights.append(render_view(kind, period, d, wall_d, textures, 1.0)[0])
        disparities.append(d)
    return np.stack(lefts), np.stack(rights), np.asarray(disparities), np.stack(masks)


def condition_batch(lefts: np.ndarray, rights: np.ndarray, deviation: RigDeviation, digit: int, sigma: float,
                    seed: int = SEED) -> StereoBatch:
    """The rendered pairs with the right camera deviating by ``deviation``, as camera frames where ``digit`` (the
    noise drawn from ``seed``)."""
    f = focal_px()
    seen = np.stack([deviate_view(r, deviation, f) for r in rights]) if not deviation.is_identity else rights
    n = len(lefts)
    batch = StereoBatch(torch.from_numpy(lefts).unsqueeze(1), torch.from_numpy(seen).unsqueeze(1),
                        torch.full((n,), f), torch.full((n,), BASELINE_M), torch.zeros(n), torch.ones(n, dtype=bool),
                        torch.tensor([[HEIGHT, WIDTH]] * n))
    if digit == 0:
        return batch
    return camera_frame_pairs(batch, digit, sigma, torch.Generator().manual_seed(seed + digit))


def outcome(setting: str, condition: str, case: tuple, nearest_m: float | None, ok: bool,
            aliases_m: list[float] | None = None, may_be_within_m: float | None = None) -> dict:
    """One panel's row; ``aliases_m``: the distances of the aliases of its objects reported as a repeated pattern
    left unranged (None: none is); ``may_be_within_m``: how near they may be (``nearest_unranged_alias_m``), which
    ``said_aloud`` compares with guide's default warning band (``guide`` says such a pattern aloud where it may
    lie within the band, :class:`~svs_torch.capture.pattern_notice.PatternNotice`)."""
    kind, period, z = case
    ranged = nearest_m is not None and abs(nearest_m - z) <= TOLERANCE * z
    said = nearest_m is None and aliases_m is not None
    return {"setting": setting, "condition": condition, "kind": kind, "period_px": period, "depth_m": z,
            "nearest_m": nearest_m, "ranged": ranged, "wrong": ok and nearest_m is not None and not ranged,
            "unranged": nearest_m is None, "said_repeated": said,
            "said_aloud": nearest_m is None and may_be_within_m is not None and may_be_within_m <= GUIDE_FAR_M,
            "truth_among_aliases": said and any(abs(a - z) <= TOLERANCE * z for a in aliases_m),
            "acc_pct": 0.0 if nearest_m is None else max(0.0, 100 * (1 - abs(z - nearest_m) / z))}


def pipeline_rows(batch: StereoBatch, config: PipelineConfig, setting: str, condition: str,
                  periods: tuple[int, ...] = PERIODS_PX) -> list[dict]:
    result = estimate_obstacle_depth(batch, config)
    nearest, rows = result.depth.nearest, []
    marked = result.unranged_repeated
    if marked is not None:
        depth_m, valid = alias_depths_m(result.dense, batch.focal_px, batch.baseline_m, batch.doffs_px)
        valid &= marked.unsqueeze(-1)
        nearest_alias = result.nearest_unranged_alias_m.tolist()  # once for the batch, not a pair at a time
    for i, case in enumerate(cases(periods)):
        ok = int(result.status[i]) == PipelineStatus.OK and bool(nearest.valid[i])
        said = marked is not None and bool(marked[i].any())
        aliases = depth_m[i][valid[i]].tolist() if said else None
        within = nearest_alias[i] if said else None
        rows.append(outcome(setting, condition, case, float(nearest.depth_m[i]) if ok else None, ok, aliases, within))
    return rows


def rival_rows(batch: StereoBatch, condition: str, periods: tuple[int, ...] = PERIODS_PX) -> list[dict]:
    """StereoSGBM's nearest obstacle per pair (module docstring); a loop over pairs, as OpenCV runs."""
    rows = []
    for i, case in enumerate(cases(periods)):
        nearest = sgbm_rival(batch.select([i]))[1]
        rows.append(outcome("OpenCV SGBM", condition, case, nearest, nearest is not None))
    return rows


def markdown(rows: list[dict], command: str) -> str:
    """One line per setting and condition: panels ranged, wrong, unranged (of 36; those said to repeat, and with the
    truth among their aliases), mean Acc, and wrong by kind."""
    lines = [f"`{command}`", "",
             "| setting | condition | ranged | wrong, status OK | unranged | said to repeat (truth among aliases) | "
             "mean Acc % | " + " | ".join(f"wrong: {k}" for k in KINDS) + " |",
             "|---|---|---|---|---|---|---|" + "---|" * len(KINDS)]
    for setting, condition in dict.fromkeys((r["setting"], r["condition"]) for r in rows):
        group = [r for r in rows if (r["setting"], r["condition"]) == (setting, condition)]
        kinds = " | ".join(str(sum(r["wrong"] for r in group if r["kind"] == k)) for k in KINDS)
        mean = sum(r["acc_pct"] for r in group) / len(group)
        said = f"{sum(r['said_repeated'] for r in group)} ({sum(r['truth_among_aliases'] for r in group)})"
        lines.append(f"| {setting} | {condition} | {sum(r['ranged'] for r in group)} | "
                     f"{sum(r['wrong'] for r in group)} | {sum(r['unranged'] for r in group)} | {said} | {mean:.2f} | "
                     f"{kinds} |")
    return "\n".join(lines) + "\n"


def _periods(text: str) -> tuple[int, ...]:
    import argparse

    try:
        periods = tuple(int(p) for p in text.split(","))
    except ValueError:
        periods = ()
    if not periods or not all(4 <= p <= 96 for p in periods):
        raise argparse.ArgumentTypeError(f"expected whole periods of 4 to 96 px, comma-separated; got {text!r}")
    return periods


def _options(parser) -> None:
    parser.add_argument("--seed", type=int, default=SEED,
                        help=f"the rendered set: textures and sensor noise (default {SEED}, the rules' own)")
    parser.add_argument("--periods", type=_periods, default=PERIODS_PX, metavar="P,P,...",
                        help="the patterns' periods, pixels at 320x240 (default "
                        + ",".join(map(str, PERIODS_PX)) + "; 32,40,48: a railing near the walker)")


def main(argv: list[str] | None = None) -> dict:
    args, base, name, started = rendered_experiment_setup(__doc__, argv, _options)
    ungated = apply_overrides(base, {"depth.coarse_retry_max_period_peak": None})
    settings = {name: base, "coarse retry for every pair": ungated}
    if base.depth.coarse_retry_max_period_peak is None:
        settings = {"coarse retry for every pair": ungated}
    lefts, rights, *_ = render_pairs(args.seed, args.periods)
    rows = []
    with torch.inference_mode():
        for condition, deviation, digit, sigma in CONDITIONS:
            batch = condition_batch(lefts, rights, deviation, digit, sigma, args.seed)
            for setting, config in settings.items():
                rows += pipeline_rows(batch, config, setting, condition, args.periods)
            if not args.no_rival:
                rows += rival_rows(batch, condition, args.periods)
    command = command_line("experiments/repeated_patterns.py", argv)
    order = list(dict.fromkeys(r["setting"] for r in rows))
    table = markdown(sorted(rows, key=lambda r: order.index(r["setting"])), command)
    return report_rows(table, rows, command, args.set, started, args.json, args.markdown)


if __name__ == "__main__":
    run_script(main)
