"""The whole benchmark of the speed issue: svs_torch as a user runs it (the command line, whole process, default
settings) against OpenCV SIFT / ORB loops doing the same work and kornia's own composition; stage times, batch
scaling, peak memory per pair, one-pair latency and ``--help`` start-up. Same as ``svs-depth bench``, but for
one difference: without ``--data`` it adds ``--data ../shared/data`` where that folder exists (the real pairs'
rows; ``svs-depth bench`` alone times synthetic pairs only).

    python experiments/bench.py [--data ../shared/data] [--pairs 64] [--repeats 3] [--threads 2] [--json out.json]
"""

from __future__ import annotations

import sys
from pathlib import Path

from svs_torch.cli import main

if __name__ == "__main__":
    argv = sys.argv[1:]
    if "--data" not in argv:
        shared = Path(__file__).resolve().parents[1].parent / "shared" / "data"
        if shared.is_dir():
            argv = ["--data", str(shared), *argv]
    if "-h" in argv or "--help" in argv:
        print("experiments/bench.py: as svs-depth bench, with --data ../shared/data where it exists and no --data "
              "is given (below, svs-depth bench's own help)\n")
    raise SystemExit(main(["bench", *argv]))
