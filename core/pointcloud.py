"""Point-cloud files of a scan: binary PLY, LAS 1.4 and numpy .npz, written atomically.

A scan is a dict of per-point arrays (``FIELDS``) plus ``object_names`` (the table that
``object_index`` points into).  Every writer writes a temporary file beside the target
and renames it into place (``os.replace``, atomic on one file system), so a scan stopped
mid-frame leaves the finished frames complete and no half-written file.

- PLY (``write_ply``): binary little-endian, one ``vertex`` element with x, y, z (double),
  range, intensity, azimuth (float), ring (ushort), time (double), object_index,
  instance_index (int), nx, ny, nz (float); the object-name table as header comments
  ``comment object <index> <name>``.
- LAS (``write_las``): written here, LAS 1.4 point data record format 6 (ASPRS LAS
  Specification 1.4 R15, tables 3, 7 and 24), coordinates quantised to ``LAS_SCALE``
  metres; intensity scaled to 0-65535, gps_time is the scan time, classification per
  point from the caller (per object), user_data the ring (clipped to 255); range, ring,
  azimuth, object_index, instance_index and the normal as Extra Bytes (record id 4), which
  laspy and PDAL read as named dimensions; the object-name table in a VLR
  (user id ``hybrid_raycast``, record id 1, names joined by newlines).
- NPZ (``write_npz``): every field plus ``object_names``.
"""

from __future__ import annotations

import datetime
import struct
from pathlib import Path

import numpy as np

from .atomic import atomic_path

__all__ = ["FIELDS", "FORMATS", "write", "write_ply", "write_las", "write_npz", "LAS_SCALE"]

#: per-point fields of a scan, and their dtype in the files
FIELDS = {
    "points": ("f8", 3), "range": ("f4", 1), "intensity": ("f4", 1), "ring": ("u2", 1), "azimuth": ("f4", 1),
    "time": ("f8", 1), "object_index": ("i4", 1), "instance_index": ("i4", 1), "normals": ("f4", 3),
}
FORMATS = ("ply", "las", "npz")
#: LAS coordinate resolution (metres): 0.1 mm, int32 covers +-214 km around the offset
LAS_SCALE = 1e-4


def _checked(fields: dict) -> tuple[dict, int]:
    missing = [k for k in FIELDS if k not in fields]
    if missing:
        raise ValueError(f"scan fields missing: {', '.join(missing)}")
    n = len(fields["points"])
    out = {}
    for k, (dt, width) in FIELDS.items():
        a = np.asarray(fields[k])
        want = (n, 3) if width == 3 else (n,)
        if a.shape != want:
            raise ValueError(f"scan field {k} must have shape {want}, got {a.shape}")
        out[k] = a.astype(dt, copy=False)
    return out, n


def write_ply(path, fields: dict, object_names) -> Path:
    f, n = _checked(fields)
    dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("range", "<f4"), ("intensity", "<f4"),
                      ("azimuth", "<f4"), ("ring", "<u2"), ("time", "<f8"), ("object_index", "<i4"),
                      ("instance_index", "<i4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")])
    rec = np.empty(n, dtype)
    rec["x"], rec["y"], rec["z"] = f["points"].T
    rec["nx"], rec["ny"], rec["nz"] = f["normals"].T
    for k in ("range", "intensity", "azimuth", "ring", "time", "object_index", "instance_index"):
        rec[k] = f[k]
    plytype = {"f8": "double", "f4": "float", "u2": "ushort", "i4": "int"}
    lines = ["ply", "format binary_little_endian 1.0", "comment written by hybrid_raycast (sensor scan)"]
    for i, name in enumerate(object_names):
        lines.append(f"comment object {i} {_one_line(name)}")
    lines.append(f"element vertex {n}")
    for name in dtype.names:
        lines.append(f"property {plytype[dtype[name].str[1:]]} {name}")
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("utf-8")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(rec.tobytes())
    return Path(path)


def _one_line(name) -> str:
    return str(name).replace("\r", " ").replace("\n", " ")


def write_npz(path, fields: dict, object_names) -> Path:
    f, _ = _checked(fields)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, object_names=np.asarray([str(x) for x in object_names], dtype=str), **f)
    return Path(path)


# -- LAS 1.4 --------------------------------------------------------------------------------

