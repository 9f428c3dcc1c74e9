"""Per-pixel features of painted road markings, at any ground resolution.

A lane marking is a thin (0.1–0.5 m), bright, unsaturated stripe on a darker,
fairly uniform road surface. The features measure exactly that, with every
filter size given in metres and converted to pixels, so one model serves
imagery from 5 to 30 cm per pixel:

* white top-hats at two scales (brightness that a flat square wider than a
  marking removes) — thin bright things — and a broad one (bright things
  narrower than a car roof or a sidewalk slab);
* brightness against the local mean, absolute and in local standard deviations;
* chroma of what the pixel adds to its background: paint adds the same
  amount to every channel whatever the colour cast of the image; a blue car
  or green grass does not;
* brightness;
* the road surface on both sides: across the direction in which the pixel
  stands out most, how much brighter it is than both sides 0.6 m away and how
  different the two sides are (a curb has asphalt on one side only);
* continuation: the narrow top-hat 0.6 m further along that line, both ways
  (maximum over a ~0.6 m cell neighbourhood; paint continues, specks do not).

Speed matters more than anything here (the whole pipeline must run at
10 Mpx/s on two cores), and so does translation invariance (a pixel must get
the same features whatever window it is read in, or tiles would disagree at
their borders). Openings, side and continuation maps are computed at full
resolution (running minima and maxima by log-doubling on uint16, box means);
the broad opening and the 3 m background statistics run on coarse grids and
are interpolated bilinearly; the grids are anchored to the image (the
``origin`` of a window), not to the window, so that tiles read with
different offsets agree. :func:`candidate_features` evaluates the features
only at pixels whose narrow top-hat exceeds a few grey levels and which are not
strongly coloured (a few to fifteen percent of an image); every other pixel
cannot be a marking. :func:`pixel_features` evaluates them everywhere.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: Names of the feature channels, in order.
FEATURE_NAMES: tuple[str, ...] = (
    "tophat_narrow",
    "tophat_wide",
    "tophat_broad",
    "contrast",
    "zscore",
    "chroma",
    "brightness",
    "side_contrast",
    "side_asymmetry",
    "side_saturation_asymmetry",
    "continuation",
)

#: Version of the feature definition; stored in model files and checked on load.
FEATURE_VERSION = "8"

#: Filter sizes, metres.
SCALES_M = {
    "tophat_narrow": 0.45,
    "tophat_wide": 0.9,
    "tophat_broad": 2.4,
    "mean": 3.0,
    "side": 0.6,
    "side_smoothing": 0.4,
    "continuation": 0.6,
}

#: Narrow top-hat (grey levels, 0–255) below which a pixel is never a marking.
CANDIDATE_TOPHAT = 12.0


class FeatureError(ValueError):
    """Input arrays of the wrong shape, type or resolution."""


def _px(size_m: float, resolution_m: float) -> int:
    """A filter size in metres as an odd pixel count ≥ 3."""
    n = int(round(size_m / resolution_m))
    return max(n, 3) | 1


def check_inputs(rgb: np.ndarray, valid: np.ndarray | None, resolution_m: float) -> np.ndarray:
    """Validate the classifier inputs; return ``valid`` as a bool array."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise FeatureError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise FeatureError(f"rgb must be uint8, got {rgb.dtype}")
    if valid is None:
        valid = np.ones(rgb.shape[:2], bool)
    valid = np.asarray(valid)
    if valid.shape != rgb.shape[:2]:
        raise FeatureError(f"valid has shape {valid.shape}, expected {rgb.shape[:2]}")
    try:
        res = float(resolution_m)
    except (TypeError, ValueError):
        raise FeatureError(f"resolution_m must be a number, got {resolution_m!r}") from None
    if not 0.01 <= res <= 1.0:
        raise FeatureError(f"resolution_m must be within [0.01, 1] m/pixel, got {resolution_m!r}")
    return valid.astype(bool, copy=False)


