"""Real stereo data sets of the shared folder, SVS resampling and collation, synthetic SVS scenes
(``synthetic``, rendered by ``scene_rendering``), and a loosely mounted right camera's view (``rig_deviation``).

May import: ``svs_torch.core`` only. No stage, the pipeline, ``evaluation`` or the CLI imports are needed to read
or make data; the stages never import it (they take a ``StereoBatch``).

Every loader's ``dtype`` (float32 by default, or float64) is that of the batch it returns: its images (gray levels
in [0, 1]), ground-truth disparities and calibration alike.
"""

from .synthetic import SyntheticScenes, random_obstacle_scenes, render_obstacle_scenes
from .formats import (read_gray_image, read_kitti_disparity, read_middlebury_calib, read_pfm, read_scaled_disparity,
                      write_kitti_disparity, write_pfm)
from .datasets import (
    detect_stereo_layout,
    list_shared_pairs,
    load_image_pair,
    load_kitti,
    load_middlebury_2001,
    load_middlebury_2003,
    load_middlebury_2005_2006,
    load_middlebury_eval3,
    load_opencv_aloe,
    load_stereo_pair,
)
from .resample import collate_stereo_batches, resize_stereo_batch
from .pair_list import PairSource, load_pair_source, read_pair_list, read_pair_sources
from .calibration import calibration_record, format_calibration, pair_calibration_source
from .camera_frames import JPEG_QUALITY_FOR_DIGIT, camera_frame_pairs, camera_frames
from .rig_deviation import LOOSE_RIG, RigDeviation, deviate_view, deviation_homography

__all__ = [
    "JPEG_QUALITY_FOR_DIGIT", "LOOSE_RIG", "PairSource", "RigDeviation", "SyntheticScenes", "calibration_record",
    "camera_frame_pairs", "deviate_view", "deviation_homography",
    "camera_frames",
    "collate_stereo_batches", "detect_stereo_layout",
    "format_calibration",
    "load_pair_source", "pair_calibration_source",
    "read_pair_list", "read_pair_sources", "list_shared_pairs", "load_image_pair", "load_kitti",
    "load_middlebury_2001", "load_middlebury_2003", "load_middlebury_2005_2006", "load_middlebury_eval3",
    "load_opencv_aloe", "load_stereo_pair", "random_obstacle_scenes", "read_gray_image", "read_middlebury_calib",
    "read_pfm", "read_scaled_disparity", "render_obstacle_scenes", "resize_stereo_batch",
    "read_kitti_disparity", "write_kitti_disparity", "write_pfm",
]
