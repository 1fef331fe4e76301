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
