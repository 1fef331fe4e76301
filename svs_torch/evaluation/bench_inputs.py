"""The inputs of ``svs-depth bench``: its input sets written as PNG pairs in a temporary folder, and the pair
lists that ``svs-depth estimate --pairs`` and the OpenCV rivals read (:mod:`.benchmark`)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["write_inputs"]


def _write_pngs(left, right, folder: Path, prefix: str) -> list[tuple[str, str]]:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    pairs = []
    for i in range(left.shape[0]):
        paths = []
        for side, images in (("left", left), ("right", right)):
            path = folder / f"{prefix}{i:04d}_{side}.png"
            cv2.imwrite(str(path), (images[i, 0] * 255).round().clamp(0, 255).byte().numpy())
            paths.append(str(path))
        pairs.append((paths[0], paths[1]))
    return pairs


def write_inputs(workdir: Path, num_pairs: int, data_dir: Path | None, seed: int = 0) -> dict[str, list]:
    """Input sets as PNG pairs: ``synthetic 320x240`` and, with ``data_dir``, ``real 320x240`` and
    ``real 640x480`` (the shared pairs resampled, repeated in order up to ``num_pairs``)."""
    import torch

    from ..data import list_shared_pairs, load_stereo_pair, resize_stereo_batch
    from ..data.synthetic import random_obstacle_scenes

    sets: dict[str, list] = {}
    scenes = random_obstacle_scenes(num_pairs, 2, generator=torch.Generator().manual_seed(seed))
    sets["synthetic 320x240"] = _write_pngs(scenes.batch.left, scenes.batch.right, workdir / "synthetic", "s")
    if data_dir is not None:
        scene_dirs = list_shared_pairs(data_dir)
        if scene_dirs:
            batches = [load_stereo_pair(path) for path in scene_dirs]
            for width, height in ((320, 240), (640, 480)):
                resized = [resize_stereo_batch(b, (width, height)) for b in batches]
                left = torch.cat([resized[i % len(resized)].left for i in range(num_pairs)])
                right = torch.cat([resized[i % len(resized)].right for i in range(num_pairs)])
                sets[f"real {width}x{height}"] = _write_pngs(left, right, workdir / f"real{width}", "r")
    return sets


def _write_list(pairs: list[tuple[str, str]], path: Path) -> Path:  # each file named relative to the list
    path.write_text("".join(f"{os.path.relpath(left, path.parent)} {os.path.relpath(right, path.parent)}\n"
                            for left, right in pairs))  # (a temporary folder's path may hold a space: C:\Users\Jo Li)
    return path