def _sliding(a: np.ndarray, n: int, axis: int, op) -> np.ndarray:
    """Running ``op`` (np.minimum/np.maximum) over a centred window of ``n`` along ``axis``."""
    r = n // 2
    length = a.shape[axis]
    pad = [(0, 0)] * a.ndim
    pad[axis] = (r, r)
    cur = np.pad(a, pad, mode="edge")
    width = 1

    def sl(start, stop):
        s = [slice(None)] * a.ndim
        s[axis] = slice(start, stop)
        return tuple(s)

    while width * 2 <= n:
        m = cur.shape[axis]
        cur = op(cur[sl(0, m - width)], cur[sl(width, m)])
        width *= 2
    if width == n:
        return cur[sl(0, length)]
    return op(cur[sl(0, length)], cur[sl(n - width, n - width + length)])


def _opening(img: np.ndarray, n: int) -> np.ndarray:
    """Grey opening by an ``n`` x ``n`` square."""
    out = _sliding(img, n, 0, np.minimum)
    out = _sliding(out, n, 1, np.minimum)
    out = _sliding(out, n, 0, np.maximum)
    return _sliding(out, n, 1, np.maximum)


def _box(img: np.ndarray, n: int) -> np.ndarray:
    """Box mean over ``n`` x ``n`` (edges repeat the border values), float32."""
    img = np.asarray(img, np.float32)
    if n > 9:
        return ndimage.uniform_filter(img, n, mode="nearest")
    # small windows: shifted sums are several times faster than the generic filter
    return _shifted_box_sum(img, n) * np.float32(1.0 / (n * n))


def _shifted_box_sum(img: np.ndarray, n: int) -> np.ndarray:
    """Box sum over ``n`` x ``n`` (edges repeat the border values), in ``img``'s dtype."""
    r = n // 2
    out = img
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (r, r)
        p = np.pad(out, pad, mode="edge")
        length = out.shape[axis]
        sl = [slice(None), slice(None)]
        sl[axis] = slice(0, length)
        acc = p[tuple(sl)].copy()
        for i in range(1, n):
            sl[axis] = slice(i, i + length)
            acc += p[tuple(sl)]
        out = acc
    return out


def _box_sum_u16(img: np.ndarray, n: int) -> np.ndarray:
    """Box sum over ``n`` x ``n`` of a uint16 image (edges repeat), uint16.

    The caller keeps ``n * n * max(img)`` below 65536.
    """
    return _shifted_box_sum(img, n)


