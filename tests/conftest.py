"""Shared fixtures: the real data folder, a seeded generator, float dtypes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parent.parent


def find_shared_data() -> Path | None:
    """The shared real data: ``$SVS_TORCH_DATA`` if set, else ``../shared/data`` beside the repository."""
    env = os.environ.get("SVS_TORCH_DATA")
    path = Path(env) if env else REPO_ROOT.parent / "shared" / "data"
    return path if (path / "MANIFEST.md").is_file() else None


def pytest_sessionstart(session) -> None:
    """Compile ``svs_torch``, ``hw`` and ``experiments`` to bytecode once, before the tests start their child
    processes (command lines, worker pools, experiments): where ``PYTHONDONTWRITEBYTECODE`` is set (as on the CI
    machine), each child compiled the modules it imports from source again, up to 0.85 s a child, about 20 s of the
    suite. The files go where Python puts them (``__pycache__``, which git ignores); a read-only install is left
    as it is."""
    import compileall
    import importlib.util

    folders = [REPO_ROOT / "experiments"]
    for package in ("svs_torch", "hw"):
        spec = importlib.util.find_spec(package)
        folders += [Path(folder) for folder in (spec.submodule_search_locations or [])] if spec else []
    for folder in folders:
        if folder.is_dir() and os.access(folder, os.W_OK):
            compileall.compile_dir(folder, quiet=2)


def pytest_report_header(config) -> str:
    """Which shared data the run reads, first thing: a clone outside the workspace skipped its real-data tests with a
    line per test at the end only (found by a newcomer's run)."""
    path = find_shared_data()
    if path is not None:
        return f"svs_torch shared data: {path}"
    return ("svs_torch shared data: NOT FOUND (set SVS_TORCH_DATA or place it at ../shared/data beside the clone): "
            "the tests that read it are skipped" + (", and fail under CI" if os.environ.get("CI") else ""))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared data folder; a missing folder fails under CI (CI always has it) and skips elsewhere."""
    path = find_shared_data()
    if path is None:
        message = "shared data not found: set SVS_TORCH_DATA or place it at ../shared/data"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(1234)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


class SpokenLines:
    """A speaker's stream (``Speaker(None, stream=SpokenLines(said))``) that appends each line it is given to
    ``said``: what a walker hears, for guide's tests."""

    def __init__(self, said: list[str]) -> None:
        self.said = said

    def write(self, text: str) -> int:
        self.said.extend(line for line in text.split("\n") if line)
        return len(text)

    def flush(self) -> None:
        pass


def draw_no_figures(monkeypatch) -> None:
    """Pipeline figures built but not drawn, for runs whose figure a test does not look at (their titles can
    still be read): drawing one was most of a demo's time (0.45 s of 0.6). Tests that look at the pixels draw."""
    import numpy as np

    import svs_torch.plotting.plots

    def undrawn(figure) -> np.ndarray:
        assert figure._suptitle is not None  # a figure pipeline_figure made, as render would have drawn
        return np.zeros((240, 320, 3), np.uint8)

    monkeypatch.setattr(svs_torch.plotting.plots, "render", undrawn)


def resolves_in_package(dotted: str) -> bool:
    """Whether ``svs_torch.a.b.c`` names a module, or an attribute (a dataclass field included) of the longest module
    prefix that imports."""
    import dataclasses
    import importlib

    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for name in parts[cut:]:
            fields = {f.name for f in dataclasses.fields(obj)} if dataclasses.is_dataclass(obj) else set()
            if not hasattr(obj, name) and name not in fields:
                return False
            obj = getattr(obj, name, None)
        return True
    return False


def render_border_strip_scene(on_border: bool = True, near_m: float = 0.8, strip_px: int = 20):
    """A synthetic 320×240 SVS pair: a wide object 1.5 m away and a strip ``near_m`` away, ``strip_px`` wide. With
    ``on_border`` the strip's left edge is the image's (its disparity, 37 px at 0.8 m, is wider than it: none of
    its pixels' matches is in the right view); otherwise it stands 0.3 m right of the optical axis."""
    from svs_torch.core.camera import SVS_CAMERA
    from svs_torch.data.synthetic import render_obstacle_scenes

    focal = SVS_CAMERA.focal_px(320)
    strip_m = strip_px * near_m / focal
    strip_x_m = -SVS_CAMERA.principal_point_px(320, 240)[0] * near_m / focal + strip_m / 2 - 0.02 if on_border \
        else 0.3
    return render_obstacle_scenes(torch.tensor([[1.5, near_m]]), torch.tensor([[[0.05, 0.0], [strip_x_m, 0.0]]]),
                                  torch.tensor([[[0.5, 0.6], [strip_m + 0.04, 0.35]]]),
                                  generator=torch.Generator().manual_seed(3))


def assert_differentiable_depths_are_the_hard_ones(result, left: torch.Tensor, right: torch.Tensor) -> None:
    """A ``differentiable=True`` pipeline result: every ranged object's differentiable median depth within 0.5 %
    of the hard one, and their sum's gradient reaching more than 100 pixels of each view (``left`` and ``right``
    require grad)."""
    objects, hard = result.depth.objects, result.hard_depth.objects
    assert bool(objects.valid.any())
    relative = (objects.depth_median_m.detach() - hard.depth_median_m).abs() / hard.depth_median_m.clamp_min(1e-9)
    assert float(relative[objects.valid].max()) < 0.005
    objects.depth_median_m[objects.valid].sum().backward()
    assert int((left.grad != 0).sum()) > 100 and int((right.grad != 0).sum()) > 100


def unmatched_pair_fields() -> dict:
    """The ``points`` and ``fundamental`` of a one-pair pipeline result without a match, for the stand-in results of
    the guide tests: guide's ViewsWatch reads a ranged pair's matches (no match: no verdict)."""
    from types import SimpleNamespace

    none = torch.zeros(1, 0, dtype=torch.bool)
    return {"points": SimpleNamespace(left=torch.zeros(1, 0, 2), right=torch.zeros(1, 0, 2), valid=none),
            "fundamental": SimpleNamespace(F=torch.zeros(1, 3, 3), inliers=none)}


def seven_by_seven_nearness():
    """The default nearness segmenter as it was before a noisy pair's map was matched with a wider window
    (``NearnessNetConfig.noisy_window_size=7``): the camera frames of the tests that pass it were chosen for what
    that map made of them (a region the dense stage then measured too little of, an inlier-free kept region, a
    noise blob ranged near), which the wider window no longer makes; those tests exercise the later stages'
    handling of such a segmentation, which still happens on other frames. Pass it as ``network``."""
    from svs_torch.segmentation.nearness import NearnessNet, NearnessNetConfig

    return NearnessNet(NearnessNetConfig(noisy_window_size=7)).eval()


@pytest.fixture
def refuse_creating_in(monkeypatch):
    """``refuse(folder, code, reason)``: ``os.open`` (as ``svs_torch.core.files`` calls it) refusing to create files
    in ``folder`` with that OSError, as a read-only mount does, whoever runs the test (root writes anywhere)."""
    from svs_torch.core import files

    real_open = os.open

    def refuse(folder: Path, code: int = 13, reason: str = "Permission denied") -> None:
        def refusing_open(path, flags, *args, **kwargs):
            if Path(path).parent == folder and flags & os.O_CREAT:
                raise OSError(code, reason, str(path))
            return real_open(path, flags, *args, **kwargs)

        monkeypatch.setattr(files.os, "open", refusing_open)

    return refuse


@pytest.fixture
def store_folder_not_writable(monkeypatch):
    """``refuse()``: from then on the results store's ``sqlite3.connect`` fails as in a folder this user cannot
    write, but for a read as an immutable file (its shared-memory file cannot be made there; root writes anywhere,
    so it is simulated)."""
    import sqlite3

    from svs_torch.evaluation import store as store_module

    connect = sqlite3.connect

    def read_only_folder(database, *args, **kwargs):
        if "immutable=1" not in str(database):
            raise sqlite3.OperationalError("unable to open database file")
        return connect(database, *args, **kwargs)

    return lambda: monkeypatch.setattr(store_module.sqlite3, "connect", read_only_folder)


# Runs each ``(runner, argv)`` given on stdin (a test module's script of experiment calls, ``-c`` style, with its
# ``sys.argv[1:]``) in turn, each with argparse's own parse_args to wrap, and prints their outputs as one JSON list.
_EXPERIMENT_CALLS_CHILD = r"""
import argparse, contextlib, io, json, sys
parse_args, outputs = argparse.ArgumentParser.parse_args, []
for runner, argv in json.load(sys.stdin):
    argparse.ArgumentParser.parse_args = parse_args
    sys.argv, out = ["-c", *argv], io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(runner, "<runner>", "exec"), {"__name__": "__main__"})
    outputs.append(out.getvalue())
print(json.dumps(outputs))
"""


@pytest.fixture(scope="session")
def experiment_calls(tmp_path_factory) -> dict[str, tuple]:
    """The experiment calls of test_experiment_commands.py (``"commands"``: its cases and their problems) and of
    test_experiment_options.py (``"options"``: its folder, case table and outcomes; absent without the shared data,
    where its tests skip), both modules' runners in one fresh process: a process each cost about 5 s, half of it
    torch's import."""
    import json
    import subprocess
    import sys

    import test_experiment_commands as commands
    import test_experiment_options as options

    command_cases = commands.parse_cases(str(tmp_path_factory.mktemp("reports")))
    jobs = [(commands.RUNNER, [json.dumps([case[1:] for case in command_cases])])]
    data = find_shared_data()
    if data is not None:
        folder = tmp_path_factory.mktemp("experiment_options")
        table = options.case_table(data, folder)
        cases = [list(case) for cases in table.values() for case in cases]
        jobs.append((options.RUNNER, [str(REPO_ROOT), json.dumps(cases)]))
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", _EXPERIMENT_CALLS_CHILD], input=json.dumps(jobs), cwd=REPO_ROOT,
                          env=env, capture_output=True, text=True, timeout=400, check=True)
    outputs = [json.loads(output) for output in json.loads(done.stdout)]
    calls = {"commands": (command_cases, outputs[0])}
    if data is not None:
        calls["options"] = (folder, table, outputs[1])
    return calls


@pytest.fixture(autouse=True, scope="session")
def _socket_links_close_at_once():
    """pyserial's ``socket://`` close sleeps 0.3 s ("in case of quick reconnects, give the server some time"); a
    real board's bridge may need it, the emulator of these tests does not (it takes each new connection as it
    comes)."""
    import types

    import serial.urlhandler.protocol_socket as socket_protocol

    real_time = socket_protocol.time
    socket_protocol.time = types.SimpleNamespace(sleep=lambda seconds: None)
    yield
    socket_protocol.time = real_time
