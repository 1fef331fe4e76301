"""Choose ``PipelineConfig.coarse_retry_below_share`` on the tuned split only (issue 33, item 1: camera frames).

A pair whose dense map measured less than this share of its kept regions' pixels is measured again at half the
working width. The tuned scenes run through experiments/real_rig.py's clean pair and its eight camera-frame
conditions (JPEG digit 1–8 after sensor noise σ 2–8), at full and at half contrast (``--contrast 0.5``: the tuning
set for camera frames, whose weak texture is what the held-out split's scenes lose to JPEG), at 320×240 and native
size, with the pass off and at each candidate share. Per row: the mean per-object Eq. (9) accuracy over the split's
pairs of the clean pair, and over its 8 × 10 camera frames. The held-out split is not read.

Usage (2-core machine, about 6 minutes)::

    python experiments/coarse_retry.py [--shares 0.35,0.45,0.55] [--markdown coarse_retry.md]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_rig  # noqa: E402
from paper_table1 import split_scenes  # noqa: E402
from svs_torch.cli.common import unit_interval_float  # noqa: E402
from run_metadata import add_common_options, comma_list, output_path, run_script  # noqa: E402

from svs_torch.core.files import write_bytes_atomic  # noqa: E402
from svs_torch.pipeline import PipelineConfig  # noqa: E402


def measure(data: Path, share: float | None, sizes: list[str], contrasts: list[float]) -> dict[tuple, tuple]:
    """``{(size, contrast): (clean mean %, camera frames mean %)}`` for one setting of the share."""
    config = dataclasses.replace(PipelineConfig(), coarse_retry_below_share=share)
    tuned = {"tuned": split_scenes(data)["tuned"]}
    out = {}
    for size in sizes:
        for contrast in contrasts:
            rows = real_rig.run(tuned, [size], config, rival=False, only=("clean", "jpeg"), progress=False,
                                contrast=contrast)
            clean = [r["acc_objects"] for r in rows if r["condition"] == "clean"]
            frames = [r["acc_objects"] for r in rows if r["condition"].startswith("jpeg")]
            out[(size, contrast)] = (statistics.fmean(clean), statistics.fmean(frames))
    return out


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_options(parser, data_type=Path, sizes="320x240,native")
    parser.add_argument("--shares", default="0.35,0.45,0.55", type=comma_list(unit_interval_float, "shares"),
                        help="comma-separated values of PipelineConfig.coarse_retry_below_share compared with off "
                             "(default: %(default)s)")
    parser.add_argument("--contrasts", default="1,0.5", type=comma_list(unit_interval_float, "factors"),
                        help="comma-separated contrast factors of the tuned split (default: %(default)s)")
    parser.add_argument("--markdown", type=output_path, help="write the table as Markdown to FILE")
    args = parser.parse_args(argv)
    try:
        shares = [None] + [float(s) for s in args.shares.split(",")]
        contrasts = [float(c) for c in args.contrasts.split(",")]
    except ValueError as error:
        parser.error(f"--shares / --contrasts: expected comma-separated numbers ({error})")
    sizes = args.sizes.split(",")
    columns = [(size, contrast) for size in sizes for contrast in contrasts]
    lines = ["| coarse_retry_below_share | " + " | ".join(f"{s} contrast {c:g}: clean / frames %" for s, c in columns)
             + " |", "|" + "---|" * (len(columns) + 1)]
    for share in shares:
        print(f"share {share} ...", file=sys.stderr, flush=True)
        result = measure(args.data, share, sizes, contrasts)
        lines.append(f"| {'off' if share is None else share} | "
                     + " | ".join(f"{result[k][0]:.2f} / {result[k][1]:.2f}" for k in columns) + " |")
    table = "\n".join(lines) + "\n"
    print(table)
    if args.markdown:
        write_bytes_atomic(args.markdown, table.encode("utf-8"))
    return table


if __name__ == "__main__":
    run_script(main)
