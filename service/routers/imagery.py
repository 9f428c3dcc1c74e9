"""Imagery: streamed GeoTIFF upload (stored as a COG), listing, and WebMercatorQuad PNG tiles."""

from __future__ import annotations

import errno
import functools
import logging
import os
import re
import threading
import uuid
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Depends, Request, Response
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from mapbuilder.store import ImageryInfo

from ..deps import Context, get_ctx, require_read, require_write
from ..problems import Problem
from ._common import JSON, base_url, declared_length, link, parse_id, receive_to_file, storage_failures

log = logging.getLogger(__name__)

router = APIRouter(tags=["Imagery"], dependencies=[Depends(require_read)])

UPLOAD_TYPES = ("image/tiff", "image/geotiff", "image/tiff; application=geotiff", "application/octet-stream")
MapId = PathParam(..., max_length=64)


def imagery_json(i: ImageryInfo, request: Request) -> dict[str, Any]:
    url = f"{base_url(request)}/collections/{i.map_id}/imagery/{i.id}"
    return {
        "id": str(i.id),
        "mapId": i.map_id,
        "crs": i.crs,
        "bounds": list(i.bounds),
        "resolution_m": i.resolution_m,
        "created": i.created_at.isoformat() if i.created_at else None,
        "links": [link(url, "self", JSON)],
    }


#: GDAL's messages when writing (not reading) a file fails ("Write error at scanline",
#: "IO error writing tag data", "Seek error"...): its exception carries no errno, and
#: with the folder in place the only cause left is the storage.
_WRITE_FAILED = re.compile(r"writ|seek error|no space left|file too large|disk quota|free disk space", re.I)


