"""Evaluation of the pipeline against ground truth, and parameter sweeps: one subpackage that imports the
pipeline and that the pipeline never imports.

* :mod:`.metrics`: per-pair truth and scores (Eq. (9) of R_min, R_max and each object; dense and sparse
  disparity errors; inlier precision), batched over a :class:`~svs_torch.pipeline.PipelineResult`;
* :mod:`.stereo_metrics`: the Middlebury SDK's and KITTI's metrics of dense disparity maps (bad-t, avgerr,
  rms, A50–A99, D1, with their density), on all and non-occluded GT, batched;
* :mod:`.runner`: batched evaluation of a list of pairs, and its summary;
* :mod:`.overrides`: presets and dotted-path overrides of :class:`~svs_torch.pipeline.PipelineConfig`, applied
  to the configuration as a whole by :mod:`.config_tree`;
* :mod:`.store`: the SQLite results store (schema in its docstring); :mod:`.store_access`: who may write one;
* :mod:`.sweep`: sweep files, tasks and runs; :mod:`.executors`: the local process pool and Dask;
* :mod:`.report`: summaries, CSV and plots of a results store;
* :mod:`.disparity_errors`: disparity errors of the dense map and of the sparse inliers against the truth;
* :mod:`.export`: dense disparity maps written in the Middlebury and KITTI formats;
* :mod:`.benchmark`, :mod:`.bench_rivals`: ``svs-depth bench`` (pairs a second) and its rivals; :mod:`.bench_inputs`
  its input pairs; :mod:`.bench_processes` its child processes, none left behind when it is interrupted;
  :mod:`.frame_latency`: ``guide``'s one-frame latency on real scenes, frame by frame.

May import: ``svs_torch.core``, the stages' public names, the pipeline and ``data``. Only the CLI and the
experiments import it.

Every name here is imported from its submodule on first use (PEP 562), as ``svs_torch.capture``'s are: a submodule
that needs no torch (:mod:`.store_access`) loads without it, e.g. in a process that only holds a store's
configurations.
"""

from ..core.lazy_names import lazy_names

_SUBMODULE = {
    **dict.fromkeys(("DisparityErrors", "dense_disparity_errors", "disparity_map_errors", "sparse_disparity_errors"),
                    "disparity_errors"),
    **dict.fromkeys(("NOMINAL_BASELINE_M", "NOMINAL_FOCAL_PX", "ObjectTruth", "PairEstimate", "PairEvaluation",
                     "PairScore", "accuracy_pct", "estimates_from_result", "evaluate_result", "measured_regions",
                     "object_truth", "score_pair", "truth_list", "with_nominal_calibration"), "metrics"),
    **dict.fromkeys(("EvalSetup", "evaluate_block", "evaluate_pairs", "summarize"), "runner"),
    **dict.fromkeys(("STEREO_SCOPES", "StereoMetrics", "dense_map_metrics", "measure_stereo_metrics",
                     "object_map_metrics"), "stereo_metrics"),
}
__getattr__, __dir__ = lazy_names(__name__, _SUBMODULE)

__all__ = [
    "NOMINAL_BASELINE_M", "NOMINAL_FOCAL_PX", "DisparityErrors", "EvalSetup", "ObjectTruth", "PairEstimate",
    "PairEvaluation", "PairScore", "accuracy_pct", "dense_disparity_errors", "disparity_map_errors",
    "estimates_from_result",
    "evaluate_block", "evaluate_pairs", "evaluate_result", "measured_regions", "object_truth", "score_pair",
    "sparse_disparity_errors",
    "summarize", "truth_list", "with_nominal_calibration",
    "STEREO_SCOPES", "StereoMetrics", "dense_map_metrics", "measure_stereo_metrics", "object_map_metrics",
]
