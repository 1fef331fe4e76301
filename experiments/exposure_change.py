"""How far the two views' quartile map would move a pair (``|scale − 1| + |offset|``,
:func:`svs_torch.pipeline.exposure.exposure_change`) on the tuned split's pairs, with and without a gain difference
between the cameras, and how many pairs the exposure retry runs again: what the retry's ``min_change``
(``RETRY_MIN_CHANGE``) was chosen on (experiments/exposure.md, "Which pairs are retried"). Tuning data only.

Pairs: the tuned split (10 Middlebury eval3 scenes) under every condition of experiments/real_rig.py (clean, JPEG
at the board's eight digits with sensor noise, each misalignment), at each size. Groups:

- ``without a gain``: every condition but the gains and "combined", the two scenes shot at another exposure or
  under another lamp (MotorcycleE, PianoL) aside;
- ``MotorcycleE, PianoL without a gain``: those two scenes' same conditions (their views differ in exposure);
- ``a gain (±30 %, combined −20 %)``: "gain +30%", "gain -30%" and "combined", every scene.

With ``--count-retries`` the default pipeline runs every pair at ``min_change`` 0.05 (the retry's first setting)
and at ``RETRY_MIN_CHANGE``, each without the test of the map at the matched points
(``PipelineConfig.exposure_retry_max_residual_ratio`` None), and at the default, and the pairs each runs again
are counted (about 2 minutes for both sizes; experiments/exposure.md, "The map at the matched points").

    python experiments/exposure_change.py [--sizes 320x240,native] [--count-retries] [--limit N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import real_rig  # noqa: E402
from run_metadata import add_common_options, run_script, scene_limit  # noqa: E402

from svs_torch.data import load_stereo_pair  # noqa: E402
from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth  # noqa: E402
from svs_torch.pipeline import run as pipeline_run  # noqa: E402
from svs_torch.pipeline.exposure import RETRY_MIN_CHANGE, ExposureConfig, exposure_change  # noqa: E402

#: The tuned scenes whose two views were shot at another exposure or under another lamp.
OTHER_EXPOSURE = ("MotorcycleE", "PianoL")


def group_of(scene: str, condition: str) -> str:
    """The group (module docstring) of a tuned ``scene``'s pair under ``condition``."""
    if "gain" in condition or condition == "combined":
        return "a gain (±30 %, combined −20 %)"
    return "MotorcycleE, PianoL without a gain" if scene in OTHER_EXPOSURE else "without a gain"


#: The retry settings ``--count-retries`` compares: (name, ``min_change``, ``exposure_retry_max_residual_ratio``).
RETRY_SETTINGS = (("min_change 0.05, no map test", 0.05, None),
                  (f"min_change {RETRY_MIN_CHANGE:g}, no map test", RETRY_MIN_CHANGE, None),
                  ("the default (the map test at 0.8)", RETRY_MIN_CHANGE, 0.8))


def count_retries(batch, min_change: float, max_residual_ratio: float | None) -> int:
    """How many pairs of ``batch`` the default pipeline, with its retry at ``min_change`` and
    ``exposure_retry_max_residual_ratio``, runs a second time (the pairs handed to the second run)."""
    counted = []
    retry = pipeline_run.retry_with_exposure

    def counting(batch, result, config, run):
        def counted_run(pairs, settings):
            counted.append(pairs.batch_size)
            return run(pairs, settings)
        return retry(batch, result, config, counted_run)

    pipeline_run.retry_with_exposure = counting
    try:
        with torch.inference_mode():
            estimate_obstacle_depth(batch, PipelineConfig(exposure_retry=ExposureConfig(min_change=min_change),
                                                          exposure_retry_max_residual_ratio=max_residual_ratio))
    finally:
        pipeline_run.retry_with_exposure = retry
    return sum(counted)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_options(parser, data_type=Path, sizes="320x240,native")
    parser.add_argument("--count-retries", action="store_true", help="also count the pairs each retry reaches")
    parser.add_argument("--limit", type=scene_limit, help="only the first N tuned scenes")
    args = parser.parse_args(argv)
    scenes = real_rig.scene_splits(args.data, ["tuned"], args.limit)["tuned"]
    out: dict = {}
    for size in args.sizes.split(","):
        changes: dict[str, list[tuple[float, str]]] = {}
        retried = {name: 0 for name, _, _ in RETRY_SETTINGS}
        for index, path in enumerate(scenes):
            pair = real_rig.resample(load_stereo_pair(path), size)
            views = real_rig.conditions(pair, index)
            batch = real_rig.stack_conditions(pair, views)
            for (condition, _, _), change in zip(views, exposure_change(batch.left, batch.right, batch.image_hw)):
                changes.setdefault(group_of(path.name, condition), []).append((float(change), path.name))
            if args.count_retries:
                for name, min_change, ratio in RETRY_SETTINGS:
                    retried[name] += count_retries(batch, min_change, ratio)
        print(f"{size}:")
        for group, values in changes.items():
            ordered = sorted(value for value, _ in values)
            # The end nearest the other groups: a gain's smallest change, the others' largest.
            which, extreme = ("smallest", min(values)) if group.startswith("a gain") else ("largest", max(values))
            print(f"  {group:36s} {len(values):3d} pairs: min {ordered[0]:.3f}, median {statistics.median(ordered):.3f}"
                  f", 90th percentile {ordered[int(0.9 * (len(ordered) - 1))]:.3f}, max {ordered[-1]:.3f} "
                  f"(the {which}: {extreme[1]})")
        if args.count_retries:
            total = sum(len(values) for values in changes.values())
            print("  run again: " + ", ".join(f"{name}: {n} of {total}" for name, n in retried.items()))
        out[size] = {"changes": changes, "retried": retried}
    return out


if __name__ == "__main__":
    run_script(main)
