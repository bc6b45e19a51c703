"""The time-versus-rays picture: total time of each structure against the ray count.

The decision is written in large type above the plot.  Log-log axes.  The grid's line is R t_G (its build is already paid: the decision
treats it as sunk), each candidate's is T_B + R t; the first candidate line crosses the
grid's at the break-even R*.  The shaded band is the break-even interval [low, high]; the
dashed vertical line is the expected ray count.  Colours: grid orange, BVH blue, Embree
green.  Decade ticks on both axes carry labels ("1e6" rays, "1e-3" seconds) drawn with a
3x5 pixel font.

Pure numpy rasterisation (Blender ships no matplotlib): ``plot_rgba`` returns an
(H, W, 4) float array and ``write_png`` saves one; neither needs Blender.  The CLI
writes the PNG; ``ui/plot.py`` shows the same raster in the sidebar.  The figures come
from an analysis record (``figures_from_record``) or from ``scene.hybrid_raycast``
(``settings.figures_from_props``).
"""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np

COLORS = {
    "grid": (1.0, 0.55, 0.1),
    "bvh": (0.25, 0.6, 1.0),
    "embree": (0.35, 0.85, 0.35),
}
BACKGROUND = (0.13, 0.13, 0.13, 1.0)
AXIS = (0.75, 0.75, 0.75)
TEXT = (0.85, 0.85, 0.85)

# 3x5 glyphs, rows top to bottom, 3 bits per row (left = 4)
_FONT = {
    "0": (7, 5, 5, 5, 7), "1": (2, 6, 2, 2, 7), "2": (7, 1, 7, 4, 7), "3": (7, 1, 7, 1, 7),
    "4": (5, 5, 7, 1, 1), "5": (7, 4, 7, 1, 7), "6": (7, 4, 7, 5, 7), "7": (7, 1, 1, 2, 2),
    "8": (7, 5, 7, 5, 7), "9": (7, 5, 7, 1, 7), "e": (0, 7, 7, 4, 7), "-": (0, 0, 7, 0, 0),
    "r": (0, 6, 5, 4, 4), "a": (0, 3, 5, 5, 3), "y": (0, 5, 7, 1, 6), "s": (0, 3, 6, 1, 6),
    "t": (2, 7, 2, 2, 3), "i": (2, 0, 2, 2, 2), "m": (0, 7, 7, 5, 5), " ": (0, 0, 0, 0, 0),
    "x": (0, 5, 2, 5, 5), "=": (0, 7, 0, 7, 0), "g": (7, 5, 7, 1, 7), "b": (4, 4, 7, 5, 7),
    "v": (0, 5, 5, 5, 2), "h": (4, 4, 7, 5, 5), "E": (7, 4, 7, 4, 7), "G": (7, 4, 5, 5, 7),
    "B": (6, 5, 6, 5, 6), "R": (6, 5, 6, 5, 5), "I": (7, 2, 2, 2, 7), "D": (6, 5, 5, 5, 6),
    "V": (5, 5, 5, 5, 2), "H": (5, 5, 7, 5, 5), "M": (5, 7, 7, 5, 5), "*": (0, 5, 2, 5, 0),
}


def figures_from_record(record: dict) -> dict:
    """What the plot needs (``plot_rgba``'s ``f``), from an analysis record (``operators.analyze``)."""
    st = record["structures"]
    be = record["break_even"]
    return {
        "grid_per_ray": st["grid"]["per_ray"],
        "candidates": {k: (v["build_time"], v["per_ray"]) for k, v in st.items() if k != "grid"},
        "expected_rays": record["expected_rays"],
        "decision": record["decision"],
        "break_even": be["rays"], "break_even_low": be["low"], "break_even_high": be["high"],
    }


def _x_range(f):
    marks = [x for x in (f["expected_rays"], f["break_even"], f["break_even_low"], f["break_even_high"])
             if x is not None and x > 0 and math.isfinite(x)]
    lo = math.floor(math.log10(min(marks))) - 1 if marks else 3
    hi = math.ceil(math.log10(max(marks))) + 1 if marks else 9
    if hi - lo < 4:
        lo, hi = lo - (4 - (hi - lo)) // 2, hi + (4 - (hi - lo) + 1) // 2
    return float(lo), float(hi)


def curves(f, xs):
    """{kind: total time at the ray counts ``xs``} (the grid's build is sunk)."""
    out = {"grid": np.asarray(xs, np.float64) * max(f["grid_per_ray"], 0.0)}
    for k, (b, t) in f["candidates"].items():
        out[k] = b + np.asarray(xs, np.float64) * t
    return out


def _text(img, x, y, s, color, scale=1):
    """Draw ``s`` with its top-left corner at pixel (x, y)."""
    h, w = img.shape[:2]
    for ch in s:
        rows = _FONT.get(ch, _FONT[" "])
        for r, bits in enumerate(rows):
            for c in range(3):
                if bits & (4 >> c):
                    y0, x0 = y + r * scale, x + c * scale
                    if 0 <= y0 and y0 + scale <= h and 0 <= x0 and x0 + scale <= w:
                        img[y0:y0 + scale, x0:x0 + scale, :3] = color
        x += 4 * scale


