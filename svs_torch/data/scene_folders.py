"""Which scenes a folder stands for, for the lists of :mod:`svs_torch.data.pair_list`: itself, or its scene
sub-folders, with the shared data folder's data sets giving their pairs, and each folder that holds part of a
scene's files named with what it lacks.

Why the last: a folder of scene folders left a scene without its ``calib.txt`` (or with ``IM0.PNG`` for ``im0.png``)
out of ``eval`` without a word; an audit found three of five scenes dropped under "2 pairs, 1 failed".
"""

from __future__ import annotations

from pathlib import Path

from ..core.files import display_path
from .datasets import (SHARED_DATA_FOLDERS, detect_stereo_layout, kitti_left_images, list_shared_pairs,
                       partial_scene_reason, warn_unreadable)

__all__ = ["folder_scenes"]


def folder_scenes(folder: Path) -> list[tuple[str, str | None]]:
    """The scenes ``folder`` stands for, in order, as ``(path, problem)``: a scene's path (a folder, or a KITTI
    left image) with None; a folder that holds part of a scene's files with why it is none (a one-line reason naming
    it). Empty: no scene in it. Looks one level down (and in the shared data folder's data sets)."""
    own = _scene_or_partial(folder)
    if own:
        return own
    shared = [(str(path), _problem(path)) for path in list_shared_pairs(folder)]  # (im0.png missing, calib.txt not)
    try:
        children = warn_unreadable(sorted(child for child in folder.iterdir() if child.is_dir()))
    except OSError:  # a folder that cannot be listed holds no scene we can read
        return shared
    if shared:  # the data sets' folders gave their pairs; a scene beside them is one more (not one instead)
        listed = {path for path, _ in shared}
        partial = [grandchild for name in SHARED_DATA_FOLDERS for grandchild in sorted((folder / name).glob("*"))
                   if str(grandchild) not in listed and grandchild.is_dir() and partial_scene_reason(grandchild)]
        children = partial + [child for child in children if child.name not in SHARED_DATA_FOLDERS]
    return shared + [scene for child in children for scene in _scene_or_partial(child)]


def _scene_or_partial(folder: Path) -> list[tuple[str, str | None]]:
    """A scene folder's pairs; a folder with part of a scene's files, itself with its problem; else nothing."""
    if detect_stereo_layout(folder):
        return _scene_paths(folder)
    problem = _problem(folder)
    return [(str(folder), problem)] if problem else []


def _problem(path: Path) -> str | None:
    """What a folder holding part of a scene's files lacks, naming it; None for another path."""
    partial = partial_scene_reason(path)
    return f"{display_path(path)}: {partial}" if partial else None


def _scene_paths(folder: Path) -> list[tuple[str, str | None]]:
    """A scene folder's pairs: itself, or each frame of a KITTI training folder (its left images), as the shared
    data folder lists them: ``load_stereo_pair`` on the folder alone reads only frame 000000_10."""
    if detect_stereo_layout(folder) == "kitti":
        lefts = kitti_left_images(folder)  # the frames with truth: a download's _11 frames have none
        if lefts:
            return [(str(path), None) for path in lefts]
    return [(str(folder), None)]
