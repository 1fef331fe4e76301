"""An evaluation's summary gathered pair by pair, so that a run over thousands of pairs need not hold their rows.

:func:`~.runner.summarize` is a :class:`RunningSummary` fed the whole list; ``svs-depth eval`` feeds it each row as
the row is printed and stored, and drops the row (an audit of bulk runs: every row of a run was held to the end for
its summary, about 4.4 kB a pair, and an ``eval --db`` run again over a store that held them all held them twice
over). Its figures are those of the list, bit for bit: each mean is :func:`math.fsum` over the values, as
:func:`statistics.fmean` takes it, of the exact running sum that :meth:`_ExactSum.add` keeps (Shewchuk's partials,
the sum's exact value in a few floats), and what it lists (failures, names) is what the list gives.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter

from .metrics import UNRUN_STATUSES, PairEvaluation
from .stereo_metrics import STEREO_FIELDS, STEREO_SCOPES

__all__ = ["RunningSummary", "UNSCORED_NAMES"]

#: The most names a summary's ``unscored`` lists: a run over thousands of a camera's pairs (no truth) is not a list of
#: thousands of names in every summary. Its ``nominal_calibration`` lists as many: 2 288 KITTI pairs scored with a
#: nominal calibration were 95 % of a 63 kB summary line, in every row of a sweep's store too.
UNSCORED_NAMES = 100

#: The accuracies averaged over the scored pairs (a failed one as 0 %), and apart over the nominal ones.
ACCURACIES = ("acc_r_min_pct", "acc_r_max_pct", "acc_objects_pct")
#: The fields averaged over the pairs that have them.
MEANS = ("dense_error_median_px", "dense_within_1px", "dense_within_3px", "sparse_error_median_px",
         "sparse_within_1px", "sparse_within_3px", "inlier_precision", *STEREO_FIELDS)


class _ExactSum:
    """The exact sum of the floats added (non-overlapping partials; infinities and NaNs apart), and their count:
    :meth:`mean` is ``statistics.fmean`` of them, to the bit."""

    __slots__ = ("partials", "special", "count")

    def __init__(self) -> None:
        self.partials: list[float] = []
        self.special: list[float] = []  # inf, -inf, nan: fsum's own rules for them, whatever the finite ones
        self.count = 0

    def add(self, value: float) -> None:
        self.count += 1
        value = float(value)
        if not math.isfinite(value):
            self.special.append(value)
            return
        kept = 0
        for partial in self.partials:  # (the recipe math.fsum itself follows)
            if abs(value) < abs(partial):
                value, partial = partial, value
            high = value + partial
            low = partial - (high - value)
            if low:
                self.partials[kept] = low
                kept += 1
            value = high
        self.partials[kept:] = [value]

    def mean(self) -> float | None:
        return math.fsum(self.partials + self.special) / self.count if self.count else None


class RunningSummary:
    """:func:`~.runner.summarize`'s figures over the pairs :meth:`add` was given, in that order; :meth:`summary`
    gives them at any point (an interrupted run's summary of the pairs done)."""

    def __init__(self) -> None:
        self.pairs = 0
        self.failures: list[tuple[str, str, str | None]] = []
        self.scored = {key: _ExactSum() for key in ACCURACIES}
        self.nominal = {key: _ExactSum() for key in ACCURACIES}
        self.nominal_count = 0
        self.nominal_first: list[str] = []  # the UNSCORED_NAMES names first in sorted order, like unscored_first
        self.unscored = 0
        self.unscored_first: list[str] = []  # the UNSCORED_NAMES names first in sorted order, as summarize's
        self.means = {key: _ExactSum() for key in MEANS}
        self.ran, self.pipeline_s = 0, 0
        self.statuses: Counter[str] = Counter()
        self.scope_pairs = dict.fromkeys(STEREO_SCOPES, 0)

    def add(self, e: PairEvaluation) -> None:
        """Count one pair's evaluation."""
        self.pairs += 1
        if not e.ok:
            self.failures.append((e.name, e.status, e.reason))
        if e.acc_r_min_pct is not None or (e.has_truth and not e.ok):  # it has truth: scored, a failure at 0 %
            group = self.scored if e.calibrated is not False else self.nominal  # nominal: apart from the headline
            for key in ACCURACIES:
                group[key].add(getattr(e, key) or 0.0)
            if e.calibrated is False:
                self.nominal_count += 1
                bisect.insort(self.nominal_first, e.name)
                del self.nominal_first[UNSCORED_NAMES:]
        if e.ok and e.acc_r_min_pct is None:
            self.unscored += 1
            bisect.insort(self.unscored_first, e.name)
            del self.unscored_first[UNSCORED_NAMES:]
        for key, total in self.means.items():
            if (value := getattr(e, key)) is not None:
                total.add(value)
        if e.status not in UNRUN_STATUSES:
            self.ran += 1
            self.pipeline_s += e.time_s  # (in order from 0, as sum() adds)
        self.statuses[e.status] += 1
        for scope in STEREO_SCOPES:
            self.scope_pairs[scope] += getattr(e, f"{scope}_density") is not None

    def summary(self, wall_s: float | None = None) -> dict:
        """The summary dict (:func:`~.runner.summarize` says what each entry is)."""
        seconds = wall_s if wall_s is not None else self.pipeline_s
        return {
            "pairs": self.pairs, "failed": len(self.failures), "scored": self.scored["acc_r_min_pct"].count,
            **{key: self.scored[key].mean() for key in ACCURACIES},
            "nominal_calibration": {"scored": self.nominal_count, "names": list(self.nominal_first),
                                    **{key: self.nominal[key].mean() for key in ACCURACIES}},
            "unscored": {"count": self.unscored, "names": list(self.unscored_first)},
            **{key: self.means[key].mean() for key in MEANS[:7]},
            "pipeline_s_per_pair": self.pipeline_s / self.ran if self.ran else None,
            "pairs_per_s": self.pairs / seconds if self.pairs and seconds > 0 else None,
            "statuses": {status: self.statuses[status] for status in sorted(self.statuses)},
            # Sorted by name: a summary does not depend on the order of the list either.
            "failures": [{"name": name, "status": status, "reason": reason}
                         for name, status, reason in sorted(self.failures, key=lambda failure: failure[0])],
            **{key: self.means[key].mean() for key in STEREO_FIELDS},
            **{f"{scope}_pairs": count for scope, count in self.scope_pairs.items()},
        }
