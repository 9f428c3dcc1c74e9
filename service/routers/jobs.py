"""Map builds as jobs with OGC API Processes status words."""

from __future__ import annotations

import os
import threading
from typing import Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, JSONResponse
from pydantic import BaseModel, ConfigDict, Field

from mapbuilder.cluster import ClusterParams
from mapbuilder.store import JobInfo, UnknownImageryError

from ..deps import Context, get_ctx, require_read, require_write
from ..jobs import build_job_params
from ..problems import Problem
from ._common import JSON, base_url, link, parse_id

router = APIRouter(tags=["Jobs"], dependencies=[Depends(require_read)])


class BuildIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    imagery: str | int = Field(..., description="Id of imagery uploaded to this map")
    tile_px: int = Field(2048, ge=64, le=8192, description="Core size of a tile, pixels")
    halo_m: float = Field(4.0, gt=0, le=100, description="Halo read around each tile, metres")
    threshold: float | None = Field(
        None, gt=0, lt=1,
        description="Marking probability threshold (default: 0.2 when verifying, 0.5 when not)")
    threshold_low: float | None = Field(
        None, gt=0, lt=1,
        description="Hysteresis: pixels above this join a marking that has pixels above "
        "`threshold` (default: 0.05 when verifying with the shipped CNN verifier)")
    hysteresis: bool = Field(True, description="false keeps only the pixels above `threshold`")
    verify: bool = Field(
        True, description="Check each detected marking with the cluster verifier (a small CNN on an "
        "oriented crop around it); false keeps every cluster the pixel classifier finds")
    verify_threshold: float = Field(
        ClusterParams.verify_threshold, gt=0, lt=1,
        description="Verifier probability a marking needs to be kept: lower keeps more markings, "
        "higher drops more false ones")
    verify_continuation_min: float = Field(
        ClusterParams.verify_continuation_min, ge=0, lt=1,
        description="Verifier probability a rejected piece of a line needs to be kept because it "
        "continues a kept one: lower takes back more of what the verifier doubts, kerbs included; "
        "at or above `verify_threshold`, none")


def _progress(job: JobInfo) -> float:
    """A job's progress in percent; a running import's on SQLite from the file it keeps it in."""
    if job.kind == "import" and job.status == "running":
        from ..jobs import read_progress

        return max(job.progress, read_progress(job) or 0.0)
    return job.progress


def job_json(job: JobInfo, request: Request) -> dict[str, Any]:
    images = [i.get("path") for i in job.params.get("images", [])] if isinstance(job.params, dict) else []
    imagery_ids = []
    if job.map_id is not None and images:
        try:
            by_path = {i.path: i.id for i in request.app.state.ctx.store.list_imagery(job.map_id)}
            imagery_ids = [str(by_path[p]) for p in images if p in by_path]
        except Exception:
            imagery_ids = []
    out = {
        "jobID": str(job.id),
        "type": "process",
        "processID": job.kind,
        "status": job.status,
        "progress": int(round(_progress(job))),
        "message": job.error or "",
        "created": job.created_at.isoformat() if job.created_at else None,
        "started": job.started_at.isoformat() if job.started_at else None,
        "finished": job.finished_at.isoformat() if job.finished_at else None,
        "updated": job.updated_at.isoformat() if job.updated_at else None,
        "mapId": job.map_id,
        "imagery": imagery_ids,
        "links": [link(f"{base_url(request)}/jobs/{job.id}", "self", JSON)],
    }
    if images:
        out["links"].append(link(f"{base_url(request)}/jobs/{job.id}/quicklook.png", "preview", "image/png",
                                 "The map's markings over the build's imagery"))
    result = job.params.get("result") if isinstance(job.params, dict) else None
    if job.kind == "import" and result:  # what a synchronous import answers
        out["result"] = {"imported": result["imported"], "first_id": str(result["first_id"]),
                         "last_id": str(result["last_id"]), "changeset": str(result["changeset"])}  # fmt: skip
        out["links"].append(link(f"{base_url(request)}/collections/{job.map_id}/changesets/{result['changeset']}",
                                 "changeset", JSON, "The import's changeset"))  # fmt: skip
    if job.status == "failed":
        out["error"] = job.error or "failed"
    if job.map_id is not None:
        out["links"].append(link(f"{base_url(request)}/collections/{job.map_id}", "collection", JSON))
    return out


