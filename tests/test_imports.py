"""The command line answers ``--help`` without loading torch: the package's public names load on first use."""

from __future__ import annotations

import subprocess
import sys


def test_cli_help_does_not_import_torch():
    code = ("import sys; from svs_torch.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('torch', 'kornia', 'cv2', 'numpy') if m in sys.modules]\n"
            "print('HEAVY', heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "HEAVY []" in out and "usage: svs-depth" in out


def stderr_without_torch(*lines: str) -> str:
    """The standard error of ``lines`` (Python calling the CLI's ``main``) run in a fresh process, after checking
    that they left torch unloaded."""
    code = "\n".join(["import sys; from svs_torch.cli import main", *lines, "print('TORCH', 'torch' in sys.modules)"])
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "TORCH False" in run.stdout, run.stderr
    return run.stderr


def test_a_device_command_refuses_bad_arguments_without_loading_torch():
    """Found by an audit: 'svs-depth capture --out-dir d' without board URLs took 3 s to be told, the time torch
    takes to load: the capture package imported its torch modules up front. Its names now load on first use."""
    stderr = stderr_without_torch("import svs_torch.capture",
                                  "assert main(['capture', '--out-dir', 'never-made']) == 2",
                                  "from svs_torch.capture import CaptureError, WarningPolicy, Speaker")
    assert "--left, --right" in stderr
    import svs_torch.capture as capture  # its torch-side names still load, on first use

    assert capture.SVSStereoCamera.__module__ == "svs_torch.capture.stereo"


def test_estimate_says_a_pair_list_it_cannot_read_without_loading_torch(tmp_path):
    """Found by an audit: 'estimate --pairs missing.txt' loaded the pipeline (2.5 s) before saying the list was not
    there (a list that cannot be read gave no lines to choose workers by, so it took the in-process path); a folder
    of scenes or a device likewise. Said at once now, as the list's reading says it."""
    stderr = stderr_without_torch(f"assert main(['estimate', '--pairs', {str(tmp_path / 'missing.txt')!r}]) == 2",
                                  "assert main(['estimate', '--pairs', '/dev/null']) == 2")
    assert f"--pairs: expected a list file, got no file: {tmp_path / 'missing.txt'}" in stderr
    assert "--pairs: expected a list file, got a special file: /dev/null" in stderr


def test_guide_says_a_missing_board_url_without_loading_torch():
    """Found by an audit: 'guide --left ""' (a URL left out by a script) loaded the pipeline (2.5 s) before saying
    that both board URLs are needed; as capture, it says so at once now."""
    stderr = stderr_without_torch(
        "assert main(['guide', '--left', '', '--right', 'socket://board:10001', '--no-speech']) == 2")
    assert "--left, --right: give both board URLs, or --emulator" in stderr


def test_results_says_a_store_it_cannot_read_without_loading_torch(tmp_path):
    """'svs-depth results missing.sqlite' loaded torch (2 s) before saying there was no such file (left alone in an
    earlier stop); a folder likewise. Said at once now, in the words the store itself uses, naming the positional
    as the usage line shows it."""
    stderr = stderr_without_torch(f"assert main(['results', {str(tmp_path / 'missing.sqlite')!r}]) == 2",
                                  f"assert main(['results', {str(tmp_path)!r}]) == 2")
    assert f"FILE.sqlite: expected a results file, got no file: {tmp_path / 'missing.sqlite'}" in stderr
    assert f"FILE.sqlite: expected a results file, got a folder: {tmp_path}" in stderr


def test_public_names_load_on_first_use():
    import svs_torch
    from svs_torch.core.checks import InputError

    assert svs_torch.InputError is InputError
    assert svs_torch.PipelineConfig().max_ratio > 0
    assert "estimate_obstacle_depth" in dir(svs_torch)
    try:
        svs_torch.no_such_name  # noqa: B018
    except AttributeError as error:
        assert "no_such_name" in str(error)
    else:
        raise AssertionError("an unknown name must raise AttributeError")


def test_rendering_and_ranging_a_scene_do_not_import_sympy():
    # torch.broadcast_shapes imports torch._refs and sympy on its first call: 0.6-1.2 s of `svs-depth demo`'s
    # whole process, which renders a scene and ranges it (svs_torch.data.heap_rendering.rays_shape).
    code = ("import sys, torch\n"
            "from svs_torch.data.synthetic import random_obstacle_scenes\n"
            "from svs_torch.pipeline import estimate_obstacle_depth\n"
            "scenes = random_obstacle_scenes(1, 2, generator=torch.Generator().manual_seed(0), floor_height_m=1.2)\n"
            "estimate_obstacle_depth(scenes.batch)\n"
            "print('SYMPY', 'sympy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "SYMPY False" in out


def test_rays_shape_is_the_broadcast_shape():
    import torch

    from svs_torch.data.heap_rendering import rays_shape

    x, y = torch.zeros(1, 1, 1, 7), torch.zeros(1, 1, 5, 1)
    assert rays_shape(3, x, y) == (3, 1, *torch.broadcast_shapes(x.shape, y.shape)[-2:]) == (3, 1, 5, 7)
    assert rays_shape(2, torch.zeros(2, 1, 4, 6), torch.zeros(6)) == (2, 1, 4, 6)


def test_every_command_help_answers_without_torch_and_quotes_the_configuration():
    """'svs-depth estimate --help' (and features', fundamental's) loaded torch, 2.3-3.0 s, to read two defaults from
    PipelineConfig (left alone in earlier stops). The configuration and the help now take them from torch-free modules
    (``features.limits``, ``geometry.match_ratios``); the help still quotes the configuration's values. Every other
    command's help answered without torch already, and must go on doing so."""
    from svs_torch.cli import build_parser
    from svs_torch.cli.features import COMMAND_MAX_KEYPOINTS
    from svs_torch.pipeline import PipelineConfig

    commands = sorted(build_parser()._subparsers._group_actions[0].choices)
    code = ("import contextlib, io, sys\nfrom svs_torch.cli import main\n"
            f"for command in {commands!r}:\n    out = io.StringIO()\n    with contextlib.redirect_stdout(out):\n"
            "        try:\n            main([command, '--help'])\n        except SystemExit:\n            pass\n"
            "    print('COMMAND', command, ' '.join(out.getvalue().split()))\nprint('TORCH', 'torch' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "TORCH False" in run.stdout, run.stderr
    helps = dict(line.split(" ", 2)[1:] for line in run.stdout.splitlines() if line.startswith("COMMAND "))
    assert {"estimate", "features", "fundamental", "guide", "eval"} <= set(helps) == set(commands)
    config, paper = PipelineConfig(), PipelineConfig.paper()
    for command in ("estimate", "features", "fundamental"):
        assert (f"ratio test of the matching (default: {config.max_ratio}; --preset paper: {paper.max_ratio}, "
                "MATLAB's MaxRatio)") in helps[command], command
        cap = (f"{COMMAND_MAX_KEYPOINTS}, every keypoint found; --preset paper: {paper.surf.max_keypoints}"
               if command == "features" else f"{config.surf.max_keypoints}")
        assert f"strongest keypoints kept per image (default: {cap})" in helps[command], command
