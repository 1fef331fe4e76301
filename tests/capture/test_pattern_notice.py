"""guide and a repeated pattern it could not range (a fence, a railing, a grate): what the walker hears
(:mod:`svs_torch.capture.pattern_notice`), on the rendered panels of experiments/repeated_patterns.py."""

from __future__ import annotations

import dataclasses
import io
import math
import sys
from pathlib import Path

import pytest
import torch
from test_frozen import frames, pair, run_guide

from svs_torch.capture.guide import CANNOT_SEE, WarningPolicy
from svs_torch.capture.pattern_notice import REPEATED_PATTERN, PatternNotice
from svs_torch.cli.guide_loop import GUIDE_READY
from svs_torch.core.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))

#: Rendered panels (kind, period px, distance m): as a loose rig's frames, guide leaves the bars without a distance,
#: ranges the checker's near part and not its other part, and ranges the grate whole.
BARS, CHECKER, GRATE = ("bars", 8, 1.5), ("checker", 8, 1.0), ("grate", 8, 1.5)


@pytest.fixture(scope="module")
def panels():
    """The pipeline's one-pair results (as guide ranges them) on the rendered panels of seed 7 as a loose rig's
    camera frames (every deviation at once, JPEG digit 4, σ 4)."""
    import repeated_patterns as rp

    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    lefts, rights, _, _ = rp.render_pairs(periods=(8,))
    views = rp.condition_batch(lefts, rights, rp.LOOSE_RIG, 4, 4.0)
    picked = [rp.cases((8,)).index(case) for case in (BARS, CHECKER, GRATE)]
    with torch.inference_mode():
        results = {case: estimate_obstacle_depth(views.select([index]), PipelineConfig())
                   for case, index in zip((BARS, CHECKER, GRATE), picked)}
        results["batch"] = estimate_obstacle_depth(views.select(picked), PipelineConfig())
    return results


def nearest_alias_m(result) -> float | None:
    """The one pair's :attr:`PipelineResult.nearest_unranged_alias_m`, None where NaN (no unranged pattern)."""
    value = float(result.nearest_unranged_alias_m[0])
    return None if math.isnan(value) else value


def test_the_nearest_alias_of_an_unranged_pattern_bounds_how_near_it_may_be(panels):
    """The bars' nearest alias, of those ``estimate --json`` lists: nearer than the truth, which is among them; a
    pair ranged whole has no unranged pattern (NaN); the same, batched, and 0 for a pattern no alias bounds."""
    from svs_torch.depth.alias_choice import alias_depths_m, nearest_alias_depth_m

    bars = panels[BARS]
    assert bool(bars.unranged_repeated[0].all()) and not bool(bars.depth.objects.valid.any())
    depth_m, valid = alias_depths_m(bars.dense, bars.focal_px, bars.baseline_m, bars.doffs_px)
    aliases = depth_m[0][valid[0] & bars.unranged_repeated[0, :, None]]
    assert nearest_alias_m(bars) == pytest.approx(float(aliases.min())) and nearest_alias_m(bars) < 0.5
    assert float((aliases - BARS[2]).abs().min()) < 0.05 * BARS[2]
    assert not bool(panels[GRATE].unranged_repeated.any()) and nearest_alias_m(panels[GRATE]) is None
    # Batched: each pair its own (the three panels as one batch); an unranged object whose shift was not fitted
    # has no alias, so it may be anywhere (0).
    alone = [float(panels[case].nearest_unranged_alias_m[0]) for case in (BARS, CHECKER, GRATE)]
    torch.testing.assert_close(panels["batch"].nearest_unranged_alias_m, torch.tensor(alone), equal_nan=True)
    fitted = bars.dense.repeated.fitted.clone()
    fitted[0, 0] = False
    unfitted = dataclasses.replace(bars.dense, repeated=dataclasses.replace(bars.dense.repeated, fitted=fitted))
    assert nearest_alias_depth_m(unfitted, bars.unranged_repeated, bars.focal_px, bars.baseline_m).tolist() == [0.0]
    with pytest.raises(InputError, match=r"unranged: expected \(1, 2\)"):
        nearest_alias_depth_m(bars.dense, torch.ones(1, 3, dtype=torch.bool), bars.focal_px, bars.baseline_m)


