"""What ``svs-depth guide`` keeps of a walk besides its warnings: a JSON line per pair it ranged (``--json``) and
the pairs themselves (``--record DIR``).

Why: an assistive-technology developer needs to know, after the walk, what the guide saw and said: a warning that
came late, or one about the wrong thing, is found in the record and ranged again offline. ``--record`` writes
``capture``'s layout (each board's JPEG exactly as received, and ``index.jsonl``, a line per pair flushed only
after both its images are in place), so ``svs-depth estimate --pairs DIR/index.jsonl --floor on --camera-frames``
(and guide's ``--second-passes off``, ``--calibration``: :func:`replay_command`) ranges the same pairs with guide's
settings and gives the same results: both decode a JPEG to its luma the same way
(:data:`svs_torch.core.image_files.JPEG_GRAY_DECODE`). A frame libjpeg finds damaged on the link is never
ranged: the pair is grabbed again (:class:`~svs_torch.capture.DamagedFrameError`), as ``estimate`` refuses such a
file (BAD_INPUT); damage libjpeg does not notice (a flipped bit that decodes to other values) is ranged by both.
Each line (on stdout with ``--json``, in the index with
``--record``) holds the capture fields (``capture``'s module docstring), the per-pair fields of ``estimate --json``
(:func:`~svs_torch.cli.estimate_report.pair_report`) with the ``calibration`` its metres use, and guide's own:
``warning`` (the pair's own distance ``distance_m`` and its obstacle's ``side``, the median of the last
``--confirm-frames`` pairs' that the class was judged on ``confirmed_m`` and the side said with it
``confirmed_side``, that median's pair's, the class ``clear`` / ``warn`` / ``stop`` and the words said, if any),
``dropped_pairs`` (pairs that arrived while the previous one was ranged and were never ranged), ``latency_s``
(from the request of the left frame, when the board grabbed it, to the warning: its encoding and the link's transfer
included) and ``cameras_swapped`` (capture's mark of boards answering in each other's roles, which ``estimate``
of the record says on each such pair). Only the pairs guide ranged are kept: the record is what the walker was told
about.
"""

from __future__ import annotations

import collections
import contextlib
import os
import stat
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from ..core.files import display_path, error_text, null_device_on
from ..core.workers import signals_held
from .common import dumps_strict
from .pairs_folder import CALIBRATION_NAME, PairsIndex, drop_unused_pairs_folder, open_pairs_index, replay_command, \
    save_pair
from .estimate_report import pair_report

__all__ = ["GuideLog", "replay_command"]


