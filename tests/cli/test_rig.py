"""``--calibration`` of the commands (svs_torch.cli.rig): what it says of the pairs it does not apply to."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

import svs_torch.evaluation.kept_rows as kept_rows
from svs_torch.cli.rig import warn_scenes_keep_their_own


def _warned(scenes: list[str]) -> str:
    with pytest.warns(UserWarning) as caught:
        warn_scenes_keep_their_own(SimpleNamespace(calibration="rig.json"), scenes)
    assert len(caught) == 1
    return str(caught[0].message)


@pytest.mark.parametrize(("count", "listed"), [(1, "S0"), (3, "S0, S1, S2"), (4, "S0, S1, S2 and 1 more"),
                                               (7, "S0, S1, S2 and 4 more")])
def test_scene_folders_a_rig_calibration_skips_are_listed_as_the_sweeps_notices_list_them(monkeypatch, count, listed):
    """The warning named the first three scenes and how many more with its own copy of kept_rows.named's formatting
    (the sweep's and results' notices); found on reading the change that moved results' copy. It now calls named
    itself: the same words, one place to change them."""
    scenes = [f"S{i}" for i in range(count)]
    assert f"not applied to {count} scene folder{'s' * (count > 1)} ({listed}): a scene is not" in _warned(scenes)
    monkeypatch.setattr(kept_rows, "named", lambda names: f"{len(names)} by named")
    assert f"({count} by named): a scene is not" in _warned(scenes)


def test_nothing_is_said_without_a_calibration_or_without_scene_folders(recwarn):
    warn_scenes_keep_their_own(SimpleNamespace(calibration=None), ["S0"])
    warn_scenes_keep_their_own(SimpleNamespace(calibration="rig.json"), [])
    assert not recwarn.list
