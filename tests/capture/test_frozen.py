"""A frozen camera: one board that sends its last frame again while the other's frames go on (the rule, and
``guide``'s handling of it with a fake camera; the emulator's ``--freeze`` fault in
``tests/capture/test_capture_emulator.py``, guide against it in ``tests/capture/test_guide.py``)."""

from __future__ import annotations

import argparse
import io
import time
from types import SimpleNamespace

import pytest
import torch
from conftest import SpokenLines, unmatched_pair_fields

from svs_torch.capture.frozen import BOTH_FROZEN_S, FROZEN_PAIRS, ONE_FROZEN_S, FrozenCameraWatch
from svs_torch.core.types import StereoBatch


def frames(count: int, seed: int = 0) -> list[torch.Tensor]:
    """``count`` different textured (1, 1, 24, 32) frames."""
    generator = torch.Generator().manual_seed(seed)
    return [torch.rand(1, 1, 24, 32, generator=generator) for _ in range(count)]


def pair(left: torch.Tensor, right: torch.Tensor) -> StereoBatch:
    return StereoBatch.from_images(left, right, 276.0, 0.1075)


def watched(pairs: list[StereoBatch], watch: FrozenCameraWatch | None = None) -> list[str | None]:
    watch = watch or FrozenCameraWatch()
    return [watch.update(batch) for batch in pairs]


@pytest.mark.parametrize("camera", ["left", "right"])
def test_a_camera_whose_frame_comes_again_while_the_others_change_is_frozen(camera):
    stale, fresh = frames(1, seed=1)[0], frames(5)
    pairs = [pair(stale, new) if camera == "left" else pair(new, stale) for new in fresh]
    # the first pair has nothing to compare with; the first repeat alone could be a scene's step between the grabs
    assert watched(pairs) == [None] * FROZEN_PAIRS + [camera] * (5 - FROZEN_PAIRS)
    # pixel for pixel, not the same tensor: a frame decoded again from the same bytes is a new tensor
    copies = [pair(stale.clone(), new) if camera == "left" else pair(new, stale.clone()) for new in fresh]
    assert watched(copies) == watched(pairs)


def test_frames_unchanged_in_both_cameras_are_a_still_scene_not_a_frozen_camera():
    """The emulator's frames have no noise by default: of a still scene, both cameras send one frame again."""
    left, right = frames(2)
    assert watched([pair(left, right)] * 6) == [None] * 6


def test_both_cameras_unchanged_for_seconds_are_both_frozen():
    """Found by an audit: both boards frozen (the emulator's --freeze, noise σ 4) gave one old pair again and again,
    and guide ranged it for good. Both frames unchanged is a still noise-free scene for a while (an image folder's
    pair lasts 1 s), never for BOTH_FROZEN_S seconds of a real sensor's frames: then "both"."""
    left, right = frames(2)
    watch = FrozenCameraWatch()
    # the first repeat, at 0.5 s, starts the clock
    times = [0.0, 0.5, 1.0, BOTH_FROZEN_S + 0.49, BOTH_FROZEN_S + 0.5, BOTH_FROZEN_S + 0.6]
    assert [watch.update(pair(left, right), now_s) for now_s in times] == [None] * 4 + ["both"] * 2
    assert watch.update(pair(*frames(2, seed=3)), 9.0) is None  # new frames: the count starts again
    assert watched([pair(left, right)] * 6) == [None] * 6  # not judged without the time (capture's index)
    flat = torch.zeros(1, 1, 24, 32)
    assert [watch.update(pair(flat, flat), t) for t in (10.0, 20.0, 30.0)] == [None] * 3  # dark: the pipeline's


def test_a_scene_that_steps_between_the_two_boards_grabs_is_not_a_frozen_camera():
    """Frames without noise (the emulator's keyframes, an image folder's pairs): a step that lands between the left
    and the right grab of one pair leaves the left frame as it was and the right one new; the next pair, the left
    is new and the right as it was. Neither camera is frozen."""
    a_left, a_right, b_left, b_right, c_left, c_right = frames(6)
    steps = [pair(a_left, a_right), pair(a_left, b_right), pair(b_left, b_right), pair(b_left, b_right),
             pair(b_left, c_right), pair(c_left, c_right)]
    assert watched(steps) == [None] * 6


