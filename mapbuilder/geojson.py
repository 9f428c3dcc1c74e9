"""GeoJSON (RFC 7946) and GeoPackage exchange of markings.

A marking is a Feature with a Point geometry at its centroid, in WGS84
lon/lat, and the properties ``weight``, ``length_m``, ``width_m``,
``bearing_deg`` (clockwise from true north), ``score``, ``kind``, ``source``,
``status`` and ``version``. Properties lanemap does not know are kept in the
marking's ``extra`` and written back on export.

GeoPackage export goes through pyogrio (GDAL), in the map's storage CRS, so
that QGIS and other GIS open it directly; a GeoPackage of Points in any CRS
(such an export, or a survey) is read back as the same markings.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import shutil
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, TextIO

import numpy as np

from .model import SOURCES, STATUSES, Marking

#: Properties with a column of their own; anything else goes to ``extra``.
KNOWN_PROPERTIES = (
    "weight", "length_m", "width_m", "bearing_deg", "score", "kind", "source", "status",
)  # fmt: skip
#: Written on export, ignored on import (the store assigns them).
OUTPUT_ONLY = ("version", "id")

#: Largest GeoJSON file `read_geojson_file` accepts, bytes.
MAX_FILE_BYTES = 1 << 30


class GeoJSONError(ValueError):
    """The GeoJSON cannot be read as markings; the message names the feature and problem."""


class InvalidJSONError(GeoJSONError):
    """The text is not JSON at all (not UTF-8, a syntax error, a number that is not finite, or
    nested too deeply), as opposed to JSON that is not GeoJSON of markings."""


def _num(where: str, name: str, value: Any, *, optional: bool = True) -> float | None:
    if value is None:
        if optional:
            return None
        raise GeoJSONError(f"{where}: property {name!r} is required")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise GeoJSONError(f"{where}: property {name!r} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise GeoJSONError(f"{where}: property {name!r} must be finite")
    return v


def feature_to_marking(feature: Any, index: int | None = None, *, default_source: str = "imported") -> Marking:
    """Turn one GeoJSON Feature into a :class:`Marking` positioned by ``lon``/``lat``.

    Raises
    ------
    GeoJSONError
        For a feature that is not an object, lacks a Point geometry, has
        coordinates out of range or property values of the wrong type.
    """
    where = "feature" if index is None else f"feature {index}"
    if not isinstance(feature, dict) or feature.get("type") != "Feature":
        raise GeoJSONError(f"{where}: not a GeoJSON Feature object")
    geom = feature.get("geometry")
    if geom is None:
        raise GeoJSONError(f"{where}: has no geometry (a Point at the marking's centroid is required)")
    if not isinstance(geom, dict) or geom.get("type") != "Point":
        kind = geom.get("type") if isinstance(geom, dict) else type(geom).__name__
        raise GeoJSONError(f"{where}: geometry must be a Point, got {kind}")
    coords = geom.get("coordinates")
    if (
        not isinstance(coords, (list, tuple))
        or len(coords) < 2
        or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in coords[:2])
    ):
        raise GeoJSONError(f"{where}: Point coordinates must be [lon, lat] numbers")
    lon, lat = float(coords[0]), float(coords[1])
    if not (math.isfinite(lon) and math.isfinite(lat) and -180 <= lon <= 180 and -90 <= lat <= 90):
        raise GeoJSONError(
            f"{where}: coordinates [{coords[0]}, {coords[1]}] out of range "
            "(GeoJSON is [lon, lat] in degrees, lon in [-180, 180], lat in [-90, 90])"
        )
    props = feature.get("properties") or {}
    if not isinstance(props, dict):
        raise GeoJSONError(f"{where}: properties must be an object")
    weight = _num(where, "weight", props.get("weight"))
    if weight is not None and weight <= 0:
        raise GeoJSONError(f"{where}: property 'weight' must be > 0, got {props['weight']!r}")
    length = _num(where, "length_m", props.get("length_m"))
    width = _num(where, "width_m", props.get("width_m"))
    for name, v in (("length_m", length), ("width_m", width)):
        if v is not None and v < 0:
            raise GeoJSONError(f"{where}: property {name!r} must be >= 0")
    source = props.get("source", default_source)
    if source not in SOURCES:
        raise GeoJSONError(f"{where}: property 'source' must be one of {', '.join(SOURCES)}, got {source!r}")
    status = props.get("status", "unreviewed")
    if status not in STATUSES:
        raise GeoJSONError(f"{where}: property 'status' must be one of {', '.join(STATUSES)}, got {status!r}")
    kind = props.get("kind")
    if kind is not None and not isinstance(kind, str):
        raise GeoJSONError(f"{where}: property 'kind' must be a string")
    extra = {k: v for k, v in props.items() if k not in KNOWN_PROPERTIES and k not in OUTPUT_ONLY}
    # One string per distinct value rather than one per marking: 170 bytes a marking of a city's import.
    return Marking(
        x=math.nan,
        y=math.nan,
        lon=lon,
        lat=lat,
        weight=weight if weight is not None else 1.0,
        length_m=length or 0.0,
        width_m=width or 0.0,
        bearing_deg=(_num(where, "bearing_deg", props.get("bearing_deg")) or 0.0) % 180.0,
        score=_num(where, "score", props.get("score")),
        kind=_intern(kind),
        source=sys.intern(source),
        status=sys.intern(status),
        extra=extra,
    )


#: Features converted between two calls of a reader's ``progress``.
PROGRESS_STEP = 10_000


def read_feature_collection(obj: Any, progress: Callable[[int, int], None] | None = None) -> list[Marking]:
    """Markings from a parsed GeoJSON FeatureCollection (or a single Feature).

    ``progress``, optional: called with the features converted so far and
    their total, every :data:`PROGRESS_STEP` features and at the end.
    """
    if isinstance(obj, dict) and obj.get("type") == "Feature":
        return [feature_to_marking(obj, 0)]
    _check_collection(obj)
    feats = obj["features"]
    out: list[Marking] = []
    for start in range(0, len(feats), PROGRESS_STEP):
        out.extend(feature_to_marking(f, start + i) for i, f in enumerate(feats[start : start + PROGRESS_STEP]))
        if progress is not None:
            progress(len(out), len(feats))
    return out


def _check_collection(obj: Any) -> None:
    """Refuse what is not a FeatureCollection of WGS84 features, by its members (a ``features``
    array read feature by feature stands there as an empty list)."""
    if not isinstance(obj, dict) or obj.get("type") != "FeatureCollection":
        raise GeoJSONError("not a GeoJSON FeatureCollection (expected an object with \"type\": \"FeatureCollection\")")
    if not isinstance(obj.get("features"), list):
        raise GeoJSONError("FeatureCollection has no \"features\" array")
    crs = obj.get("crs")
    if crs is not None:
        name = (crs.get("properties") or {}).get("name", "") if isinstance(crs, dict) else ""
        if "CRS84" not in str(name) and "4326" not in str(name):
            raise GeoJSONError(f"GeoJSON must be WGS84 lon/lat (RFC 7946); it declares crs {name!r}")


def _reject_constant(value: str):
    raise InvalidJSONError(f"invalid JSON number {value}")


def _readable(path: str | Path) -> Path:
    """``path`` as a Path, once it is known to exist and to be at most ``MAX_FILE_BYTES`` long."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise GeoJSONError(f"cannot read {path}: {exc.strerror}") from None
    if size > MAX_FILE_BYTES:
        raise GeoJSONError(f"{path} is larger than {MAX_FILE_BYTES} bytes")
    return path


