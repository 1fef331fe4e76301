"""Option values out of what they can mean are refused when parsed, exit 2 with one line naming the option and the
range it takes (an audit of option bounds: each was taken before, and ran to nonsense or to a hang)."""

from __future__ import annotations

import pytest

from svs_torch.cli import main

def _refused(capsys, argv: list[str]) -> str:
    """The one error line of ``svs-depth argv``, which must exit 2 before anything runs."""
    with pytest.raises(SystemExit) as exited:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exited.value.code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("command", ["estimate", "eval"])
@pytest.mark.parametrize("option, value, expected", [
    # 1e30 ranged Teddy at 3e27 m with the status OK; 1e39 overflowed float32 ("focal_px: ... got inf")
    ("--focal-px", "1e30", "a focal length in pixels over 0 and at most 1,000,000"),
    ("--focal-px", "1e39", "a focal length in pixels over 0 and at most 1,000,000"),
    ("--baseline-m", "1e20", "a baseline in metres over 0 and at most 100"),
    # every object at 0.000 m, status OK
    ("--doffs-px", "1e30", "pixels from -1,000,000 to 1,000,000"),
])
def test_calibration_options_out_of_any_rig_are_refused(capsys, command, option, value, expected):
    # (refused when parsed: the pair's files are never read)
    err = _refused(capsys, [command, "left.png", "right.png", f"{option}={value}"] if command == "estimate"
                   else [command, "scenes/", f"{option}={value}"])
    assert f"argument {option}: expected {expected}, got '{value}'" in err


def test_calibration_options_of_real_rigs_are_taken():
    """The bounds' own values and the shared data's rigs (KITTI's focal and baseline, MiddEval3's doffs) parse."""
    from svs_torch.cli.rig import baseline_m_value, doffs_px_value, focal_px_value

    assert focal_px_value("1e6") == 1e6 and focal_px_value("721.5") == 721.5
    assert baseline_m_value("100") == 100 and baseline_m_value("0.54") == 0.54
    assert doffs_px_value("-1e6") == -1e6 and doffs_px_value("131.111") == 131.111