class GuideLog:
    """The ``--json`` lines (to ``stream``; None: none) and the ``--record`` folder (``record_dir``, checked by
    :func:`~svs_torch.cli.capture.new_pairs_folder`; None: none) of one guide run, whose ``--floor`` and
    ``--calibration`` were ``floor`` and ``calibration``. :meth:`open` before the first pair, :meth:`close` after
    the last; :meth:`summary` then says what was recorded. ``second_passes`` is guide's ``--second-passes``,
    ``quality`` its ``--quality`` and ``emulator`` :func:`~svs_torch.cli.link_options.emulator_record` (each line
    records them, as capture's index does)."""

    def __init__(self, stream: TextIO | None, record_dir: Path | None, floor: str = "on",
                 calibration: str | None = None, rig=None, second_passes: str = "on", quality: int | None = None,
                 emulator: dict | None = None) -> None:
        self.stream, self.record_dir = stream, record_dir
        # the --quality digit the frames were sent at, as capture records it (None: the board's own, unread)
        self.quality = quality
        self.emulator = emulator  # the in-process emulator's scene, as capture records it (None: boards)
        # guide's settings that estimate needs to range the pairs alike (replay_command's)
        self.replay = (floor, calibration, second_passes)
        self.rig = rig  # the StereoCalibration read from ``calibration`` (None: the SVS model)
        self._calibrations: dict[tuple[int, int], dict] = {}
        self._index: PairsIndex | None = None
        self._made = False  # the record's folder was made by open()
        self.num_recorded = 0
        # capture's cameras_swapped of the boards ranged now (guide_loop's role check; None: a build naming no role)
        self.cameras_swapped: bool | None = None
        self.record_error: str | None = None  # why the recording stopped (a full disk), None: it did not
        self.json_error: str | None = None  # why the --json lines stopped (stdout's disk full), None: they did not
        # Where stdout's file ends after each of the last lines ([None]: not a regular file). A flush may say
        # nothing of a line the file took only part of (a full disk), and fail at the next line instead.
        self._line_ends: collections.deque[int | None] = collections.deque(maxlen=64)

    def open(self) -> None:
        """Create the record's folder and index (once: a camera opened again appends to the same index), and with
        ``--calibration`` a copy of the rig's calibration beside the pairs, as ``capture`` keeps it (the replay
        command names the copy: the original's relative path broke from another folder)."""
        if self.record_dir is not None and self._index is None and self.record_error is None:
            # The index first (only the run that made it cleans the folder up; another guide or capture into
            # it is refused there), then the calibration beside it.
            self._index, self._made = open_pairs_index(self.record_dir, "--record")
            if self.rig is not None:
                from ..geometry.calibration import write_calibration

                write_calibration(self.record_dir / CALIBRATION_NAME, self.rig, "--record")
                self.replay = (self.replay[0], str(self.record_dir / CALIBRATION_NAME), self.replay[2])

    def write(self, pair, result, elapsed_s: float, warning: dict[str, Any], num_dropped: int) -> None:
        """Keep pair ``pair`` (a :class:`~svs_torch.capture.stereo.StereoPair`) and its one-pair ``result``,
        ranged in ``elapsed_s`` seconds, with what guide made of it (``warning``) and how many pairs it skipped
        before it (``num_dropped``)."""
        if self.stream is None and self._index is None:
            return
        latency_s = time.monotonic() - pair.left.request_monotonic_s  # before the files are written
        # estimate --json's sizes too (an audit: the README promises its fields); guide ranges the frame as it came
        size = list(pair.left.size_wh)
        report = pair_report(result, 0, (1.0, 1.0), elapsed_s, tuple(reversed(size)))
        with signals_held():  # the pair's images and its index line, both or neither (pairs_folder's docstring)
            record = self._saved(pair)
            record.update(report, calibration_rectified=self.rig is not None,
                          calibration=self._calibration(pair.left.size_wh), image_size_px=size, working_size_px=size)
            record.update(warning=warning, dropped_pairs=num_dropped, latency_s=round(latency_s, 6),
                          quality=self.quality, emulator=self.emulator, cameras_swapped=self.cameras_swapped)
            if self._index is not None:  # after both images are in place (save_pair)
                try:
                    self._index.append(record)
                    self.num_recorded += 1
                except OSError as error:  # its images removed (PairsIndex.append): the --json line names none
                    self._stop_recording(error)
                    record.pop("left"), record.pop("right")
        self._emit(record)

    def _saved(self, pair) -> dict[str, Any]:
        """``pair``'s index record, its images written into the record while it is kept."""
        if self._index is not None:
            try:
                return save_pair(self.record_dir, pair, "--record")
            except OSError as error:  # neither image left (save_pair)
                self._stop_recording(error)
        return save_pair(None, pair)

    def _stop_recording(self, error: OSError) -> None:
        """Stop the record, not the guide: a walker still needs the warnings when the disk is full (it stopped
        guide, exit 1, an audit). Said once on stderr, and in :meth:`summary`."""
        self.close()
        self.record_error = error_text(error)
        print(f"svs-depth guide: {self.record_error}; recording stopped after {_pairs(self.num_recorded)}, the "
              f"warnings go on", file=sys.stderr, flush=True)

    def _calibration(self, size_wh: tuple[int, int]) -> dict:
        """The calibration the metres of a pair of ``size_wh`` use, as ``estimate --json`` names it
        (:func:`~svs_torch.data.calibration_record`): the ``--calibration`` rig scaled to the frames, which guide
        rectifies them with, or the SVS model guide ranges them with."""
        if size_wh not in self._calibrations:
            from ..core.camera import SVS_CAMERA
            from ..data.calibration import SVS_MODEL_ASSUMED, calibration_fields, rig_scaled_source

            if self.rig is None:
                values = (SVS_MODEL_ASSUMED, False, SVS_CAMERA.focal_px(size_wh[0]), SVS_CAMERA.baseline_m, 0.0)
            else:
                rig = self.rig.scaled_to(size_wh, "--calibration")
                # With the size it was made at, as estimate's line of the same pair: guide's named the file alone
                source = rig_scaled_source(f"--calibration {self.replay[1]} (the pair rectified by it)",
                                           self.rig.image_wh, size_wh)
                values = (source, True, rig.focal_px, rig.baseline_m, rig.doffs_px)
            self._calibrations[size_wh] = calibration_fields(*values)
        return self._calibrations[size_wh]

    def event(self, name: str, **fields: Any) -> None:
        """A ``--json`` line ``{"event": name, "wall_s": ..., **fields}`` (the camera lost or back, guide unable
        to see or seeing again); never in the record, whose lines are pairs that ``estimate --pairs`` reads."""
        self._emit({"event": name, "wall_s": round(time.time(), 3), **fields})

    def _emit(self, line: dict[str, Any]) -> None:
        """Write one ``--json`` line. One that cannot be written (a full disk under ``--json > walk.jsonl``) stops
        the lines, not the guide (:func:`_stop_lines`): the record's full disk was kept from ending the walk, and the
        help's own ``--json --record walk/ > walk.jsonl`` then ended it on stdout's (exit 1, an audit of long
        walks). A closed pipe (BrokenPipeError) still ends guide, as for every command."""
        if self.stream is None:
            return
        text = dumps_strict(line) + "\n"  # (ASCII: as many bytes as characters; NaN, inf: null, as estimate --json)
        if not self._line_ends:
            self._line_ends.append(_file_offset(self.stream))
        try:
            self.stream.write(text)
            self.stream.flush()
        except BrokenPipeError:
            raise
        except OSError as error:
            stream, self.stream = self.stream, None
            self.json_error = _stop_lines(stream, error, self._line_ends)
            print(f"svs-depth guide: {self.json_error}; the --json lines stopped (the last one written whole is "
                  "kept), the warnings go on", file=sys.stderr, flush=True)
            return
        if self._line_ends[-1] is not None:
            self._line_ends.append(self._line_ends[-1] + len(text))

    def close(self) -> None:
        """Close the index (safe to call twice). With no pair recorded, what open() wrote is removed: guide stopped
        before its first pair left an empty index.jsonl, and the same command again was refused ("index.jsonl
        already exists; choose a new folder", an audit of interrupts)."""
        if self._index is not None:
            self._index.close()
            self._index = None
            if not self.num_recorded:
                drop_unused_pairs_folder(self.record_dir, self._made)

    def summary(self) -> str | None:
        """What was recorded and how to range it again (None: nothing recorded)."""
        if not self.num_recorded:
            return None
        stopped = "" if self.record_error is None else " (then the recording stopped: see above)"
        return (f"svs-depth guide: recorded {_pairs(self.num_recorded)} in {display_path(self.record_dir)}{stopped}; "
                f"range them again with: {replay_command(self.record_dir, *self.replay)}")


