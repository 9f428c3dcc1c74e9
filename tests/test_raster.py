"""Reading imagery: masks, reprojection through WarpedVRT, and rejection of unusable files."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning
from rasterio.transform import from_origin
from rasterio.warp import Resampling, calculate_default_transform, reproject
from rasterio.windows import Window

from tests._build_helpers import USGS_ALPHA, USGS_BASE, USGS_NODATA
from mapbuilder.raster import (
    ImageryError,
    default_storage_crs,
    imaged_ground,
    inspect_imagery,
    open_grid,
)


def _read_all(path, storage_crs=None):
    info = inspect_imagery(path, storage_crs)
    with open_grid(path, info.grid) as reader:
        rgb, valid = reader.read(Window(0, 0, info.grid.width, info.grid.height))
    return info, rgb, valid


def _write(path, data, **profile):
    base = dict(driver="GTiff", dtype="uint8", count=data.shape[0], height=data.shape[1],
                width=data.shape[2])
    base.update(profile)
    with rasterio.open(path, "w", **base) as dst:
        dst.write(data)


def test_plain_rgb_is_read_on_its_own_grid():
    info, rgb, valid = _read_all(USGS_BASE)
    assert info.grid.crs == "EPSG:26913"
    assert not info.grid.warped
    assert info.mask == "none"
    assert rgb.shape == (232, 383, 3) and rgb.dtype == np.uint8
    assert valid.all()
    assert info.grid.resolution_m == pytest.approx(0.15, abs=1e-3)
    with rasterio.open(USGS_BASE) as src:
        np.testing.assert_array_equal(rgb, src.read().transpose(1, 2, 0))
    # band-sequential, as GDAL read it: no interleaved copy of the window
    assert all(rgb[..., c].flags.c_contiguous for c in range(3))


@pytest.mark.parametrize(
    "path, kind", [(USGS_ALPHA, "alpha"), (USGS_NODATA, "nodata")]
)
def test_masked_variants_give_the_files_own_mask(path, kind):
    info, rgb, valid = _read_all(path)
    assert info.mask == kind
    with rasterio.open(path) as src:
        expected = src.dataset_mask() > 0
    np.testing.assert_array_equal(valid, expected)
    assert (~valid).sum() > 1000
    # Same pixels as the unmasked original where valid.
    _, base_rgb, _ = _read_all(USGS_BASE)
    np.testing.assert_array_equal(rgb[valid], base_rgb[valid])


def test_window_reads_are_clipped_and_match_full_reads():
    info = inspect_imagery(USGS_ALPHA)
    with open_grid(USGS_ALPHA, info.grid) as reader:
        full_rgb, full_valid = reader.read(Window(0, 0, info.grid.width, info.grid.height))
        rgb, valid = reader.read(Window(300, 200, 200, 200))
    assert rgb.shape == (32, 83, 3)
    np.testing.assert_array_equal(rgb, full_rgb[200:, 300:])
    np.testing.assert_array_equal(valid, full_valid[200:, 300:])


def test_internal_mask_band(tmp_path):
    with rasterio.open(USGS_BASE) as src:
        data, profile = src.read(), src.profile
    path = tmp_path / "masked.tif"
    mask = np.full(data.shape[1:], 255, np.uint8)
    mask[:50, :80] = 0
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(data)
            dst.write_mask(mask)
    info, rgb, valid = _read_all(path)
    assert info.mask == "mask"
    np.testing.assert_array_equal(valid, mask > 0)


def test_geographic_image_is_read_through_a_warped_vrt(tmp_path):
    geo = tmp_path / "geo.tif"
    with rasterio.open(USGS_ALPHA) as src:
        t, w, h = calculate_default_transform(src.crs, "EPSG:4326", src.width, src.height,
                                              *src.bounds)
        profile = src.profile
        profile.update(crs="EPSG:4326", transform=t, width=w, height=h)
        with rasterio.open(geo, "w", **profile) as dst:
            for b in range(1, src.count + 1):
                reproject(rasterio.band(src, b), rasterio.band(dst, b),
                          resampling=Resampling.nearest)
        src_bounds = src.bounds
    # A new map from a geographic image is stored in its UTM zone.
    assert default_storage_crs(geo) == "EPSG:32613"
    info, rgb, valid = _read_all(geo)
    assert info.grid.warped and info.grid.crs == "EPSG:32613"
    assert info.src_crs == "EPSG:4326"
    # The ground size of the geographic file's pixels (its reprojection coarsened them a little).
    assert info.grid.resolution_m == pytest.approx(0.155, abs=0.01)
    # The warped grid lands where the original UTM image is (NAD83 ≈ WGS84 here).
    minx, miny, maxx, maxy = info.grid.bounds
    assert minx == pytest.approx(src_bounds.left, abs=1.0)
    assert maxy == pytest.approx(src_bounds.top, abs=1.0)
    # The alpha-masked corner stays invalid; the image body is valid and not black.
    assert valid.mean() > 0.8 and (~valid).sum() > 5000
    assert rgb[valid].mean() > 40


def test_other_metric_crs_is_warped_into_the_storage_crs():
    info, rgb, valid = _read_all(USGS_BASE, "EPSG:32613")
    assert info.grid.warped
    assert info.grid.crs == "EPSG:32613"
    # Pixels outside the image footprint read as invalid, not as black road.
    assert valid.mean() > 0.95
    assert rgb[valid].mean() > 40


def test_no_georeferencing_is_rejected(tmp_path):
    path = tmp_path / "plain.tif"
    with pytest.warns(NotGeoreferencedWarning):
        _write(path, np.zeros((3, 64, 64), np.uint8))
    with pytest.raises(ImageryError, match="georeferenced"):
        inspect_imagery(path)


def test_coarse_resolution_is_rejected(tmp_path):
    path = tmp_path / "coarse.tif"
    _write(path, np.zeros((3, 64, 64), np.uint8), crs="EPSG:25832",
           transform=from_origin(456000, 5430000, 0.5, 0.5))
    with pytest.raises(ImageryError, match="coarser than 0.3"):
        inspect_imagery(path)


def test_single_band_is_rejected(tmp_path):
    path = tmp_path / "grey.tif"
    _write(path, np.zeros((1, 64, 64), np.uint8), crs="EPSG:25832",
           transform=from_origin(456000, 5430000, 0.1, 0.1))
    with pytest.raises(ImageryError, match="single band"):
        inspect_imagery(path)


def test_unreadable_file_is_rejected(tmp_path):
    path = tmp_path / "junk.tif"
    path.write_bytes(b"not a tiff")
    with pytest.raises(ImageryError, match="cannot open"):
        inspect_imagery(path)


def test_geographic_storage_crs_is_rejected():
    with pytest.raises(ImageryError, match="not projected"):
        inspect_imagery(USGS_BASE, "EPSG:4326")


def test_rotated_geotransform_is_warped_north_up(tmp_path):
    from affine import Affine

    with rasterio.open(USGS_BASE) as src:
        data, profile = src.read(), src.profile
    t = Affine.translation(519467.5, 4311669.8) @ Affine.rotation(10.0) @ Affine.scale(0.15, -0.15)
    path = tmp_path / "rotated.tif"
    profile.update(transform=t)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    info, rgb, valid = _read_all(path)
    assert info.grid.warped and info.grid.crs == "EPSG:26913"
    a, b, _, d, e, _ = info.grid.transform
    assert b == 0 and d == 0 and a > 0 and e < 0
    assert info.grid.resolution_m == pytest.approx(0.15, rel=0.05)
    # The rotated footprint covers part of the north-up grid; the corners are invalid.
    assert 0.6 < valid.mean() < 0.95
    assert not valid[0, 0] and not valid[-1, -1]
    assert rgb[valid].mean() > 40


def test_the_ground_a_window_images_is_its_wholly_valid_cells():
    """A window with a nodata corner and a hole: the footprint is drawn in 2 m cells that are
    valid throughout, so no masked pixel lies in it, and it never reaches past the window."""
    import shapely
    from affine import Affine

    t = Affine(0.1, 0, 500000.0, 0, -0.1, 5400000.0)  # 10 cm pixels, north up
    valid = np.ones((300, 500), bool)
    full = shapely.from_wkb(imaged_ground(valid, t))
    assert full.equals(shapely.box(500000.0, 5399970.0, 500050.0, 5400000.0))
    rows, cols = np.mgrid[:300, :500]
    valid[rows + cols < 150] = False  # a triangle of nodata in the north-west corner
    valid[100:130, 200:260] = False  # a hole, 3 m x 6 m
    ground = shapely.from_wkb(imaged_ground(valid, t))
    assert ground.is_valid and not ground.is_empty
    r, c = np.nonzero(~valid)
    x, y = t * (c + 0.5, r + 0.5)
    assert not shapely.contains_xy(ground, x, y).any()
    assert shapely.box(500000.0, 5399970.0, 500050.0, 5400000.0).contains(ground)
    # what it leaves out is the masked ground and at most a cell along its borders
    masked_m2 = (~valid).sum() * 0.01
    assert masked_m2 < 1500.0 - ground.area < masked_m2 + 2.0 * (2 * 15 * 1.42 + 2 * (3 + 6) + 4 * 2)
    r, c = 150, 400  # deep inside the valid ground
    assert ground.contains(shapely.Point(*(t * (c, r))))
    assert shapely.from_wkb(imaged_ground(np.zeros((40, 40), bool), t)).is_empty