def _pairs(count: int) -> list[list[tuple]]:
    """One camera opening streaming ``count`` pairs (guide compares their frames; the result is the panel's)."""
    return [[(pair(*frames(2, seed=index)), 0.0) for index in range(count)]]


def test_guide_says_an_unranged_pattern_that_may_be_near_where_it_was_silent(monkeypatch, panels):
    """Was: guide on the bars (nothing ranged) said nothing, then after --blind-s "Cannot see ahead": neither tells a
    walker that a fence may be an arm's length away. Now, confirmed on a majority of 3 pairs, it says
    REPEATED_PATTERN, again after --repeat-s while the bars stay in view, with its nearest alias logged; and it
    sees, so never "Cannot see ahead"."""
    shown = io.StringIO()
    session, said, events, _ = run_guide(monkeypatch, _pairs(40), 40, result=panels[BARS],
                                         policy=WarningPolicy(repeat_s=0.1), status_stream=shown)
    assert said[:2] == [GUIDE_READY, REPEATED_PATTERN] and said.count(REPEATED_PATTERN) >= 2
    assert CANNOT_SEE not in " ".join(said)
    nearest = round(nearest_alias_m(panels[BARS]), 3)
    assert [event for event in events if event[0] == "repeated_pattern"] == [("repeated_pattern", nearest)] * len(
        [line for line in said if line == REPEATED_PATTERN])
    assert "cannot_see" not in [name for name, _ in events]
    assert "a repeated pattern seen, not ranged" in shown.getvalue()
    # --json's per-pair 'warning' holds the words said on the pair, as for a warning
    assert [w["message"] for w in session.log.warnings if w["message"]] == said[1:]


def test_guide_says_no_pattern_beyond_the_band_nor_one_beside_a_warning(monkeypatch, panels):
    """Bars whose nearest alias lies beyond --far-m are no warning: not said, and not seen (nothing ranged), so
    "Cannot see ahead" as before. The checker's near part ranged (a warning in effect) and its other part not:
    the warning alone, not the two by turns."""
    _, said, _, _ = run_guide(monkeypatch, _pairs(30), 30, result=panels[BARS],
                              policy=WarningPolicy(near_m=0.1, far_m=0.3, repeat_s=0.1))
    assert REPEATED_PATTERN not in said and CANNOT_SEE in " ".join(said)
    assert nearest_alias_m(panels[CHECKER]) is not None
    _, said, _, _ = run_guide(monkeypatch, _pairs(30), 30, result=panels[CHECKER], policy=WarningPolicy(repeat_s=0.1))
    assert said[0] == GUIDE_READY and said[1:] and all(line == "Stop. Obstacle at 0.9 metres" for line in said[1:])


def test_the_notice_is_confirmed_repeated_and_new_after_the_pattern_left():
    notice = PatternNotice(far_m=2.0, repeat_s=1.0, confirm_frames=3)
    assert notice.update(0.4, 0.0) is None  # one pair of 3: not confirmed
    assert notice.update(None, 0.1) is None and notice.update(0.5, 0.2) == REPEATED_PATTERN  # 2 of 3
    assert notice.nearest_m == 0.5
    assert notice.update(0.4, 0.3) is None and notice.update(0.4, 1.3) == REPEATED_PATTERN  # after repeat_s
    assert notice.update(0.4, 2.4, quiet=False) is None  # not over a warning or another message
    assert notice.update(0.4, 2.5) == REPEATED_PATTERN
    assert [notice.update(None, 2.6 + step / 10) for step in range(3)] == [None] * 3  # out of view: forgotten
    assert notice.update(0.4, 3.0) is None and notice.update(0.4, 3.1) == REPEATED_PATTERN  # a new one, at once
    assert PatternNotice(far_m=0.3).counts(0.31) is False and PatternNotice(far_m=0.3).counts(0.0) is True
    notice.reset()
    assert notice.nearest_m is None and notice.update(0.4, 3.2) is None


