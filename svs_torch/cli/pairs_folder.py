"""The folder of saved pairs that ``capture --out-dir`` and ``guide --record`` write (the layout of
:mod:`svs_torch.cli.capture`'s docstring): each board's JPEG as received and ``index.jsonl``, a line per pair.

A pair is in the folder whole or not at all. Why: on a full disk ``capture`` left a left image without its right
one, and an index line cut short would stop ``estimate --pairs`` at that line; so a pair's images are removed when
one of them, or its index line, cannot be written, and a line cut short is cut off the index again. Every error names
the option and the file (``--record: cannot write 'walk/pair000003_right.jpg': No space left on device``).

Only the standard library is imported: the folder is checked before torch loads.
"""

from __future__ import annotations

import contextlib
import os
import shlex
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..core.errors import InputError
from ..core.files import check_path_given, check_writable_folder, display_path, path_kind, write_bytes_atomic, \
    write_errors_named
from .common import dumps_strict

if TYPE_CHECKING:
    from ..capture.stereo import Frame, StereoPair

__all__ = ["CALIBRATION_NAME", "INDEX_NAME", "PairsIndex", "new_pairs_folder", "replay_command", "save_pair"]

INDEX_NAME = "index.jsonl"
CALIBRATION_NAME = "calibration.json"  # a copy of --calibration's file
#: The names of a pair's images: ``pair000000_left.jpg``.
PAIR_FILE_PATTERN = "pair[0-9][0-9][0-9][0-9][0-9][0-9]_*.jpg"


def new_pairs_folder(value: str, option: str) -> Path:
    """The folder ``value`` of ``option`` that pairs will be saved to (created later, if missing), checked before
    the camera opens: a file there or on the way to it, or a folder already holding an ``index.jsonl``, a
    ``calibration.json`` or pair images, is refused (nothing is ever appended to, or written over, another run's
    pairs)."""
    check_path_given(value, option, "a folder name")  # '' saved the pairs into the current folder
    out = Path(value)
    kind = path_kind(out, option)
    if kind not in ("missing", "folder"):
        raise InputError(f"{option}: expected a folder, got {'a file' if kind == 'file' else 'a device or socket'}: "
                         f"{display_path(out)}")
    if kind == "folder":
        # A calibration.json too: written over by --calibration in silence (an audit), and without --calibration
        # read by estimate --pairs as the new pairs' rig (calibration_kept_beside).
        for name in (INDEX_NAME, CALIBRATION_NAME):
            if path_kind(out / name, option) != "missing":
                raise InputError(f"{option}: {display_path(out / name)} already exists; choose a new folder")
        held = next(out.glob(PAIR_FILE_PATTERN), None)
        if held is not None:  # an index deleted, or another tool's pairs: they were written over without a word
            raise InputError(f"{option}: {display_path(held)} already exists; choose a new folder")
        check_writable_folder(out, option)
        return out
    # The nearest existing folder on the way must take files before the camera opens; a file on the way (a/b where
    # a is a file) failed only at the first pair, as "[Errno 20] Not a directory".
    ancestor, kind = next((p, kind) for p in out.absolute().parents if (kind := path_kind(p, option)) != "missing")
    if kind != "folder":
        raise InputError(f"{option}: expected a folder, but {display_path(ancestor)} on its path is not a folder")
    check_writable_folder(ancestor, option)
    return out


def save_pair(out: Path | None, pair: StereoPair, option: str = "--out-dir") -> dict[str, Any]:
    """Write both JPEGs as received into ``out`` (None: write nothing); the pair's index record (the module
    docstring of :mod:`svs_torch.cli.capture`; without ``left``/``right`` when nothing was written).

    Raises:
        OSError: naming ``option`` and the file that could not be written; neither image of the pair is left.
    """
    record: dict[str, Any] = {"index": pair.index}
    written: list[Path] = []
    try:
        for name, frame in (("left", pair.left), ("right", pair.right)):
            if out is not None:
                path = out / f"pair{pair.index:06d}_{name}.jpg"
                with write_errors_named(option, path):
                    write_bytes_atomic(path, frame.jpeg)
                written.append(path)
                record[name] = path.name
    except OSError:
        remove_files(written)
        raise
    record["width"], record["height"] = pair.left.size_wh
    for name, frame in (("left", pair.left), ("right", pair.right)):
        record.update(_frame_fields(name, frame))
    record["time_between_frames_s"] = pair.time_between_frames_s
    return record


def _frame_fields(name: str, frame: Frame) -> dict[str, Any]:
    return {f"{name}_bytes": len(frame.jpeg), f"{name}_request_monotonic_s": frame.request_monotonic_s,
            f"{name}_header_monotonic_s": frame.header_monotonic_s,
            f"{name}_arrival_monotonic_s": frame.arrival_monotonic_s,
            f"{name}_arrival_wall_s": frame.arrival_wall_s, f"{name}_attempts": frame.attempts}


