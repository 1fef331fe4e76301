"""The inputs of ``svs-depth bench``: its input sets written as PNG pairs in a temporary folder, and the pair
lists that ``svs-depth estimate --pairs`` and the OpenCV rivals read (:mod:`.benchmark`)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CHUNK_PAIRS", "write_inputs"]


#: Synthetic scenes rendered, and real pairs resampled, a chunk at a time: a scene takes about 20 MB while it is
#: rendered (64 at once: 1.4 GB), so the README's --pairs 512 needed near 10 GB at once, beyond the '3 GB' bench's
#: help promises (an audit). Runs of up to 64 pairs (the default) render one chunk: the scenes they always did.
CHUNK_PAIRS = 64


def _write_pngs(left, right, folder: Path, prefix: str, first: int = 0) -> list[tuple[str, str]]:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    pairs = []
    for i in range(left.shape[0]):
        paths = []
        for side, images in (("left", left), ("right", right)):
            path = folder / f"{prefix}{first + i:04d}_{side}.png"
            cv2.imwrite(str(path), (images[i, 0] * 255).round().clamp(0, 255).byte().numpy())
            paths.append(str(path))
        pairs.append((paths[0], paths[1]))
    return pairs


def write_inputs(workdir: Path, num_pairs: int, data_dir: Path | None, seed: int = 0) -> dict[str, list]:
    """Input sets as PNG pairs: ``synthetic 320x240`` and, with ``data_dir``, ``real 320x240`` and
    ``real 640x480`` (the shared pairs resampled, repeated in order up to ``num_pairs``); made and written
    :data:`CHUNK_PAIRS` at a time (the synthetic scenes drawn chunk after chunk from one generator)."""
    import torch

    from ..data import list_shared_pairs, load_stereo_pair, resize_stereo_batch
    from ..data.synthetic import random_obstacle_scenes

    generator, synthetic = torch.Generator().manual_seed(seed), []
    for first in range(0, num_pairs, CHUNK_PAIRS):
        scenes = random_obstacle_scenes(min(CHUNK_PAIRS, num_pairs - first), 2, generator=generator)
        synthetic += _write_pngs(scenes.batch.left, scenes.batch.right, workdir / "synthetic", "s", first)
        del scenes  # (before the next chunk is rendered)
    sets: dict[str, list] = {"synthetic 320x240": synthetic}
    scene_dirs = list_shared_pairs(data_dir) if data_dir is not None else []
    batches = [load_stereo_pair(path) for path in scene_dirs]
    for width, height in ((320, 240), (640, 480)) if batches else ():
        resized = [resize_stereo_batch(b, (width, height)) for b in batches]
        pairs = sets[f"real {width}x{height}"] = []
        for first in range(0, num_pairs, CHUNK_PAIRS):
            chosen = [resized[i % len(resized)] for i in range(first, min(first + CHUNK_PAIRS, num_pairs))]
            pairs += _write_pngs(torch.cat([b.left for b in chosen]), torch.cat([b.right for b in chosen]),
                                 workdir / f"real{width}", "r", first)
    return sets


def _write_list(pairs: list[tuple[str, str]], path: Path) -> Path:  # each file named relative to the list
    path.write_text("".join(f"{os.path.relpath(left, path.parent)} {os.path.relpath(right, path.parent)}\n"
                            for left, right in pairs))  # (a temporary folder's path may hold a space: C:\Users\Jo Li)
    return path
