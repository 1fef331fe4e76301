"""Which files a dataset's pair is read from, so that no output is written over one of them. Standard library only:
the command line checks its outputs with it before torch loads.

Why: ``estimate Art --figure Art/disp1.png`` wrote the figure over the scene's ground truth and ``eval kitti
--disparity-out kitti/disp_occ --disparity-format kitti`` replaced KITTI's ground truth with its own maps (a 16-bit
PNG named as the frame, taken for a map of its own), each with exit 0 (an audit of the files the commands write).
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import InputError
from .files import make_output_folder

__all__ = ["KITTI_LAYOUTS", "KITTI_LEFT_FOLDERS", "files_read_with", "make_export_folder", "resized_maps_note"]

#: The KITTI training layouts, 2012 then 2015: (left, right, truth, non-occluded truth) folders and the name prefix.
KITTI_LAYOUTS = (("colored_0", "colored_1", "disp_occ", "disp_noc", "kitti2012"),
                 ("image_2", "image_3", "disp_occ_0", "disp_noc_0", "kitti2015"))
#: The folders of a KITTI training folder's left images.
KITTI_LEFT_FOLDERS = tuple(layout[0] for layout in KITTI_LAYOUTS)


def files_read_with(source: str | None, name: str) -> list[tuple[str, str]]:
    """``(file, what it is)`` for every file an input ``source`` named ``name`` may be read from: an image itself;
    a scene folder's files (its views, ground truth, masks, calibration; a KITTI dataset's, every frame's); a KITTI
    frame's left image and the frame's files in each folder of its dataset (its right view, its ground truth)."""
    if not source or not (path := Path(source)).exists():
        return []
    if path.is_file():
        if path.parent.name not in KITTI_LEFT_FOLDERS:
            return [(source, f"the {name}")]
        frame = path.parent.parent.glob(f"*/{path.name}")
        return [(source, f"the {name}")] + [(str(f), f"KITTI frame {path.stem}'s {f.parent.name}/ file") for f in frame]
    files = [f for f in path.iterdir() if f.is_file()]
    if any((path / folder).is_dir() for folder in KITTI_LEFT_FOLDERS):
        files += [f for f in path.glob("*/*") if f.is_file()]
    return [(str(f), f"a file of the scene {source}") for f in files]


def make_export_folder(folder: str | os.PathLike, name: str) -> bool:
    """The folder of an export of disparity maps made if missing (:func:`~.files.make_output_folder`), or
    :class:`InputError` naming ``name`` where it cannot be, or where it is a folder of a KITTI dataset (beside its
    ``colored_0/`` or ``image_2/``: a map named as a frame would replace its ground truth or a view). True where
    this call made it."""
    _check_not_in_kitti_dataset(folder, name)
    made = not os.path.lexists(folder)
    make_output_folder(folder, name)
    return made


def _check_not_in_kitti_dataset(folder: str | os.PathLike, name: str) -> None:
    """:class:`InputError` naming ``name`` when ``folder`` is one of a KITTI dataset's folders."""
    parent = Path(os.path.realpath(folder)).parent
    beside = next((left for left in KITTI_LEFT_FOLDERS if (parent / left).is_dir()), None)
    if beside is not None:
        raise InputError(f"{name}: {folder} is a folder of the KITTI dataset {parent} (beside its {beside}/): a map "
                         f"written there would replace a frame's ground truth or view; name a folder outside it")


def resized_maps_note(size_wh: tuple[int, int]) -> str:
    """What ``eval`` or ``estimate`` with ``--size WxH --disparity-out`` is told: its maps are at the size the pipeline
    ran at, which the official tools do not score. The MiddEval3 SDK's ``evaldisp`` reads a map only at its ground
    truth's size or exactly 1/2 or 1/4 of it (it refuses others: "GT disp size must be exactly 1, 2, or 4 * disp size"),
    the KITTI devkit only at its size; the README's example at 320x240 wrote maps both refuse, exit 0, nothing said (an
    audit of the export; estimate wrote them in silence after eval warned, another audit)."""
    return (f"--disparity-out: the maps are {size_wh[0]}x{size_wh[1]}, the --size the pipeline ran at, whatever "
            "each pair's own size: the MiddEval3 SDK scores a map only at its ground truth's size or exactly 1/2 or "
            "1/4 of it, the KITTI devkit only at its size; for maps they score, run without --size")
