"""Stage 1, segmentation: where the obstacles are, in both views.

``threshold`` (Otsu), ``morphology`` (opening), ``components`` (connected regions, their properties and the kept
ones), ``canny`` (the paper's edge-based comparison), ``segment`` (the paper's rule: threshold, opening, the
largest regions, and :class:`SegmentationConfig`), ``soft`` (a differentiable mask), ``learned`` (the older
learned segmenter: its training truth, its segmentation and soft depths), ``network`` (the small U-Net that
segments from the pair, and its stereo features), ``network_files`` (the networks' weights files), ``nearness``
(the default: the near side of the pair's measured disparity, corrected by the network), with ``nearness_denoise``
(its map made usable on camera frames), ``nearness_split`` (where it splits near from far), ``nearness_regions``
(the regions' measured disparity and area in the right view, as the nearness rules weigh them), ``ground_plane`` and
``ground_plane_grid`` (the floor found in its map and taken out) and ``interior`` (kept regions cut to their
interior); ``stereo`` (both views of every pair segmented by the configured segmenter); ``weights/``
holds the shipped networks and ``kernels/`` the C kernels of the runs, their labels and the gray levels, beside
the torch code they speed up.

May import: ``svs_torch.core`` and the public names of the later stages it measures with (the nearness and
learned segmenters run ``depth``'s dense matching). Never the pipeline, ``evaluation``, ``data`` or the CLI.

The names below were the old ``svs_torch.segmentation`` module's, and stay importable from here.
"""

from .segment import SegmentationConfig, keep_largest_regions, keep_regions, segment_images, segment_stereo

__all__ = ["SegmentationConfig", "segment_images", "segment_stereo", "keep_largest_regions", "keep_regions"]