def open_pairs_index(folder: Path, option: str) -> tuple[PairsIndex, bool]:
    """``folder``'s new index (:class:`PairsIndex`), the folder made if missing, and whether this call made it
    (a folder it made is removed again where the index cannot be made). Only the run whose index this is may
    clean the folder up (:func:`drop_unused_pairs_folder`): two runs into one folder, checked free by both,
    cannot both make it."""
    made = False
    if not folder.is_dir():
        try:
            folder.mkdir(parents=True)
            made = True
        except FileExistsError:  # another run made it meanwhile
            pass
    try:
        return PairsIndex(folder, option), made
    except BaseException:
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def remove_files(paths: list[Path]) -> None:
    """Remove what of ``paths`` exists (a pair that could not be kept whole), ignoring what cannot be."""
    for path in paths:
        with contextlib.suppress(OSError):
            path.unlink()


class PairsIndex:
    """``folder``'s ``index.jsonl``, created new (``"x"``), a line per pair appended and on disk before
    :meth:`append` returns; a line that cannot be written whole is cut off again and its pair's images removed.
    A context manager (closes the file)."""

    def __init__(self, folder: Path, option: str) -> None:
        self.path, self.option = folder / INDEX_NAME, option
        with write_errors_named(option, self.path):
            try:
                self._file = open(self.path, "xb", buffering=0)
            except FileExistsError:  # new_pairs_folder saw none: another run made it since (an audit: two captures
                # into one folder; the refused one's clean-up removed the other's index and folder)
                raise InputError(f"{option}: {display_path(self.path)} was made by another run since this one "
                                 "started (two runs writing one folder?); choose a new folder") from None
        self._length = 0  # the index's bytes of whole lines

    def append(self, record: dict[str, Any]) -> None:
        """Write ``record`` as one line. Raises OSError naming the option and the index (then the index holds the
        lines before it only, and the images ``record`` names are removed)."""
        # Strict JSON (NaN, inf: null), as every other JSON line of svs-depth: json.dumps wrote NaN, which strict
        # readers (jq, JavaScript's JSON.parse) refuse
        line = memoryview((dumps_strict(record) + "\n").encode())
        try:
            with write_errors_named(self.option, self.path):
                while line:  # an unbuffered write may take part of the line
                    line = line[self._file.write(line):]
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(self._file.fileno(), self._length)
                self._file.seek(self._length)
            remove_files([self.path.parent / record[view] for view in ("left", "right") if view in record])
            raise
        self._length = self._file.tell()

    def close(self) -> None:
        """Close the file (safe to call twice)."""
        self._file.close()

    def __enter__(self) -> PairsIndex:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def replay_command(folder: Path, floor: str | None = None, calibration: str | None = None,
                   second_passes: str = "on") -> str:
    """The ``estimate`` command that ranges a pairs folder's pairs (``capture --out`` or ``guide --record``) as camera
    frames (``--camera-frames``), with ``--floor`` (guide's setting; None: estimate's default) and ``--calibration``
    (the rig's file kept beside them) where given, and guide's ``--second-passes off`` (without it, estimate measured
    again the noisy pairs that guide ranged once: other distances, an audit)."""
    options = (f" --floor {floor}" if floor else "") + " --camera-frames"
    if second_passes == "off":
        options += " --second-passes off"
    if calibration:
        options += f" {_path_option('--calibration', calibration)}"
    return f"svs-depth estimate {_path_option('--pairs', folder / INDEX_NAME)}{options} --json"


def _path_option(option: str, path: str | Path) -> str:
    """``option`` with ``path`` whole, quoted for a shell: :func:`display_path` shortened a long one with an
    ellipsis, and the printed command then named no file (an audit). Escaped as display_path does only where it
    holds a control character, which a command on one line cannot. A path that starts with '-' (``--record=-walk``)
    is joined with '=': estimate took ``--pairs -walk/index.jsonl`` for two options."""
    text = str(path)
    word = shlex.quote(text if text.isprintable() else display_path(text))
    return f"{option}={word}" if text.startswith("-") else f"{option} {word}"


def drop_unused_pairs_folder(folder: Path, made: bool) -> None:
    """Remove what a capture that saved no pair wrote in ``folder``: its empty ``index.jsonl``, its copy of
    ``calibration.json``, and the folder if it made it. A capture stopped before its first pair said "interrupted
    after 0 pairs (index.jsonl lists them)", and the same command again was refused: "index.jsonl already exists;
    choose a new folder" (an audit of interrupts). An index that lists a pair is never touched."""
    index = folder / INDEX_NAME
    with contextlib.suppress(OSError):
        if index.is_file() and index.stat().st_size:
            return
        index.unlink(missing_ok=True)
        (folder / CALIBRATION_NAME).unlink(missing_ok=True)  # this run's: new_pairs_folder refused one already there
        if made:
            folder.rmdir()
