"""Real grayscale images from the shared data, read with OpenCV itself (an independent decoder)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

#: Left/right image pairs (relative to the data folder) covering every dataset in the MANIFEST.
PAIRS = [
    ("middlebury_eval3_Q/Teddy/im0.png", "middlebury_eval3_Q/Teddy/im1.png"),
    ("middlebury_eval3_Q/Piano/im0.png", "middlebury_eval3_Q/Piano/im1.png"),
    ("middlebury_eval3_Q/Motorcycle/im0.png", "middlebury_eval3_Q/Motorcycle/im1.png"),
    ("middlebury_2005_2006_third/Art/view1.png", "middlebury_2005_2006_third/Art/view5.png"),
    ("middlebury_2005_2006_third/Bowling2/view1.png", "middlebury_2005_2006_third/Bowling2/view5.png"),
    ("middlebury_2005_2006_third/Midd1/view1.png", "middlebury_2005_2006_third/Midd1/view5.png"),
    ("middlebury_2003_quarter/Cones/imL.png", "middlebury_2003_quarter/Cones/imR.png"),
    ("middlebury_2001/Tsukuba/imL.png", "middlebury_2001/Tsukuba/imR.png"),
    ("kitti/stereo2015_training/image_2/000000_10.png", "kitti/stereo2015_training/image_3/000000_10.png"),
    ("opencv_samples/left01.jpg", "opencv_samples/right01.jpg"),
]


def read_gray(data_dir: Path, relative: str, size_wh: tuple[int, int] | None = None) -> np.ndarray:
    """uint8 grayscale image, optionally resized with area interpolation (as an SVS-sized frame)."""
    image = cv2.imread(str(data_dir / relative), cv2.IMREAD_GRAYSCALE)
    assert image is not None, relative
    if size_wh is not None:
        image = cv2.resize(image, size_wh, interpolation=cv2.INTER_AREA)
    return image


def opencv_segmentation(gray: np.ndarray, kernel: np.ndarray, connectivity: int = 8):
    """The paper's pre-processing done by OpenCV: Otsu, erode, dilate, connected components with stats."""
    level, binary = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    opened = cv2.dilate(cv2.erode(binary, kernel), kernel)
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(opened, connectivity=connectivity)
    return level, binary > 0, opened > 0, count - 1, labels, stats[1:], centroids[1:]