def _polyline(img, px, py, color, width=2):
    """Anti-alias-free thick polyline through pixel coordinates (float arrays)."""
    h, w = img.shape[:2]
    pts_x, pts_y = [], []
    for i in range(len(px) - 1):
        n = int(max(abs(px[i + 1] - px[i]), abs(py[i + 1] - py[i]), 1) * 2) + 1
        s = np.linspace(0.0, 1.0, n)
        pts_x.append(px[i] + s * (px[i + 1] - px[i]))
        pts_y.append(py[i] + s * (py[i + 1] - py[i]))
    if not pts_x:
        return
    x = np.concatenate(pts_x)
    y = np.concatenate(pts_y)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = np.round(x[ok]).astype(int), np.round(y[ok]).astype(int)
    for dx in range(-(width // 2), width - width // 2):
        for dy in range(-(width // 2), width - width // 2):
            xx, yy = x + dx, y + dy
            keep = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
            img[yy[keep], xx[keep], :3] = color


def plot_rgba(f: dict, width: int = 256, height: int = 256, *, scale: int | None = None) -> np.ndarray:
    """(height, width, 4) float32 RGBA, top row first: the plot of ``f`` (``figures_from_*``)."""
    s = scale or max(1, min(width, height) // 200)
    img = np.empty((height, width, 4), np.float32)
    img[:] = BACKGROUND
    decision = f.get("decision")
    big = max(2, min(width // 50, height // 40))  # the decision's letter scale
    title = 5 * big + 8 * s if decision else 0
    left, right, top, bottom = 22 * s, width - 6 * s, 6 * s + title, height - 14 * s
    if decision:  # the decision in large type, in its structure's colour, centred
        tw = (4 * len(decision) - 1) * big
        _text(img, (width - tw) // 2, 4 * s, decision, COLORS.get(decision.lower(), TEXT), big)
    x0, x1 = _x_range(f)
    xs = np.logspace(x0, x1, 256)
    cs = curves(f, xs)
    ys = np.concatenate([c[c > 0] for c in cs.values()]) if cs else np.array([1.0])
    ys = ys[np.isfinite(ys)]
    if ys.size == 0:
        ys = np.array([1e-3, 1.0])
    y0, y1 = math.floor(math.log10(ys.min())), math.ceil(math.log10(ys.max()))
    if y1 - y0 < 2:
        y1 += 1
        y0 -= 1

    def X(x):
        return left + (np.log10(np.maximum(x, 1e-300)) - x0) / (x1 - x0) * (right - left)

    def Y(y):
        return bottom - (np.log10(np.maximum(y, 1e-300)) - y0) / (y1 - y0) * (bottom - top)

    # the break-even interval, shaded
    lo, hi = f["break_even_low"], f["break_even_high"]
    if lo is not None or hi is not None:
        a = int(np.clip(X(lo) if lo is not None else right, left, right))
        b = int(np.clip(X(hi) if hi is not None else right, left, right))
        img[top:bottom, a:max(b, a + 1), :3] = (0.2, 0.2, 0.26)
    # grid lines and ticks at decades
    for k in range(int(x0), int(x1) + 1):
        px = int(round(float(X(10.0 ** k))))
        img[top:bottom, px:px + 1, :3] = (0.19, 0.19, 0.19)
        img[bottom:bottom + 3 * s, px:px + max(1, s // 2 + 1), :3] = AXIS
        if (k - int(x0)) % max(1, int((x1 - x0) // 4)) == 0:
            label = f"1e{k}"
            _text(img, px - len(label) * 2 * s, bottom + 4 * s, label, TEXT, s)
    for k in range(int(y0), int(y1) + 1):
        py = int(round(float(Y(10.0 ** k))))
        img[py:py + 1, left:right, :3] = (0.19, 0.19, 0.19)
        img[py:py + max(1, s // 2 + 1), left - 3 * s:left, :3] = AXIS
        if (k - int(y0)) % max(1, int((y1 - y0 + 3) // 4)) == 0:
            label = f"1e{k}"
            _text(img, max(0, left - 4 * s - len(label) * 4 * s), py - 2 * s, label, TEXT, s)
    # axes
    img[top:bottom + 1, left:left + s, :3] = AXIS
    img[bottom:bottom + s, left:right, :3] = AXIS
    # the expected rays, dashed
    e = f["expected_rays"]
    if e and e > 0:
        px = int(round(float(X(e))))
        if left <= px < right:
            for yy in range(top, bottom, 6 * s):
                img[yy:yy + 3 * s, px:px + s, :3] = (1.0, 1.0, 1.0)
    # the curves: candidates first, the grid on top
    for kind in [k for k in cs if k != "grid"] + ["grid"]:
        _polyline(img, X(xs), Y(cs[kind]), COLORS.get(kind, (0.9, 0.9, 0.9)), width=2 * s)
    # the break-even point
    be = f["break_even"]
    if be is not None and be > 0:
        bx, by = float(X(be)), float(Y(be * f["grid_per_ray"]))
        if left <= bx <= right and top <= by <= bottom:
            r = 3 * s
            yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
            ring = np.abs(np.hypot(xx, yy) - r) < 0.8 * s + 0.2
            ys_, xs_ = (yy[ring] + int(round(by))), (xx[ring] + int(round(bx)))
            keep = (ys_ >= 0) & (ys_ < height) & (xs_ >= 0) & (xs_ < width)
            img[ys_[keep], xs_[keep], :3] = (1.0, 1.0, 1.0)
    _text(img, right - 17 * s, bottom - 7 * s, "rays", TEXT, s)
    _text(img, left + 3 * s, top + 1 * s, "time s", TEXT, s)
    return img


def write_png(path, rgba: np.ndarray) -> str:
    """Save a top-first (H, W, 4) float array in [0, 1] as an 8-bit RGBA PNG (no Blender needed)."""
    a = (np.clip(rgba, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    h, w = a.shape[:2]
    raw = b"".join(b"\x00" + a[r].tobytes() for r in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    with open(path, "wb") as fh:
        fh.write(png)
    return str(path)
