"""Open and validate aerial imagery, and read it window by window in the map's CRS.

Any GeoTIFF or COG that rasterio opens is accepted when it has at least three
8-bit bands (RGB, optionally an alpha band), georeferencing, and a ground
resolution of 0.3 m or finer. Validity comes from whichever the file carries:
an alpha band, a nodata value, or an internal/external mask band.

The pipeline reads pixels on a :class:`PixelGrid` in the map's metric storage
CRS. When the file is already in that CRS with a north-up geotransform, the
grid is the file's own and windows are read directly; otherwise (a geographic
CRS, another projection, a rotated geotransform) the file is read through a
:class:`rasterio.vrt.WarpedVRT` onto a square-pixel grid in the storage CRS.
A :class:`PixelGrid` is plain data, so a worker process can rebuild exactly
the same reader from the file path and the grid.
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS as ProjCRS
from rasterio.enums import ColorInterp, MaskFlags, Resampling
from rasterio.errors import NotGeoreferencedWarning, RasterioIOError
from rasterio.vrt import WarpedVRT
from rasterio.warp import calculate_default_transform
from rasterio.windows import Window

from .crs import CRSError, metric_crs, utm_crs_for, to_wgs84

log = logging.getLogger(__name__)

#: Coarsest ground resolution the classifier is meant for, metres per pixel.
MAX_RESOLUTION_M = 0.3


class ImageryError(ValueError):
    """The imagery cannot be used: unreadable, not georeferenced, too coarse, too few bands."""


@dataclass(frozen=True)
class PixelGrid:
    """The north-up pixel grid the pipeline reads, in the storage CRS.

    Attributes
    ----------
    crs : str
        Metric storage CRS (anything pyproj parses, e.g. ``"EPSG:25832"``).
    transform : tuple of 6 float
        Affine ``(a, b, c, d, e, f)`` from pixel (col, row) to CRS metres.
    width, height : int
        Grid size, pixels.
    warped : bool
        True when the file is read through a WarpedVRT.
    """

    crs: str
    transform: tuple[float, float, float, float, float, float]
    width: int
    height: int
    warped: bool = False

    @property
    def affine(self) -> Affine:
        return Affine(*self.transform)

    @property
    def resolution_m(self) -> float:
        """Ground sampling distance, metres per pixel (the coarser axis)."""
        a, b, _, d, e, _ = self.transform
        return float(max(math.hypot(a, d), math.hypot(b, e)))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(minx, miny, maxx, maxy)`` of the grid in the storage CRS, metres."""
        a, b, c0, d, e, f0 = self.transform
        corners = [(c, r) for c in (0, self.width) for r in (0, self.height)]
        xs = [a * c + b * r + c0 for c, r in corners]
        ys = [d * c + e * r + f0 for c, r in corners]
        return (min(xs), min(ys), max(xs), max(ys))

    @property
    def megapixels(self) -> float:
        return self.width * self.height / 1e6


@dataclass(frozen=True)
class RasterInfo:
    """What :func:`inspect_imagery` found out about a file.

    Attributes
    ----------
    path : str
        Absolute path of the file.
    src_crs : str
        The file's own CRS (EPSG code where it has one, WKT otherwise).
    src_resolution_m : float
        The file's ground resolution, metres per pixel (after reprojection to
        the storage CRS for a geographic file).
    count : int
        Number of bands.
    mask : str
        Where validity comes from: ``"alpha"``, ``"nodata"``, ``"mask"`` or ``"none"``.
    grid : PixelGrid
        The grid the pipeline reads.
    """

    path: str
    src_crs: str
    src_resolution_m: float
    count: int
    mask: str
    grid: PixelGrid


def _crs_string(crs) -> str:
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_wkt()


def _same_crs(a: str, b) -> bool:
    try:
        return ProjCRS.from_user_input(a).equals(ProjCRS.from_user_input(b.to_wkt()),
                                                 ignore_axis_order=True)
    except Exception:  # an exotic WKT pyproj cannot parse: treat as different and warp
        return False


def _mask_kind(src) -> str:
    flags = src.mask_flag_enums[0] if src.count else ()
    if MaskFlags.alpha in flags or (src.count >= 4 and src.colorinterp[3] == ColorInterp.alpha):
        return "alpha"
    if MaskFlags.nodata in flags or src.nodata is not None:
        return "nodata"
    if MaskFlags.per_dataset in flags:
        return "mask"
    return "none"


