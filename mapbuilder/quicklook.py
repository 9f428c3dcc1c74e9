"""A quicklook of a build: its markings drawn over the imagery, downsampled, as one PNG.

After a build of a whole city, a look at one picture shows what no count
does: a district with no markings (a dark image, a wrong model), kerbs along
every street, a tile seam. Each marking is drawn as its axis, coloured by its
score (the classifier's mean probability), over the images reprojected into
the map's CRS at a resolution that keeps the long side of the picture within
``max_px``. Pixel ``(col, row)`` of the PNG is at ``minx + (col + 0.5) * res``,
``maxy - (row + 0.5) * res`` of :attr:`Quicklook.bounds` and
:attr:`Quicklook.resolution_m`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .model import Marking


@dataclass
class Quicklook:
    """Where a quicklook went and what it shows.

    Attributes
    ----------
    path : Path
    bounds : (minx, miny, maxx, maxy)
        The picture's extent in the map's CRS, metres.
    resolution_m : float
        Metres per pixel of the picture.
    shape : (rows, cols)
    markings : int
        Markings drawn.
    """

    path: Path
    bounds: tuple[float, float, float, float]
    resolution_m: float
    shape: tuple[int, int]
    markings: int


def _footprints(images: Sequence[str], crs: str) -> tuple[tuple[float, float, float, float], float]:
    """The union of the images' footprints in ``crs`` and the finest of their pixel sizes there, metres."""
    import rasterio
    from rasterio.warp import transform_bounds

    boxes, finest = [], math.inf
    for path in images:
        with rasterio.open(path) as ds:
            box = transform_bounds(ds.crs, crs, *ds.bounds, densify_pts=21)
            finest = min(finest, (box[2] - box[0]) / ds.width, (box[3] - box[1]) / ds.height)
        boxes.append(box)
    b = np.array(boxes)
    return (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())), finest


#: GDAL's block cache while a quicklook reads an image, MB: a strip's blocks (a strip of
#: 512 rows of a 20,000-pixel-wide RGB image is 31 MB).
QUICKLOOK_CACHE_MB = 96
#: Rows of the image (rounded up to whole rows of its blocks) read at a time: bounds the
#: full-resolution window GDAL holds while it averages it down.
QUICKLOOK_STRIP_SOURCE_ROWS = 512


def _canvas(images: Sequence[str], crs: str, bounds, res: float, shape) -> np.ndarray:
    """The images as one RGB array (uint8) on the picture's grid; black where none is."""
    from rasterio.transform import from_origin

    out = np.zeros((*shape, 3), np.uint8)
    transform = from_origin(bounds[0], bounds[3], res, res)
    for path in images:
        _paint(out, path, crs, transform, res)
    return out


