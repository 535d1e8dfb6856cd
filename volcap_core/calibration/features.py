"""SIFT features (pycolmap's CPU SIFT, the same extractor COLMAP's database uses) and matching.

``cv2`` is imported before ``pycolmap`` on purpose: the other order crashed on PNG writes (zlib
clash, see NOTES). Keypoints are returned in OpenCV pixel coordinates (centre of the top-left
pixel at (0, 0)); COLMAP reports them +0.5.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2  # noqa: F401  (must come before pycolmap)
import numpy as np
import pycolmap

from hardware.lens_models import COLMAP_PIXEL_OFFSET


@dataclass(frozen=True)
class SiftOptions:
    """What the calibration uses: more features than COLMAP's default thresholds give on small
    images, affine-adapted shapes (they matched 30°-apart views markedly better), and more octaves
    for zoomed frames whose background is many times larger than in the wide cameras."""

    peak_threshold: float = 0.002
    max_num_features: int = 8192
    num_octaves: int = 4
    first_octave: int = -1
    estimate_affine_shape: bool = True
    num_threads: int = 2

    def colmap(self) -> pycolmap.FeatureExtractionOptions:
        eo = pycolmap.FeatureExtractionOptions()
        eo.num_threads = self.num_threads
        eo.sift.peak_threshold = self.peak_threshold
        eo.sift.max_num_features = self.max_num_features
        eo.sift.num_octaves = self.num_octaves
        eo.sift.first_octave = self.first_octave
        eo.sift.estimate_affine_shape = self.estimate_affine_shape
        return eo


_EXTRACTORS: dict[SiftOptions, object] = {}


def extract_sift(gray: np.ndarray, options: SiftOptions = SiftOptions()) -> tuple[np.ndarray, np.ndarray]:
    """SIFT on a uint8 gray image [H, W] -> keypoints [K, 4] (x, y OpenCV px, scale px,
    orientation rad) float32 and descriptors [K, 128] uint8 (COLMAP's L1-root normalisation)."""
    if gray.dtype != np.uint8 or gray.ndim != 2:
        raise ValueError(f"extract_sift needs a uint8 [H, W] image, got {gray.dtype} {gray.shape}")
    fe = _EXTRACTORS.get(options)
    if fe is None:
        fe = pycolmap.FeatureExtractor.create(options.colmap(), pycolmap.Device.cpu)
        _EXTRACTORS[options] = fe
    k, d = fe.extract_from_uint8_array(np.ascontiguousarray(gray))
    kp = pycolmap.keypoints_to_matrix(k).astype(np.float32).reshape(-1, 4)
    kp[:, :2] -= COLMAP_PIXEL_OFFSET
    return kp, np.asarray(d.data, np.uint8).reshape(-1, 128)


def match_descriptors(query: np.ndarray, train: np.ndarray, ratio: float = 0.8,
                      mutual: bool = False) -> np.ndarray:
    """Nearest-neighbour matches [M, 2] (query index, train index) passing Lowe's ratio test;
    ``mutual`` also requires the train descriptor's nearest query to be the same one."""
    if len(query) < 1 or len(train) < 2:
        return np.zeros((0, 2), np.int64)
    q = np.asarray(query, np.float32)
    t = np.asarray(train, np.float32)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    knn = bf.knnMatch(q, t, k=2)
    out = [(m[0].queryIdx, m[0].trainIdx) for m in knn
           if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if not out:
        return np.zeros((0, 2), np.int64)
    res = np.asarray(out, np.int64)
    if mutual:
        back = bf.match(t, q)
        best_q = np.full(len(t), -1, np.int64)
        for m in back:
            best_q[m.queryIdx] = m.trainIdx
        res = res[best_q[res[:, 1]] == res[:, 0]]
    return res