def _check_source(src, path: str) -> None:
    if src.count < 3:
        kind = "a single band" if src.count == 1 else f"{src.count} bands"
        raise ImageryError(
            f"{path}: image has {kind}; an RGB image (3 bands, optionally alpha) is required"
        )
    if src.dtypes[0] != "uint8":
        raise ImageryError(f"{path}: bands are {src.dtypes[0]}; 8-bit (uint8) RGB is required")
    if src.crs is None:
        raise ImageryError(f"{path}: image has no CRS (not georeferenced)")
    if src.transform.is_identity or src.transform == Affine.identity():
        raise ImageryError(f"{path}: image has no geotransform (not georeferenced)")


def _native_resolution(src, dst_crs: str) -> float:
    """Side of a square pixel of the same ground area as the file's pixels, in ``dst_crs``.

    Measured on the pixel at the image centre, so that a rotated or sheared
    geotransform keeps its resolution (GDAL's default warp size would coarsen it).
    """
    from rasterio.warp import transform as warp_transform

    c, r = src.width / 2.0, src.height / 2.0
    t = src.transform
    pts = [t * (c, r), t * (c + 1, r), t * (c, r + 1)]
    xs, ys = warp_transform(src.crs, dst_crs, [p[0] for p in pts], [p[1] for p in pts])
    ax, ay = xs[1] - xs[0], ys[1] - ys[0]
    bx, by = xs[2] - xs[0], ys[2] - ys[0]
    return math.sqrt(abs(ax * by - ay * bx))


