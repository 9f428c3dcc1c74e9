"""Helpers of the synthetic-render, classifier and training tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from scipy import ndimage

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
KARLSRUHE_OSM = SHARED_DATA / "karlsruhe-lanelet2" / "mapping_example.osm"
USGS_DIR = SHARED_DATA / "usgs-hro-colorado"
USGS = USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1.tif"
USGS_ALPHA = USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1_alpha.tif"
USGS_NODATA = USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1_nodata.tif"

#: The four stall lines visible in the USGS crop (EPSG:26913): white vertical
#: stripes between the parked cars, located by hand on an enlarged plot of
#: the crop (pixel columns 131, 150, 170, 190; rows 74–110, i.e. from the
#: aisle to the curb of the planted island). A fifth lies under a tree crown.
USGS_STALLS_X = (519487.2, 519490.0, 519493.0, 519496.0)
USGS_STALLS_Y = (4311653.2, 4311658.6)


def read_rgb(path):
    """(rgb (H, W, 3) uint8, valid (H, W) bool, transform, crs) of a GeoTIFF."""
    with rasterio.open(path) as ds:
        rgb = np.moveaxis(ds.read([1, 2, 3]), 0, -1)
        return rgb, ds.dataset_mask() > 0, ds.transform, ds.crs


def pixel_precision_recall(prob, label, valid, thr=0.5):
    """Precision (a predicted pixel within 1 px of a painted one) and recall at ``thr``."""
    pred = (prob > thr) & valid
    near = ndimage.binary_dilation(label, iterations=1)
    precision = (pred & near).sum() / max(pred.sum(), 1)
    recall = (pred & label).sum() / max((label & valid).sum(), 1)
    return float(precision), float(recall)


def stall_line_scores(prob, transform, thr=0.5):
    """Share of pixels above ``thr`` near the USGS stall lines, and each line's coverage."""
    rows, cols = np.nonzero(prob > thr)
    x = transform.c + (cols + 0.5) * transform.a
    y = transform.f + (rows + 0.5) * transform.e
    dist = np.min(np.abs(x[:, None] - np.array(USGS_STALLS_X)[None]), axis=1)
    near = (dist < 0.45) & (y > USGS_STALLS_Y[0] - 0.45) & (y < USGS_STALLS_Y[1] + 0.45)
    cover = []
    for sx in USGS_STALLS_X:
        ys = np.arange(USGS_STALLS_Y[0] + 0.2, USGS_STALLS_Y[1] - 0.2, 0.15)
        cover.append(float(np.mean([np.any((np.abs(x - sx) < 0.3) & (np.abs(y - v) < 0.15)) for v in ys])))
    return (float(near.mean()) if len(x) else 0.0), cover
