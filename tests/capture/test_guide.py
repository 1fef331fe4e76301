"""The live-guide pieces with fake distances and a fake clock: warning policy, speech output, fps meter."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import re
import stat
import sys
import time
import warnings

import pytest

from svs_torch.capture.guide import (CANNOT_SEE, CLEAR, CONFIRM_FRAMES, SEEING_AGAIN, SPEECH_MISSING, STOP, WARN,
                                     FpsMeter, LiveGuide, SightWatch, Speaker, StatusLine, WarningPolicy)
from svs_torch.core.checks import InputError


def run_policy(policy: WarningPolicy, samples: list[tuple[float, float | None]]) -> list[str | None]:
    return [policy.update(distance, now) for now, distance in samples]


@pytest.mark.parametrize("distance, expected", [
    (None, CLEAR), (float("inf"), CLEAR), (float("nan"), CLEAR), (2.5, CLEAR), (2.0, WARN), (1.5, WARN),
    (1.0, WARN), (0.99, STOP), (0.0, STOP),
])
def test_classify_default_band(distance, expected):
    assert WarningPolicy().classify(distance) == expected


def test_sight_watch_says_when_nothing_was_ranged_for_a_while():
    """Silence must mean "nothing near": no pair ranged for blind_s seconds (from the start too) is said once,
    the first ranged pair after it too; a single failure among ranged pairs says nothing; 0 never says it."""
    watch = SightWatch(blind_s=2.0, start_s=0.0)
    said = [watch.update(ranged, now) for now, ranged in
            [(0.5, True), (1.0, False), (2.4, False), (2.6, False), (3.0, False), (3.5, False), (4.0, True),
             (4.5, True), (5.0, False)]]
    # Seeing again takes a majority of the last 3 pairs seen, as a warning does (an audit: a covered lens's noise,
    # ranged now and then, said "Seeing ahead again" at each such pair while the lens stayed covered).
    assert said == [None, None, None, CANNOT_SEE, None, None, None, SEEING_AGAIN, None]
    covered = SightWatch(blind_s=1.0, start_s=0.0)
    seen = [False, False, True, False, False, True, False, False, False, True, False, True, True]
    said = [covered.update(s, 0.5 * (i + 1)) for i, s in enumerate(seen)]
    assert said.count(CANNOT_SEE) == 1 and said.count(SEEING_AGAIN) == 1 and said[-2] == SEEING_AGAIN
    assert SightWatch(blind_s=1.0, start_s=0.0, confirm_frames=1).update(False, 1.0) == CANNOT_SEE
    assert SightWatch(blind_s=1.0, start_s=0.0).update(False, 1.0) == CANNOT_SEE  # never ranged since the start
    never = SightWatch(blind_s=0.0, start_s=0.0)
    assert [never.update(False, t) for t in (1.0, 100.0)] == [None, None]
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(InputError, match="blind_s"):
            SightWatch(blind_s=bad)


def test_warning_policy_reset_warns_again_at_once():
    policy = WarningPolicy(repeat_s=10.0)
    assert policy.update(1.5, 0.0) is not None and policy.update(1.5, 1.0) is None  # rate-limited
    policy.reset()
    assert policy.current == CLEAR and policy.update(1.5, 2.0) is not None  # after a loss: at once


def test_warns_in_band_and_rate_limits_repeats():
    said = run_policy(WarningPolicy(repeat_s=3.0), [(0.0, 1.5), (1.0, 1.4), (2.9, 1.3), (3.1, 1.3), (4.0, 1.2)])
    assert said == ["Obstacle ahead, 1.5 metres", None, None, "Obstacle ahead, 1.3 metres", None]


def test_class_change_speaks_at_once():
    """A more urgent class is said at once; a less urgent one waits for repeat_s (a walker swaying on the near edge
    heard "Stop" and "Obstacle ahead" by turns every 0.6 s: an audit), unless a clear spell of CLEAR_SPELL_S came
    between (then it is a new obstacle: one 6 s after a clear path went unsaid until repeat_s ran out)."""
    said = run_policy(WarningPolicy(repeat_s=10.0, confirm_frames=1),
                      [(0.0, 1.5), (0.5, 0.8), (0.6, 0.7), (1.0, 3.0), (1.2, 1.8), (10.6, 1.8)])
    assert said == ["Obstacle ahead, 1.5 metres", "Stop. Obstacle at 0.8 metres", None, None, None,
                    "Obstacle ahead, 1.8 metres"]
    sway = run_policy(WarningPolicy(confirm_frames=1), [(0.3 * i, 0.95 if i % 2 else 1.15) for i in range(1, 13)])
    # 0.95 / 1.15 m by turns, 0.3 s apart: "Stop" at 0.3 s and again once repeat_s (3 s) ran out, nothing between
    assert [(i, m) for i, m in enumerate(sway) if m] == [(0, "Stop. Obstacle at 0.9 metres"),
                                                         (10, "Stop. Obstacle at 0.9 metres")]
    new_obstacle = run_policy(WarningPolicy(repeat_s=10.0, confirm_frames=1),
                              [(0.0, 1.9), (0.2, None), (1.0, None), (1.3, None), (8.0, 1.9)])
    assert new_obstacle == ["Obstacle ahead, 1.9 metres", None, None, None, "Obstacle ahead, 1.9 metres"]
    flicker = run_policy(WarningPolicy(repeat_s=10.0, confirm_frames=1), [(0.0, 1.9), (0.5, None), (1.0, 1.9)])
    assert flicker == ["Obstacle ahead, 1.9 metres", None, None]  # under CLEAR_SPELL_S: the same obstacle


def test_silent_beyond_band_and_without_obstacle():
    assert run_policy(WarningPolicy(), [(0.0, 5.0), (1.0, None), (2.0, 2.3)]) == [None, None, None]


def test_hysteresis_stops_flapping_on_band_edge():
    samples = [(0.1 * i, 1.97 if i % 2 else 2.04) for i in range(10)]
    policy = WarningPolicy(repeat_s=100.0, hysteresis_m=0.1, confirm_frames=1)
    said = run_policy(policy, samples)
    assert said[0] is None and said[1] == "Obstacle ahead, 2.0 metres"
    assert said[2:] == [None] * 8 and policy.current == WARN
    assert run_policy(policy, [(2.0, 2.2)]) == [None] and policy.current == CLEAR  # well past the edge
    flappy = run_policy(WarningPolicy(repeat_s=100.0, hysteresis_m=0.0, confirm_frames=1), samples)
    assert flappy[1] == "Obstacle ahead, 2.0 metres" and sum(m is not None for m in flappy) == 1  # not 5 times


def test_an_obstacle_seen_every_other_frame_is_said_once_per_repeat():
    """Found by a review of the guide: a frame with no obstacle dropped the class to clear, and the next frame in
    the band was a class change, said at once: a detection every other frame was said on every second frame (20
    messages in 2 s), each cutting the last one off. A return to the class last spoken waits for repeat_s; a more
    urgent class is still said at once."""
    flicker = [(i / 20, [1.5, None][i % 2]) for i in range(80)]
    said = [m for m in run_policy(WarningPolicy(repeat_s=3.0, confirm_frames=1), flicker) if m]
    assert said == ["Obstacle ahead, 1.5 metres", "Obstacle ahead, 1.5 metres"]  # at 0 s and at 3 s
    edge = [(i / 20, [1.9, 2.2][i % 2]) for i in range(40)]
    assert len([m for m in run_policy(WarningPolicy(repeat_s=3.0, confirm_frames=1), edge) if m]) == 1
    closer = run_policy(WarningPolicy(repeat_s=3.0, confirm_frames=1), [(0.0, 1.5), (0.05, None), (0.1, 0.8)])
    assert closer == ["Obstacle ahead, 1.5 metres", None, "Stop. Obstacle at 0.8 metres"]


def test_one_noisy_frame_neither_warns_nor_silences_a_warning():
    """The default rule judges the median of the last three frames (CONFIRM_FRAMES): a single frame ranged wrong
    (a far wall's frame ranged at 1.6 m; one frame of an obstacle in the band that found nothing) changes nothing,
    where each frame alone says the wall's wrong frame; a true obstacle is warned of on its second frame, at the median's
    distance, and two frames in a row with no obstacle end the warning."""
    assert CONFIRM_FRAMES == 3
    distances = [3.9, 1.6, 3.9, 3.9, 1.5, 1.4, None, 1.3, None, None]
    frames = [(0.05 * i, d) for i, d in enumerate(distances)]
    policy = WarningPolicy(repeat_s=10.0)
    said = run_policy(policy, frames)
    assert said == [None] * 5 + ["Obstacle ahead, 1.5 metres"] + [None] * 4
    assert policy.current == CLEAR and policy.confirmed_m is None
    alone = run_policy(WarningPolicy(repeat_s=10.0, confirm_frames=1), frames)
    assert alone == [None, "Obstacle ahead, 1.6 metres"] + [None] * 8  # the wall's wrong frame is said


def test_confirmed_distance_is_the_median_of_the_last_frames():
    """An odd count takes the middle distance, an even one the farther middle one (a warning needs a majority); a
    frame without an obstacle counts as farther than any; reset forgets the frames."""
    policy = WarningPolicy(confirm_frames=3)
    assert [policy.confirm(d) for d in (2.0, 1.0, 1.5, 3.0, None, None)] == [2.0, 2.0, 1.5, 1.5, 3.0, None]
    two = WarningPolicy(confirm_frames=2)
    assert [two.confirm(d) for d in (1.2, 1.8, float("nan"), 1.0)] == [1.2, 1.8, None, None]
    policy.update(1.2, 0.0)
    policy.reset()
    assert policy.confirmed_m is None and policy.confirm(1.3) == 1.3  # the frames before the reset are gone
    for bad in (0, -1, 2.5, True, "3"):
        with pytest.raises(InputError, match="confirm_frames: expected a whole number of frames >= 1"):
            WarningPolicy(confirm_frames=bad)


def test_nearer_obstacle_on_another_side_is_said_within_repeat():
    """Someone stepping in beside the obstacle warned of, nearer by nearer_elsewhere_m or more, is said at once
    (it waited for repeat_s before, in the same class); a side change alone, a nearer distance on the same side,
    the same obstacle drifting into another third as it nears, or a flicker back to the farther one is not."""
    def said(samples, **kwargs):
        policy = WarningPolicy(repeat_s=3.0, confirm_frames=1, **kwargs)
        return [policy.update(distance, now, side) for now, distance, side in samples]

    step_in = [(0.0, 1.8, "left"), (0.5, 1.3, "right"), (0.6, 1.8, "left"), (0.7, 1.3, "right")]
    assert said(step_in) == ["Obstacle on the left, 1.8 metres", "Obstacle on the right, 1.3 metres", None, None]
    assert said(step_in, nearer_elsewhere_m=math.inf) == ["Obstacle on the left, 1.8 metres", None, None, None]
    assert said(step_in, nearer_elsewhere_m=0.6) == ["Obstacle on the left, 1.8 metres", None, None, None]
    same_side = [(0.0, 1.8, "left"), (0.5, 1.3, "left")]
    assert said(same_side) == ["Obstacle on the left, 1.8 metres", None]
    # The same obstacle nearing, its centroid crossing into the centre third: not a jump from the pair before.
    drift = [(0.05 * i, 1.8 - 0.07 * i, "left" if i < 3 else "centre") for i in range(10)]
    assert said(drift) == ["Obstacle on the left, 1.8 metres"] + [None] * 9
    # Below the band: "Stop" again for a nearer one elsewhere; the side unknown is never a new obstacle.
    assert said([(0.0, 0.9, "left"), (0.5, 0.5, "right")])[1] == "Stop. Obstacle on the right at 0.5 metres"
    assert said([(0.0, 1.8, None), (0.5, 1.3, "right"), (0.6, 1.2, None)]) == [
        "Obstacle ahead, 1.8 metres", None, None]


def test_no_warning_below_band_when_disabled():
    policy = WarningPolicy(warn_below_band=False)
    assert run_policy(policy, [(0.0, 0.5)]) == [None]
    assert policy.classify(0.5) == CLEAR


@pytest.mark.parametrize("kwargs, message", [
    ({"near_m": 2.0, "far_m": 1.0}, "near_m, far_m: expected 0 <= near_m < far_m, got 2.0, 1.0"),
    ({"repeat_s": -1.0}, "repeat_s, hysteresis_m, nearer_elsewhere_m: expected non-negative"),
    ({"nearer_elsewhere_m": -0.1}, "nearer_elsewhere_m: expected non-negative values, got 3.0, 0.1, -0.1"),
    ({"nearer_elsewhere_m": float("nan")}, "nearer_elsewhere_m: expected non-negative"),
])
def test_policy_rejects_bad_settings(kwargs, message):
    with pytest.raises(InputError, match=message):
        WarningPolicy(**kwargs)


def test_speaker_text_only():
    stream = io.StringIO()
    speaker = Speaker(None, stream=stream)
    assert not speaker.speaks
    speaker.say("Obstacle ahead, 1.5 metres")
    assert stream.getvalue() == "Obstacle ahead, 1.5 metres\n"


def test_speaker_runs_the_speech_program(tmp_path):
    record = tmp_path / "spoken.txt"
    fake = tmp_path / "fake-espeak"
    fake.write_text(f"#!{sys.executable}\nimport sys\nopen({str(record)!r}, 'a').write(' '.join(sys.argv[1:]) + '\\n')\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    speaker = Speaker(str(fake), words_per_minute=150, stream=None)
    assert speaker.speaks
    speaker.say("Stop. Obstacle at 0.8 metres")
    speaker.close()
    assert record.read_text() == "-s 150 Stop. Obstacle at 0.8 metres\n"


def test_a_repeated_message_still_being_said_is_not_cut_off(tmp_path):
    """The same message again while it is still spoken lets it finish (a --repeat-s shorter than the sentence had
    restarted it mid-word each time); a different one interrupts it at once; after it ends, a repeat is said."""
    record = tmp_path / "spoken.txt"
    # Speaks the first message for 2 s (it must still be speaking when it is said again), the other for 0.2 s (its
    # end is waited for twice, before it is said again and at close: 2 s each made the test 4 s), writing what it
    # started.
    fake = tmp_path / "slow-espeak"
    fake.write_text(f"#!{sys.executable}\nimport sys, time\nopen({str(record)!r}, 'a').write(sys.argv[-1] + '\\n')\n"
                    "time.sleep(2 if sys.argv[-1].startswith('Obstacle ahead') else 0.2)\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    def started(count: int) -> None:  # the fake has begun its count-th sentence
        deadline = time.monotonic() + 20
        while not (record.exists() and len(record.read_text().splitlines()) >= count):
            assert time.monotonic() < deadline
            time.sleep(0.02)

    stream = io.StringIO()
    speaker = Speaker(str(fake), stream=stream)
    speaker.say("Obstacle ahead, 1.5 metres")
    first = speaker._process
    started(1)
    speaker.say("Obstacle ahead, 1.5 metres")
    assert speaker._process is first and first.poll() is None  # not restarted
    speaker.say("Stop. Obstacle at 0.9 metres")
    assert first.poll() is not None and speaker._process is not first  # a new message cuts in
    started(2)
    speaker._process.wait(timeout=10)
    speaker.say("Stop. Obstacle at 0.9 metres")  # the last one has ended: said again
    started(3)
    speaker.close()
    assert stream.getvalue().count("\n") == 4  # every message is still printed
    assert record.read_text().splitlines() == ["Obstacle ahead, 1.5 metres", "Stop. Obstacle at 0.9 metres",
                                               "Stop. Obstacle at 0.9 metres"]


def test_speaker_falls_back_to_text_when_program_fails(tmp_path):
    stream = io.StringIO()
    speaker = Speaker(str(tmp_path / "missing-espeak"), stream=stream)
    speaker.say("hello")
    assert not speaker.speaks
    assert "speech disabled" in stream.getvalue() and stream.getvalue().startswith("hello\n")


def test_speaker_says_the_words_when_their_print_fails(tmp_path):
    """Found by an audit of a closed terminal: the words were printed first, and a print to a terminal that had
    hung up (EIO) raised before "Guide stopped. No more warnings." was spoken. Now spoken first, then printed."""
    import errno

    class HungUpTerminal(io.StringIO):
        def write(self, text: str) -> int:
            raise OSError(errno.EIO, "Input/output error")

    record = tmp_path / "spoken.txt"
    fake = tmp_path / "fake-espeak"
    fake.write_text(f"#!{sys.executable}\nimport sys\nopen({str(record)!r}, 'a').write(sys.argv[-1] + '\\n')\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    speaker = Speaker(str(fake), stream=HungUpTerminal())
    with pytest.raises(OSError):
        speaker.say("Guide stopped. No more warnings.")
    speaker.close()
    assert record.read_text() == "Guide stopped. No more warnings.\n"


def test_speaker_auto_finds_espeak(monkeypatch):
    monkeypatch.setattr("shutil.which", lambda name: "/usr/bin/espeak-ng" if name == "espeak-ng" else None)
    assert Speaker().executable == "/usr/bin/espeak-ng"
    monkeypatch.setattr("shutil.which", lambda name: None)
    assert not Speaker().speaks


def test_speaker_says_once_per_process_that_espeak_is_missing(monkeypatch):
    monkeypatch.setattr("shutil.which", lambda name: None)
    monkeypatch.setattr("svs_torch.capture.speech._NOTICES_GIVEN", set())
    stream = io.StringIO()
    first = Speaker(stream=stream, notices=stream)
    for _ in range(3):
        first.say("Obstacle ahead, 1.5 metres")
    Speaker(stream=stream, notices=stream).say("Stop. Obstacle at 0.8 metres")  # a second speaker: no second notice
    lines = stream.getvalue().splitlines()
    assert lines[0] == SPEECH_MISSING and "apt-get install espeak-ng" in lines[0]
    assert lines.count(SPEECH_MISSING) == 1 and len(lines) == 5
    quiet = io.StringIO()
    Speaker(None, stream=quiet).say("hello")  # --no-speech: text only, and no notice
    assert quiet.getvalue() == "hello\n"


def test_the_notice_that_espeak_is_missing_goes_to_stderr_not_among_the_warnings(monkeypatch, capsys):
    """Found by an audit: in text mode guide prints its warnings on stdout, and the notice went there too, where a
    program reading the warnings took it for one."""
    monkeypatch.setattr("shutil.which", lambda name: None)
    monkeypatch.setattr("svs_torch.capture.speech._NOTICES_GIVEN", set())
    warnings_out = io.StringIO()
    Speaker(stream=warnings_out).say("Obstacle ahead, 1.5 metres")
    assert warnings_out.getvalue() == "Obstacle ahead, 1.5 metres\n"
    assert capsys.readouterr().err.strip() == SPEECH_MISSING


def test_the_side_said_is_that_of_the_obstacle_whose_distance_is_said():
    """Found by an audit of a guide walk: the distance is the median of the last frames', the side was the current
    frame's, so "Stop. Obstacle on the right at 0.9 metres" named a 0.94 m obstacle on the left and the side of one at
    0.80 m on the right."""
    policy = WarningPolicy(near_m=1.0, far_m=2.0, confirm_frames=3, repeat_s=0.0)
    said = [policy.update(d, now_s=i, side=s) for i, (d, s) in
            enumerate([(1.5, "left"), (1.4, "left"), (0.94, "left"), (0.80, "right"), (0.85, "right")])]
    assert said[2] == "Obstacle on the left, 1.4 metres"  # the median of 1.5, 1.4, 0.94 is the second frame's
    assert said[3] == "Stop. Obstacle on the left at 0.9 metres"  # 0.94 m, the left obstacle's: not "on the right"
    assert said[4] == "Stop. Obstacle on the right at 0.8 metres"  # 0.94, 0.80, 0.85: the right one's 0.85
    policy.update(0.82, now_s=5, side="right")
    assert (policy.confirmed_m, policy.confirmed_side) == (0.82, "right")  # 0.80, 0.85, 0.82: the median's side


def test_fps_meter():
    meter = FpsMeter(window_s=1.0)
    assert meter.tick(0.0) == 0.0
    for i in range(1, 11):
        rate = meter.tick(i * 0.1)
    assert rate == pytest.approx(10.0)
    assert meter.tick(5.0) == 0.0  # the old ticks left the window
    with pytest.raises(InputError, match="window_s"):
        FpsMeter(window_s=0.0)
    for endless in (math.nan, math.inf):  # taken before: no tick ever left the window, which grew all the walk long
        with pytest.raises(InputError, match="window_s: expected a positive finite window"):
            FpsMeter(window_s=endless)


def test_live_guide_with_fake_distances():
    stream = io.StringIO()
    guide = LiveGuide(WarningPolicy(repeat_s=2.0, confirm_frames=1), Speaker(None, stream=stream),
                      FpsMeter(window_s=5.0))
    distances = [3.0, 2.5, 1.9, 1.8, 1.7, 1.2, 0.9, 0.9, None, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5]
    said = [guide.update(d, now_s=0.25 * i) for i, d in enumerate(distances)]
    # The relief after "Stop" waits for repeat_s (2 s after it, at 3.5 s), as a repeat would.
    assert said == [None, None, "Obstacle ahead, 1.9 metres", None, None, None, "Stop. Obstacle at 0.9 metres",
                    None, None, None, None, None, None, None, "Obstacle ahead, 1.5 metres"]
    assert stream.getvalue().splitlines() == [m for m in said if m]
    assert guide.meter.fps == pytest.approx(4.0)
    assert guide.status(1.5) == "  4.0 fps  nearest 1.5 m  warn"


def test_status_before_a_second_frame_shows_no_rate():
    """One frame has no rate: the status says "--" (guide --count 1 ended on "0.0 fps", read as a stalled camera)."""
    guide = LiveGuide(WarningPolicy(), Speaker(None, stream=io.StringIO()), FpsMeter(window_s=5.0))
    assert guide.status(None) == "   -- fps  nearest none  clear"
    guide.update(None, now_s=1.0)
    assert not guide.meter.measured
    assert guide.status(None).startswith("   -- fps")
    guide.update(None, now_s=1.5)
    assert guide.meter.measured
    assert guide.status(None).startswith("  2.0 fps")


def terminal_screen(text: str) -> list[str]:
    """What a terminal shows after ``text``: ``\\r`` returns to the start of the line (later text overwrites),
    ``\\n`` starts a new one."""
    lines, column = [""], 0
    for char in text:
        if char == "\n":
            lines.append("")
            column = 0
        elif char == "\r":
            column = 0
        else:
            lines[-1] = lines[-1][:column] + char + lines[-1][column + 1:]
            column += 1
    return [line.rstrip() for line in lines if line.strip()]


def test_warnings_get_their_own_line_and_the_status_line_is_redrawn():
    terminal = io.StringIO()  # stdout and stderr on one terminal
    status_line = StatusLine(terminal, tty=True)
    status_line.show(" 12.5 fps  nearest 1.4 m  warn  left")
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = status_line.show_warning
        warnings.warn("left/right: expected the left board to be the stereo master", RuntimeWarning)
    speaker = Speaker(None, stream=status_line.lines_above(terminal))
    speaker.say("Obstacle ahead, 1.4 metres")
    status_line.show(" 12.0 fps  nearest 1.3 m  warn  left")
    status_line.close()
    assert terminal_screen(terminal.getvalue()) == [
        "warning: left/right: expected the left board to be the stereo master",
        "Obstacle ahead, 1.4 metres",
        " 12.0 fps  nearest 1.3 m  warn  left",
    ]


def test_status_line_into_a_log_is_a_plain_line_every_interval():
    """Into a file or a pipe the status is never redrawn with carriage returns (a log would show the whole walk as
    one line): a plain line at most every interval, messages on lines of their own, the last status at close."""
    log, now = io.StringIO(), [0.0]
    status_line = StatusLine(log, interval_s=5.0, clock=lambda: now[0])
    assert not status_line.tty  # a StringIO has no terminal behind it
    for step in range(12):  # a frame every second
        now[0] = float(step)
        status_line.show(f"{step:5.1f} fps  nearest 1.4 m  warn  left")
        if step == 3:
            status_line.message("Obstacle ahead, 1.4 metres")
    status_line.close()
    assert "\r" not in log.getvalue()
    assert log.getvalue().splitlines() == [
        "Obstacle ahead, 1.4 metres",
        "  5.0 fps  nearest 1.4 m  warn  left",
        " 10.0 fps  nearest 1.4 m  warn  left",
        " 11.0 fps  nearest 1.4 m  warn  left",
    ]


class _Terminal(io.StringIO):
    """A stream with a terminal behind it."""

    def isatty(self) -> bool:
        return True


def test_status_line_on_a_dumb_terminal_is_not_redrawn(monkeypatch):
    """Was (an audit of terminal output): in an Emacs shell buffer (TERM=dumb) guide's status, redrawn with carriage
    returns some 8 times a second, grew one line for the whole walk, each redraw read aloud. Now it is plain lines
    there, as in a log."""
    monkeypatch.setenv("TERM", "xterm")
    assert StatusLine(_Terminal()).tty
    monkeypatch.setenv("TERM", "dumb")
    terminal, now = _Terminal(), [0.0]
    status_line = StatusLine(terminal, interval_s=5.0, clock=lambda: now[0])
    for step in range(7):
        now[0] = float(step)
        status_line.show(f"{step:5.1f} fps  nearest 1.4 m  warn  left")
    status_line.close()
    assert not status_line.tty and "\r" not in terminal.getvalue()
    assert terminal.getvalue().splitlines() == ["  5.0 fps  nearest 1.4 m  warn  left",
                                                "  6.0 fps  nearest 1.4 m  warn  left"]


def test_status_line_plain_or_off_with_svs_torch_progress(monkeypatch):
    """Was (an audit of terminal output): a walker's screen reader read guide's status line at every redraw, some 8
    a second, over the spoken warnings, with no way to stop it. SVS_TORCH_PROGRESS=plain makes it a plain line
    every interval on a terminal; =off silences it, and the warnings still get their lines."""
    monkeypatch.setenv("TERM", "xterm")
    monkeypatch.setenv("SVS_TORCH_PROGRESS", "plain")
    assert not StatusLine(_Terminal()).tty
    monkeypatch.setenv("SVS_TORCH_PROGRESS", "off")
    terminal, now = _Terminal(), [0.0]
    status_line = StatusLine(terminal, interval_s=5.0, clock=lambda: now[0])
    for step in range(12):
        now[0] = float(step)
        status_line.show(f"{step:5.1f} fps  nearest 1.4 m  warn  left")
        if step == 3:
            status_line.message("Obstacle ahead, 1.4 metres")
    status_line.close()
    assert terminal.getvalue() == "Obstacle ahead, 1.4 metres\n"


def test_status_line_close_prints_nothing_twice():
    log = io.StringIO()
    status_line = StatusLine(log, tty=False)
    status_line.show("  1.0 fps  nearest none  clear  -")
    status_line.close()
    status_line.close()
    assert log.getvalue() == "  1.0 fps  nearest none  clear  -\n"


def test_guide_prints_warnings_above_its_status_line(monkeypatch):
    """The live loop, with a library warning on every pair: each warning is a whole line of its own, and every
    status line stays whole (before, a warning was printed onto the status line)."""
    import svs_torch.pipeline as pipeline
    from svs_torch.cli import main

    real = pipeline.estimate_obstacle_depth

    def warning_pipeline(batch, *args, **kwargs):
        warnings.warn("a library warning while ranging", UserWarning)
        return real(batch, *args, **kwargs)

    monkeypatch.setattr(pipeline, "estimate_obstacle_depth", warning_pipeline)
    terminal = io.StringIO()
    monkeypatch.setattr(sys, "stdout", terminal)
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main(["guide", "--emulator", "--count", "3", "--no-speech", "--far-m", "5.0"]) == 0
    screen = terminal_screen(terminal.getvalue())
    assert "warning: a library warning while ranging" in screen
    status = [line for line in screen if "fps" in line]
    assert status and all(re.fullmatch(r"\s*[\d.]+ fps  nearest (none|[\d.]+ m)  \w+  \w+", line) for line in status)
    assert all(line.startswith(("svs-depth: emulator on", "Guide ready.", "warning: ", "Obstacle", "Stop",
                                "Guide stopped.", "guide stopped"))
               for line in screen if "fps" not in line), screen


def test_guide_on_an_emulated_loose_rig_aligns_each_pair_and_ranges_it(monkeypatch, capsys):
    """``guide --emulator --emulator-loose-rig``: the right board rolled, tilted, shifted, scaled and darker (the
    issue's envelope at once); every pair guide grabs is ranged, its views aligned by the row alignment."""
    import svs_torch.pipeline as pipeline
    from svs_torch.cli import main

    real, aligned = pipeline.estimate_obstacle_depth, []

    def recording_pipeline(*args, **kwargs):
        result = real(*args, **kwargs)
        aligned.extend(result.row_aligned.tolist())
        return result

    monkeypatch.setattr(pipeline, "estimate_obstacle_depth", recording_pipeline)
    assert main(["guide", "--emulator", "--emulator-loose-rig", "--count", "3", "--no-speech", "--json",
                 "--second-passes", "off"]) == 0
    pairs = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    pairs = [pair for pair in pairs if "event" not in pair]
    assert len(pairs) == 3 and all(pair["status"] == "OK" for pair in pairs), pairs
    assert len(aligned) == 4 and all(aligned[1:])  # the first: guide's warm-up pair, before the camera opens


def test_guide_on_an_emulated_floor_leaves_the_floor_out_by_default(monkeypatch):
    """``guide --emulator --emulator-floor-m 1.3`` shows the cameras over a floor; by default (a walker's command)
    and with ``--floor on`` it runs the pipeline with the ground plane (what every pair is ranged with), with
    ``--floor off`` without it."""
    import svs_torch.pipeline as pipeline
    from svs_torch.cli import main
    from svs_torch.segmentation.ground_plane import GroundPlaneConfig

    real, grounds = pipeline.estimate_obstacle_depth, []

    def recording_pipeline(batch, config, *args, **kwargs):
        grounds.append(config.segmentation.ground)
        return real(batch, config, *args, **kwargs)

    monkeypatch.setattr(pipeline, "estimate_obstacle_depth", recording_pipeline)
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert main(["guide", "--emulator", "--emulator-floor-m", "1.3", "--count", "2", "--no-speech"]) == 0
    # Each run ranges its warm-up pair first, with the configuration of the camera's pairs.
    assert len(grounds) == 3 and all(g == GroundPlaneConfig() for g in grounds)
    grounds.clear()
    assert main(["guide", "--emulator", "--emulator-floor-m", "1.3", "--floor", "on", "--count", "1",
                 "--no-speech"]) == 0
    assert grounds == [GroundPlaneConfig()] * 2
    grounds.clear()
    assert main(["guide", "--emulator", "--emulator-floor-m", "1.3", "--floor", "off", "--count", "1",
                 "--no-speech"]) == 0
    assert grounds == [None] * 2


def test_guide_second_passes_off_runs_neither_retry(monkeypatch):
    """``guide`` runs the pipeline with the coarse and the exposure retries (``PipelineConfig.for_guide``), and
    ``--second-passes off`` without either; every other setting, guide's segmentation included, is the same."""
    import svs_torch.pipeline as pipeline
    from svs_torch.cli import main
    from svs_torch.pipeline import PipelineConfig

    real, configs = pipeline.estimate_obstacle_depth, []

    def recording_pipeline(batch, config, *args, **kwargs):
        configs.append(config)
        return real(batch, config, *args, **kwargs)

    monkeypatch.setattr(pipeline, "estimate_obstacle_depth", recording_pipeline)
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    default = PipelineConfig()
    for extra, passes in (([], True), (["--second-passes", "on"], True), (["--second-passes", "off"], False)):
        configs.clear()
        assert main(["guide", "--emulator", "--count", "1", "--no-speech", *extra]) == 0
        assert len(configs) == 2 and configs[0] == configs[1]  # the warm-up pair's and the camera's
        config = configs[-1]
        assert config == default.for_guide(second_passes=passes)
        assert config.segmentation == default.segmentation.for_guide()
        assert (config.coarse_retry_below_share, config.exposure_retry) == (
            (default.coarse_retry_below_share, default.exposure_retry) if passes else (None, None))
        assert dataclasses.replace(config, coarse_retry_below_share=default.coarse_retry_below_share,
                                   exposure_retry=default.exposure_retry, segmentation=default.segmentation) == default


@pytest.mark.parametrize("size", ["320x240", "160x120"])
def test_guide_refuses_an_emulated_heap_out_of_view(capsys, size):
    """A heap the emulator's cameras cannot see (below the view of cameras 1.3 m high pitched 20° down, or under
    2 px high far off) is refused naming the distances seen: it was accepted, and guide ran with nothing to warn
    of. The nearest bound holds against the renderer's own heap mask: pixels from there on, none 5 cm nearer."""
    import torch

    from svs_torch.cli import main
    from svs_torch.data.synthetic import render_obstacle_scenes

    for heap in ("0.5", "500"):
        assert main(["guide", "--emulator", "--emulator-floor-m", "1.3", "--emulator-heap-m", heap, "--size", size,
                     "--count", "1", "--no-speech"]) == 2
        err = capsys.readouterr().err
        found = re.search(r"--emulator-heap-m: expected (\S+) to (\S+) metres, where cameras 1.3 m over the floor, "
                          rf"pitched 20° down, see the heap at {size}; got {heap} \((\w+),", err)
        # The side it missed, said (a heap too near was told it stood behind the emulator's wall).
        assert found and found.group(3) == ("nearer" if heap == "0.5" else "farther"), err
    nearest_m = float(found.group(1))
    width, height = map(int, size.split("x"))

    def heap_pixels(ahead_m: float) -> int:
        scenes = render_obstacle_scenes(torch.tensor([[2.0]]), torch.tensor([[[9.0, 0.0]]]),
                                        torch.tensor([[[0.1, 0.1]]]), size_wh=(width, height), floor_height_m=1.3,
                                        camera_pitch_deg=20.0, heaps=torch.tensor([[0.0, ahead_m, 0.45, 0.35]]),
                                        generator=torch.Generator().manual_seed(0))
        return int(scenes.heap_mask.sum())

    assert heap_pixels(nearest_m + 0.02) > 0 and heap_pixels(nearest_m - 0.05) == 0


def test_guide_refuses_an_emulated_heap_behind_the_wall(capsys):
    """A heap behind the emulator's wall (4 m along the cameras' axis) renders not a pixel: 4.5 to 48 m ahead of
    cameras 1.3 m high were taken, the error's own range said "0.78 to 48", and 0.78 itself was refused (the bound
    rounded for the message). The far bound holds against the renderer's heap mask (pixels at it, none 5 cm
    farther), and both bounds said are taken."""
    import torch

    from svs_torch.cli import main
    from svs_torch.cli.capture import check_heap_in_view
    from svs_torch.data.synthetic import render_obstacle_scenes

    for heap in ("4.5", "48"):
        assert main(["guide", "--emulator", "--emulator-floor-m", "1.3", "--emulator-heap-m", heap, "--count", "1",
                     "--no-speech"]) == 2
        err = capsys.readouterr().err
        found = re.search(rf"--emulator-heap-m: expected (\S+) to (\S+) metres, .*; got {heap} \(farther, it stands "
                          r"behind the emulator's wall, 4 m along their axis\)", err)
        assert found, err
    nearest_m, farthest_m = (float(bound) for bound in found.groups())

    def heap_pixels(ahead_m: float) -> int:
        scenes = render_obstacle_scenes(torch.tensor([[2.0]]), torch.tensor([[[9.0, 0.0]]]),
                                        torch.tensor([[[0.1, 0.1]]]), floor_height_m=1.3, camera_pitch_deg=20.0,
                                        heaps=torch.tensor([[0.0, ahead_m, 0.45, 0.35]]),
                                        generator=torch.Generator().manual_seed(0))
        return int(scenes.heap_mask.sum())

    assert heap_pixels(farthest_m) > 0 and heap_pixels(farthest_m + 0.05) == 0
    for heap_m in (nearest_m, farthest_m):
        check_heap_in_view(heap_m, 1.3, (320, 240))  # the bounds said are the bounds applied


def test_guide_puts_a_heap_only_on_an_emulated_floor(monkeypatch, capsys):
    """``--emulator-heap-m`` without ``--emulator-floor-m`` is refused before anything runs (a heap stands on the
    floor); with it, the emulator's track carries the heap."""
    import hw.frames as frames

    from svs_torch.cli import main

    # Before the speaker too (an audit: its "espeak-ng is not installed" notice came first, two lines).
    assert main(["guide", "--emulator", "--emulator-heap-m", "1.5", "--count", "1"]) == 2
    err = capsys.readouterr().err
    assert "--emulator-heap-m: expected --emulator-floor-m too" in err and err.count("\n") == 1, err
    tracks = []
    real = frames.ObstacleTrack

    def recording_track(*args, **kwargs):
        tracks.append(real(*args, **kwargs))
        return tracks[-1]

    monkeypatch.setattr(frames, "ObstacleTrack", recording_track)
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    assert main(["guide", "--emulator", "--emulator-floor-m", "1.3", "--emulator-heap-m", "1.5", "--count", "1",
                 "--no-speech"]) == 0
    assert [(t.floor_height_m, t.heap_ahead_m) for t in tracks] == [(1.3, 1.5)]


def test_warm_up_ranges_one_camera_frame_pair_of_the_frame_size_and_shows_no_warning():
    import torch

    from svs_torch.cli.guide_warm_up import warm_up
    from svs_torch.core.camera import SVS_CAMERA

    seen = []

    def ranged(batch):
        warnings.warn("about the warm-up pair", UserWarning)
        seen.append(batch)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seconds = warm_up(ranged, (160, 120))
    assert not caught
    assert len(seen) == 1 and seconds > 0
    batch = seen[0]
    assert batch.left.shape == batch.right.shape == (1, 1, 120, 160) and batch.names == ("warm-up",)
    assert not bool(batch.calibrated[0]) and float(batch.focal_px[0]) == pytest.approx(SVS_CAMERA.focal_px(160))
    levels = batch.left * 255  # a camera's frame: whole 8-bit levels, not a rendered image's
    assert float((levels - levels.round()).abs().max()) < 1e-3 and not torch.equal(batch.left, batch.right)


def test_every_kornia_module_the_pipeline_imports_at_first_need_is_imported_by_guide_s_warm_up():
    import ast
    import pathlib

    import svs_torch
    from svs_torch.cli.guide_warm_up import DEFERRED_MODULES

    root = pathlib.Path(svs_torch.__file__).parent
    deferred = set()
    for package in ("core", "segmentation", "features", "geometry", "depth", "pipeline"):
        for path in (root / package).rglob("*.py"):
            for function in ast.walk(ast.parse(path.read_text())):
                if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                for node in ast.walk(function):
                    if isinstance(node, ast.ImportFrom):
                        deferred.add(node.module or "")
                    elif isinstance(node, ast.Import):
                        deferred.update(alias.name for alias in node.names)
    kornia = {name for name in deferred if name.split(".")[0] == "kornia"}
    assert kornia and kornia <= set(DEFERRED_MODULES), kornia - set(DEFERRED_MODULES)


def test_guide_ranges_its_warm_up_pair_before_the_camera_s_first_and_reports_only_the_camera_s(monkeypatch, capsys):
    import json

    import svs_torch.pipeline as pipeline
    from svs_torch.cli import main

    real = pipeline.estimate_obstacle_depth
    names = []

    def named(batch, *args, **kwargs):
        names.append(batch.names[0])
        return real(batch, *args, **kwargs)

    monkeypatch.setattr(pipeline, "estimate_obstacle_depth", named)
    assert main(["guide", "--emulator", "--count", "2", "--no-speech", "--json"]) == 0
    assert names[0] == "warm-up" and names.count("warm-up") == 1 and len(names) == 3
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len([line for line in lines if "event" not in line]) == 2


def test_guide_says_how_far_ahead_along_the_floor_a_heap_lies(monkeypatch, capsys):
    """A heap of rocks centred 1.0 m ahead on the emulator's floor (the camera 1.3 m up, pitched 20°): the axis depth
    of its nearest visible part reads over 1.15 m, "Obstacle ahead"; along the floor the segmenter found, under
    1 m, and guide says "Stop" (svs_torch.depth.floor_distance). With ``--floor off`` no floor is found and the
    axis depth is what is said, as before."""
    import json

    from svs_torch.cli import main

    command = ["guide", "--emulator", "--emulator-floor-m", "1.3", "--emulator-heap-m", "1.0", "--count", "2",
               "--no-speech", "--json"]
    assert main(command) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    pairs = [line for line in lines if "warning" in line]
    assert len(pairs) == 2
    for pair in pairs:
        assert pair["floor"]["camera_height_m"] == pytest.approx(1.3, rel=0.08)
        assert pair["floor"]["pitch_deg"] == pytest.approx(20.0, abs=3.0)
        assert pair["nearest_surface_m"] > 1.15
        assert pair["warning"]["distance_along"] == "floor" and pair["warning"]["floor_age_s"] == 0.0
        assert pair["warning"]["distance_m"] == pair["nearest_ahead_surface_m"] < 1.0
        assert pair["warning"]["class"] == STOP
        assert any(obj["ahead_p10_m"] == pair["nearest_ahead_surface_m"] for obj in pair["objects"])
    assert pairs[0]["warning"]["message"].startswith("Stop.")
    assert main([*command[:-4], "--floor", "off", *command[-4:]]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    for pair in (line for line in lines if "warning" in line):
        assert pair["floor"] is None and pair["nearest_ahead_m"] is None and pair["warning"]["distance_along"] == "axis"
        assert pair["warning"]["distance_m"] == pair["nearest_surface_m"]
        assert all(obj["ahead_m"] is None for obj in pair["objects"])


def test_guide_ranges_along_the_floor_it_found_last_for_a_while():
    """A pair whose floor rule found no floor is ranged along the floor found last, for FLOOR_MEMORY_S seconds
    (what ``pipeline.result_along_floor`` measures on the pair's own maps), then along the camera's axis."""
    import math

    import torch

    from svs_torch.cli.guide_loop import FLOOR_MEMORY_S, FloorMemory
    from svs_torch.data.synthetic import render_obstacle_scenes
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth, result_along_floor

    scenes = render_obstacle_scenes(torch.tensor([[1.6]]), torch.tensor([[[0.5, 0.2]]]), torch.tensor([[[0.4, 0.5]]]),
                                    generator=torch.Generator().manual_seed(3), floor_height_m=1.3,
                                    camera_pitch_deg=20.0, heaps=torch.tensor([[-0.3, 1.2, 0.45, 0.35]]))
    found = estimate_obstacle_depth(scenes.batch, PipelineConfig().for_guide())
    assert bool(found.floor.floor.found[0])
    again = result_along_floor(found, found.floor.floor)  # the same maps along the same floor: the same distances
    assert torch.equal(again.nearest.surface_m, found.floor.nearest.surface_m)
    floorless = dataclasses.replace(found, floor=dataclasses.replace(found.floor, floor=dataclasses.replace(
        found.floor.floor, found=torch.tensor([False]))))
    memory = FloorMemory()
    assert memory.nearest(floorless, 0.0)[1:] == ("axis", None)  # nothing found yet: along the camera's axis
    nearest, along, age = memory.nearest(found, 10.0)
    assert (along, age) == ("floor", 0.0) and float(nearest.surface_m[0]) == float(found.floor.nearest.surface_m[0])
    nearest, along, age = memory.nearest(floorless, 10.0 + FLOOR_MEMORY_S / 2)
    assert (along, age) == ("remembered_floor", FLOOR_MEMORY_S / 2)
    assert float(nearest.surface_m[0]) == float(found.floor.nearest.surface_m[0])
    axis = float(found.depth.nearest.surface_m[0])
    assert not math.isclose(axis, float(nearest.surface_m[0]), rel_tol=0.1)
    nearest, along, age = memory.nearest(floorless, 10.1 + FLOOR_MEMORY_S)
    assert (along, age) == ("axis", None) and float(nearest.surface_m[0]) == axis
    # the rig's pitch as worn, where no floor was seen lately: ahead along a level floor under it (20°, as rendered)
    worn = FloorMemory(worn_pitch_deg=20.0)
    nearest, along, age = worn.nearest(floorless, 0.0)
    assert (along, age) == ("camera_pitch", None)
    assert float(nearest.surface_m[0]) == pytest.approx(float(found.floor.nearest.surface_m[0]), rel=0.05)


@pytest.mark.parametrize("distance_class, distance, side, words", [
    (WARN, 1.46, "left", "Obstacle on the left, 1.5 metres"),
    (WARN, 1.46, "right", "Obstacle on the right, 1.5 metres"), (WARN, 1.46, "centre", "Obstacle ahead, 1.5 metres"),
    (WARN, 1.46, None, "Obstacle ahead, 1.5 metres"), (STOP, 0.97, "centre", "Stop. Obstacle at 0.9 metres"),
    (STOP, 0.7, "left", "Stop. Obstacle on the left at 0.7 metres"),
    (STOP, 0.84, "right", "Stop. Obstacle on the right at 0.8 metres")])
def test_a_warning_says_the_side_and_stop_never_reads_as_the_band_s_edge(distance_class, distance, side, words):
    """The side is said where it is not straight ahead; "Stop"'s distance is rounded down (0.97 m was "1.0 metres",
    the band's edge, and 0.7 m must not read 0.6 from 0.7·10 = 6.999…)."""
    assert WarningPolicy.message(distance_class, distance, side) == words


def test_the_side_is_said_with_the_warning_but_never_makes_one_alone():
    policy = WarningPolicy(repeat_s=3.0, confirm_frames=1)
    assert policy.update(1.5, 0.0, "left") == "Obstacle on the left, 1.5 metres"
    assert policy.update(1.5, 0.5, "right") is None  # the same class within repeat_s: the side alone says nothing
    assert policy.update(0.8, 1.0, "right") == "Stop. Obstacle on the right at 0.8 metres"
    guide = LiveGuide(WarningPolicy(confirm_frames=1), Speaker(None, stream=None))
    assert guide.update(1.2, 0.0, "right") == "Obstacle on the right, 1.2 metres"


def test_guide_ranges_along_a_level_floor_under_the_camera_s_pitch_as_worn(capsys):
    """``--camera-pitch-deg``: where no floor was found (here the floor rule is off), the distance runs ahead along a
    level floor under the camera so pitched, nearer than along its axis; refused out of range."""
    import json

    from svs_torch.cli import main

    command = ["guide", "--emulator", "--emulator-floor-m", "1.3", "--emulator-heap-m", "1.0", "--floor", "off",
               "--count", "1", "--no-speech", "--json"]
    assert main([*command, "--camera-pitch-deg", "20"]) == 0
    pair = next(json.loads(line) for line in capsys.readouterr().out.splitlines() if '"warning"' in line)
    assert pair["warning"]["distance_along"] == "camera_pitch" and pair["warning"]["floor_age_s"] is None
    assert pair["warning"]["distance_m"] < 0.95 * pair["nearest_surface_m"]
    with pytest.raises(SystemExit):
        main([*command, "--camera-pitch-deg", "75"])
    assert "--camera-pitch-deg: expected degrees from -45 to 60" in capsys.readouterr().err


def test_a_class_held_by_the_hysteresis_past_the_band_is_not_said_again():
    """An obstacle at 2.08 m with a 1-2 m band stays "warn" (within the 0.1 m hysteresis) but is not repeated every
    --repeat-s as "Obstacle ahead, 2.1 metres"; back inside the band it is said again after --repeat-s."""
    policy = WarningPolicy(repeat_s=3.0, hysteresis_m=0.1, confirm_frames=1)
    assert policy.update(1.9, 0.0) == "Obstacle ahead, 1.9 metres"
    assert [policy.update(2.08, t) for t in (1.0, 4.0, 8.0)] == [None, None, None] and policy.current == WARN
    assert policy.update(1.95, 9.0) == "Obstacle ahead, 1.9 metres"
    assert policy.update(0.9, 9.5) == "Stop. Obstacle at 0.9 metres"  # more urgent: at once


def test_the_status_line_shows_stop_s_distance_as_it_is_said():
    """"Stop. Obstacle at 0.9 metres" was followed by the status line "nearest 1.0 m  stop" (0.97 m rounded up)."""
    guide = LiveGuide(WarningPolicy(confirm_frames=1), Speaker(None, stream=None))
    assert guide.update(0.97, 0.0) == "Stop. Obstacle at 0.9 metres"
    assert "nearest 0.9 m  stop" in guide.status(0.97)
    assert "nearest 1.5 m  warn" in guide.status(1.46, WARN)


@pytest.mark.parametrize("swapped", [True, False])
def test_guide_says_aloud_once_that_the_boards_answer_in_the_wrong_roles(capsys, tmp_path, swapped):
    """Left alone at the last two stops, then fixed: --left and --right swapped (the left URL reaches the slave)
    make every distance wrong, and guide only printed the driver's warning, which a walker does not read. Its
    --record's pairs carry capture's mark (they were unmarked, an audit), which estimate of the record says."""
    import json

    from hw.emulator import EmulatorServer
    from hw.frames import SyntheticSource
    from svs_torch.cli import main
    from svs_torch.cli.guide_loop import CAMERAS_SWAPPED

    with EmulatorServer(left_port=0, right_port=0, source=SyntheticSource()) as server:
        left, right = (server.urls[name] for name in (("right", "left") if swapped else ("left", "right")))
        argv = ["guide", "--left", left, "--right", right, "--count", "2", "--no-speech", "--json"]
        assert main(argv + ["--record", str(tmp_path / "walk")]) == 0
    out, err = capsys.readouterr()
    events = [line for line in map(json.loads, out.splitlines()) if line.get("event") == "cameras_swapped"]
    if swapped:
        assert err.count(CAMERAS_SWAPPED) == 1 and "to be the stereo master" in err
        assert [(e["left_role"], e["right_role"]) for e in events] == [("slave", "master")]
    else:
        assert CAMERAS_SWAPPED not in err and "stereo master" not in err and not events
    index = (tmp_path / "walk" / "index.jsonl").read_text().splitlines()
    assert [json.loads(line)["cameras_swapped"] for line in index] == [swapped] * len(index) and index
    assert main(["estimate", "--pairs", str(tmp_path / "walk" / "index.jsonl"), "--json"]) in (0, 1)
    ranged = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line.get("cameras_swapped", False) for line in ranged if "status" in line] == [swapped] * len(index)


@pytest.mark.parametrize("swapped", [True, False])
def test_guide_says_aloud_once_that_the_boards_sit_in_each_others_place(capsys, swapped):
    """Found by an audit: boards remounted in each other's place answer in their right roles, so guide said nothing,
    while every left view was the right camera's and the pairs were ranged, wrongly. Now the pairs' matches, lying
    to the right in the right view, make guide say "Check the cameras" once, print why and log it."""
    import json

    from hw.emulator import EmulatorServer
    from hw.frames import SyntheticSource
    from svs_torch.cli import main
    from svs_torch.cli.guide_loop import CAMERAS_SWAPPED

    with EmulatorServer(left_port=0, right_port=0, source=SyntheticSource(), boards_swapped=swapped) as server:
        argv = ["guide", "--left", server.urls["left"], "--right", server.urls["right"], "--count", "6",
                "--no-speech", "--json"]
        assert main(argv) == 0
    out, err = capsys.readouterr()
    events = [line for line in map(json.loads, out.splitlines()) if line.get("event") == "cameras_mounted_wrong"]
    if swapped:
        assert err.count(CAMERAS_SWAPPED) == 1 and "the two boards mounted in each other's place" in err
        assert [e["views"] for e in events] == ["swapped"] and "stereo master" not in err
    else:
        assert CAMERAS_SWAPPED not in err and not events


def test_the_views_watch_tells_a_rig_on_its_side_once_a_majority_of_pairs_show_it(data_dir):
    """guide's ViewsWatch on Teddy's pair turned a quarter (a rig worn on its side): the third of five pairs makes
    the majority, said once a run; the upright pair never."""
    import torch

    from svs_torch.cli.guide_views import ViewsWatch
    from svs_torch.data import load_stereo_pair, resize_stereo_batch
    from svs_torch.pipeline import PipelineConfig, estimate_obstacle_depth

    upright = resize_stereo_batch(load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy"), (240, 200))
    turned = dataclasses.replace(upright, left=upright.left.rot90(1, (2, 3)).contiguous(),
                                 right=upright.right.rot90(1, (2, 3)).contiguous(),
                                 image_hw=upright.image_hw.flip(1), disparity_px=None, disparity_valid=None,
                                 disparity_nonoccluded=None)
    with torch.inference_mode():
        results = {name: estimate_obstacle_depth(batch, PipelineConfig())
                   for name, batch in (("upright", upright), ("turned", turned))}
    watch = ViewsWatch()
    assert [watch.update(results["turned"]) for _ in range(5)] == [None, None, "turned", None, None]
    assert "the rig worn on its side" in ViewsWatch.line("turned")
    watch = ViewsWatch()
    assert [watch.update(results["upright"]) for _ in range(5)] == [None] * 5


def test_guide_does_not_range_the_pairs_of_a_board_that_sends_one_frame_again(capsys):
    """Found by an audit of the device side: with the right board's sensor stalled (the emulator's --freeze: each
    grab answered with its last frame's bytes again) guide ranged every pair, the right frame old, the left new
    (distances 2.1 m then 4.1 m while both boxes moved), without a word. Now those pairs are not ranged, each is a
    camera_frozen event naming the right camera, and "Cannot see ahead" comes with "Check the right camera."."""
    import json

    from hw.emulator import EmulatorServer
    from hw.emulator_state import Faults
    from hw.frames import SyntheticSource
    from svs_torch.cli import main
    from svs_torch.cli.guide_loop import CHECK_CAMERA

    # noise: the left board's frames change from grab to grab, as a real sensor's do; 5 ms a grab: 38 not ranged
    # take more than --blind-s
    faults = {"left": Faults(grab_delay_s=0.005), "right": Faults(grab_delay_s=0.005, frozen_grabs=10**6)}
    with EmulatorServer(left_port=0, right_port=0, source=SyntheticSource(renderer="simple"), noise_sigma=2.0,
                        faults=faults) as server:
        assert main(["guide", "--left", server.urls["left"], "--right", server.urls["right"], "--count", "40",
                     "--blind-s", "0.1", "--no-speech", "--json", "--second-passes", "off"]) == 0
    out, err = capsys.readouterr()
    lines = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    frozen = [line["camera"] for line in lines if line.get("event") == "camera_frozen"]
    assert frozen == ["right"] * 38 and sum("event" not in line for line in lines) == 2
    assert err.count(f"{CANNOT_SEE} {CHECK_CAMERA.format('right')}") == 1
    assert "(2 ranged; 38 not: one camera sent its last frame again)" in err


def test_a_warning_held_by_the_hysteresis_beyond_the_band_is_not_said_after_a_stop():
    """After "Stop", the obstacle gone and a wall left at 2.08 m (a 1-2 m band; "warn" held by the 0.1 m
    hysteresis) was said "Obstacle ahead, 2.1 metres" once --repeat-s ran out: beyond the band is silence."""
    policy = WarningPolicy(repeat_s=3.0, hysteresis_m=0.1, confirm_frames=1)
    assert policy.update(0.9, 0.0) == "Stop. Obstacle at 0.9 metres"
    assert [policy.update(2.08, t) for t in (1.0, 3.1, 6.5)] == [None, None, None] and policy.current == WARN
    assert policy.update(1.5, 7.0) == "Obstacle ahead, 1.5 metres"  # back inside the band: said


def test_guide_says_aloud_that_it_stopped_on_an_error(capsys):
    """A camera that never answered (here: links refused) ended guide with an error line only, on a screen the
    walker does not see, and the silence after it read as a clear way: it is said as a warning is."""
    import socket

    from svs_torch.cli import main
    from svs_torch.cli.guide_loop import GUIDE_STOPPED

    ports = []
    for _ in range(2):  # two ports nothing listens on
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            ports.append(probe.getsockname()[1])
    assert main(["guide", "--left", f"socket://127.0.0.1:{ports[0]}", "--right", f"socket://127.0.0.1:{ports[1]}",
                 "--timeout", "0.2", "--retries", "0", "--no-speech"]) == 1
    out, err = capsys.readouterr()
    assert out.splitlines() == [GUIDE_STOPPED] and "svs-depth guide: error: left camera" in err


def test_the_emulated_heaps_bounds_say_which_one_a_heap_missed():
    """The reason given with the bounds is the bound missed: below the view (too near), under 2 pixels high (a small
    view) or behind the emulator's wall; a nearest bound of 0 is said as "more than 0" (0 itself is refused: it said
    "expected 0.00 to ...")."""
    from svs_torch.cli.capture import check_heap_in_view

    for floor_m, heap_m, size_wh, said in (
            (1.3, 0.5, (320, 240), r"expected 0\.\d\d to 4\.\d\d metres.*\(nearer, it lies below their view\)"),
            (1.3, 5.0, (320, 240), r"\(farther, it stands behind the emulator's wall, 4 m along their axis\)"),
            (0.5, 3.9, (16, 12), r"expected more than 0 to 2\.\d\d metres.*\(farther, it is under 2 pixels high\)")):
        with pytest.raises(InputError, match=f"^--emulator-heap-m: {said}" if said.startswith("expected") else said):
            check_heap_in_view(heap_m, floor_m, size_wh)