def default_storage_crs(path: str | os.PathLike) -> str:
    """The metric CRS a new map built from this image is stored in.

    The file's own CRS when it is projected in metres, else the UTM zone of its
    centre.
    """
    path = str(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            src = rasterio.open(path)
        with src:
            _check_source(src, path)
            own = _crs_string(src.crs)
            try:
                metric_crs(own)
                return own
            except CRSError:
                pass
            left, bottom, right, top = src.bounds
            lon, lat = to_wgs84(own).transform((left + right) / 2, (bottom + top) / 2)
    except RasterioIOError as exc:
        raise ImageryError(f"cannot open image {path}: {exc}") from exc
    return utm_crs_for(float(lon), float(lat))


def inspect_imagery(path: str | os.PathLike, storage_crs: str | None = None) -> RasterInfo:
    """Validate an image and choose the pixel grid the pipeline reads.

    Parameters
    ----------
    path : path
        A GeoTIFF/COG (or any raster rasterio opens).
    storage_crs : str, optional
        The map's metric CRS; None chooses :func:`default_storage_crs`.

    Raises
    ------
    ImageryError
        Unreadable file, no georeferencing, fewer than three bands, not 8-bit,
        or ground resolution coarser than :data:`MAX_RESOLUTION_M`.
    """
    path = str(Path(path).resolve())
    if storage_crs is None:
        storage_crs = default_storage_crs(path)
    try:
        metric_crs(storage_crs)
    except CRSError as exc:
        raise ImageryError(str(exc)) from exc
    try:
        with warnings.catch_warnings():
            # A file without georeferencing is reported below as an ImageryError.
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            src = rasterio.open(path)
    except RasterioIOError as exc:
        raise ImageryError(f"cannot open image {path}: {exc}") from exc
    with src:
        _check_source(src, path)
        t = src.transform
        north_up = t.b == 0 and t.d == 0 and t.a > 0 and t.e < 0
        if north_up and _same_crs(storage_crs, src.crs):
            grid = PixelGrid(storage_crs, tuple(t)[:6], src.width, src.height, warped=False)
        else:
            res = _native_resolution(src, storage_crs)
            dst, w, h = calculate_default_transform(
                src.crs, storage_crs, src.width, src.height, *src.bounds, resolution=res
            )
            grid = PixelGrid(storage_crs, tuple(dst)[:6], int(w), int(h), warped=True)
        info = RasterInfo(
            path=path,
            src_crs=_crs_string(src.crs),
            src_resolution_m=grid.resolution_m,
            count=src.count,
            mask=_mask_kind(src),
            grid=grid,
        )
    if info.src_resolution_m > MAX_RESOLUTION_M:
        raise ImageryError(
            f"{path}: ground resolution {info.src_resolution_m:.3f} m/pixel is coarser than "
            f"{MAX_RESOLUTION_M} m/pixel; lane markings cannot be measured"
        )
    log.debug("imagery %s: %s", path, info)
    return info


class GridReader:
    """Reads windows of RGB and validity from one file on a :class:`PixelGrid`.

    Use :func:`open_grid` to make one. Windows are clipped to the grid.
    """

    def __init__(self, src, vrt, info_mask: str, grid: PixelGrid):
        self._src = src
        self._vrt = vrt
        self._mask = info_mask
        self.grid = grid

    @property
    def dataset(self):
        return self._vrt if self._vrt is not None else self._src

    def read(self, window: Window) -> tuple[np.ndarray, np.ndarray]:
        """Read a window.

        Returns
        -------
        rgb : (H, W, 3) uint8
            A channel-last view of the band-sequential data GDAL returns: each
            channel ``rgb[..., c]`` is contiguous, and interleaving the
            channels (a copy) would cost more than a tenth of a tile's time.
        valid : (H, W) bool
            False where the file says nodata (alpha 0, nodata value in every
            band, mask 0) or outside the image footprint.
        """
        ds = self.dataset
        window = window.intersection(Window(0, 0, self.grid.width, self.grid.height))
        if self._vrt is None and self._mask == "alpha":
            data = ds.read((1, 2, 3, 4), window=window)
            rgb, valid = data[:3], data[3] > 0
        else:
            rgb = ds.read((1, 2, 3), window=window)
            if self._vrt is None and self._mask == "none":
                valid = np.ones(rgb.shape[1:], bool)
            elif self._vrt is None and self._mask == "nodata":
                valid = np.any(rgb != np.uint8(self._src.nodata), axis=0)
            else:
                valid = ds.dataset_mask(window=window) > 0
        return rgb.transpose(1, 2, 0), valid

    def close(self) -> None:
        if self._vrt is not None:
            self._vrt.close()
        self._src.close()


@contextmanager
def open_grid(path: str | os.PathLike, grid: PixelGrid) -> Iterator[GridReader]:
    """Open ``path`` for reading on ``grid`` (through a WarpedVRT if ``grid.warped``)."""
    reader = make_reader(path, grid)
    try:
        yield reader
    finally:
        reader.close()


def make_reader(path: str | os.PathLike, grid: PixelGrid) -> GridReader:
    """Like :func:`open_grid`, for callers that keep the reader open (caller closes)."""
    try:
        src = rasterio.open(str(path))
    except RasterioIOError as exc:
        raise ImageryError(f"cannot open image {path}: {exc}") from exc
    mask = _mask_kind(src)
    vrt = None
    if grid.warped:
        vrt = WarpedVRT(
            src,
            crs=grid.crs,
            transform=grid.affine,
            width=grid.width,
            height=grid.height,
            resampling=Resampling.bilinear,
            # Without alpha or nodata the area outside the footprint would read as black.
            add_alpha=mask in ("none", "mask"),
        )
    return GridReader(src, vrt, mask, grid)


#: Side of the cells the ground a window images is drawn in, metres
#: (:func:`imaged_ground`).
GROUND_CELL_M = 2.0


def imaged_ground(valid: np.ndarray, transform: Affine, cell_m: float = GROUND_CELL_M) -> bytes:
    """The ground a window's imagery shows, as WKB of a polygon in the grid's CRS.

    Parameters
    ----------
    valid : (H, W) ndarray of bool
        The window's valid pixels (:meth:`GridReader.read`).
    transform : Affine
        From the window's pixel (col, row) to the CRS, metres.
    cell_m : float
        The footprint is drawn in square cells of about this side, metres;
        a cell counts only when every pixel in it is valid, so the footprint
        never claims ground the imagery leaves out (it may leave out up to a
        cell along a nodata border).

    Returns
    -------
    bytes
        WKB of a Polygon or MultiPolygon (empty when no cell is wholly valid).
    """
    import shapely
    from rasterio.features import shapes
    from shapely.geometry import shape

    h, w = valid.shape
    x0, y0 = transform * (0, 0)
    x1, y1 = transform * (w, h)
    window = shapely.box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
    if valid.all():
        return shapely.to_wkb(window)
    res = math.hypot(transform.a, transform.d)
    c = max(1, int(round(cell_m / res)))
    rows, cols = -(-h // c), -(-w // c)
    # Cells cut by the window's own border count by the pixels inside it.
    padded = np.ones((rows * c, cols * c), bool)
    padded[:h, :w] = valid
    cells = padded.reshape(rows, c, cols, c).all(axis=(1, 3))
    polys = [shape(g) for g, _ in
             shapes(cells.view(np.uint8), mask=cells, connectivity=4, transform=transform * Affine.scale(c))]
    ground = shapely.intersection(shapely.union_all(polys), window) if polys else shapely.Polygon()
    return shapely.to_wkb(ground)
