"""The pipeline's JSON on a fixed list of real and synthetic pairs, recorded once and compared after a change that
must not change results (a move of modules, a split of functions).

    python experiments/fixed_list_check.py record /tmp/regroup_fixed/before.json
    python experiments/fixed_list_check.py compare /tmp/regroup_fixed/before.json

``record`` writes the inputs once into ``--workdir`` (default ``/tmp/regroup_fixed``): six seeded synthetic
320x240 pairs as PNG files and a list naming them and five shared real scenes (``$SVS_TORCH_DATA`` or
``../shared/data``); then runs ``python -m svs_torch.cli estimate --pairs LIST --json`` under four settings (the
default, ``--preset paper``, ``--segmenter learned``, ``--segmenter otsu --canny``) in a subprocess, so the
package found first on ``PYTHONPATH`` is the one measured. ``compare`` runs the same and exits 1 on any
difference, naming the first few. Fields that measure time or name the build are left out (``EXCLUDED``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
#: Real pairs under the shared data folder: scene folders (with their own calibration) and one KITTI image pair.
REAL_SCENES = ("middlebury_eval3_Q/Teddy", "middlebury_eval3_Q/ArtL", "middlebury_2005_2006_third/Art",
               "middlebury_2003_quarter/Cones",
               "kitti/stereo2012_training/colored_0/000000_10.png kitti/stereo2012_training/colored_1/000000_10.png")
NUM_SYNTHETIC = 6
SETTINGS = {
    "default": ["--size", "320x240"],
    "paper": ["--size", "320x240", "--preset", "paper"],
    "learned": ["--size", "320x240", "--segmenter", "learned"],
    "otsu-canny": ["--size", "320x240", "--segmenter", "otsu", "--canny"],
}
#: Timing and build fields: they differ from run to run whatever the code.
EXCLUDED = frozenset({"time_s", "seconds", "elapsed_s", "timings", "timing", "time_ms", "version",
                      "svs_torch_version", "kernels"})


def _data_dir() -> Path:
    env = os.environ.get("SVS_TORCH_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


def write_list(workdir: Path) -> Path:
    """The pair list (synthetic PNGs written on first use, then reused)."""
    listing = workdir / "pairs.txt"
    if listing.is_file():
        return listing
    import cv2
    import torch

    from svs_torch.data.synthetic import random_obstacle_scenes

    scenes = random_obstacle_scenes(NUM_SYNTHETIC, 2, generator=torch.Generator().manual_seed(7))
    lines = [" ".join(str(_data_dir() / part) for part in scene.split()) for scene in REAL_SCENES]
    (workdir / "synthetic").mkdir(parents=True, exist_ok=True)
    for i in range(NUM_SYNTHETIC):
        paths = []
        for side, images in (("left", scenes.batch.left), ("right", scenes.batch.right)):
            path = workdir / "synthetic" / f"s{i}_{side}.png"
            cv2.imwrite(str(path), (images[i, 0] * 255).round().clamp(0, 255).byte().numpy())
            paths.append(str(path))
        lines.append(" ".join(paths))
    listing.write_text("".join(line + "\n" for line in lines))
    return listing


def _strip(value):
    if isinstance(value, dict):
        return {key: _strip(item) for key, item in value.items() if key not in EXCLUDED}
    if isinstance(value, list):
        return [_strip(item) for item in value]
    return value


def run_all(workdir: Path) -> dict[str, list]:
    """Each setting's JSON lines, parsed, with the excluded fields removed."""
    listing = write_list(workdir)
    results = {}
    for name, options in SETTINGS.items():
        command = [sys.executable, "-m", "svs_torch.cli", "estimate", "--pairs", str(listing), "--json",
                   "--workers", "1", *options]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode not in (0, 2):
            raise SystemExit(f"{name}: exit {done.returncode}\n{done.stderr}")
        results[name] = [_strip(json.loads(line)) for line in done.stdout.splitlines() if line.strip()]
    return results


def _differences(before, after, where="") -> list[str]:
    if isinstance(before, dict) and isinstance(after, dict):
        out = [f"{where}.{key}: only on one side" for key in sorted(set(before) ^ set(after))]
        for key in sorted(set(before) & set(after)):
            out += _differences(before[key], after[key], f"{where}.{key}")
        return out
    if isinstance(before, list) and isinstance(after, list) and len(before) == len(after):
        return [d for i, (b, a) in enumerate(zip(before, after)) for d in _differences(b, a, f"{where}[{i}]")]
    return [] if before == after else [f"{where}: {before!r} -> {after!r}"]


def _checked_record(parser: argparse.ArgumentParser, args: argparse.Namespace):
    """Before the run: for record, a file ``json`` can be written as (:func:`run_metadata.output_path`); for
    compare, the record read. An audit: a folder, a missing folder or a missing record failed only after every
    pair of the list had been run, in a traceback."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from run_metadata import output_path

    try:
        if args.action == "record":
            output_path(str(args.json))
            return None
        return json.loads(args.json.read_text())
    except (argparse.ArgumentTypeError, OSError, ValueError) as error:
        parser.error(f"argument json: {error}")


def _checked_workdir(parser: argparse.ArgumentParser, workdir: Path) -> None:
    """``workdir`` made, with room for the list's synthetic pairs, before the run: an unwritable one (``/proc``, a
    file, a read-only share) ended in a traceback from ``mkdir`` (an audit). A workdir already holding its list is
    only read."""
    import tempfile

    if (workdir / "pairs.txt").is_file():
        return
    try:
        (workdir / "synthetic").mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=workdir):  # a folder that exists may still refuse a new file
            pass
    except OSError as error:
        # The path that failed is named: "/proc: No such file or directory" read as if /proc were missing.
        failed = f"{error.filename}: " if error.filename and str(error.filename) != str(workdir) else ""
        parser.error(f"argument --workdir: cannot write the pair list and its synthetic pairs in {workdir} "
                     f"({failed}{error.strerror or error})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("action", choices=("record", "compare"),
                        help="record the fixed list's results, or compare against a record")
    parser.add_argument("json", type=Path, help="the recorded results (written by record, read by compare)")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/regroup_fixed"),
                        help="where the pair list and its synthetic pairs are written, then reused (default: "
                             "%(default)s)")
    args = parser.parse_args(argv)
    recorded = _checked_record(parser, args)
    _checked_workdir(parser, args.workdir)
    results = run_all(args.workdir)
    if args.action == "record":
        from run_metadata import write_text_whole  # (the path is set above)

        write_text_whole(args.json, json.dumps(results, indent=1, sort_keys=True) + "\n")
        print(f"recorded {sum(map(len, results.values()))} results in {args.json}")
        return 0
    differences = _differences(recorded, results)
    for line in differences[:20]:
        print(line)
    print(f"{len(differences)} differences over {sum(map(len, results.values()))} results")
    return 1 if differences else 0


if __name__ == "__main__":
    sys.exit(main())
