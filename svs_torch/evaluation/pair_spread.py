"""The results figure's per-pair panel when a store holds many pairs: each accuracy sorted over the pairs.

Why: the per-scene bars (one group of three a pair, :func:`~svs_torch.evaluation.report.results_figure`) drew a
figure 9 845 px wide for 400 pairs and 77 605 px for 3 200, whose names nobody reads (an audit of bulk
evaluation). Past :data:`MAX_SCENE_BARS` pairs the panel shows how the accuracy spreads over them instead, and
names the lowest pairs by object accuracy, the ones a researcher looks at next, in a panel 8 in wide.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["MAX_SCENE_BARS", "sorted_accuracies"]

#: The most pairs drawn as bars of their own (60 pairs at 0.22 in each: a panel 14.7 in wide).
MAX_SCENE_BARS = 60

#: How many of the lowest pairs by object accuracy the panel names.
NAMED_LOWEST = 3


def sorted_accuracies(axis, rows: Sequence[dict], scored: Sequence[bool], names: Sequence[str]) -> list[float]:
    """Draw on ``axis`` each of R_min's, R_max's and the objects' accuracies of the scored ``rows`` (``scored``:
    counted by the summary's rules, a failed pair with ground truth at 0 %) sorted from lowest to highest against
    the share of the scored pairs, and name the :data:`NAMED_LOWEST` lowest by object accuracy (``names``: each
    row's tick name). Returns every value drawn, for the caller's zoom."""
    counted = [(row, name) for row, name, count in zip(rows, names, scored) if count]
    drawn: list[float] = []
    for key, label in (("acc_r_min_pct", "R_min"), ("acc_r_max_pct", "R_max"), ("acc_objects_pct", "objects")):
        values = sorted(row[key] or 0.0 for row, _ in counted)
        axis.plot([100.0 * (i + 0.5) / len(values) for i in range(len(values))], values, label=label)
        drawn += values
    lowest = sorted(counted, key=lambda item: item[0]["acc_objects_pct"] or 0.0)[:NAMED_LOWEST]
    if lowest:
        said = "; ".join(f"{name} {row['acc_objects_pct'] or 0.0:.1f} %" for row, name in lowest)
        axis.text(0.01, 0.02, f"lowest by objects: {said}", transform=axis.transAxes, fontsize=7, va="bottom")
    left_out = len(rows) - len(counted)
    axis.set_xlabel(f"share of the {len(counted)} scored pairs, %, each accuracy sorted"
                    + (f" ({left_out} without ground truth not drawn)" if left_out else ""), fontsize=8)
    axis.set_xlim(0.0, 100.0)
    return drawn