@pytest.mark.parametrize("camera", ["left", "right"])
def test_a_camera_frozen_beside_a_scene_that_steps_seldom_is_named_within_seconds(camera):
    """Found by an audit: the emulator's left board frozen from the start, no noise: the right frames change at
    each 0.5 s step of the scene only, both repeat between the steps, so no two pairs in a row showed the freeze;
    guide ranged the old left frame with new right ones for good ("Stop" for boxes 1.6 m away). 10 pairs a second."""
    stale, steps = frames(1, seed=1)[0], frames(12)
    watch = FrozenCameraWatch()
    judged = []
    for index in range(60):
        new = steps[index // 5]  # the scene steps every 5 pairs
        judged.append(watch.update(pair(stale, new) if camera == "left" else pair(new, stale), index / 10))
    first = judged.index(camera)
    assert set(judged[:first]) == {None} and set(judged[first:]) == {camera}
    assert ONE_FROZEN_S <= first / 10 <= ONE_FROZEN_S + 0.1  # its first repeat starts the clock (0.1 s)
    # both still for as long, neither changing: the rule of both, not of one
    left, right = frames(2, seed=4)
    assert [watch.update(pair(left, right), t) for t in (10.0, 10.5, 10.5 + ONE_FROZEN_S - 0.1)] == [None] * 3


def test_a_flat_frame_sent_again_is_not_a_frozen_camera():
    """A covered lens, the dark or a clipped sky gives one flat frame after another: the pipeline finds it blank."""
    black = torch.zeros(1, 1, 24, 32)
    assert watched([pair(black.clone(), new) for new in frames(5)]) == [None] * 5
    assert watched([pair(new, torch.ones(1, 1, 24, 32)) for new in frames(5)]) == [None] * 5


def test_frames_from_before_a_reset_are_not_compared_with():
    stale, fresh = frames(1, seed=1)[0], frames(4)
    watch = FrozenCameraWatch()
    assert watched([pair(stale, new) for new in fresh[:2]], watch) == [None, None]
    watch.reset()  # (guide: the camera opened again after a loss)
    assert watched([pair(stale, new) for new in fresh[2:]], watch) == [None, None]
    assert watch.update(None) is None  # no pair: nothing compared, nothing forgotten
    assert watch.update(pair(stale, frames(1, seed=2)[0])) == "left"


def run_guide(monkeypatch, streams: list[list[tuple[StereoBatch, float]]], count: int, blind_s: float = 0.15,
              unranged_repeated: torch.Tensor | None = None, status_stream=None, result=None, policy=None):
    """``guide``'s session over a fake camera: each open streams the next of ``streams`` (pairs and their frames'
    gaps in seconds, or None for a tick without a pair, 10 ms apart), lost after each but the last. Returns the
    session, the lines said, the logged events (name, camera or nearest_alias_m) and the pairs ranged (each seen). Each pair's result
    is ``result`` (a PipelineResult of one pair), or has no obstacle, and no kept object but those
    ``unranged_repeated`` marks (not one, or None); the status line goes to ``status_stream`` (None: nowhere);
    ``policy``: the WarningPolicy (default its own)."""
    from svs_torch.capture.guide import LiveGuide, Speaker, StatusLine, WarningPolicy
    from svs_torch.capture.link_types import CaptureError
    from svs_torch.cli import guide_loop

    said, events, ranged, opened = [], [], [], []

    class Camera:
        next_index, max_frame_gap_s = 0, 0.25

        def stream_batches(self, batch_size, num_batches=None, idle_s=None):
            opened.append(True)
            for index, item in enumerate(streams[len(opened) - 1]):
                time.sleep(0.01)
                yield None if item is None else SimpleNamespace(  # None: a tick, no pair came
                    batch=item[0], num_dropped=0, pairs=[SimpleNamespace(index=index, time_between_frames_s=item[1])])
            if len(opened) < len(streams):
                raise CaptureError("left camera: no reply")

    def ranging(batch):
        ranged.append(batch)
        if result is not None:
            return result
        return SimpleNamespace(status=torch.tensor([0]), segmentation=SimpleNamespace(from_disparity=None),
                               depth=SimpleNamespace(nearest=SimpleNamespace(valid=torch.tensor([False]),
                                                                            surface_m=torch.tensor([0.0]),
                                                                            side=torch.tensor([0]))),
                               unranged_repeated=unranged_repeated, nearest_unranged_alias_m=None,
                               **unmatched_pair_fields())

    monkeypatch.setattr(guide_loop, "open_stereo_camera", lambda *args, **kwargs: Camera())
    log = guide_loop.GuideLog(None, None)
    # (name, its camera, or its nearest_alias_m)
    monkeypatch.setattr(log, "event", lambda name, **fields: events.append(
        (name, fields.get("camera", fields.get("nearest_alias_m")))))
    log.warnings = []  # each ranged pair's 'warning', as --json writes it
    monkeypatch.setattr(log, "write", lambda pair, result, elapsed_s, warning, dropped: log.warnings.append(warning))
    guide = LiveGuide(policy or WarningPolicy(), Speaker(None, stream=SpokenLines(said)))
    args = argparse.Namespace(count=count, blind_s=blind_s, give_up_s=0, reconnect_s=0.01)
    status_line = StatusLine(status_stream, interval_s=0.0, tty=False)
    session = guide_loop.GuideSession(args, (32, 24), ranging, guide, status_line, log)
    session.run()
    return session, said, events, ranged


def test_guide_does_not_range_a_frozen_cameras_pairs_and_says_which_to_check_once(monkeypatch):
    """guide ranged a stalled board's old frame beside the other board's new one: distances of where obstacles
    were. Now such pairs are not ranged nor seen ({"event": "camera_frozen", "camera": "left"}), "Cannot see ahead"
    comes after --blind-s with "Check the left camera." (once a run), and a frame from before a loss is not
    compared with one after it."""
    from svs_torch.capture.guide import CANNOT_SEE
    from svs_torch.cli import guide_loop

    stale = frames(1, seed=1)[0]
    fresh = iter(frames(200))
    streams = [[(pair(stale, next(fresh)), 0.0) for _ in range(count)] for count in (2, 40)]  # lost after 2 pairs
    session, said, events, ranged = run_guide(monkeypatch, streams, count=42)
    frozen = [camera for name, camera in events if name == "camera_frozen"]
    # 2 pairs before the loss, then 2 after it (not compared with those before it) are ranged; the rest are not
    assert len(ranged) == 2 + FROZEN_PAIRS and frozen == ["left"] * (40 - FROZEN_PAIRS)
    assert said.count(f"{CANNOT_SEE} {guide_loop.CHECK_CAMERA.format('left')}") == 1
    assert said.count(CANNOT_SEE) == 0 and ("cannot_see", None) in events
    assert session.stopped_text().endswith(f"(4 ranged; {len(frozen)} not: one camera sent its last frame again)")


def test_a_camera_that_freezes_while_guide_is_already_blind_is_still_named(monkeypatch):
    """Found by an audit: "Check the left camera." was said only with "Cannot see ahead", so a board that stalled
    while guide was already blind was never named: its link first froze (no pair for longer than --blind-s:
    "Cannot see ahead"), then it answered with its last frame again and again, and the walker never heard which
    camera to check. Now it is said then, with "Cannot see ahead" again before it (a newer message cuts off an older
    one: nothing of that one is lost), once a run."""
    from svs_torch.capture.guide import CANNOT_SEE
    from svs_torch.cli import guide_loop

    stale, fresh = frames(1, seed=1)[0], iter(frames(200))
    # a pair ranged, 0.3 s of ticks without a pair (the link froze), then the left board's last frame again
    stream = [(pair(stale, next(fresh)), 0.0)] + [None] * 30 + [(pair(stale, next(fresh)), 0.0) for _ in range(30)]
    session, said, events, ranged = run_guide(monkeypatch, [stream], count=31)
    check = f"{CANNOT_SEE} {guide_loop.CHECK_CAMERA.format('left')}"
    assert said == [guide_loop.GUIDE_READY, CANNOT_SEE, check]
    # the first pair after the freeze is compared with the one before it: one repeat alone is no freeze
    assert len(ranged) == FROZEN_PAIRS and [name for name, _ in events].count("camera_frozen") == 31 - FROZEN_PAIRS


def test_with_blind_s_0_a_frozen_camera_is_still_named(monkeypatch):
    """Found by an audit: "Check the left camera." was said only with "Cannot see ahead", which --blind-s 0 turns
    off, so under it a stalled board's pairs went unranged in silence (38 of 40 here, only "Guide ready." said): the
    walker heard a clear way. Now the check is said alone once the camera is judged frozen, once a run, and still no
    "Cannot see ahead"."""
    from svs_torch.cli import guide_loop

    stale, fresh = frames(1, seed=1)[0], iter(frames(200))
    stream = [(pair(stale, next(fresh)), 0.0) for _ in range(40)]
    session, said, events, ranged = run_guide(monkeypatch, [stream], count=40, blind_s=0.0)
    assert said == [guide_loop.GUIDE_READY, guide_loop.CHECK_CAMERA.format("left")]
    assert len(ranged) == FROZEN_PAIRS and ("cannot_see", None) not in events


def test_guide_does_not_range_the_pairs_of_two_frozen_boards_and_says_to_check_the_cameras(monkeypatch):
    """Both boards sending their last frames again: after the seconds the watch waits (cut to 0 here) the pairs are
    not ranged, "camera_frozen" names both, and "Cannot see ahead" comes with "Check the cameras." once."""
    from svs_torch.capture.guide import CANNOT_SEE
    from svs_torch.cli import guide_loop

    monkeypatch.setattr(guide_loop, "FrozenCameraWatch", lambda: FrozenCameraWatch(both_frozen_s=0.0))
    stale = pair(*frames(2, seed=1))
    session, said, events, ranged = run_guide(monkeypatch, [[(stale, 0.0)] * 40], count=40)
    assert len(ranged) == 1 and [camera for name, camera in events if name == "camera_frozen"] == ["both"] * 39
    assert said.count(f"{CANNOT_SEE} {guide_loop.CHECK_CAMERAS}") == 1
    # found by an audit: the summary said "39 not: one camera sent its last frame again" of both boards' pairs
    assert session.stopped_text().endswith("(1 ranged; 39 not: both cameras sent their last frames again)")


@pytest.mark.parametrize("frozen_pairs", [0, -1, 1.5, True, None])
def test_the_watch_refuses_a_count_it_cannot_judge_by(frozen_pairs):
    # 0 was taken, and every pair, the first one too, named the left camera frozen.
    from svs_torch.core.errors import InputError

    with pytest.raises(InputError, match=r"frozen_pairs: expected a whole number of pairs >= 1"):
        FrozenCameraWatch(frozen_pairs)
    left, right = frames(2)
    assert FrozenCameraWatch(1).update(pair(left, right)) is None
