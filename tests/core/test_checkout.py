"""The checkout reports record as the code that ran (:mod:`svs_torch.core.checkout`): one reader for sweeps'
stores, the benchmark and the experiments, which had three that disagreed."""

import subprocess

from svs_torch import __version__
from svs_torch.core import checkout


def _git(head: str, status: str):
    def run(command, **kwargs):
        assert kwargs.get("timeout"), "a git that does not answer must not hold a report forever"
        return subprocess.CompletedProcess(command, 0, head if "rev-parse" in command else status, "")
    return run


def test_the_benchmark_and_a_sweep_record_the_same_commit(monkeypatch):
    """The benchmark recorded 7 characters of the commit, a sweep's store 12: the same run read as two commits."""
    from svs_torch.evaluation import benchmark, sweep

    monkeypatch.setattr(checkout.subprocess, "run", _git("0123456789abcdef0123\n", ""))
    assert benchmark.short_commit() == "0123456789ab"
    assert sweep.code_version() == f"{__version__}+git.0123456789ab"


def test_edited_code_is_recorded_as_dirty(monkeypatch):
    monkeypatch.setattr(checkout.subprocess, "run", _git("0123456789abcdef\n", " M svs_torch/pipeline/run.py\n"))
    assert checkout.short_commit() == "0123456789ab-dirty"
    assert checkout.code_version().endswith("+git.0123456789ab-dirty")


def test_outside_a_checkout_the_version_alone_is_recorded(monkeypatch):
    """An installed wheel (git answers 128), no git at all, or a git that hangs: the version alone, no traceback."""
    for failure in (subprocess.CalledProcessError(128, "git"), FileNotFoundError("git"),
                    subprocess.TimeoutExpired("git", 10)):
        def run(command, failure=failure, **kwargs):
            raise failure
        monkeypatch.setattr(checkout.subprocess, "run", run)
        assert checkout.checkout_commit() is None
        assert checkout.short_commit() == "unknown" and checkout.code_version() == __version__