def _paint(out: np.ndarray, path: str, crs: str, transform, res: float) -> None:
    """Paint one image's valid pixels into ``out`` (the picture's grid ``transform``).

    The image is first averaged down in its own grid, by whole pixels, to about
    twice the picture's resolution, a strip of whole rows of its blocks at a
    time (each block decoded once, a strip's worth held); only that small array
    is reprojected. Warping or resampling the full image in GDAL in one step
    held or decoded far more (1.3 GB and 40 s for a 419 Mpx JPEG GeoTIFF,
    against 0.4 GB and 12 s).
    """
    import rasterio
    from rasterio.enums import MaskFlags, Resampling
    from rasterio.warp import reproject
    from rasterio.windows import Window

    with rasterio.Env(GDAL_CACHEMAX=QUICKLOOK_CACHE_MB), rasterio.open(path) as ds:
        native = max(abs(ds.res[0]), abs(ds.res[1]))
        k = max(1, int(res / native / 2)) if ds.crs.is_projected else 1
        h, w = max(1, ds.height // k), max(1, ds.width // k)
        every_valid = all(MaskFlags.all_valid in flags for flags in ds.mask_flag_enums)
        small = np.zeros((3, h, w), ds.dtypes[0])
        mask = np.full((h, w), 255, np.uint8)
        strip = math.lcm(ds.block_shapes[0][0], k)
        strip *= max(1, QUICKLOOK_STRIP_SOURCE_ROWS // strip)
        for r0 in range(0, h * k, strip):
            r1 = min(h * k, r0 + strip)
            win = Window(0, r0, w * k, r1 - r0)
            a = ds.read(indexes=[1, 2, 3], window=win)
            small[:, r0 // k:r1 // k] = a.reshape(3, (r1 - r0) // k, k, w, k).mean(axis=(2, 4))
            if not every_valid:
                m = ds.dataset_mask(window=win).reshape((r1 - r0) // k, k, w, k).mean(axis=(1, 3))
                mask[r0 // k:r1 // k] = np.where(m >= 128, 255, 0)
        src_transform = ds.transform * ds.transform.scale(k, k)
        src_crs = ds.crs
    if small.dtype != np.uint8:  # 16-bit imagery: stretch its 2-98 % range
        v = small[:, mask > 0].astype(float)
        lo, hi = (np.percentile(v, (2, 98)) if v.size else (0.0, 1.0))
        small = np.clip((small - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    rows, cols = out.shape[:2]
    rgb = np.zeros((3, rows, cols), np.uint8)
    valid = np.zeros((rows, cols), np.uint8)
    reproject(small, rgb, src_transform=src_transform, src_crs=src_crs, dst_transform=transform, dst_crs=crs,
              resampling=Resampling.average)
    reproject(mask, valid, src_transform=src_transform, src_crs=src_crs, dst_transform=transform, dst_crs=crs,
              resampling=Resampling.nearest)
    keep = valid > 0
    out[keep] = rgb.transpose(1, 2, 0)[keep]


def map_quicklook(store, map_id: str, images: Sequence[str], out: Path | str, *, max_px: int = 3000,
                  title: str = "") -> Quicklook:  # fmt: skip
    """:func:`render_quicklook` of the markings of a map (a :class:`~mapbuilder.store.Store`'s) that
    the localizer uses (unreviewed and accepted) over ``images``, in the map's CRS.

    What ``lanemap build --quicklook`` and a build job's ``quicklook.png`` draw; the images'
    headers are read once, for the markings' box and for the picture.
    """
    crs = store.get_map(map_id).crs
    footprints = _footprints(images, crs)
    shown = store.query_bbox(map_id, *footprints[0], statuses=("unreviewed", "accepted"))
    return render_quicklook(images, shown, crs, out, max_px=max_px, title=title, footprints=footprints)


def render_quicklook(
    images: Sequence[str], markings: Sequence[Marking], crs: str, out: Path | str, *,
    max_px: int = 3000, title: str = "", footprints: tuple | None = None,
) -> Quicklook:  # fmt: skip
    """Draw ``markings`` (in ``crs``) over ``images`` and save the picture as a PNG.

    Parameters
    ----------
    images : sequence of str
        GeoTIFFs, in any CRS (reprojected to ``crs``).
    markings : sequence of Marking
        Drawn as their axis (end points, else length and bearing), coloured by score.
    crs : str
        The map's CRS, metric.
    max_px : int
        Longest side of the picture, pixels (not finer than the imagery needs to be).
    footprints : optional
        The images' union footprint and finest pixel size in ``crs`` when the caller has
        read them already (:func:`map_quicklook`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    bounds, finest = footprints or _footprints(images, crs)
    width, height = bounds[2] - bounds[0], bounds[3] - bounds[1]
    res = max(max(width, height) / max(int(max_px), 64), finest)
    shape = (max(1, math.ceil(height / res - 1e-6)), max(1, math.ceil(width / res - 1e-6)))
    bounds = (bounds[0], bounds[3] - shape[0] * res, bounds[0] + shape[1] * res, bounds[3])
    canvas = _canvas(images, crs, bounds, res, shape)

    # The markings are drawn on a transparent figure and laid over the imagery here: drawn
    # with imshow, a 3000-pixel picture took matplotlib 0.8 GB of float copies.
    dpi = 100
    fig = plt.figure(figsize=(shape[1] / dpi, shape[0] / dpi), dpi=dpi)
    fig.patch.set_alpha(0.0)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    ax.set_xlim(bounds[0], bounds[2])
    ax.set_ylim(bounds[1], bounds[3])
    if markings:
        seg = np.empty((len(markings), 2, 2))
        score = np.full(len(markings), np.nan)
        for i, m in enumerate(markings):
            if None not in (m.x0, m.y0, m.x1, m.y1):
                seg[i] = ((m.x0, m.y0), (m.x1, m.y1))
            else:
                b = math.radians(m.bearing_deg)
                dx, dy = 0.5 * m.length_m * math.sin(b), 0.5 * m.length_m * math.cos(b)
                seg[i] = ((m.x - dx, m.y - dy), (m.x + dx, m.y + dy))
            if m.score is not None:
                score[i] = m.score
        # A marking shorter than a pixel still shows: at least two pixels long.
        lw = max(1.0, min(3.0, 0.3 / res * 72 / dpi))
        known = np.isfinite(score)
        if known.any():
            lines = LineCollection(seg[known], array=score[known], cmap="plasma", norm=plt.Normalize(0, 1),
                                   linewidths=lw)  # fmt: skip
            ax.add_collection(lines)
            cax = fig.add_axes((0.78, 0.03, 0.18, 0.015))
            bar = fig.colorbar(lines, cax=cax, orientation="horizontal")
            bar.set_label("score", color="white", fontsize=8)
            bar.ax.tick_params(colors="white", labelsize=7)
        if (~known).any():
            ax.add_collection(LineCollection(seg[~known], colors="cyan", linewidths=lw))
    label = f"{title}  " if title else ""
    ax.text(0.01, 0.99, f"{label}{len(markings):,} markings, {res:.2f} m per pixel", transform=ax.transAxes,
            va="top", ha="left", fontsize=9, color="white", bbox={"facecolor": "black", "alpha": 0.6, "pad": 3})
    fig.canvas.draw()
    over = np.asarray(fig.canvas.buffer_rgba())[: shape[0], : shape[1]]
    plt.close(fig)
    picture = canvas[: over.shape[0], : over.shape[1]]
    alpha = over[..., 3:4].astype(np.uint16)
    picture = ((picture * (255 - alpha) + over[..., :3] * alpha + 127) // 255).astype(np.uint8)
    out = Path(out)
    plt.imsave(out, picture, format="png")
    return Quicklook(out, bounds, res, picture.shape[:2], len(markings))