@router.post("/collections/{mapId}/builds", summary="Build the map's markings from uploaded imagery",
             status_code=202)  # fmt: skip
def post_build(
    body: BuildIn,
    request: Request,
    mapId: str = PathParam(..., max_length=64),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    from mapbuilder.build import BuildParams, default_threshold, default_threshold_low

    info = ctx.store.get_map(mapId)
    imagery_id = parse_id(body.imagery, "imagery")
    try:
        img = ctx.store.get_imagery(imagery_id)
    except UnknownImageryError:
        raise Problem(422, f"imagery: map {mapId!r} has no imagery {imagery_id}", "unknown-imagery") from None
    if img.map_id != mapId:
        raise Problem(422, f"imagery: map {mapId!r} has no imagery {imagery_id}", "unknown-imagery")
    try:
        threshold = body.threshold if body.threshold is not None else default_threshold(body.verify)
        threshold_low = body.threshold_low
        if not body.hysteresis:
            if threshold_low is not None:
                raise ValueError("threshold_low is given but hysteresis is false; drop one")
        elif threshold_low is None:
            threshold_low = default_threshold_low(body.verify, None, threshold)
        params = BuildParams(tile_px=body.tile_px, halo_m=body.halo_m,
                             cluster=ClusterParams(threshold=threshold, threshold_low=threshold_low,
                                                   verify=body.verify,
                                                   verify_threshold=body.verify_threshold,
                                                   verify_continuation_min=body.verify_continuation_min))
    except ValueError as exc:
        raise Problem(422, f"body: {exc}", "invalid-build") from None
    missing = f"imagery {imagery_id}: its file is missing on the server"
    if not os.path.isfile(img.path):
        raise Problem(409, missing, "imagery-missing")
    active = ctx.store.find_jobs(kind="build", map_id=mapId, status=("accepted", "running"))
    if active:
        raise Problem(409, f"map {mapId!r} already has a build running (job {active[0].id}); "
                      "wait for it or DELETE it first", "build-running", jobID=str(active[0].id))  # fmt: skip
    crs = info.crs
    if crs is None:
        from mapbuilder.raster import default_storage_crs

        crs = default_storage_crs(img.path)
    try:
        job_params = build_job_params([img.path], params, crs)
    except OSError:  # removed since the check above
        raise Problem(409, missing, "imagery-missing") from None
    # Only an accepted build shapes the map, and at once, so the collection
    # reads as the job will build it: a map created without a CRS takes its
    # image's (as it would its first import's), and one created empty covers
    # its imagery (mapbuilder.build._ensure_map does the same for the CLI).
    if info.crs is None:
        job_params["crs"] = ctx.store.adopt_crs(mapId, crs)  # another request's, had it come first
    if info.coverage is None:
        ctx.store.adopt_coverage(mapId, "imagery")
    job_id = ctx.store.create_job("build", mapId, job_params)
    if ctx.jobs is not None:
        ctx.jobs.submit(job_id)
    job = ctx.store.get_job(job_id)
    url = f"{base_url(request)}/jobs/{job_id}"
    return JSONResponse(job_json(job, request), status_code=202, headers={"Location": url})


@router.get("/jobs", summary="Jobs, newest first")
def list_jobs(
    request: Request,
    map: str | None = Query(None, max_length=64, description="Only the jobs of this map"),
    status: str | None = Query(None, max_length=20, description="Only jobs in this status"),
    limit: int = Query(100, ge=1, le=1000),
    ctx: Context = Depends(get_ctx),
) -> dict:
    from mapbuilder.store import JOB_STATUSES

    if status is not None and status not in JOB_STATUSES:
        raise Problem(400, f"status: {status[:40]!r} is not one of {', '.join(JOB_STATUSES)}", "invalid-parameter")
    jobs = ctx.store.find_jobs(map_id=map, status=status)[::-1][:limit]
    return {"jobs": [job_json(j, request) for j in jobs],
            "links": [link(f"{base_url(request)}/jobs", "self", JSON)]}  # fmt: skip


@router.get("/jobs/{jobId}", summary="A job's status")
def get_job(request: Request, jobId: str = PathParam(..., max_length=40), ctx: Context = Depends(get_ctx)):
    return job_json(ctx.store.get_job(parse_id(jobId, "jobId")), request)


@router.get(
    "/jobs/{jobId}/quicklook.png", summary="A build's quicklook: the map's markings over its imagery",
    description="The build's images, reprojected to the map's CRS and downsampled to at most `size` pixels "
    "on the long side (never finer than the imagery), with the map's unreviewed and accepted markings "
    "over them, coloured by score: what `lanemap build --quicklook` saves. It shows the map as it is now, "
    "so a running build's picture fills in as its tiles are stored. Made on first request and kept "
    "until the map changes (`X-Map-Revision` names the revision it shows); a large build's first one "
    "takes seconds.",
    responses={200: {"content": {"image/png": {}}, "description": "A PNG picture"},
               409: {"description": "The job has no imagery, or its files are missing on the server"}},
    response_class=FileResponse,
)  # fmt: skip
def job_quicklook(
    jobId: str = PathParam(..., max_length=40),
    size: int = Query(1500, ge=64, le=4000, description="Longest side of the picture, pixels"),
    ctx: Context = Depends(get_ctx),
):
    job = ctx.store.get_job(parse_id(jobId, "jobId"))
    images = [i.get("path") for i in job.params.get("images", [])] if isinstance(job.params, dict) else []
    if job.map_id is None or not images:
        raise Problem(409, f"job {job.id} has no imagery to show", "no-imagery")
    if not all(isinstance(p, str) and os.path.isfile(p) for p in images):
        raise Problem(409, f"job {job.id}: its imagery is missing on the server", "imagery-missing")
    revision = ctx.store.map_revision(job.map_id)
    folder = ctx.data_dir / "quicklooks"
    path = folder / f"job-{job.id}-r{revision}-{size}.png"
    if not path.is_file():
        _render_quicklook(ctx, job, images, path, size)
    return FileResponse(path, media_type="image/png", headers={"X-Map-Revision": str(revision),
                                                                "Cache-Control": "no-cache"})  # fmt: skip


def _render_quicklook(ctx: Context, job: JobInfo, images: list[str], path, size: int) -> None:
    """Render a job's quicklook into ``path`` (written whole, then renamed) and drop its older ones."""
    from mapbuilder.quicklook import map_quicklook

    part = path.with_name(f"{path.stem}.{os.getpid()}.{threading.get_ident()}.part.png")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        map_quicklook(ctx.store, job.map_id, images, part, max_px=size, title=f"map {job.map_id}, job {job.id}")
        part.replace(path)
        current = path.name.rsplit("-", 1)[0] + "-"  # job-{id}-r{revision}-: other sizes stay
        for old in path.parent.glob(f"job-{job.id}-r*.png"):
            if not old.name.startswith(current) and ".part." not in old.name:
                old.unlink(missing_ok=True)
    except OSError as exc:
        part.unlink(missing_ok=True)
        raise Problem(500, f"the quicklook cannot be written in the server's data folder: "
                           f"{exc.strerror or exc.__class__.__name__}", "storage-not-writable") from None


@router.delete("/jobs/{jobId}", summary="Cancel (dismiss) a job")
def delete_job(
    request: Request,
    jobId: str = PathParam(..., max_length=40),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    job_id = parse_id(jobId, "jobId")
    job = ctx.store.get_job(job_id)
    if job.status in ("accepted", "running"):
        if ctx.jobs is not None:
            ctx.jobs.cancel(job_id)
        else:
            ctx.store.update_job(job_id, status="dismissed", error="cancelled")
    return job_json(ctx.store.get_job(job_id), request)