@pytest.mark.parametrize("kwargs, match", [({"far_m": 0.0}, "far_m, repeat_s"), ({"repeat_s": -1.0}, "far_m"),
                                           ({"far_m": float("nan")}, "far_m"),
                                           ({"confirm_frames": 0}, "confirm_frames: expected a whole number")])
def test_the_notice_refuses_bad_settings_by_name(kwargs, match):
    with pytest.raises(InputError, match=match):
        PatternNotice(**kwargs)


def test_guide_shows_a_repeated_pattern_it_saw_but_could_not_range(monkeypatch, panels):
    """Was: a fence ahead whose alias the views could not tell (svs_torch.depth.alias_choice) left guide's status
    line at "nearest none", like a clear path. Now the line says a repeated pattern was seen and not ranged."""
    streams = [[(pair(*frames(2, seed=3)), 0.0)]]
    for result, marked, expected in ((panels[BARS], None, 1), (None, torch.tensor([[False, False]]), 0),
                                     (None, None, 0), (panels[GRATE], None, 0)):
        shown = io.StringIO()
        run_guide(monkeypatch, streams, count=1, unranged_repeated=marked, status_stream=shown, result=result)
        lines = shown.getvalue().splitlines()
        assert lines and sum("a repeated pattern seen, not ranged" in line for line in lines) == expected, lines


def test_a_covered_lens_or_unrelated_views_make_no_pattern_to_speak_of():
    """Noise is no fence: a covered lens's dark noise and two unrelated random views, as the board's digit 4 frames
    through guide's configuration, have no unranged repeated object, so guide never says REPEATED_PATTERN for them
    (nor counts them as seen). With the period test's least peak at 0.05 instead of its default, the first noise
    pair here reads as a pattern at 0.38 m."""
    from svs_torch.core.types import StereoBatch
    from svs_torch.data import camera_frame_pairs
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    generator = torch.Generator().manual_seed(0)
    left = 0.08 + 0.02 * torch.randn(6, 1, 240, 320, generator=generator)
    right = 0.08 + 0.02 * torch.randn(6, 1, 240, 320, generator=generator)
    left[3:], right[3:] = torch.rand(3, 1, 240, 320, generator=generator), torch.rand(3, 1, 240, 320,
                                                                                      generator=generator)
    frames = camera_frame_pairs(StereoBatch.from_images(left.clamp(0, 1), right.clamp(0, 1), 276.0, 0.1075), 4, 4.0,
                                torch.Generator().manual_seed(1))
    with torch.inference_mode():
        result = estimate_obstacle_depth(frames, PipelineConfig().for_guide())
    assert bool(result.nearest_unranged_alias_m.isnan().all()), result.nearest_unranged_alias_m


def test_the_report_of_each_pair_computes_alias_distances_only_where_a_pattern_was_left_unranged(panels,
                                                                                                  monkeypatch):
    """Found profiling ``estimate --pairs``: every pair's report took its dense map out of the batch and computed the
    distances a repeat fits (0.5 ms of 46 a pair) and then threw them away where no object was left unranged. The
    bars (left without a distance) still get theirs; the grate (ranged whole) gets None without them computed."""
    import svs_torch.depth.alias_choice as alias_choice
    from svs_torch.cli.object_report import repeated_fields

    bars = repeated_fields(panels[BARS], 0, (1.0, 1.0))
    told = [field["alias_depths_m"] for field in bars if field["alias_depths_m"] is not None]
    assert told and all(len(aliases) >= 2 and aliases == sorted(aliases) for aliases in told)
    grate = repeated_fields(panels[GRATE], 0, (1.0, 1.0))
    monkeypatch.setattr(alias_choice, "alias_depths_m", lambda *args: pytest.fail("computed for nothing"))
    assert repeated_fields(panels[GRATE], 0, (1.0, 1.0)) == grate
    assert all(field["alias_depths_m"] is None for field in grate) and any(field["period_px"] for field in grate)
