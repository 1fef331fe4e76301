"""Batched evaluation of a list of pairs: load, resample, run the pipeline on blocks of pairs, score, summarise.

One bad pair never stops the others: an entry that cannot be loaded is ``BAD_INPUT``, a pair under 5×5 pixels
``TOO_SMALL``, and a block whose pipeline run raises is run again pair by pair, so only the pair that raises is
``ERROR`` (with the exception in ``reason``). Each pair's result does not depend on its block, bit for bit: the
pipeline runs pairs of different sizes as groups of one size, each on its own pixels
(:mod:`svs_torch.core.size_groups`), and seeds RANSAC per pair, so a block can be re-run alone, at another batch size or
in another order with equal results (``tests/pipeline/test_batch_independence.py``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import torch

from ..core.camera import calibration_value_expected, too_many_pixels
from ..core.checks import InputError
from ..core.daemon_task import DaemonTask
from ..core.size_groups import same_size_indices
from ..core.types import StereoBatch
from ..data import (calibration_record, collate_stereo_batches, load_pair_source, pair_calibration_source,
                    resize_stereo_batch)
from ..data.calibration import rig_scaled_source
from ..data.pair_list import OWN_CALIBRATION_UNDER_RIG, PairSource
from ..geometry.calibration import StereoCalibration, rectify_with_calibration
from ..pipeline import PipelineConfig, PipelineResult, estimate_obstacle_depth
from ..pipeline import run as run_module
from .metrics import PairEvaluation, evaluate_result, with_nominal_calibration
from .running_summary import UNSCORED_NAMES, RunningSummary

__all__ = ["EvalSetup", "LoadedPair", "evaluate_block", "evaluate_pairs", "load_block", "run_loaded",
           "summarize", "MIN_SIDE_PX"]

#: The smallest side the feature stage handles (SURF's first octave needs 5 pixels for its 3×3×3 non-maximum
#: suppression); the command line refuses smaller pairs with the same TOO_SMALL status.
MIN_SIDE_PX = 5


@dataclass(frozen=True)
class EvalSetup:
    """How every pair of an evaluation is run.

    Attributes:
        config: the pipeline configuration.
        size_wh: resample every pair to (width, height) first; None keeps each pair's own size (pairs of
            different sizes are then padded into one batch, and the pipeline runs each size apart).
        focal_px, baseline_m, doffs_px: calibration of listed file pairs that carry none (None: the SVS model).
        calibration: a rig's :class:`~svs_torch.geometry.calibration.StereoCalibration` for those pairs instead:
            they are rectified with it and take its focal, baseline and doffs (scenes keep their own; a pair
            listed with a calibration is BAD_INPUT, ``OWN_CALIBRATION_UNDER_RIG``).
        calibration_source: how the reports name that calibration (its file), for the pairs it rectified.
        max_pixels: a pair of more pixels run at its own size (``size_wh`` None) is ``BAD_INPUT`` (the command
            line's 16 megapixels: a 6000x4000 pair took 3.9 GB, and memory grows with the pixels); None: any.
        resize_with: the setting the reason of such a pair names to resample it (a sweep's is its file's size).
    """

    config: PipelineConfig = PipelineConfig()
    size_wh: tuple[int, int] | None = None
    focal_px: float | None = None
    baseline_m: float | None = None
    doffs_px: float = 0.0
    calibration: StereoCalibration | None = None
    calibration_source: str = "a rig's calibration (the pair rectified by it)"
    max_pixels: int | None = None
    resize_with: str = "--size"


@dataclass(frozen=True)
class LoadedPair:
    """A listed pair after loading: ``batch`` (B = 1, resampled, nominal calibration where it had none) or
    None with the ``status`` and ``reason`` it gets instead; ``calibrated``: the data's own calibration;
    ``calibration``: the one its metres use and where it came from (:func:`~svs_torch.data.calibration_record`,
    at the input size); ``px_scale``: the input's width over the batch's (native pixels per pixel the pipeline
    ran at)."""

    source: PairSource
    batch: StereoBatch | None
    status: str | None = None
    reason: str | None = None
    calibrated: bool = False
    calibration: dict | None = None
    px_scale: float = 1.0
    name: str | None = None  # the batch's name for the pair (``eval3/Teddy``), once it was read
    has_truth: bool = False  # it was read with ground truth: a pair that then fails still counts 0 %


def _load_one(source: PairSource, setup: EvalSetup) -> LoadedPair:
    if setup.calibration is not None and source.calibration is not None:  # a listed line's own: not the rig's
        return LoadedPair(source, None, "BAD_INPUT", OWN_CALIBRATION_UNDER_RIG)
    try:
        batch = load_pair_source(source, setup.focal_px, setup.baseline_m, setup.doffs_px)
    except (InputError, OSError) as error:
        return LoadedPair(source, None, "BAD_INPUT", " ".join(str(error).split()))
    origin = pair_calibration_source(source, setup.focal_px, setup.baseline_m, setup.doffs_px)
    if setup.calibration is not None and not source.scene:
        try:
            batch = rectify_with_calibration(batch, setup.calibration)
        except InputError as error:
            return LoadedPair(source, None, "BAD_INPUT", " ".join(str(error).split()))
        # was "the SVS model assumed", beside the rig's own focal and baseline
        origin = rig_scaled_source(setup.calibration_source, setup.calibration.image_wh, batch.size_hw[::-1])
    calibrated = bool(batch.calibrated[0])
    given = not source.scene and (setup.focal_px is not None or setup.baseline_m is not None)
    if not calibrated and batch.disparity_px is not None and not given:
        # The truth needs some f·B to have a depth (Eq. (9) does not depend on which): say so, and why.
        batch = with_nominal_calibration(batch)
        origin = "nominal, for scoring only: no calibration shipped or given"
    elif not calibrated and batch.disparity_px is not None:
        # A lone --focal-px or --baseline-m is the user's, the SVS model the rest: as `estimate` ranges the pair.
        batch = dataclasses.replace(batch, calibrated=torch.ones_like(batch.calibrated))
    # A pair without truth keeps its loader's values (the SVS model where none was given): `estimate`'s metres.
    calibration = dict(calibration_record(batch, 0, origin), measured=calibrated)
    native_width = batch.size_hw[1]
    if setup.size_wh is not None:
        batch = resize_stereo_batch(batch, setup.size_wh)
    height, width = batch.size_hw
    read = dict(calibrated=calibrated, calibration=calibration, name=batch.names[0] if batch.names else None,
                has_truth=batch.disparity_px is not None and bool(batch.disparity_valid.any()))
    too_many = None if setup.size_wh is not None or setup.max_pixels is None else too_many_pixels(
        (height, width), setup.max_pixels, resize_with=setup.resize_with)
    if too_many:
        return LoadedPair(source, None, "BAD_INPUT", too_many, **read)
    if min(height, width) < MIN_SIDE_PX:
        return LoadedPair(source, None, "TOO_SMALL", f"image {width}x{height} is smaller than "
                                                     f"{MIN_SIDE_PX}x{MIN_SIDE_PX} pixels", **read)
    return LoadedPair(source, batch, px_scale=native_width / batch.size_hw[1], **read)


def load_block(sources: Sequence[PairSource], setup: EvalSetup) -> list[LoadedPair]:
    """Load a block of listed pairs (each failure kept as its own status)."""
    return [_load_one(source, setup) for source in sources]


def _unrun(pair: LoadedPair, status: str | None = None, reason: str | None = None) -> PairEvaluation:
    """A pair the pipeline gave no result for: one it could not load, or ``status`` ``ERROR``. Once read, it keeps
    its name, calibration and whether it has truth, so a failure with truth counts 0 % as the pipeline's do."""
    return PairEvaluation(name=pair.name or pair.source.loaded_name, status=status or pair.status,
                          reason=reason or pair.reason, calibrated=pair.calibrated if pair.name else None,
                          calibration=pair.calibration, has_truth=pair.has_truth)


#: ``on_result(batch, result, seconds per pair)``: called with each pipeline run (e.g. to write its maps).
OnResult = Callable[[StereoBatch, PipelineResult, float], None]


#: Whether this process has run the pipeline once: its first run pays the kernels' loading and the first calls'
#: set-up (0.12 against 0.07 s for three 320×240 pairs), which the timed seconds per pair charged to whichever
#: configuration ran first, and results ranked by (an audit: swapping a sweep's order swapped its "best").
_WARMED_UP = False


def _warm_up(pair: StereoBatch, config: PipelineConfig) -> None:
    """Run the pipeline once, untimed and discarded, on the first pair of this process's first batch."""
    global _WARMED_UP
    if not _WARMED_UP:
        _WARMED_UP = True
        with torch.no_grad():
            estimate_obstacle_depth(pair, config)


def _run_batch(pairs: list[LoadedPair], config: PipelineConfig,
               on_result: OnResult | None = None) -> list[PairEvaluation]:
    batch = collate_stereo_batches([p.batch for p in pairs], mode="pad")
    _warm_up(pairs[0].batch, config)
    started = time.perf_counter()
    with torch.no_grad():
        result = estimate_obstacle_depth(batch, config)
    per_pair = (time.perf_counter() - started) / len(pairs)
    scored = evaluate_result(batch, result, per_pair, [p.calibrated for p in pairs], [p.px_scale for p in pairs])
    if on_result is not None:
        try:
            on_result(batch, result, per_pair)
        except Exception as error:
            raise _OutputFailed(error) from error
    return [dataclasses.replace(e, calibration=p.calibration) for e, p in zip(scored, pairs)]


class _OutputFailed(Exception):
    """``on_result`` raised: an output of the run (a map export) failed, not the pair; re-raised as it was."""

    def __init__(self, error: Exception) -> None:
        super().__init__(str(error))
        self.error = error


def run_loaded(pairs: Sequence[LoadedPair], config: PipelineConfig,
               on_result: OnResult | None = None) -> list[PairEvaluation]:
    """Run the pipeline on the loaded pairs of a block, those of each size as one batch
    (:func:`~svs_torch.core.size_groups.same_size_indices`), and score them, in order (``on_result``: see
    :data:`OnResult`; an exception it raises stops the run: a map export that cannot be written, a full disk,
    is not the pairs' failure, and scored as one it read as a 33 % accuracy)."""
    runnable = [p for p in pairs if p.batch is not None]
    scored: dict[int, PairEvaluation] = {}
    # At most the pipeline's chunk of pixels a batch: its result, merged over its chunks, was held whole until
    # scored (an audit: a --batch-size of 48 native MiddEval3 pairs peaked at 1.09 GB, now 0.95 GB, the rest
    # being the loaded pairs of the block and of the next, decoded ahead).
    for indices, _ in same_size_indices([p.batch.size_hw for p in runnable], run_module.CHUNK_PIXELS):
        group = [runnable[i] for i in indices]
        try:
            scored.update(zip(indices, _run_batch(group, config, on_result)))
        except _OutputFailed as failed:
            raise failed.error from None
        except Exception:  # noqa: BLE001 -- find the pair that raises: every other pair still gets its result
            for index, pair in zip(indices, group):
                try:
                    scored[index] = _run_batch([pair], config, on_result)[0]
                except _OutputFailed as failed:
                    raise failed.error from None
                except Exception as error:  # noqa: BLE001 -- counted as ERROR with its message, never hidden
                    scored[index] = _unrun(pair, "ERROR", f"{type(error).__name__}: {' '.join(str(error).split())}")
    ran = iter(scored[index] for index in range(len(runnable)))
    return [next(ran) if p.batch is not None else _unrun(p) for p in pairs]


def _expect(condition: bool, message: str) -> None:
    if not condition:
        raise InputError(message)


def _check_list(parts: object, kind: type, name: str, expected: str) -> None:
    """``parts`` a list (or tuple) of ``kind``, from a script: a folder's name given for the pairs was read letter by
    letter, to "'str' object has no attribute 'problem'" (an audit). Shared with :mod:`.sweep`."""
    bad = parts if not isinstance(parts, (list, tuple)) else next((p for p in parts if not isinstance(p, kind)), None)
    _expect(bad is None, f"{name}: expected a list of {expected}, got {bad!r:.80}")


def _check_call(sources: Sequence[PairSource], setup: EvalSetup, batch_size: int = 1) -> None:
    """Refuse a bad argument of :func:`evaluate_block` or :func:`evaluate_pairs` by name, before any pair is loaded
    (an audit of the API: a folder's name for ``sources`` was an AttributeError from the loader; a dict for the
    configuration made every pair ERROR; a ``batch_size`` of -1 evaluated nothing, without a word; a ``max_pixels``
    or ``doffs_px`` of another type was a TypeError from deep inside; a negative ``focal_px`` every pair's
    BAD_INPUT, where the command line refuses its option)."""
    _check_list(sources, PairSource, "sources", "PairSource (read_pair_sources)")
    _expect(isinstance(setup, EvalSetup), f"setup: expected an EvalSetup, got {type(setup).__name__}")
    _expect(isinstance(setup.config, PipelineConfig),
            f"setup.config: expected a PipelineConfig, got {type(setup.config).__name__}")
    for name, value, least in (("batch_size", batch_size, 1), ("setup.max_pixels", setup.max_pixels, 1)):
        _expect(value is None and name != "batch_size" or type(value) is int and value >= least,
                f"{name}: expected an integer of at least {least}, got {value!r}")
    for key in ("focal_px", "baseline_m", "doffs_px"):
        value = getattr(setup, key)
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        expected = (calibration_value_expected(key, value) if number  # (doffs 0.0 is none: None is no number)
                    else "a number" if value is not None or key == "doffs_px" else None)
        _expect(expected is None, f"setup.{key}: expected {expected}, got {value!r}")
    _expect(setup.calibration is None or isinstance(setup.calibration, StereoCalibration),
            f"setup.calibration: expected a StereoCalibration, got {type(setup.calibration).__name__}")


def evaluate_block(sources: Sequence[PairSource], setup: EvalSetup) -> list[PairEvaluation]:
    """Load, run and score one block of pairs as one batch (a bad argument: an InputError naming it)."""
    _check_call(sources, setup)
    return run_loaded(load_block(sources, setup), setup.config)


def evaluate_pairs(sources: Sequence[PairSource], setup: EvalSetup, batch_size: int = 16,
                   on_block: Callable[[int], None] | None = None,
                   on_result: OnResult | None = None) -> Iterator[tuple[PairSource, PairEvaluation]]:
    """Evaluate every listed pair in blocks of ``batch_size``, in order; the next block is decoded in a thread
    while the pipeline runs on the current one. ``on_block(n)`` is called after each block of n pairs;
    ``on_result`` with each pipeline run (:data:`OnResult`)."""
    _check_call(sources, setup, batch_size)
    blocks = [list(sources[i:i + batch_size]) for i in range(0, len(sources), batch_size)]
    if not blocks:
        return
    # A daemon thread, not an executor: a Ctrl-C must never wait on the decoding (core.daemon_task says why)
    pending = DaemonTask(load_block, blocks[0], setup, name="svs-decode-ahead")
    for number, block in enumerate(blocks):
        loaded = pending.result()
        if number + 1 < len(blocks):
            pending = DaemonTask(load_block, blocks[number + 1], setup, name="svs-decode-ahead")
        yield from zip(block, run_loaded(loaded, setup.config, on_result))
        if on_block is not None:
            on_block(len(block))


def summarize(evaluations: Sequence[PairEvaluation], wall_s: float | None = None) -> dict:
    """One summary of an evaluation.

    ``pairs`` every listed pair, ``failed`` those whose status is not OK (listed in ``failures``), ``scored``
    those with ground truth and their data's own calibration whose accuracy counts: every such pair, a failed
    one at 0 % (a failed pair whose segmentation kept nothing has no object truth, and still counts 0 %).
    ``acc_*_pct`` are means over the scored pairs; pairs scored with a nominal calibration (``calibrated``
    False: the data ship none) are kept apart in ``nominal_calibration`` (their count ``scored``, the first
    :data:`UNSCORED_NAMES` of their names in sorted order, and their means);
    disparity errors are means over the pairs that have them; ``pairs_per_s`` is pairs over
    ``wall_s`` (the whole run: loading included) when given, else over the summed pipeline time;
    ``pipeline_s_per_pair`` is the mean pipeline time of the pairs it ran on. The stereo metrics
    (:data:`~svs_torch.evaluation.stereo_metrics.STEREO_FIELDS`) are means over the pairs that have them;
    ``<scope>_pairs`` counts those pairs for each scope. ``unscored``: the pairs ranged (status OK) but not scored
    (no ground truth, or none where they were ranged), their count and the first :data:`UNSCORED_NAMES` names: a
    scene whose truth had gone missing (a KITTI folder without ``disp_occ``, a PFM of unknown values only) read as
    one more OK row (an audit).
    """
    summary = RunningSummary()
    for evaluation in evaluations:
        summary.add(evaluation)
    return summary.summary(wall_s)