def _file_offset(stream) -> int | None:
    """Where ``stream``'s regular file stands after its last flush (None: a pipe, a terminal, no file)."""
    try:
        fd = stream.fileno()
        return os.lseek(fd, 0, os.SEEK_CUR) if stat.S_ISREG(os.fstat(fd).st_mode) else None
    except (OSError, ValueError, AttributeError):  # (io.UnsupportedOperation is both)
        return None


def _stop_lines(stream, error: OSError, line_ends) -> str:
    """Stop writing to ``stream`` after ``error``: its file is cut back to the last of ``line_ends`` (where its
    lines ended, in order) that it holds whole (nothing written half-way), and what ``stream`` still buffers, and
    anything after, goes to /dev/null (the interpreter's last flush failed again, exit 1 after a whole walk).
    Returns ``error`` worded as the record's is (:func:`~svs_torch.core.files.error_text`: "No space left on
    device: standard output", not Python's "[Errno 28] ... 'standard output'", an audit)."""
    with contextlib.suppress(OSError, ValueError, AttributeError):  # (io.UnsupportedOperation is both)
        fd = stream.fileno()
        size = os.fstat(fd).st_size
        whole = [end for end in line_ends if end is not None and end <= size]
        if whole:
            os.ftruncate(fd, whole[-1])
        null_device_on(fd)
        stream.flush()
    return error_text(error)


def _pairs(count: int) -> str:
    return f"{count} pair{'' if count == 1 else 's'}"

