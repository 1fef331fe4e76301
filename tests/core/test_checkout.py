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


def test_a_package_installed_inside_another_checkout_records_no_commit(tmp_path):
    """An installed copy (site-packages in a virtual environment inside a user's own git project) is not a checkout
    of svs_torch: git answered from the enclosing project, and reports recorded that project's commit, and its
    edits as ``-dirty``, as the code that ran."""
    import importlib.util
    import shutil

    project = tmp_path / "project"
    installed = project / ".venv" / "site-packages" / "svs_torch" / "core"
    installed.mkdir(parents=True)
    shutil.copy(checkout.__file__, installed / "checkout.py")
    git = ["git", "-C", str(project), "-c", "user.name=a", "-c", "user.email=a@b.c"]
    subprocess.run([*git, "init", "-q"], check=True)
    (project / "notes.txt").write_text("a user's project\n")
    subprocess.run([*git, "add", "notes.txt"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "theirs"], check=True)
    spec = importlib.util.spec_from_file_location("installed_checkout", installed / "checkout.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.checkout_commit() is None
