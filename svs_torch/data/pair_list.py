"""Lists of stereo pairs: the one reader behind ``svs-depth estimate --pairs``, ``eval`` and ``sweep``.

A pair comes from one of:

* a line ``LEFT RIGHT`` of a list file (two image files; the calibration of the command, or the SVS model);
* a line ``LEFT RIGHT FOCAL_PX BASELINE_M [DOFFS_PX]`` (the pair's own calibration, for the input image size);
* a line naming a scene folder of any shared format (MiddEval3, Middlebury 2001–2006, KITTI, OpenCV aloe:
  :func:`~svs_torch.data.load_stereo_pair` detects it; the scene's own calibration and ground truth), or a
  folder of scene folders;
* ``svs-depth capture``'s ``index.jsonl`` (one JSON object per pair with ``left`` and ``right`` file names, and
  optionally ``focal_px``, ``baseline_m``, ``doffs_px`` as JSON numbers);
* a PATH argument: a scene folder, a folder of scene folders, the shared data folder (every pair of
  :func:`~svs_torch.data.list_shared_pairs`), a list file or an ``index.jsonl``.

List files take ``#`` comments and shell quoting (paths with spaces), as a shell reads them (a ``#`` inside a word, as
in ``take#2/left.png``, is part of it; on Windows a backslash is a path's separator, not an escape); relative paths are
relative to the list.
Every pair keeps its own calibration, each number in the range its command-line option takes (``--focal-px`` 1 to
1e6 px, ``--baseline-m`` 0.001 to 100 m, ``--doffs-px`` within ±1e6 px:
:data:`svs_torch.core.camera.CALIBRATION_RANGES`). An entry that cannot be a pair (wrong field count, a bad number,
a number out of its range, a folder that holds no scene or only part of one's files) is kept as a
:class:`PairSource` with ``problem`` set, so that it gets its own line and status (``BAD_INPUT``) while the others
run; a missing or unreadable list as a whole is an :class:`InputError`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from ..core.camera import calibration_value_expected
from ..core.checks import InputError, check_instance
from ..core.files import check_list_file, check_path_given, display_path, path_kind, split_list_line
from ..core.types import StereoBatch
from .datasets import KITTI_LEFT_FOLDERS, load_image_pair, load_stereo_pair, scene_name, unreadable_reason
from .pair_names import pair_identity, unusable_name, with_distinct_names
from .scene_folders import folder_scenes

__all__ = ["OWN_CALIBRATION_UNDER_RIG", "PairSource", "capture_folder_hint", "is_kitti_left_image", "read_pair_list",
           "read_pair_sources", "load_pair_source", "unique_sources", "with_distinct_names"]

#: An index.jsonl line's calibration fields, in a list line's order.
CALIBRATION_KEYS = ("focal_px", "baseline_m", "doffs_px")
#: What a list line may hold, for error messages.
LINE_FORMS = "'LEFT RIGHT', 'LEFT RIGHT FOCAL_PX BASELINE_M [DOFFS_PX]' or a scene folder"
#: A list line with its own calibration in a run rectified by ``--calibration`` (estimate --pairs, eval): the rig's
#: settings (no F rectification, a 2 px row band) are the run's, so another camera's pair would be ranged
#: unrectified (an audit: 0.90 m for a board at 0.33 m, said nowhere). Its status is BAD_INPUT with this reason.
OWN_CALIBRATION_UNDER_RIG = ("--calibration: the line gives its own FOCAL_PX BASELINE_M, so it is not the rig's pair, "
                             "and the run's settings for the rig's rectified pairs would range it unrectified; list "
                             "it in a run without --calibration")


@dataclass(frozen=True)
class PairSource:
    """One listed pair, not yet loaded.

    Attributes:
        left: the left image file; for a scene, its folder (or a KITTI left image); for a bad entry, its text.
        right: the right image file; None for a scene or a bad entry.
        scene: True for a scene folder, loaded by :func:`~svs_torch.data.load_stereo_pair` (own calibration, GT).
        focal_px, baseline_m, doffs_px: the calibration listed with the pair (for its input image size); None
            where the list gives none (a scene's own, or the caller's default).
        problem: why the entry cannot be a pair (a one-line reason naming the list and line); None if it can.
        listed_at: ``"line N of LIST"`` for a file pair read from a list file's line (for reports, and errors
            about its files).
        list_file: the list file (as its name was given) the entry was read from; None for a scene folder named
            itself. A results store forgets a bad line of this list that is no longer bad (mended or removed).
        label: the name to report the pair by where another listed pair would have its name (two folders both
            called ``Teddy``): the name with the folders that tell them apart, ``eval3/Teddy (a)``. None: its
            own name.
        frozen_camera, time_between_frames_s, cameras_swapped: what an ``index.jsonl`` line records of the pair's
            frames (capture's docstring): the camera whose frame came again (``"left"``/``"right"``), how far apart,
            in seconds, the two frames arrived, and whether the boards answered in each other's roles (true/false);
            None where the line says nothing (or is no index line).
    """

    left: str
    right: str | None = None
    scene: bool = False
    focal_px: float | None = None
    baseline_m: float | None = None
    doffs_px: float | None = None
    problem: str | None = None
    listed_at: str | None = None
    list_file: str | None = field(default=None, compare=False)  # where it was read, not what it is
    label: str | None = None
    frozen_camera: str | None = field(default=None, compare=False)  # what capture saw of it, not what it is
    time_between_frames_s: float | None = field(default=None, compare=False)
    cameras_swapped: bool | None = field(default=None, compare=False)

    @property
    def pair_id(self) -> str:
        """A stable identity for result stores: absolute paths, links resolved (a folder and a link to it are one
        pair, as within a run: :func:`unique_sources`), and the listed calibration, if any."""
        if self.problem is not None:
            return f"bad:{self.problem}"
        parts = [os.path.realpath(self.left)] + ([os.path.realpath(self.right)] if self.right else [])
        if self.focal_px is not None:
            parts.append(f"f={self.focal_px!r},B={self.baseline_m!r},doffs={self.doffs_px or 0.0!r}")
        return "|".join(parts)

    @property
    def name(self) -> str:
        """A short readable name: ``parent/name`` of the scene folder or the left file (or the :attr:`label`)."""
        path = Path(self.left)
        if self.label is not None:
            return self.label
        if self.problem is not None:
            return self.left[:60]
        if self.scene and _kind(path) == "file":  # a KITTI left image: data set / frame
            return f"{path.parent.parent.name}/{path.stem}"
        return f"{path.resolve().parent.name}/{path.name}"  # "L.png" listed alone: its folder's name, not "/L.png"

    @property
    def loaded_name(self) -> str:
        """The name :func:`load_pair_source` gives the pair's batch, known without loading it: the :attr:`label`,
        else a scene's as its loader names it from its file names alone (:func:`~svs_torch.data.datasets.scene_name`:
        ``eval3/Teddy``, not the folders' ``middlebury_eval3_Q/Teddy``), else :attr:`name`. What a pair's rows are
        named by whether it loads or not."""
        return scene_name(self.left) if self.scene and self.label is None and self.problem is None else self.name

    @property
    def calibration(self) -> dict | None:
        """The listed calibration as a dict, or None."""
        if self.focal_px is None:
            return None
        return {"focal_px": self.focal_px, "baseline_m": self.baseline_m, "doffs_px": self.doffs_px or 0.0}


def _bad(where: str, problem: str, text: str) -> PairSource:
    return PairSource(left=text.strip(), problem=f"{where}: expected {LINE_FORMS}, got {problem}: "
                                                 f"{text.strip()[:80]!r}")


def _calibration(fields: Sequence[str], where: str, text: str,
                 named_as_columns: bool = True) -> PairSource | tuple[float, float, float]:
    """(focal, baseline, doffs) from the numbers of a line, or a bad entry naming the first bad one: as a list line's
    column (``FOCAL_PX``), or ``named_as_columns`` False, as an index line's key (``focal_px``)."""
    values = []
    for key, number in zip(CALIBRATION_KEYS, fields):
        try:
            value = float(number)
        except ValueError:
            value = math.nan
        name = key.upper() if named_as_columns else key
        # The options' bounds: a line's baseline of 1e9 ranged Teddy at 4.5e10 m and a focal of 1e30 at 2e27 m, with
        # the status OK; a focal of 1e300 was refused as "focal_px: ... got inf", naming no line (an audit).
        if (expected := calibration_value_expected(key, value)) is not None:
            shown = number if len(number) <= 40 else number[:37] + "..."  # (not a number 400 digits long, in full)
            return PairSource(left=text.strip(), problem=f"{where}: {name}: expected {expected}, got {shown!r}")
        values.append(value)
    if len(values) == 2:
        values.append(0.0)
    return values[0], values[1], values[2]


def _scenes_in(folder: Path) -> list[PairSource]:
    """The scenes a folder stands for (:func:`~svs_torch.data.scene_folders.folder_scenes`), a folder that holds
    part of a scene's files as a bad entry saying what it lacks."""
    return [PairSource(left=path, scene=True) if problem is None else PairSource(left=path, problem=problem)
            for path, problem in folder_scenes(folder)]


def _kind(path: Path) -> str:
    """:func:`~svs_torch.core.files.path_kind`, with ``"unusable"`` for a name no file can have (a list line's problem,
    not an error of the whole list)."""
    try:
        return path_kind(path, "path")
    except InputError:
        return "unusable"


def is_kitti_left_image(path: str | Path) -> bool:
    """Whether ``path`` is a KITTI frame's left image (``image_2/000001_10.png``), which stands for its frame's scene
    (:func:`~svs_torch.data.load_stereo_pair` loads it so)."""
    path = Path(path)
    return _kind(path) == "file" and path.parent.name in KITTI_LEFT_FOLDERS


def capture_folder_hint(folder: str | Path) -> str:
    """What a folder without a scene is where it holds capture's or guide --record's ``index.jsonl``, to end "no
    stereo scene in the folder" with: the folder itself was refused so, naming no way to range its pairs (an audit).
    "" for any other folder."""
    index = Path(folder) / "index.jsonl"
    return f" (a capture folder: give its index, {display_path(index)})" if _kind(index) == "file" else ""


def _line_sources(fields: list[str], base: Path, where: str, text: str) -> list[PairSource]:
    """The pair (or scenes) of one list line."""
    paths = [str(p if Path(p).is_absolute() else base / p) for p in fields[:2]]
    if len(fields) == 1:
        path = Path(paths[0])
        if _kind(path) == "folder":
            scenes = _scenes_in(path)
            return scenes or [PairSource(left=text.strip(), problem=f"{where}: no stereo scene in the folder "
                                                                    f"{path}{capture_folder_hint(path)}")]
        if is_kitti_left_image(path):
            return [PairSource(left=str(path), scene=True)]
        if _kind(path) == "missing":  # a scene folder not there: "expected 'LEFT RIGHT', ... got 1 field" (an audit)
            problem = f"{where}: no such file or folder (one field names a scene folder): {display_path(path)}"
            return [PairSource(left=text.strip(), problem=problem)]
        return [_bad(where, "1 field", text)]
    if len(fields) in (2, 4, 5):
        if len(fields) == 2:
            return [PairSource(left=paths[0], right=paths[1], listed_at=where.split(": ", 1)[-1])]
        calibration = _calibration(fields[2:], where, text)
        if isinstance(calibration, PairSource):
            return [calibration]
        focal, baseline, doffs = calibration
        return [PairSource(left=paths[0], right=paths[1], focal_px=focal, baseline_m=baseline, doffs_px=doffs,
                           listed_at=where.split(": ", 1)[-1])]
    return [_bad(where, f"{len(fields)} fields", text)]


def _read_text(path: Path, name: str) -> str:
    check_list_file(path, name)
    try:
        return path.read_bytes().decode("utf-8-sig")  # "-sig": a Windows editor's byte-order mark is not text
    except UnicodeDecodeError:
        raise InputError(f"{name}: expected a UTF-8 text file with one {LINE_FORMS} per line: {path}") from None
    except OSError as error:
        raise InputError(f"{name}: cannot read {path}: {error.strerror or error}") from None


def _capture_marks(record: dict) -> dict:
    """The :class:`PairSource` fields of what an index line records of its frames (None where it holds no such
    value): ``estimate --pairs`` and ``eval`` say which listed pairs are not one stereo moment, or came from boards
    in each other's roles, as capture did."""
    frozen, gap_s = record.get("frozen_camera"), record.get("time_between_frames_s")
    finite = isinstance(gap_s, (int, float)) and not isinstance(gap_s, bool) and math.isfinite(gap_s)
    swapped = record.get("cameras_swapped")
    return {"frozen_camera": frozen if frozen in ("left", "right", "both") else None,
            "time_between_frames_s": float(gap_s) if finite else None,
            "cameras_swapped": swapped if isinstance(swapped, bool) else None}


def _index_sources(text: str, path: Path, name: str) -> list[PairSource]:
    """The pairs of ``svs-depth capture``'s ``index.jsonl`` (file names relative to its folder)."""
    sources = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{name}: line {number} of {path}"
        try:
            record = json.loads(line)
        except (ValueError, RecursionError):  # (nested too deep: an internal RecursionError, an audit)
            record = None
        if not (isinstance(record, dict) and isinstance(record.get("left"), str) and record["left"]
                and isinstance(record.get("right"), str) and record["right"]):  # ("": the index's folder)
            sources.append(PairSource(left=line.strip()[:80], problem=f"{where}: expected a JSON object with "
                                                                      f"'left' and 'right' file names"))
            continue
        if unusable_name(record["left"] + record["right"]):  # a NUL, a lone surrogate: valid JSON, no file's name
            sources.append(PairSource(left=line[:80], problem=f"{where}: a NUL or surrogate in a file name"))
            continue
        left, right = (str(p if Path(p).is_absolute() else path.parent / p)
                       for p in (record["left"], record["right"]))
        numbers, marks = [record.get(key) for key in CALIBRATION_KEYS], _capture_marks(record)
        if all(number is None for number in numbers):
            # listed_at: a frame that fails to load names its line, as a list's line does (an audit: it did not)
            sources.append(PairSource(left=left, right=right, listed_at=where.split(": ", 1)[-1], **marks))
            continue
        if None in numbers[:2]:  # checked first: a doffs_px without both would be read in baseline_m's place
            given = ", ".join(key for key, number in zip(CALIBRATION_KEYS, numbers) if number is not None)
            sources.append(PairSource(left=line.strip()[:80], problem=f"{where}: expected both focal_px and "
                                                                      f"baseline_m in a calibration, got {given}"))
            continue
        wrong = [key for key, number in zip(CALIBRATION_KEYS, numbers) if number is not None
                 and not (isinstance(number, (int, float)) and not isinstance(number, bool))]
        if wrong:  # JSON numbers, as capture writes them: "500" was taken as 500 (a calibration file refuses it)
            sources.append(PairSource(left=line.strip()[:80], problem=f"{where}: {wrong[0]}: expected a JSON number, "
                                                                      f"got {json.dumps(record[wrong[0]])[:40]}"))
            continue
        calibration = _calibration([str(v) for v in numbers if v is not None], where, line, named_as_columns=False)
        if isinstance(calibration, PairSource):
            sources.append(calibration)
            continue
        sources.append(PairSource(left=left, right=right, focal_px=calibration[0], baseline_m=calibration[1],
                                  doffs_px=calibration[2], listed_at=where.split(": ", 1)[-1], **marks))
    if not sources:
        raise InputError(f"{name}: no pair listed in {path}")
    return sources


def unique_sources(sources: Sequence[PairSource]) -> tuple[list[PairSource], list[PairSource]]:
    """``sources`` with each pair once, in order of first listing (the same files, however spelled or linked to,
    and the same listed calibration), and the entries dropped as repeats. Why links too: a scene reached through a
    symbolic link beside its own folder was evaluated twice, counted twice in every mean."""
    seen: set = set()
    unique, repeated = [], []
    for source in sources:
        key = source.pair_id if source.problem is not None else pair_identity(source)
        (repeated if key in seen else unique).append(source)
        seen.add(key)
    return unique, repeated


def read_pair_list(path: str | Path, name: str = "pairs") -> list[PairSource]:
    """The pairs of a list file or a capture ``index.jsonl`` (``*.jsonl``), in order (see the module docstring).

    Raises:
        InputError: (naming ``name``) for a missing, unreadable or non-UTF-8 file, or one that lists nothing.
            A bad line is not an error: it becomes a :class:`PairSource` with ``problem`` set.
    """
    check_path_given(path, name, "a list file name")
    path = Path(path)
    text = _read_text(path, name)
    if path.suffix == ".jsonl":
        return [replace(source, list_file=str(path)) for source in _index_sources(text, path, name)]
    sources: list[PairSource] = []
    for number, line in enumerate(text.splitlines(), start=1):
        where = f"{name}: line {number} of {path}"
        try:
            fields = split_list_line(line)
        except ValueError:
            sources.append(_bad(where, "unbalanced quotes", line))
            continue
        if not fields:
            continue
        if "\0" in line:
            sources.append(_bad(where, "a NUL character", line.replace("\0", "")))
            continue
        if "" in fields[:2]:  # ('"" R.png') read as the list's folder: "expected a file, got a directory" (an audit)
            sources.append(_bad(where, "an empty file name", line))
            continue
        sources.extend(_line_sources(fields, path.parent, where, line))
    if not sources:
        raise InputError(f"{name}: no pair listed in {path}")
    return [replace(source, list_file=str(path)) for source in with_distinct_names(sources)]


def read_pair_sources(paths: Sequence[str | Path] | str | Path, name: str = "path") -> list[PairSource]:
    """The pairs of PATH arguments: scene folders, folders of scene folders, the shared data folder, list files
    and ``index.jsonl`` files, in order. One path alone is a list of one: its letters were read as paths, to
    "no stereo scene in the folder /" (an audit); None, or an entry of another type, is refused by name.

    Raises:
        InputError: naming ``name`` and the path: a path that does not exist, a folder without a scene, a bad list."""
    paths = [paths] if isinstance(paths, (str, os.PathLike)) or paths is None else paths
    sources: list[PairSource] = []
    for given in paths:
        check_path_given(given, name, "a scene folder, a pair list or index.jsonl")  # ('' is '.': eval "$UNSET")
        path = Path(given)
        kind = path_kind(path, name)
        if kind == "folder":
            if reason := unreadable_reason(path):  # ("Permission denied: PATH/middlebury_eval3_Q", naming no argument)
                raise InputError(f"{name}: cannot read the folder {path} ({reason})")
            found = _scenes_in(path)
            if not found:
                raise InputError(f"{name}: no stereo scene (MiddEval3, Middlebury 2001–2006, KITTI, OpenCV aloe) "
                                 f"in the folder {path}{capture_folder_hint(path)}")
            sources += found
        elif is_kitti_left_image(path):
            sources.append(PairSource(left=str(path), scene=True))
        elif kind == "file":
            sources += read_pair_list(path, name)
        elif kind == "other":  # (was "no such file or folder" for /dev/null: an audit)
            raise InputError(f"{name}: expected a scene folder, a pair list or index.jsonl, got a special file: {path}")
        else:
            raise InputError(f"{name}: no such file or folder: {path}")
    return with_distinct_names(sources)


def load_pair_source(source: PairSource, focal_px: float | None = None, baseline_m: float | None = None,
                     doffs_px: float = 0.0, dtype: torch.dtype = torch.float32, truth: bool = True) -> StereoBatch:
    """Load one listed pair as a B = 1 batch named ``source.name``, at its input size.

    A scene keeps its own calibration and ground truth (``truth`` False: none read); a file pair takes its listed
    calibration, else ``focal_px`` / ``baseline_m`` / ``doffs_px`` (None: the SVS model;
    :func:`~svs_torch.data.load_image_pair`).

    Raises:
        InputError: the entry's ``problem``, why its files cannot be read, or a ``source`` that is no PairSource.
    """
    check_instance(source, "source", PairSource)  # a folder's name: "'str' object has no attribute 'problem'"
    if source.problem is not None:
        raise InputError(source.problem)
    if source.scene:
        batch = load_stereo_pair(source.left, dtype, truth)
    else:
        listed = source.focal_px is not None
        try:
            batch = load_image_pair(source.left, source.right, source.focal_px if listed else focal_px,
                                    source.baseline_m if listed else baseline_m,
                                    (source.doffs_px or 0.0) if listed else doffs_px, dtype)
        except InputError as error:
            if source.listed_at is None:
                raise
            # Which line of a long list named the file: "left: file not found: a/left1.jpg" alone did not say.
            raise InputError(f"{error} ({source.listed_at})") from None
    return batch if source.scene and source.label is None else replace(batch, names=(source.name,))
