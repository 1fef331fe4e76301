"""Pair-level parity of the C kernels and the torch paths: ``svs-depth estimate --pairs LIST --json`` over the shared
real pairs at 320×240, once with the kernels and once with ``SVS_TORCH_KERNELS=torch``, and the pairs whose JSON
lines differ, field by field (the time per pair aside).

    python experiments/kernel_parity.py [--data ../shared/data] [--size 320x240] [--workers 1]
    python experiments/kernel_parity.py --torch lk_refine,usurf_describe   # those two off in the first run too

The list: every scene folder of ``svs_torch.data.list_shared_pairs`` (Middlebury, KITTI, OpenCV's Aloe) and
OpenCV's 13 chessboard pairs. Each run is a separate process, so the switch holds for every stage. ``--torch``
turns the named kernels off in the kernels' run (their wrappers answer None, so their callers run the torch
paths; through a ``sitecustomize`` on the run's PYTHONPATH, so worker processes take it too): with the kernels
that are not bit for bit off, no pair may differ.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from svs_torch.data import list_shared_pairs  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from svs_torch.cli.common import positive_int  # noqa: E402
from run_metadata import add_data_option, run_script, size_list  # noqa: E402

#: Fields that are measurements of the run, not results.
TIMING = {"elapsed_s", "time_s", "ms", "elapsed_ms"}


def pair_lines(data_dir: Path) -> list[str]:
    lines = [str(p) for p in list_shared_pairs(data_dir) if p.is_dir() and p.name != "opencv_samples"]
    lines += [str(p) for p in list_shared_pairs(data_dir) if not p.is_dir() or p.name == "opencv_samples"]
    samples = data_dir / "opencv_samples"
    lines += [f"{left} {samples / left.name.replace('left', 'right')}" for left in sorted(samples.glob("left*.jpg"))]
    return lines


#: The stages whose ``kernels`` module :data:`SITECUSTOMIZE` reaches.
STAGES = ("segmentation", "features", "geometry", "depth")
#: Loaded at start-up by every process of a run (``sitecustomize``): the kernels named in
#: ``SVS_PARITY_TORCH_KERNELS`` (in their stage's ``kernels`` module) answer None, so their torch paths run.
SITECUSTOMIZE = f"""import os
if os.environ.get("SVS_PARITY_TORCH_KERNELS"):
    import importlib
    for _name in os.environ["SVS_PARITY_TORCH_KERNELS"].split(","):
        for _stage in {STAGES!r}:
            _kernels = importlib.import_module(f"svs_torch.{{_stage}}.kernels")
            if hasattr(_kernels, _name):
                setattr(_kernels, _name, lambda *args, **kwargs: None)
"""


def kernel_names(text: str) -> str:
    """An ``argparse`` type for ``--torch``: names of kernels, comma-separated, each a function of a stage's
    ``kernels`` module that answers None (or False) when it did not run, so that its caller runs the torch path. A
    name of none (a typo, a renamed kernel) turned nothing off, and the run was reported as "kernels (but NAME)"
    with every kernel on (an audit)."""
    import importlib
    import inspect

    modules = [importlib.import_module(f"svs_torch.{stage}.kernels") for stage in STAGES]
    known = sorted(name for module in modules for name, value in vars(module).items()
                   if inspect.isfunction(value) and value.__module__ == module.__name__ and not name.startswith("_")
                   and (str(value.__annotations__.get("return")).endswith("| None")
                        or value.__annotations__.get("return") == "bool"))
    unknown = [name for name in text.split(",") if name not in known]
    if text and unknown:
        raise argparse.ArgumentTypeError(f"expected kernel names among {', '.join(known)}, comma-separated, got "
                                         f"{', '.join(repr(name) for name in unknown)}")
    return text


def size_wxh(text: str) -> str:
    """An ``argparse`` type for ``--size``: one WxH size (a bad one was "58 of 58 pairs were not read", exit 1,
    after the runs: an audit)."""
    try:
        if text != "native" and "," not in text:
            return size_list("wxh")(text)
    except argparse.ArgumentTypeError:
        pass
    raise argparse.ArgumentTypeError(f"expected one WxH size such as 320x240, each side 1 to 8192, got {text!r}")


def run(pair_list: Path, size: str, workers: int, kernels: bool, torch_only: str = "") -> tuple[list[dict], float]:
    env = dict(os.environ, PYTHONPATH=f"{pair_list.parent}{os.pathsep}{REPO}")
    if not kernels:
        env["SVS_TORCH_KERNELS"] = "torch"
    if torch_only:
        env["SVS_PARITY_TORCH_KERNELS"] = torch_only
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "svs_torch.cli", "estimate", "--pairs", str(pair_list), "--json",
                           "--size", size, "--workers", str(workers)], capture_output=True, text=True, env=env,
                          check=False)
    elapsed = time.perf_counter() - start
    records = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    if not records:
        sys.exit(f"estimate gave no JSON lines (exit {done.returncode}):\n{done.stderr[-2000:]}")
    return records, elapsed


def differences(a, b, path: str = "") -> list[tuple[str, object, object]]:
    """The leaves where two JSON values differ (timing fields skipped)."""
    if isinstance(a, dict) and isinstance(b, dict):
        found = []
        for key in sorted(set(a) | set(b)):
            if key in TIMING or key.endswith("_ms") or key.endswith("_s") and "time" in key:
                continue
            found += differences(a.get(key), b.get(key), f"{path}.{key}" if path else key)
        return found
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [(path, a, b)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_option(parser, Path)
    parser.add_argument("--size", default="320x240", type=size_wxh, help="pairs resized to WxH (default: %(default)s)")
    parser.add_argument("--workers", type=positive_int, default=1, help="processes (default: %(default)s)")
    parser.add_argument("--torch", default="", type=kernel_names,
                        help="kernels to turn off in the kernels' run, comma-separated")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        pair_list = Path(folder) / "pairs.txt"
        # Absolute: estimate reads a list's relative paths from the list's folder (here a temporary one).
        lines = pair_lines(args.data.resolve())
        pair_list.write_text("\n".join(lines) + "\n")
        (Path(folder) / "sitecustomize.py").write_text(SITECUSTOMIZE)
        fused, fused_s = run(pair_list, args.size, args.workers, kernels=True, torch_only=args.torch)
        eager, eager_s = run(pair_list, args.size, args.workers, kernels=False)
    unread = [line for line, a, b in zip(lines, fused, eager) if "BAD_INPUT" in (a.get("status"), b.get("status"))]
    if unread:  # equal error lines are no parity: say so rather than count them as agreeing
        sys.exit(f"{len(unread)} of {len(lines)} pairs were not read (BAD_INPUT), first: {unread[0]}")
    off = f" (but {args.torch})" if args.torch else ""
    print(f"{len(lines)} pairs at {args.size}: kernels{off} {fused_s:.1f} s, torch paths {eager_s:.1f} s (wall, "
          "with start-up)")
    differing = 0
    for line, a, b in zip(lines, fused, eager):
        found = differences(a, b)
        if found:
            differing += 1
            print(f"\n{line}")
            for field, x, y in found:
                print(f"  {field}: kernels {x!r}  torch {y!r}")
    print(f"\n{differing} of {len(lines)} pairs differ")


if __name__ == "__main__":
    run_script(main)