def _storage_short(folder: Path, need: int) -> bool:
    """Whether ``folder``'s file system has less than ``need`` bytes free."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < need


class StorageFullError(OSError):
    """The converted image could not be written: the disk or a size limit is full."""


def convert_to_cog(src: Path, dst: Path, map_crs: str | None) -> Any:
    """Check a GeoTIFF's georeferencing and write it as a Cloud Optimized GeoTIFF with overviews.

    Raises
    ------
    ImageryError
        The upload is no usable GeoTIFF (nothing is written).
    StorageFullError
        Writing the COG failed for lack of space (the partial file is removed).
    """
    import rasterio
    from rasterio.shutil import copy as rio_copy

    from mapbuilder.raster import ImageryError, inspect_imagery

    try:
        info = inspect_imagery(src, map_crs)
    except ImageryError as exc:
        # Server paths are no business of the client.
        msg = str(exc).replace(str(src.resolve()), "upload").replace(str(src), "upload").replace(src.name, "file")
        raise ImageryError(msg) from None
    try:
        rio_copy(str(src), str(dst), driver="COG", COMPRESS="DEFLATE", PREDICTOR="2", BLOCKSIZE="512",
                 OVERVIEWS="AUTO", BIGTIFF="IF_SAFER")  # fmt: skip
        with rasterio.open(dst) as ds:
            ds.read(1, window=((0, min(16, ds.height)), (0, min(16, ds.width))))
    except OSError:
        dst.unlink(missing_ok=True)
        raise
    except Exception as exc:  # GDAL cannot read all of it (truncated, damaged), or cannot write
        dst.unlink(missing_ok=True)
        if _WRITE_FAILED.search(str(exc)) or _storage_short(dst.parent, 2 * src.stat().st_size):
            log.error("writing %s failed: %s", dst, exc)
            raise StorageFullError(errno.ENOSPC, "No space left on device or file size limit reached") from None
        raise ImageryError(f"upload: the GeoTIFF cannot be read in full ({exc})") from None
    return info


@router.post(
    "/collections/{mapId}/imagery", summary="Upload a GeoTIFF (raw request body)", status_code=201,
    openapi_extra={"requestBody": {"required": True, "content": {
        "image/tiff": {"schema": {"type": "string", "format": "binary"}},
        "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
    }}},
)  # fmt: skip
async def upload_imagery(
    request: Request,
    mapId: str = MapId,
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    limit = ctx.settings.max_upload_bytes
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in {t.split(";")[0] for t in UPLOAD_TYPES}:
        raise Problem(415, f"Content-Type {ctype or '(none)'} is not accepted: send the GeoTIFF as image/tiff",
                      "unsupported-media-type")  # fmt: skip
    declared = declared_length(request, limit, "upload")
    info = await run_in_threadpool(ctx.store.get_map, mapId)
    folder = ctx.data_dir / "imagery" / mapId
    tmp_dir = ctx.data_dir / "imagery" / ".incoming"
    token = uuid.uuid4().hex
    tmp = tmp_dir / f"{token}.tif"
    dst = folder / f"{token}.cog.tif"
    with storage_failures("upload", tmp, also=(dst,)):
        await run_in_threadpool(tmp_dir.mkdir, parents=True, exist_ok=True)
        size = await receive_to_file(request, tmp, limit, "upload")
        if declared is not None and size != declared:
            raise Problem(400, f"upload is truncated: {size} of {declared} bytes arrived", "truncated-upload")
        if size == 0:
            raise Problem(422, "body: the upload is empty; send a GeoTIFF", "invalid-imagery")
        await run_in_threadpool(folder.mkdir, parents=True, exist_ok=True)
        raster = await run_in_threadpool(convert_to_cog, tmp, dst, info.crs)
    grid = raster.grid
    try:
        imagery_id = await run_in_threadpool(
            ctx.store.add_imagery, mapId, str(dst.resolve()), grid.crs, grid.bounds, grid.resolution_m
        )
    except Exception:
        dst.unlink(missing_ok=True)
        raise
    img = await run_in_threadpool(ctx.store.get_imagery, imagery_id)
    body = imagery_json(img, request)
    return JSONResponse(body, status_code=201, headers={"Location": body["links"][0]["href"]})


@router.get("/collections/{mapId}/imagery", summary="The map's imagery")
def list_imagery(request: Request, mapId: str = MapId, ctx: Context = Depends(get_ctx)) -> dict:
    return {"imagery": [imagery_json(i, request) for i in ctx.store.list_imagery(mapId)],
            "links": [link(f"{base_url(request)}/collections/{mapId}/imagery", "self", JSON)]}  # fmt: skip


@router.get("/collections/{mapId}/imagery/{imageryId}", summary="One image")
def get_imagery(request: Request, mapId: str = MapId, imageryId: str = PathParam(..., max_length=40),
                ctx: Context = Depends(get_ctx)) -> dict:  # fmt: skip
    img = ctx.store.get_imagery(parse_id(imageryId, "imageryId"))
    if img.map_id != mapId:
        raise Problem(404, f"map {mapId!r} has no imagery {imageryId}", "unknown-imagery")
    return imagery_json(img, request)


# ---------------------------------------------------------------------------- tiles
def render_tile(paths: list[str], z: int, x: int, y: int) -> bytes | None:
    """A 256 px WebMercatorQuad PNG of the first image covering the tile; None if none does."""
    stamps = []
    for path in paths:
        try:
            stamps.append((path, os.stat(path).st_mtime_ns))
        except OSError:
            continue
    return _render_tile(tuple(stamps), z, x, y)


#: rio-tiler's package imports are circular: a browser's first burst of tile requests
#: importing it from several threads at once fails with "partially initialized module".
_TILER_IMPORT = threading.Lock()


@functools.lru_cache(maxsize=512)
def _render_tile(stamps: tuple[tuple[str, int], ...], z: int, x: int, y: int) -> bytes | None:
    # Keyed by file and modification time: panning back to a tile costs nothing.
    with _TILER_IMPORT:
        from rio_tiler.errors import TileOutsideBounds
        from rio_tiler.io import Reader

    for path, _mtime in stamps:
        try:
            with Reader(path) as src:
                if not src.tile_exists(x, y, z):
                    continue
                img = src.tile(x, y, z, tilesize=256)
        except TileOutsideBounds:
            continue
        return img.render(img_format="PNG", add_mask=True)
    return None


@router.get(
    "/collections/{mapId}/imagery/tiles/WebMercatorQuad/{z}/{x}/{y}.png",
    summary="A basemap tile of the map's imagery",
    responses={200: {"content": {"image/png": {}}}, 404: {"description": "No imagery there"}},
)  # fmt: skip
def tile(
    mapId: str = MapId,
    z: int = PathParam(..., ge=0, le=24),
    x: int = PathParam(..., ge=0),
    y: int = PathParam(..., ge=0),
    ctx: Context = Depends(get_ctx),
):
    n = 1 << z
    if x >= n or y >= n:
        raise Problem(400, f"tile {z}/{x}/{y}: x and y must be below {n} at zoom {z}", "invalid-tile")
    images = [i for i in ctx.store.list_imagery(mapId) if os.path.isfile(i.path)]
    data = render_tile([i.path for i in reversed(images)], z, x, y)
    if data is None:
        raise Problem(404, f"map {mapId!r} has no imagery in tile {z}/{x}/{y}", "no-imagery")
    return Response(data, media_type="image/png", headers={"Cache-Control": "public, max-age=300"})
