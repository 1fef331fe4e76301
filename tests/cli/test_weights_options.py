"""A weights file given to the commands (estimate and segment --segmenter, eval --set / --config, a sweep file) that
cannot be used is refused when the arguments are checked, in one line naming the option and the file."""

from __future__ import annotations

import pytest
from real_images import PAIRS

from svs_torch.cli import main

TEDDY = PAIRS[0]


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as exit_:  # argparse's own exit for a value its type refused
        code = exit_.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture
def truncated(tmp_path):
    """The first half of the shipped nearness weights: a copy cut short."""
    from svs_torch.segmentation.network_files import NEARNESS_WEIGHTS

    path = tmp_path / "cut short.pt"
    content = NEARNESS_WEIGHTS.read_bytes()
    path.write_bytes(content[:len(content) // 2])
    return path


@pytest.mark.parametrize("command", ["estimate", "segment"])
def test_segmenter_weights_are_read_when_the_option_is_checked(data_dir, capsys, truncated, command):
    """Found by an audit: the file was first read by the run, after a --pairs list's pairs were read and its workers
    started, and the error named neither --segmenter nor the option's argument."""
    left, right = (str(data_dir / p) for p in TEDDY)
    code, out, err = run_cli(capsys, command, left, right, "--size", "160x120", "--segmenter", f"nearness:{truncated}")
    assert code == 2 and out == ""
    assert f"argument --segmenter: '{truncated}' is not a weights file (not tensors saved by torch.save" in err
    assert err.count("\n") == 1


def test_eval_refuses_a_bad_weights_file_before_any_pair(data_dir, capsys, truncated, tmp_path):
    """Found by an audit: eval --set segmentation.segmenter=nearness:BAD ran every pair into an ERROR row (and into
    --db) and exited 0."""
    db = tmp_path / "results.sqlite"
    code, out, err = run_cli(capsys, "eval", str(data_dir / "middlebury_eval3_Q" / "Teddy"), "--size", "160x120",
                             "--set", f"segmentation.segmenter=nearness:{truncated}", "--db", str(db))
    assert code == 2 and out == "" and not db.exists()
    assert err.startswith(f"svs-depth eval: error: --set: segmentation.segmenter = 'nearness:{truncated}': "
                          f"segmenter: '{truncated}' is not a weights file") and err.count("\n") == 1


def test_a_sweep_file_naming_a_bad_weights_file_fails_before_any_work(data_dir, capsys, truncated, tmp_path):
    """Found by an audit: the sweep stored ERROR rows for that configuration, exit status 0, though its help says a
    bad file fails before any work with one line."""
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'paths = ["{data_dir / "middlebury_eval3_Q" / "Teddy"}"]\nsize = "160x120"\n[grid]\n'
                     f'"segmentation.segmenter" = ["nearness", "nearness:{truncated}"]\n', encoding="utf-8")
    db = tmp_path / "sweep.sqlite"
    code, _, err = run_cli(capsys, "sweep", str(sweep), "--db", str(db), "--workers", "0")
    assert code == 2 and not db.exists()
    assert f"grid: segmentation.segmenter = 'nearness:{truncated}': segmenter: '{truncated}' is not a weights" in err
    assert err.count("\n") == 1