def read_geojson_file(path: str | Path, progress: Callable[[int, int], None] | None = None) -> list[Marking]:
    """Read markings from a GeoJSON file; every problem is a :class:`GeoJSONError`.

    ``progress``: as for :func:`read_feature_collection`, once the file is parsed.
    """
    path = _readable(path)
    with open(path, "rb") as fh:
        return read_geojson_stream(fh, str(path), progress)


def read_geojson_stream(fh: BinaryIO, name: str,
                        progress: Callable[[int, int], None] | None = None) -> list[Marking]:  # fmt: skip
    """Read markings from GeoJSON bytes read from ``fh`` (a file, standard input), at most
    ``MAX_FILE_BYTES`` of them; ``name`` names the source in errors."""
    data = fh.read(MAX_FILE_BYTES + 1)
    if len(data) > MAX_FILE_BYTES:
        raise GeoJSONError(f"{name} is larger than {MAX_FILE_BYTES} bytes")
    text = decode_json_bytes(data, name)
    del data  # held once as text while it is read, not twice
    return read_geojson_text(text, name, progress)


def decode_json_bytes(data: bytes, name: str) -> str:
    """JSON text encoded as UTF-8 (a byte order mark, as some Windows tools write, is dropped);
    :class:`InvalidJSONError` where it is not UTF-8."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InvalidJSONError(f"{name} is not UTF-8 text") from None


def read_geojson_text(text: str, name: str,
                      progress: Callable[[int, int], None] | None = None) -> list[Marking]:  # fmt: skip
    """Read markings from GeoJSON text, a feature at a time; ``name`` names the source in errors.
    Raises :class:`InvalidJSONError` where ``text`` is not JSON, and :class:`GeoJSONError` where
    it is not GeoJSON of markings."""
    try:
        return _read_collection_text(text, progress)
    except InvalidJSONError as exc:  # a number that is not finite
        raise InvalidJSONError(f"{name} is not valid JSON: {exc}") from None
    except json.JSONDecodeError as exc:
        raise InvalidJSONError(f"{name} is not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except RecursionError:
        raise InvalidJSONError(f"{name} is not valid JSON: nested too deeply") from None


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise InvalidJSONError(f"invalid JSON number {text} (numbers must be finite)")
    return v


_DECODER = json.JSONDecoder(parse_constant=_reject_constant, parse_float=_finite_float)


def _read_collection_text(text: str, progress: Callable[[int, int], None] | None) -> list[Marking]:
    """``read_feature_collection(json.loads(text))``, its features parsed and converted one at a
    time: the parsed objects of a whole file took 1.9 GB for 1,000,000 features (a 300 MB file),
    its markings a fraction of that. ``progress`` gets the features converted and, until the
    end, their number estimated from the share of the text read."""
    ws = _WHITESPACE.match
    i = ws(text, 0).end()
    if text[i:i + 1] != "{":  # not an object: as json.loads says, or not a FeatureCollection
        return read_feature_collection(_DECODER.decode(text), progress)
    members: dict[str, Any] = {}
    out: list[Marking] | None = None
    i = ws(text, i + 1).end()
    closed = text[i:i + 1] == "}"
    while not closed:
        if text[i:i + 1] != '"':
            raise json.JSONDecodeError("Expecting property name enclosed in double quotes", text, i)
        key, i = _DECODER.raw_decode(text, i)
        i = ws(text, i).end()
        if text[i:i + 1] != ":":
            raise json.JSONDecodeError("Expecting ':' delimiter", text, i)
        i = ws(text, i + 1).end()
        if key == "features" and text[i:i + 1] == "[":
            if out is not None:
                raise GeoJSONError('FeatureCollection has two "features" members')
            out, i = _read_features(text, i, progress)
            members[key] = []
        else:
            members[key], i = _DECODER.raw_decode(text, i)
        i = ws(text, i).end()
        closed = text[i:i + 1] == "}"
        if not closed and text[i:i + 1] != ",":
            raise json.JSONDecodeError("Expecting ',' delimiter", text, i)
        i = ws(text, i + 1).end() if not closed else i
    end = ws(text, i + 1).end()
    if end != len(text):
        raise json.JSONDecodeError("Extra data", text, end)
    if members.get("type") == "Feature" and out is None:
        return [feature_to_marking(members, 0)]
    _check_collection(members)
    return out if out is not None else []


def _read_features(text: str, i: int, progress: Callable[[int, int], None] | None) -> tuple[list[Marking], int]:
    """The markings of the array of features that starts at ``text[i]``, and where it ends."""
    ws = _WHITESPACE.match
    out: list[Marking] = []
    i = ws(text, i + 1).end()
    if text[i:i + 1] == "]":
        return out, i + 1
    while True:
        feature, i = _DECODER.raw_decode(text, i)
        out.append(feature_to_marking(feature, len(out)))
        if progress is not None and len(out) % PROGRESS_STEP == 0:
            progress(len(out), max(len(out), round(len(out) * len(text) / i)))
        i = ws(text, i).end()
        if text[i:i + 1] == ",":
            i = ws(text, i + 1).end()
        elif text[i:i + 1] == "]":
            if progress is not None:
                progress(len(out), len(out))
            return out, i + 1
        else:
            raise json.JSONDecodeError("Expecting ',' delimiter", text, i)


_WHITESPACE = re.compile(r"[ \t\n\r]*")


def marking_to_feature(m: Marking) -> dict[str, Any]:
    """One marking as a GeoJSON Feature (WGS84 Point at the centroid)."""
    props: dict[str, Any] = dict(m.extra or {})
    props.update(
        weight=m.weight, length_m=m.length_m, width_m=m.width_m, bearing_deg=m.bearing_deg,
        score=m.score, kind=m.kind, source=m.source, status=m.status, version=m.version,
    )  # fmt: skip
    feature: dict[str, Any] = {
        "type": "Feature",
        "geometry": {"type": "Point", "coordinates": [m.lon, m.lat]},
        "properties": props,
    }
    if m.id is not None:
        feature["id"] = str(m.id)
    return feature


def markings_to_feature_collection(items: Iterable[Marking]) -> dict[str, Any]:
    return {"type": "FeatureCollection", "features": [marking_to_feature(m) for m in items]}


#: Free space under which a failed GeoPackage write is reported as a full disk, bytes.
_FULL_DISK_BYTES = 1 << 20


class WriteError(OSError):
    """A file could not be written; the message names the file the caller asked for."""


@contextmanager
def _atomic_target(path: Path, suffix: str) -> Iterator[Path]:
    """A temporary file beside ``path`` that replaces it when the block succeeds.

    If the block fails (a full disk, an interrupt) the temporary file is removed
    and ``path`` is left as it was; an ``OSError`` becomes a :class:`WriteError`
    that names ``path``, not the temporary file.
    """
    if not path.parent.is_dir():
        raise WriteError(f"cannot write {path}: folder {path.parent} does not exist")
    tmp = path.with_name(path.name + suffix)
    try:
        tmp.unlink(missing_ok=True)
        yield tmp
        tmp.replace(path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and not isinstance(exc, WriteError):
            named = WriteError(f"cannot write {path}: {exc.strerror or exc}")
            named.errno = exc.errno
            raise named from exc
        raise


def write_geojson_object(path: str | Path, obj: dict) -> None:
    """Write one GeoJSON object (a Feature, a geometry) to ``path``, atomically (temp file + rename)."""
    path = Path(path)
    with _atomic_target(path, ".part") as tmp:
        tmp.write_text(json.dumps(obj), encoding="utf-8")


def write_geojson(path: str | Path, items: Iterable[Marking]) -> int:
    """Write markings as a GeoJSON FeatureCollection, atomically (temp file + rename)."""
    path = Path(path)
    with _atomic_target(path, ".part") as tmp, open(tmp, "w", encoding="utf-8") as fh:
        return write_geojson_stream(fh, items)


def write_geojson_stream(fh: TextIO, items: Iterable[Marking]) -> int:
    """Write markings as a GeoJSON FeatureCollection to an open text stream; returns how many."""
    n = 0
    fh.write('{"type": "FeatureCollection", "features": [\n')
    for m in items:
        if n:
            fh.write(",\n")
        fh.write(json.dumps(marking_to_feature(m), allow_nan=False))
        n += 1
    fh.write("\n]}\n")
    return n


#: Columns of a GeoPackage export that the store assigns anew on import.
_GPKG_OUTPUT_ONLY = ("marking_id", "version", "fid")


def _plain(value: Any) -> Any:
    """A GeoPackage field value as JSON would hold it (NaN and missing values as None)."""
    if value is None:
        return None
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, bytes):
        return value.hex()
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return value


def read_gpkg(path: str | Path, progress: Callable[[int, int], None] | None = None) -> list[Marking]:
    """Read markings from a GeoPackage layer of Points in any CRS; every problem is a :class:`GeoJSONError`.

    The layer is the one named ``markings`` (what :func:`write_gpkg` writes), or the
    file's only layer. Columns are read as the GeoJSON properties of the same names
    (``weight``, ``length_m``, ``kind``, ``status``...); an export's ``extra`` column
    (a JSON object) gives back the properties lanemap does not know, other columns
    become such properties, and the ids and versions of an export are assigned anew.
    ``progress``: as for :func:`read_feature_collection`.
    """
    import pyogrio
    import pyogrio.errors
    import shapely
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError as ProjCRSError

    path = _readable(path)
    try:
        layers = [str(name) for name, _ in pyogrio.list_layers(path)]
    except (pyogrio.errors.DataSourceError, OSError) as exc:
        raise GeoJSONError(f"{path} is not a GeoPackage GDAL can open: {str(exc).splitlines()[0]}") from None
    if "markings" in layers:
        layer = "markings"
    elif len(layers) == 1:
        layer = layers[0]
    else:
        raise GeoJSONError(f"{path} has {len(layers)} layers ({', '.join(layers) or 'none'}) and none named "
                           "'markings': lanemap reads that layer, or a file's only layer")  # fmt: skip
    try:
        meta, _, geoms, values = pyogrio.raw.read(path, layer=layer, force_2d=True)
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError, OSError) as exc:
        raise GeoJSONError(f"cannot read layer {layer!r} of {path}: {str(exc).splitlines()[0]}") from None
    where = f"{path}, layer {layer!r}"
    if meta.get("crs") is None:
        raise GeoJSONError(f"{where} has no CRS: lanemap cannot tell where its points lie")
    try:
        to_lonlat = Transformer.from_crs(CRS.from_user_input(meta["crs"]), "EPSG:4326", always_xy=True)
    except ProjCRSError as exc:
        raise GeoJSONError(f"{where}: its CRS {meta['crs']!r} is not one PROJ knows ({exc})") from None
    if geoms is None:
        raise GeoJSONError(f"{where} has no geometry column (a Point at each marking's centroid is required)")
    shapes = shapely.from_wkb(geoms)
    kinds = shapely.get_type_id(shapes)
    bad = np.flatnonzero(kinds != 0)  # 0: Point; -1: a missing geometry
    if len(bad):
        i = int(bad[0])
        got = "no geometry" if shapes[i] is None else f"a {shapes[i].geom_type}"
        raise GeoJSONError(f"{where}, row {i + 1}: has {got} (a Point at the marking's centroid is required)")
    lon, lat = to_lonlat.transform(shapely.get_x(shapes), shapely.get_y(shapes))
    names = [str(n) for n in meta["fields"]]
    out: list[Marking] = []
    n = len(shapes)
    for start in range(0, n, PROGRESS_STEP):
        for i in range(start, min(start + PROGRESS_STEP, n)):
            props: dict[str, Any] = {}
            for name, col in zip(names, values):
                if name in _GPKG_OUTPUT_ONLY:
                    continue
                v = _plain(col[i])
                if name == "extra" and isinstance(v, str):
                    try:  # finite numbers only: an extra holding Infinity could not be exported
                        extra = _DECODER.decode(v)
                    except (json.JSONDecodeError, InvalidJSONError, RecursionError):
                        extra = None
                    if isinstance(extra, dict):
                        props.update({k: x for k, x in extra.items() if k not in props})
                        continue
                if v is not None:
                    props[name] = v
            feature = {"type": "Feature", "geometry": {"type": "Point", "coordinates": [float(lon[i]), float(lat[i])]},
                       "properties": props}  # fmt: skip
            try:
                out.append(feature_to_marking(feature, i))
            except GeoJSONError as exc:
                raise GeoJSONError(f"{where}, row {i + 1}: {str(exc).split(': ', 1)[1]}") from None
        if progress is not None:
            progress(len(out), n)
    return out


#: Markings turned into columns at a time when a GeoPackage is written.
GPKG_CHUNK = 50_000


def _intern(v: str | None) -> str | None:
    return v if v is None else sys.intern(v)


def write_gpkg(path: str | Path, items: Iterable[Marking], crs: str, layer: str = "markings") -> int:
    """Write markings to a GeoPackage layer of Points in the storage CRS ``crs``, into a file
    that replaces ``path`` only once all are written.

    The markings are turned into columns :data:`GPKG_CHUNK` at a time and written in one go,
    which lets GDAL build the layer's spatial index once at the end (appending a chunk at a
    time updated it marking by marking: 44 s instead of 26 s for 1,000,000); an export of
    1,000,000 peaked at 491 MB where it held every marking until the write (1.27 GB).
    """
    import pyogrio.errors
    import pyogrio.raw
    import shapely

    path = Path(path)
    cols: dict[str, tuple[str, Any]] = {
        "marking_id": ("int64", lambda m: m.id if m.id is not None else -1),
        "weight": ("float64", lambda m: m.weight),
        "length_m": ("float64", lambda m: m.length_m),
        "width_m": ("float64", lambda m: m.width_m),
        "bearing_deg": ("float64", lambda m: m.bearing_deg),
        "score": ("float64", lambda m: np.nan if m.score is None else m.score),
        "kind": ("object", lambda m: _intern(m.kind)),
        "source": ("object", lambda m: _intern(m.source)),
        "status": ("object", lambda m: _intern(m.status)),
        "version": ("int64", lambda m: m.version or 0),
        "extra": ("object", lambda m: json.dumps(m.extra) if m.extra else "{}"),
    }
    parts: list[list[np.ndarray]] = [[] for _ in cols]
    geoms: list[np.ndarray] = []
    it = iter(items)
    while chunk := list(itertools.islice(it, GPKG_CHUNK)):
        for part, (dtype, get) in zip(parts, cols.values()):
            part.append(np.array([get(m) for m in chunk], dtype=dtype))
        geoms.append(np.asarray(shapely.to_wkb(shapely.points([m.x for m in chunk], [m.y for m in chunk])),
                                dtype=object))  # fmt: skip
    field_data = [np.concatenate(part) if part else np.array([], dtype=dtype)
                  for part, (dtype, _) in zip(parts, cols.values())]  # fmt: skip
    geometry = np.concatenate(geoms) if geoms else np.array([], dtype=object)
    del parts, geoms
    with _atomic_target(path, ".part.gpkg") as tmp:
        try:
            pyogrio.raw.write(
                str(tmp),
                geometry=geometry,
                field_data=field_data,
                fields=list(cols),
                crs=crs,
                geometry_type="Point",
                driver="GPKG",
                layer=layer,
            )
        except pyogrio.errors.DataSourceError as exc:
            # GDAL reports a full disk as a failed commit; say which it was.
            reason = str(exc)
            if shutil.disk_usage(tmp.parent).free < _FULL_DISK_BYTES:
                reason = f"No space left on device ({reason})"
            raise WriteError(f"cannot write {path}: {reason}") from exc
    return len(geometry)
