"""Shared pieces of the map-builder pipeline tests: small rendered scenes and truth matching."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
USGS = SHARED / "usgs-hro-colorado"
USGS_BASE = USGS / "201404_13SED190110_201404_0x1500m_CL_1.tif"
USGS_ALPHA = USGS / "201404_13SED190110_201404_0x1500m_CL_1_alpha.tif"
USGS_NODATA = USGS / "201404_13SED190110_201404_0x1500m_CL_1_nodata.tif"


def stall_centres(first_end: tuple[float, float], n: int, spacing_m: float, length_m: float,
                  bearing_deg: float) -> np.ndarray:
    """Centres (n, 2) of ``n`` stall lines of ``length_m`` at ``bearing_deg`` whose ends lie
    on a line running east from ``first_end``, ``spacing_m`` apart."""
    b = np.radians(bearing_deg)
    u = np.array([np.sin(b), np.cos(b)])
    ends = np.array(first_end, float) + np.outer(np.arange(n) * spacing_m, [1.0, 0.0])
    return ends + 0.5 * length_m * u


class BrightnessModel:
    """A transparent stand-in classifier: bright, unsaturated pixels brighter than
    their neighbourhood are marking pixels. Picklable, so it runs in worker processes."""

    def __init__(self, contrast: float = 40.0, max_saturation: float = 60.0):
        self.contrast = contrast
        self.max_saturation = max_saturation

    def predict(self, rgb: np.ndarray, valid: np.ndarray, resolution_m: float) -> np.ndarray:
        rgbf = rgb.astype(np.float32)
        grey = rgbf.mean(axis=2)
        size = max(3, int(round(1.0 / resolution_m)) | 1)
        background = ndi.median_filter(grey, size=size)
        sat = rgbf.max(axis=2) - rgbf.min(axis=2)
        prob = (grey - background > self.contrast) & (sat < self.max_saturation)
        return (prob & valid).astype(np.float32)


def match(detected_xy: np.ndarray, truth_xy: np.ndarray, radius: float = 0.3):
    """Greedy one-to-one matching by distance; returns (pairs, distances)."""
    detected_xy = np.asarray(detected_xy, float).reshape(-1, 2)
    truth_xy = np.asarray(truth_xy, float).reshape(-1, 2)
    if not len(detected_xy) or not len(truth_xy):
        return [], np.zeros(0)
    d = np.hypot(*(detected_xy[:, None, :] - truth_xy[None, :, :]).transpose(2, 0, 1))
    order = np.argsort(d, axis=None)
    used_d, used_t, pairs, dists = set(), set(), [], []
    for flat in order:
        i, j = np.unravel_index(flat, d.shape)
        if d[i, j] > radius:
            break
        if i in used_d or j in used_t:
            continue
        used_d.add(i)
        used_t.add(j)
        pairs.append((int(i), int(j)))
        dists.append(d[i, j])
    return pairs, np.array(dists)


def pipeline_model():
    """The classifier the pipeline tests run with: the default model."""
    return None
