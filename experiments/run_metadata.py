"""What every experiment records beside its numbers: code version, library versions, machine and threads."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path


def default_data_dir() -> str:
    """The shared data: ``$SVS_TORCH_DATA``, else ``../shared/data`` beside the repository (as the tests)."""
    return os.environ.get("SVS_TORCH_DATA", str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def run_metadata(threads: int, **extra) -> dict:
    """Commit, versions (torch, kornia, OpenCV, numpy, Python), machine, CPU count, thread count, OpenMP wait
    policy and load average at the time of the call, plus the experiment's own ``extra`` settings."""
    import cv2
    import kornia
    import numpy
    import torch

    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {"commit": commit, "torch": torch.__version__, "kornia": kornia.__version__, "opencv": cv2.__version__,
            "numpy": numpy.__version__, "python": sys.version.split()[0], "machine": platform.machine(),
            "cpus": os.cpu_count(), "threads": threads, "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "load_average": os.getloadavg(), **extra}


def write_report(report: dict, table: str, json_path: Path | None, markdown_path: Path | None) -> None:
    """``report`` as JSON to ``json_path`` and ``table`` to ``markdown_path``, each where given, each written whole
    or not at all."""
    import json

    from svs_torch.core.files import write_bytes_atomic

    if json_path:
        write_bytes_atomic(json_path, json.dumps(report, indent=1).encode("utf-8"))
    if markdown_path:
        write_bytes_atomic(markdown_path, table.encode("utf-8"))
