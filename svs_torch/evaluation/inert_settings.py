"""Settings a configuration never reads: ``--set dense.window_size=9`` under the paper's range rule.

Why: the dense SAD stage and everything built on its map (the verification of the views, the second passes, the
dropped regions, the near surfaces, the exposure retry, each object's least valid pixels and its repeated-pattern
checks) run only under the dense range rule (``depth.rule = "dense"``;
:func:`~svs_torch.pipeline.estimate_obstacle_depth`). Under the paper's rule (Eq. (5)–(8) over the RANSAC inliers,
``--preset paper``) such a setting changes nothing, and a sweep over it stored one result
under as many configurations, read as "this setting does not matter" (an audit of ``--set``). It is said, not
refused: a configuration file shared between both rules is fine. Likewise the nearness segmenter's own settings (its
floor, its share of the view measured, its clipped regions, its keep rule and that rule's least areas) under Otsu
(the paper's) or the learned segmenter, which always keep the largest regions.

``tests/evaluation/test_inert_settings.py`` runs the paper preset (and the learned segmenter) with each of these set
to another value and finds every result the same, bit for bit.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

from ..pipeline import PipelineConfig

__all__ = ["DENSE_RULE_ONLY", "NEARNESS_SEGMENTER_ONLY", "inert_overrides", "warn_inert_overrides"]

#: The fields (``dense`` with every ``dense.*``, and some of ``depth``) that only the dense range rule reads
#: (``PipelineConfig``'s docstring: "under the dense rule").
DENSE_RULE_ONLY = (
    "dense", "verify_min_inliers", "verify_min_inlier_share", "verify_min_agreeing_inliers", "verify_many_inliers",
    "verify_many_inliers_min_agreeing", "verify_unanimous_min_inliers", "verify_unanimous_min_agreeing",
    "verify_whole_view", "noisy_retry_sigma_px", "noisy_features_retry_sigma_px", "coarse_retry_below_share",
    "drop_unmeasured_below_share", "drop_unmeasured_nearer_below_share", "region_interior_working_px",
    "measure_near_surface", "exposure_retry", "exposure_retry_max_residual_ratio",
    # DepthConfig's fields that measure objects on the dense map (its docstring: '"dense" rule'); the paper's rule
    # reads depth.rule, percentiles, object_percentiles, min_object_inliers and min_in_front_share.
    "depth.surface_within_in_view_top", "depth.min_object_pixels", "depth.min_object_valid_fraction",
    "depth.min_object_valid_fraction_unverified", "depth.min_object_pixels_in_view",
    "depth.coarse_retry_max_period_peak", "depth.alias_check_min_period_peak", "depth.coarse_retry_max_period_px",
    "depth.alias_check_max_period_px",
)
#: The segmentation fields only the nearness segmenter reads (``SegmentationConfig``'s docstring: its floor, its
#: share of the view measured, its clipped regions; "the other segmenters never look"). Its keep rule too, with the
#: rule's least areas: Otsu and the learned segmenter keep the largest regions whatever ``keep`` says
#: (``keep_largest_regions``; "nearest", which would need a disparity, is refused there), so
#: ``--preset paper --set segmentation.keep=nearest_first`` ran the paper's rule in silence (an audit).
NEARNESS_SEGMENTER_ONLY = ("segmentation.ground", "segmentation.min_measured_share", "segmentation.max_clipped_share",
                           "segmentation.keep", "segmentation.min_area_fraction",
                           "segmentation.near_min_area_fraction")


def _unread(config: PipelineConfig) -> list[tuple[tuple[str, ...], str]]:
    """The settings ``config`` never reads, as (dotted prefixes, why) pairs."""
    unread = []
    if config.depth.rule != "dense":
        unread.append((DENSE_RULE_ONLY, "under the paper range rule (depth.rule = 'paper'): only the dense rule reads"))
    segmenter = config.segmentation.segmenter
    if not segmenter.startswith("nearness"):
        unread.append((NEARNESS_SEGMENTER_ONLY, f"under the {segmenter.partition(':')[0]} segmenter "
                                                f"(segmentation.segmenter): only the nearness segmenter reads"))
    return unread


def inert_overrides(config: PipelineConfig, overrides: Mapping[str, Any]) -> dict[str, str]:
    """The keys of ``overrides`` (dotted, as ``--set`` takes them) that ``config``, the configuration they built,
    never reads (:data:`DENSE_RULE_ONLY` under the paper range rule, :data:`NEARNESS_SEGMENTER_ONLY` under another
    segmenter than the nearness one), each with why. In the order given."""
    unread = _unread(config)
    return {key: why for key in overrides for prefixes, why in unread
            if any(key == prefix or key.startswith(prefix + ".") for prefix in prefixes)}


def warn_inert_overrides(configs: list[tuple[PipelineConfig, Mapping[str, Any]]], source: str) -> None:
    """A ``UserWarning`` starting with ``source`` for each reason :func:`inert_overrides` finds in any of
    ``configs`` (each a configuration and the overrides that built it: a sweep's, or one command's), naming its
    keys and, for several configurations, in how many."""
    inert = [inert_overrides(config, overrides) for config, overrides in configs]
    for why in dict.fromkeys(why for found in inert for why in found.values()):
        keys = list(dict.fromkeys(key for found in inert for key, reason in found.items() if reason == why))
        count = sum(1 for found in inert if why in found.values())
        where = "" if len(configs) == 1 else f" in {count} of {len(configs)} configurations"
        head, _, tail = why.partition(": ")
        them = "it" if len(keys) == 1 else "them"
        warnings.warn(f"{source}: {', '.join(keys)}: no effect {head}{where}: {tail} {them}", stacklevel=3)
