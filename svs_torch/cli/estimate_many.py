"""``svs-depth estimate --pairs LIST``: every listed pair gets one line, in list order, its batches run in
worker processes (the parent decodes the first images ahead and only prints) or in this process.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from .capture_marks import capture_fields, capture_warning, warn_capture_marks
from .common import dumps_strict, too_small_reason
from .estimate_report import (_calibration_source, _write_disparity, claim_export_names, forget_unrun_map,
                              format_report, pair_report, rig_size, unranged_report, with_calibration)
from .features import check_native_pixels, checked_size, load_pair, warn_if_enlarged
from .progress import Progress
from .rig import (calibration_from_args, calibration_kept_beside, check_no_manual_calibration,
                  take_kept_calibration, warn_scenes_keep_their_own, with_calibrated_rectification)

__all__ = []


def _load_source(source, args: argparse.Namespace):
    """A scene folder or a pair with its own calibration, resampled to ``--size`` as :func:`load_pair` does. A scene
    whose ground truth cannot be read is ranged without it, and a warning says why: a distance needs none (an audit:
    a truncated disp0GT.pfm refused the pair)."""
    from ..core.errors import InputError
    from ..data import load_pair_source, resize_stereo_batch

    try:
        batch = load_pair_source(source)
    except InputError as error:
        if not source.scene:
            raise
        batch = load_pair_source(source, truth=False)  # the views' or calibration's own error, where it is theirs
        import warnings

        warnings.warn(f"{source.loaded_name}: its ground truth cannot be read ({error}): ranged without it",
                      stacklevel=2)
    if args.size is None:  # "" is an error (checked_size), not "native": --size "$SIZE" with SIZE unset
        check_native_pixels(batch.size_hw)  # as load_pair (a 6000x4000 scene ran here, at 3.7 GB: an audit)
        return batch, (1.0, 1.0)
    (height, width), (new_w, new_h) = batch.size_hw, checked_size(args.size)
    warn_if_enlarged((height, width), (new_w, new_h))
    return resize_stereo_batch(batch, (new_w, new_h)), (width / new_w, height / new_h)


def _load_entry(source, args) -> tuple[str | None, str | None, object]:
    """(status, reason, loaded pair) of one list entry: a pair to run has status None. Scenes and pairs listed
    with a calibration keep their own (under ``--calibration`` such a line is BAD_INPUT: it is not the rig's pair);
    the others take the command's (or the SVS model)."""
    from ..core.errors import InputError

    if source.problem:
        return "BAD_INPUT", source.problem, None
    if getattr(args, "calibration", None) and source.calibration is not None:  # a listed line's own: not the rig's
        from ..data.pair_list import OWN_CALIBRATION_UNDER_RIG

        return "BAD_INPUT", OWN_CALIBRATION_UNDER_RIG, None
    try:
        own = source.scene or source.focal_px is not None
        loaded = _load_source(source, args) if own else load_pair(source.left, source.right, args)
    except (InputError, OSError) as error:
        reason = " ".join(str(error).split())
        listed = source.listed_at and f"({source.listed_at})" not in reason  # (load_pair_source says it itself)
        return "BAD_INPUT", f"{reason} ({source.listed_at})" if listed else reason, None
    if not own:  # named as claim_export_names claims it (and load_pair_source names the others): a/x.png and
        # b/x.png were both 'x', and --disparity-out wrote the second's map over the first's in silence (an audit)
        from ..core.checks import checked_images

        with checked_images(loaded[0].left, loaded[0].right):  # ranged when they were loaded, a moment ago
            loaded = (dataclasses.replace(loaded[0], names=(source.name,)), *loaded[1:])
    reason = too_small_reason(loaded[0].size_hw)
    return ("TOO_SMALL", reason, loaded) if reason else (None, None, loaded)  # its size and calibration reported


def _estimate_chunk(chunk, args: argparse.Namespace, config) -> list[tuple[dict, str | None]]:
    """One batch of list entries run through the pipeline: each entry's report (with its ``left`` and
    ``right``) and, for a BAD_INPUT entry, the reason."""
    import torch

    entries = [_load_entry(entry, args) for entry in chunk]
    with torch.inference_mode():  # the result is read, never trained on: its tensors need no copy (core.inference)
        return _reports(chunk, entries, args, config)


def _reports(chunk, entries: list, args: argparse.Namespace, config) -> list[tuple[dict, str | None]]:
    """:func:`_estimate_chunk`'s reports of the loaded ``entries`` of ``chunk``. Each size's pairs run in
    batches of at most the pipeline's chunk of pixels, each reported and let go before the next runs (each pair's
    result is its own whatever its batch): the result of a whole ``--batch-size`` of large frames, held until
    all were reported, took gigabytes (:func:`~svs_torch.core.size_groups.same_size_indices`)."""
    from ..core.size_groups import same_size_indices
    from ..data import collate_stereo_batches
    from ..pipeline import estimate_obstacle_depth
    from ..pipeline.run import CHUNK_PIXELS

    runnable = [(position, loaded) for position, (status, _, loaded) in enumerate(entries) if status is None]
    ranged: dict[int, dict] = {}  # entry position -> its report
    for indices, _ in same_size_indices([loaded[0].size_hw for _, loaded in runnable], CHUNK_PIXELS):
        started = time.perf_counter()  # one batch a size (never padded), at most a chunk of pixels
        batch = collate_stereo_batches([runnable[i][1][0] for i in indices], mode="pad")
        result = estimate_obstacle_depth(batch, config)
        per_pair = (time.perf_counter() - started) / len(indices)
        _write_disparity(args, batch, result, per_pair)
        for row, index in enumerate(indices):
            position, loaded = runnable[index]
            source = chunk[position]
            report = pair_report(result, row, loaded[1], per_pair, tuple(batch.image_hw[row].tolist()))
            ranged[position] = with_calibration(report, batch, row, loaded[1], _calibration_source(source, args),
                                                rig_size(source, args))
        del batch, result  # before the next batch runs
    out = []
    for position, (source, (status, reason, loaded)) in enumerate(zip(chunk, entries)):
        if status is not None:
            report, bad = unranged_report(status, reason, config.depth.rule), reason if status == "BAD_INPUT" else None
            forget_unrun_map(args, source, status)
            if loaded is not None:  # too small: its size and calibration, as estimate of one pair says (an audit)
                report = with_calibration(report, loaded[0], 0, loaded[1], _calibration_source(source, args),
                                          rig_size(source, args))
        else:
            report, bad = ranged[position], None
        out.append(({"left": source.left, "right": source.right, **capture_fields(source), **report}, bad))
    return out


def _worker_setup(args: argparse.Namespace) -> tuple[list, object]:
    if args.pairs not in _WORKER_SETUP:
        config = pipeline_config_from_args(args)  # first, as in one process: a bad option is the error shown
        checked_size(args.size)
        check_no_manual_calibration(args)
        calibration_from_args(args)
        _WORKER_SETUP[args.pairs] = _read_pair_list(args.pairs), config
        claim_export_names(args, _WORKER_SETUP[args.pairs][0])
    return _WORKER_SETUP[args.pairs]


def _worker_count(args: argparse.Namespace) -> tuple[int, str | None]:
    """Worker task: the number of listed pairs, or the one-line error of a bad list or bad options (sent back
    as text: the parent, which has not imported torch, raises it)."""
    from ..core.errors import InputError

    try:
        return len(_worker_setup(args)[0]), None
    except InputError as error:
        return 0, str(error)


def _worker_chunk(args: argparse.Namespace, start: int, stop: int, decoded: dict | None = None
                  ) -> tuple[list[tuple[dict, str | None]], list[str]]:
    """Worker task: :func:`_estimate_chunk` of the list's entries ``[start, stop)``, and the warnings it raised
    (the parent shows them as its own one-line warnings). ``decoded``: image arrays the parent decoded for
    these entries (:data:`svs_torch.core.image_files.PRELOADED`), used instead of reading those files again."""
    import warnings

    from ..core.image_files import PRELOADED

    pairs, config = _worker_setup(args)
    PRELOADED.update(decoded or {})
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            lines = _estimate_chunk(pairs[start:stop], args, config)
    finally:
        PRELOADED.clear()
    return lines, [str(warning.message) for warning in caught]


def _listed_lines(path: str) -> list[tuple[str, str] | None]:
    """The list's lines read without torch, one item per non-blank, non-comment line: its two image paths for a
    plain pair line (``LEFT RIGHT`` with or without a calibration; relative to the list's folder, as
    :func:`svs_torch.data.read_pair_list` resolves them), None for any other line (an ``index.jsonl``'s all).
    Their number is about how many pairs the list holds (a scene-folder line may hold more), to choose the
    number of workers; the paths say which files to decode ahead. Neither decides a result: a list that cannot
    be read gives [] (the real reading reports why), and a line that turns into several entries only shifts
    which files are decoded ahead."""
    import os

    from ..core.files import split_list_line

    if os.path.isdir(path):  # a folder of scenes: about one pair a subfolder (the workers read the scenes)
        return [None for entry in os.scandir(path) if entry.is_dir()] or [None]
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return []
    if path.endswith(".jsonl"):
        return [None for line in text.splitlines() if line.strip()]
    lines: list[tuple[str, str] | None] = []
    for line in text.splitlines():
        try:
            fields = split_list_line(line)
        except ValueError:
            fields = [line]
        if fields:
            paths = [str(p if Path(p).is_absolute() else Path(path).parent / p) for p in fields[:2]]
            lines.append((paths[0], paths[1]) if len(fields) in (2, 4, 5) else None)
    return lines


def _decode_while(starting, lines: list[tuple[str, str] | None], batch_size: int) -> dict[int, dict]:
    """While the thread ``starting`` waits for the workers (their server imports torch, 1.0–1.5 s, on one
    core), decode the first images of the list's ``lines`` (:func:`_listed_lines`) here on the other (cv2 and
    numpy only): {chunk index: {file key: array}}, sent with each chunk so that its worker skips those reads. A
    file that does not decode is left to the worker, which reports it as it would."""
    from ..core.errors import InputError
    from ..core.image_files import preload_key, read_image_array

    decoded: dict[int, dict] = {}
    for index, pair in enumerate(lines):
        if not starting.is_alive():
            break
        for path in pair or ():
            try:
                array = read_image_array(path, "--pairs", gray=True)  # as read_gray_image reads it
                decoded.setdefault(index // batch_size, {})[preload_key(path)] = array
            except (InputError, OSError):
                pass
    return decoded


def _worker_results(args: argparse.Namespace, lines: list[tuple[str, str] | None], workers: int, threads: int
                    ) -> tuple[int, Iterator[list]]:
    """The number of listed pairs, and the chunks' results in list order from ``workers`` processes of
    :func:`svs_torch.core.workers.worker_pool`, each with ``threads`` torch threads (``lines``: the list's lines
    as :func:`_listed_lines` read them, for the images to decode ahead)."""
    from ..core.workers import abandon_pool, worker_pool
    from . import CliError

    executor = worker_pool(workers, threads, ("svs_torch.pipeline",))
    counted: dict = {}

    def start() -> None:
        # One count task per worker: each starts its process now (which waits for the server's imports), and
        # every worker reads the list it will need.
        try:
            counts = [executor.submit(_worker_count, args) for _ in range(workers)]
            counted["count"] = counts[0].result()
        except BaseException as error:  # raised again in the calling thread
            counted["error"] = error

    starting = threading.Thread(target=start, name="start-workers", daemon=True)
    try:
        starting.start()
        decoded = _decode_while(starting, lines, args.batch_size)
        starting.join()
        if "error" in counted:
            raise counted["error"]
        total, problem = counted["count"]
        if problem:
            raise CliError(problem)
    except BaseException:  # (as below)
        abandon_pool(executor)
        raise
    return total, _ordered_chunks(executor, args, total, decoded, workers)


def _ordered_chunks(executor, args: argparse.Namespace, total: int, decoded: dict[int, dict],
                    workers: int) -> Iterator[list]:
    """Every chunk of the list submitted to ``executor``, its lines yielded in list order; the workers'
    warnings shown here as this process's own. At most ``2 * workers + 1`` chunks are submitted ahead of the one
    printed, and a printed chunk's result is let go: this process held every chunk's lines to the end (3–4 kB a
    pair, 56 MB after 1 650 pairs and rising, found by an audit of long runs)."""
    import collections
    import warnings

    from ..core.workers import abandon_pool, stop_worker_server

    starts = iter(range(0, total, args.batch_size))

    def submit(start: int):
        return executor.submit(_worker_chunk, args, start, min(start + args.batch_size, total),
                               decoded.pop(start // args.batch_size, None))

    try:
        ahead = collections.deque(submit(start) for start in itertools.islice(starts, 2 * workers + 1))
        while ahead:
            lines, messages = ahead.popleft().result()
            ahead.extend(submit(start) for start in itertools.islice(starts, 1))
            for message in messages:
                warnings.warn(message, RuntimeWarning, stacklevel=2)
            yield lines
    except BaseException:  # an error, Ctrl-C or a closed pipe: nothing more is wanted, wait for none
        # Killed, not left to finish their chunks: Python's exit waited for the pool's manager thread, and so for
        # those chunks (a Ctrl-C at --batch-size 30 on 640x480 pairs took 3 s, ended by the program's own bound)
        abandon_pool(executor)
        raise
    executor.shutdown(wait=True)  # every task is done: the workers exit before this process does
    stop_worker_server()  # and their server, waited for: their CPU time counts as this process's children's


def _run_many(args: argparse.Namespace) -> int:
    """Every listed pair gets exactly one line, in list order; exit 2 (after all lines) if any was BAD_INPUT.
    With more than one worker the batches run in worker processes and this process only prints."""
    import os

    from ..core.files import check_list_file
    from ..core.workers import imports_without_collection, thread_budget

    if not os.path.isdir(args.pairs):  # a list that is not there is said at once, not after the pipeline's imports
        check_list_file(args.pairs, "--pairs")
    take_kept_calibration(args, calibration_kept_beside(args, [args.pairs]), "estimate")  # (one list: one folder)
    budget = thread_budget()
    listed = _listed_lines(args.pairs)
    chunks = -(-len(listed) // args.batch_size)
    workers = max(1, min(budget if args.workers is None else args.workers, chunks))
    if workers == 1:
        with imports_without_collection():  # the pipeline's imports (see there)
            config = pipeline_config_from_args(args)
            checked_size(args.size)  # once, not as every listed pair's BAD_INPUT
            check_no_manual_calibration(args)
            calibration_from_args(args)
        pairs = _read_pair_list(args.pairs)
        claim_export_names(args, pairs)  # the first listed pair of a name keeps it, as with workers
        total = len(pairs)
        results = (_estimate_chunk(pairs[start:start + args.batch_size], args, config)
                   for start in range(0, total, args.batch_size))
    else:
        total, results = _worker_results(args, listed, workers, max(1, budget // workers))
    bad, unrectified, marked = [], [], []
    # A bar for a person watching; in a log or a pipe, a plain line every few seconds and a summary.
    with Progress(total, "estimate") as progress:
        for lines in results:
            for report, reason in lines:
                if reason is not None:
                    bad.append(reason)
                elif report.get("calibration") and not report["calibration_rectified"]:  # (under --calibration:
                    unrectified.append(report["left"])  # a scene folder, ranged with its own calibration)
                heading, warning = f"{report['left']} {report['right'] or ''}".rstrip(), capture_warning(report)
                if warning:  # an index's frozen camera or frames apart: ranged, said (its marks kept, not its line)
                    marked.append({key: report.get(key) for key in ("frozen_camera", "frames_apart_s",
                                                                     "cameras_swapped")})
                text = None if args.json else "\n".join([heading, *format_report(report, batched=True),
                                                          *[f"  {warning}"] * bool(warning)])
                progress.write(dumps_strict(report) if args.json else text)
            progress.update(len(lines))
    warn_scenes_keep_their_own(args, unrectified)
    warn_capture_marks(marked, total)
    if bad:
        print(f"svs-depth estimate: error: --pairs: {len(bad)} of {total} pairs are BAD_INPUT (first: {bad[0]})",
              file=sys.stderr)
        return 2
    return 0


def pipeline_config_from_args(args: argparse.Namespace):
    """``--preset`` with every option the user gave (``--range``, ``--canny``, ``--camera-frames``,
    ``--second-passes``, features, segmentation)."""
    from dataclasses import replace

    from .features import preset_config
    from .segment import check_segmenter_options

    config = replace(preset_config(args), seed=args.seed)
    if args.canny:
        check_segmenter_options(config.segmentation.segmenter, canny=True)
        config = replace(config, segmentation=replace(config.segmentation, method="canny"))
    if args.range_rule:
        config = replace(config, depth=replace(config.depth, rule=args.range_rule))
    if getattr(args, "camera_frames", False):
        check_segmenter_options(config.segmentation.segmenter, camera_frames=True)
        config = replace(config, segmentation=replace(config.segmentation, camera_frames=True))
    if getattr(args, "second_passes", "on") == "off":  # as guide --second-passes off (PipelineConfig.for_guide)
        config = replace(config, coarse_retry_below_share=None, exposure_retry=None)
    return with_calibrated_rectification(config, args)


def _read_pair_list(path: str):
    """The entries of a pair list (:func:`svs_torch.data.read_pair_list`): lines ``LEFT RIGHT``, ``LEFT RIGHT
    FOCAL_PX BASELINE_M [DOFFS_PX]`` or a scene folder, or capture's ``index.jsonl``; or the scenes of a folder
    (:func:`svs_torch.data.read_pair_sources`, as eval reads one). An entry that is not a pair keeps its
    ``problem``: it still gets its own output line."""
    import os

    from ..data import read_pair_list, read_pair_sources

    if os.path.isdir(path):  # a folder of scenes, as eval takes it (an audit: "expected a list file, got a folder")
        return read_pair_sources([path], "--pairs")
    return read_pair_list(path, "--pairs")


#: This worker process's pair list and pipeline configuration, made once per list (every worker reads the list
#: itself: the parent never imports torch).
_WORKER_SETUP: dict[str, tuple[list, object]] = {}