def _bilinear(grid: np.ndarray, k: int, rows: np.ndarray, cols: np.ndarray,
              lead: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Bilinear interpolation of a (hs, ws, C) grid of ``k``-pixel blocks at full-resolution pixels.

    ``lead``: the grid's first block starts that many rows and columns before the image.
    """
    hs, ws, nc = grid.shape
    ry = np.clip((rows + lead[0] + 0.5) / k - 0.5, 0, hs - 1).astype(np.float32)
    rx = np.clip((cols + lead[1] + 0.5) / k - 0.5, 0, ws - 1).astype(np.float32)
    y0 = ry.astype(np.intp)
    x0 = rx.astype(np.intp)
    y1 = np.minimum(y0 + 1, hs - 1)
    x1 = np.minimum(x0 + 1, ws - 1)
    fy = (ry - y0)[:, None]
    fx = (rx - x0)[:, None]
    flat = grid.reshape(-1, nc)
    top = flat[y0 * ws + x0] * (1 - fx) + flat[y0 * ws + x1] * fx
    bot = flat[y1 * ws + x0] * (1 - fx) + flat[y1 * ws + x1] * fx
    return top * (1 - fy) + bot * fy


def _pad_blocks(img: np.ndarray, k: int, lead: tuple[int, int]) -> np.ndarray:
    """``img`` padded with edge values: ``lead`` rows / columns before, and after to a multiple of ``k``."""
    h, w = img.shape
    pr, pc = lead
    ph, pw = (-(h + pr)) % k, (-(w + pc)) % k
    if pr or pc or ph or pw:
        img = np.pad(img, ((pr, ph), (pc, pw)), mode="edge")
    return img


def _block_max(img: np.ndarray, k: int) -> np.ndarray:
    """Block maximum by ``k`` as float32."""
    if k <= 1:
        return img.astype(np.float32)
    h, w = img.shape
    ph, pw = (-h) % k, (-w) % k
    if ph or pw:
        img = np.pad(img, ((0, ph), (0, pw)), mode="edge")
    out = img[0::k]
    for i in range(1, k):
        out = np.maximum(out, img[i::k])
    res = out[:, 0::k]
    for j in range(1, k):
        res = np.maximum(res, out[:, j::k])
    return res.astype(np.float32)


def _block_mean(img: np.ndarray, k: int, lead: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Block mean by ``k`` of a float32 image (edge blocks padded with edge values);
    the first blocks start ``lead`` rows / columns before the image."""
    img = _pad_blocks(img, k, lead)
    acc = img[0::k].copy()
    for i in range(1, k):
        acc += img[i::k]
    out = acc[:, 0::k].copy()
    for j in range(1, k):
        out += acc[:, j::k]
    return out * np.float32(1.0 / (k * k))


def _block_min(img: np.ndarray, k: int, lead: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Block minimum by ``k`` (same dtype); the first blocks start ``lead`` before the image."""
    img = _pad_blocks(img, k, lead)
    if k <= 1:
        return img
    out = img[0::k]
    for i in range(1, k):
        out = np.minimum(out, img[i::k])
    res = out[:, 0::k]
    for j in range(1, k):
        res = np.minimum(res, out[:, j::k])
    return res


def _block_mean_rgb(rgb: np.ndarray, k: int, lead: tuple[int, int] = (0, 0)) -> list[np.ndarray]:
    """Block means of the three channels of an (H, W, 3) uint8 image by ``k``, float32;
    the first blocks start ``lead`` rows / columns before the image."""
    out = []
    for c in range(3):
        ch = _pad_blocks(rgb[..., c], k, lead)
        if k <= 1:
            out.append(ch.astype(np.float32))
            continue
        acc = ch[0::k].astype(np.uint16)
        for i in range(1, k):
            acc += ch[i::k]
        res = acc[:, 0::k].copy()
        for j in range(1, k):
            res += acc[:, j::k]
        out.append(res.astype(np.float32) * np.float32(1.0 / (k * k)))
    return out


def grid_period(resolution_m: float) -> int:
    """Pixels between the lines of the coarse grids the features interpolate from.

    :func:`candidate_features` starts a window's block grids at the multiple
    of this at or before the window's origin (row and column in the image),
    so that every window of one image uses the same blocks.
    """
    return max(1, int(round(0.2 / float(resolution_m)))) * 3


def _features(rgb, valid, resolution_m, threshold, origin=(0, 0)):
    valid = check_inputs(rgb, valid, resolution_m)
    res = float(resolution_m)
    h, w = valid.shape
    nf = len(FEATURE_NAMES)
    if h == 0 or w == 0:
        return np.empty((0, nf), np.float32), np.empty(0, np.intp), valid
    # The coarse grids are anchored to the image, not to the window: their
    # first blocks start ``lead`` pixels before the window, at the previous
    # grid line, so that overlapping windows (tiles with halos) interpolate
    # the same background at the same pixel.
    period = grid_period(res)
    lead = (int(origin[0]) % period, int(origin[1]) % period)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    lum = r.astype(np.uint16)  # 3 x brightness, 0..765
    lum += g
    lum += b
    sat = np.maximum(np.maximum(r, g), b) - np.minimum(np.minimum(r, g), b)  # uint8
    all_valid = bool(valid.all())
    lum_open = lum if all_valid else np.where(valid, lum, np.uint16(765))

    op_n = _opening(lum_open, _px(SCALES_M["tophat_narrow"], res))
    th_n = lum - np.minimum(op_n, lum)
    if threshold < 0:
        cand = np.ones((h, w), bool)
    else:
        cand = th_n > np.uint16(round(3 * threshold))
        # paint is grey or white: saturation / (brightness + 16) < 0.4, in integers
        cand &= sat.astype(np.uint16) * np.uint16(15) < lum * np.uint16(2) + np.uint16(96)
    if not all_valid:
        cand &= valid
    idx = np.flatnonzero(cand)
    rows, cols = np.divmod(idx, w)

    # neighbourhood statistics on a ~20 cm grid; invalid cells take the mean of valid ones
    k = max(1, int(round(0.2 / res)))
    r_s, g_s, b_s = _block_mean_rgb(rgb, k, lead)
    if not all_valid:
        vs = _block_min(valid.view(np.uint8), k, lead) > 0
        if vs.any():
            for ch in (r_s, g_s, b_s):
                ch[~vs] = ch[vs].mean()
    lum_s = r_s + g_s + b_s
    rk = res * k
    sq_s = lum_s * lum_s
    third = np.float32(1.0 / 3.0)
    L = lum.ravel()[idx].astype(np.float32) * third

    # Maps read at a pixel's exact neighbours are full-resolution, so that the
    # features do not depend on where a window starts; smooth backgrounds come
    # from coarse grids by bilinear interpolation, for the same reason.
    op_w = _opening(op_n, _px(SCALES_M["tophat_wide"], res))
    op_wv = op_w.ravel()[idx].astype(np.float32)
    op_b_s = _opening(_block_mean(op_w.astype(np.float32), k, lead),
                      _px(SCALES_M["tophat_broad"], rk))
    op_b = np.minimum(_bilinear(op_b_s[..., None], k, rows, cols, lead)[:, 0], op_wv) * third
    m = 3  # background statistics over 3 m need no finer grid than ~0.6 m
    bg = np.stack([_box(_block_mean(a, m), _px(SCALES_M["mean"], rk * m))
                   for a in (lum_s, sq_s, r_s, g_s, b_s)], axis=-1)
    bg = _bilinear(bg, k * m, rows, cols, lead)
    mean = bg[:, 0] * third
    std = np.sqrt(np.maximum(bg[:, 1] * (third * third) - mean * mean, 0.0))

    n_side = _px(SCALES_M["side_smoothing"], res)
    if all_valid and n_side <= 9:
        # Integer box sums of both maps at once: exact (as float32 sums of
        # integers are), half the memory traffic of two float32 passes.
        side_l = _box_sum_u16(lum, n_side).ravel()
        side_s = _box_sum_u16(sat.astype(np.uint16), n_side).ravel()
        side_scale = np.float32(1.0 / (n_side * n_side))
    else:
        lum_f = lum.astype(np.float32)
        sat_f = sat.astype(np.float32)
        if not all_valid and valid.any():
            lum_f[~valid] = lum_f[valid].mean()
            sat_f[~valid] = sat_f[valid].mean()
        side_l = _box(lum_f, n_side).ravel()
        side_s = _box(sat_f, n_side).ravel()
        side_scale = np.float32(1.0)
    n_cont = _px(0.3, res)
    th_max = _sliding(_sliding(th_n, n_cont, 0, np.maximum), n_cont, 1, np.maximum).ravel()
    d_side = SCALES_M["side"] / res
    d_cont = SCALES_M["continuation"] / res

    def at(oy: int, ox: int) -> np.ndarray:
        return np.clip(rows + oy, 0, h - 1) * w + np.clip(cols + ox, 0, w - 1)

    # both sides of the pixel across the direction it stands out most
    n = len(idx)
    best = np.full(n, -np.inf, np.float32)
    asym = np.zeros(n, np.float32)
    sasym = np.zeros(n, np.float32)
    along = np.zeros(n, np.float32)
    axes = ((0.0, 1.0), (1.0, 0.0), (0.7071, 0.7071), (0.7071, -0.7071))
    perp = (1, 0, 3, 2)
    for t, (uy, ux) in enumerate(axes):
        oy, ox = int(round(d_side * uy)), int(round(d_side * ux))
        ia, ib = at(oy, ox), at(-oy, -ox)
        la, lb = side_l[ia] * side_scale, side_l[ib] * side_scale
        c = L - np.maximum(la, lb) * third
        better = c > best
        best[better] = c[better]
        asym[better] = np.abs(la[better] - lb[better]) * third
        sasym[better] = np.abs(side_s[ia[better]] * side_scale - side_s[ib[better]] * side_scale)
        py, px_ = axes[perp[t]]
        oy, ox = int(round(d_cont * py)), int(round(d_cont * px_))
        ca = th_max[at(oy, ox)[better]]
        cb = th_max[at(-oy, -ox)[better]]
        along[better] = np.minimum(ca, cb).astype(np.float32) * third

    # what the pixel adds to the local background colour
    px = rgb[rows, cols]  # any memory layout (the reader's is band-sequential)
    d0 = px[:, 0] - bg[:, 2]
    d1 = px[:, 1] - bg[:, 3]
    d2 = px[:, 2] - bg[:, 4]
    added = np.maximum((d0 + d1 + d2) * third, 0.0)
    chroma = (np.maximum(np.maximum(d0, d1), d2) - np.minimum(np.minimum(d0, d1), d2)) / (added + 16.0)

    s = np.float32(1.0 / 128.0)
    feats = np.empty((len(idx), nf), np.float32)
    feats[:, 0] = th_n.ravel()[idx].astype(np.float32) * (third * s)
    feats[:, 1] = (L - op_wv * third) * s
    feats[:, 2] = (L - op_b) * s
    feats[:, 3] = (L - mean) * s
    feats[:, 4] = np.clip((L - mean) / (std + 4.0), -6, 6) * np.float32(1 / 3)
    feats[:, 5] = np.minimum(chroma, 4.0)
    feats[:, 6] = L * np.float32(1.0 / 255.0)
    feats[:, 7] = best * s
    feats[:, 8] = asym * s
    feats[:, 9] = sasym * np.float32(1.0 / 64.0)
    feats[:, 10] = along * s
    return feats, idx, valid


def candidate_features(
    rgb: np.ndarray, valid: np.ndarray | None, resolution_m: float,
    threshold: float = CANDIDATE_TOPHAT, origin: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray]:
    """Features of the pixels that could be markings.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Image window (with halo).
    valid : (H, W) bool or None
        False where the image has no data.
    resolution_m : float
        Ground sampling distance, metres per pixel.
    threshold : float
        Narrow top-hat (grey levels) a candidate must exceed; 0 keeps every
        valid pixel whose top-hat is positive, a negative value every valid pixel.
    origin : (int, int)
        Row and column of the window's first pixel in the image. Windows of
        one image read at different origins (tiles and their halos) then give
        a pixel the same features, away from their edges.

    Returns
    -------
    feats : (N, F) float32
        Features of the candidates (:data:`FEATURE_NAMES`).
    index : (N,) intp
        Flat (row-major) indices of the candidates in the window.
    """
    feats, idx, _ = _features(rgb, valid, resolution_m, threshold, origin)
    return feats, idx


def pixel_features(rgb: np.ndarray, valid: np.ndarray | None, resolution_m: float) -> np.ndarray:
    """Marking features of every pixel of an image window.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Image window (with halo).
    valid : (H, W) bool or None
        False where the image has no data (nodata, alpha 0, outside the image).
    resolution_m : float
        Ground sampling distance, metres per pixel.

    Returns
    -------
    (H, W, F) float32
        Features named by :data:`FEATURE_NAMES`, each scaled to roughly [-1, 1];
        zero at invalid pixels.
    """
    valid = check_inputs(rgb, valid, resolution_m)
    h, w = valid.shape
    feats, idx, _ = _features(rgb, valid, resolution_m, -1.0)
    out = np.zeros((h * w, len(FEATURE_NAMES)), np.float32)
    out[idx] = feats
    return out.reshape(h, w, -1)