_HEADER_SIZE = 375
#: global encoding bit 4: the CRS, if any, is WKT; LAS 1.4 requires it for point formats 6-10
_WKT_BIT = 16
_VLR_HEADER = struct.Struct("<H16sHH32s")
#: Extra Bytes data types (LAS 1.4 table 24)
_EB_TYPE = {"u2": 3, "i4": 6, "f4": 9, "f8": 10}
_EXTRA = (("range", "f4", "range along the ray (m)"), ("ring", "u2", "laser channel / row"),
          ("azimuth", "f4", "firing azimuth (degrees)"), ("object_index", "i4", "index into the object table"),
          ("instance_index", "i4", "index of the instance hit"), ("normal_x", "f4", "surface normal x"),
          ("normal_y", "f4", "surface normal y"), ("normal_z", "f4", "surface normal z"))


def _extra_bytes_vlr() -> bytes:
    body = b""
    for name, dt, desc in _EXTRA:
        body += struct.pack("<2sBB32s4s24s24s24s24s24s32s", b"\0\0", _EB_TYPE[dt], 0, name.encode(), b"",
                            b"", b"", b"", b"", b"", desc.encode()[:32])
    return _VLR_HEADER.pack(0, b"LASF_Spec", 4, len(body), b"extra bytes") + body


def _names_vlr(object_names) -> bytes:
    body = "\n".join(_one_line(x) for x in object_names).encode("utf-8")
    if len(body) > 65535:
        raise ValueError(f"object names take {len(body)} bytes; a LAS VLR holds at most 65,535")
    return _VLR_HEADER.pack(0, b"hybrid_raycast", 1, len(body), b"object names, one per line") + body


def write_las(path, fields: dict, object_names, classification=None) -> Path:
    """``classification``: (N,) uint8 per point (default 1, 'unclassified')."""
    f, n = _checked(fields)
    pts = f["points"]
    extra = [(name, "<" + dt) for name, dt, _ in _EXTRA]
    dtype = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2"), ("returns", "u1"),
                      ("flags", "u1"), ("classification", "u1"), ("user_data", "u1"), ("scan_angle", "<i2"),
                      ("point_source_id", "<u2"), ("gps_time", "<f8"), *extra])
    if n:
        lo = np.floor(pts.min(axis=0))
        hi = pts.max(axis=0)
        if ((hi - lo) / LAS_SCALE >= 2**31 - 1).any():
            raise ValueError(f"the scan spans {(hi - lo).max():.0f} m: too far for LAS at {LAS_SCALE} m resolution")
    else:
        lo = np.zeros(3)
    q = np.rint((pts - lo) / LAS_SCALE).astype(np.int64)
    rec = np.zeros(n, dtype)
    rec["X"], rec["Y"], rec["Z"] = q.T
    rec["intensity"] = np.rint(np.clip(f["intensity"].astype(np.float64), 0, 1) * 65535).astype(np.uint16)
    rec["returns"] = 0x11  # return 1 of 1
    if classification is None:
        rec["classification"] = 1
    else:
        c = np.asarray(classification)
        if c.shape != (n,):
            raise ValueError(f"classification must have shape ({n},), got {c.shape}")
        rec["classification"] = c
    rec["user_data"] = np.minimum(f["ring"], 255)
    rec["gps_time"] = f["time"]
    for k in ("range", "ring", "azimuth", "object_index", "instance_index"):
        rec[k] = f[k]
    rec["normal_x"], rec["normal_y"], rec["normal_z"] = f["normals"].T
    vlrs = _extra_bytes_vlr() + _names_vlr(object_names)
    if n:
        real = q * LAS_SCALE + lo
        mins, maxs = real.min(axis=0), real.max(axis=0)
    else:
        mins = maxs = np.zeros(3)
    today = datetime.date.today()
    header = struct.pack(
        "<4sHH16sBB32s32sHHHIIBHI5I3d3d6dQQIQ15Q",
        b"LASF", 0, _WKT_BIT, b"", 1, 4, b"hybrid_raycast scan", b"hybrid_raycast", today.timetuple().tm_yday, today.year,
        _HEADER_SIZE, _HEADER_SIZE + len(vlrs), 2, 6, dtype.itemsize, 0, 0, 0, 0, 0, 0,
        LAS_SCALE, LAS_SCALE, LAS_SCALE, *lo,
        maxs[0], mins[0], maxs[1], mins[1], maxs[2], mins[2],
        0, 0, 0, n, n, *([0] * 14))
    assert len(header) == _HEADER_SIZE
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(vlrs)
            fh.write(rec.tobytes())
    return Path(path)


def write(path, fmt: str, fields: dict, object_names, classification=None) -> Path:
    """Write a scan as ``fmt`` ('ply', 'las' or 'npz')."""
    if fmt == "ply":
        return write_ply(path, fields, object_names)
    if fmt == "las":
        return write_las(path, fields, object_names, classification)
    if fmt == "npz":
        return write_npz(path, fields, object_names)
    raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
