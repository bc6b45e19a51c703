"""Point-cloud files of a scan: binary PLY, LAS 1.4, numpy .npz, PCD and KITTI .bin, written atomically.

A scan is a dict of per-point arrays (``FIELDS``) plus ``object_names`` (the table that
``object_index`` points into) and ``material_names`` (the table of ``material_index``, -1 for
no material).  The fields ``OPTIONAL`` names may be left out of the dict (or be None): they
are written with their default (``cos_incidence`` NaN, ``return_index`` and ``return_count`` 1,
``material_index`` -1, ``classification`` 1 'unclassified'), so a scan dict from before
they existed still writes.  ``return_index`` is the 1-based rank by range of a return among
its beam's reported returns, ``return_count`` how many the beam reported;
``classification`` an ASPRS class (the LAS 1.4 standard point classes: 2 ground, 6 building).

Every writer writes a temporary file beside the target and renames it into place
(``os.replace``, atomic on one file system), so a scan stopped mid-frame leaves the finished
frames complete and no half-written file.

- PLY (``write_ply``): binary little-endian, one ``vertex`` element with x, y, z (double),
  range, intensity, azimuth (float), ring (ushort), time (double), object_index,
  instance_index (int), nx, ny, nz, cos_incidence (float), return_index, return_count
  (uchar), material_index (int), classification (uchar); the name tables as header comments
  ``comment object <index> <name>`` and ``comment material <index> <name>`` (the header is
  ASCII: other characters of a name are written as Python escapes, ``\\xe9``, ``\\u2013``).
- LAS (``write_las``): written here, LAS 1.4 point data record format 6 (ASPRS LAS
  Specification 1.4 R15, tables 3, 7 and 24), coordinates quantised to ``LAS_SCALE``
  metres; intensity scaled to 0-65535, gps_time is the scan time, return number and number
  of returns (byte 14, bits 0-3 and 4-7) from return_index and return_count clipped to
  1-15, classification from the field, user_data the ring (clipped to 255); range, ring,
  azimuth, object_index, instance_index, the normal, cos_incidence and material_index as
  Extra Bytes (record id 4), which laspy and PDAL read as named dimensions; the name tables
  in VLRs (user id ``hybrid_raycast``, record id 1 the objects, 2 the materials, names
  joined by newlines).
- NPZ (``write_npz``): every field plus ``object_names`` and ``material_names``.
- PCD (``write_pcd``): PCD 0.7 (the Point Cloud Library's format), ``DATA binary``: x, y, z,
  intensity, range, azimuth (float32), ring (uint16), time (float64), object_index,
  instance_index (int32), normal_x, normal_y, normal_z, cos_incidence (float32),
  return_index, return_count (uint8), material_index (int32), classification (uint8), packed
  little-endian; the name tables as header comments ``# object <index> <name>`` and
  ``# material <index> <name>``.
- KITTI (``write_kitti``): the KITTI odometry velodyne layout, x, y, z, intensity as float32,
  four per point, no other field and no name table
  (``np.fromfile(path, np.float32).reshape(-1, 4)``); the frames' sensor poses go beside the
  scans in ``poses.txt`` (``write_poses``).

``read_points`` reads the points of any PLY (ascii or binary), LAS (1.0-1.4) or numpy file,
for the ``distance`` command (a scan checked against the model it came from).
"""

from __future__ import annotations

import datetime
import struct
from pathlib import Path

import numpy as np

from .atomic import atomic_path

__all__ = ["FIELDS", "OPTIONAL", "FORMATS", "EXTENSIONS", "write", "write_ply", "write_las", "write_npz", "write_pcd",
           "write_kitti", "write_poses", "LAS_SCALE", "read_points", "PointFileError"]

#: per-point fields of a scan, and their dtype in the files
FIELDS = {
    "points": ("f8", 3), "range": ("f4", 1), "intensity": ("f4", 1), "ring": ("u2", 1), "azimuth": ("f4", 1),
    "time": ("f8", 1), "object_index": ("i4", 1), "instance_index": ("i4", 1), "normals": ("f4", 3),
    "cos_incidence": ("f4", 1), "return_index": ("u1", 1), "return_count": ("u1", 1),
    "material_index": ("i4", 1), "classification": ("u1", 1),
}
#: fields a scan may leave out, and the value each point then gets (module doc)
OPTIONAL = {"cos_incidence": np.nan, "return_index": 1, "return_count": 1, "material_index": -1,
            "classification": 1}
FORMATS = ("ply", "las", "npz", "pcd", "kitti")
#: each format's file extension (a KITTI velodyne scan is a .bin)
EXTENSIONS = {"ply": "ply", "las": "las", "npz": "npz", "pcd": "pcd", "kitti": "bin"}
#: LAS coordinate resolution (metres): 0.1 mm, int32 covers +-214 km around the offset
LAS_SCALE = 1e-4


def _checked(fields: dict) -> tuple[dict, int]:
    missing = [k for k in FIELDS if fields.get(k) is None and k not in OPTIONAL]
    if missing:
        raise ValueError(f"scan fields missing: {', '.join(missing)}")
    n = len(fields["points"])
    out = {}
    for k, (dt, width) in FIELDS.items():
        if fields.get(k) is None:
            out[k] = np.full(n, OPTIONAL[k], dt)
            continue
        a = np.asarray(fields[k])
        want = (n, 3) if width == 3 else (n,)
        if a.shape != want:
            raise ValueError(f"scan field {k} must have shape {want}, got {a.shape}")
        if dt == "u1" and a.size and (a.min() < 0 or a.max() > 255):
            # astype would wrap 256 to 0 without a word
            raise ValueError(f"scan field {k} must hold whole numbers 0-255, got {a.min()} to {a.max()}")
        out[k] = a.astype(dt, copy=False)
    return out, n


def _table(kind: str, names, prefix: str) -> list[str]:
    """Header lines ``<prefix><kind> <index> <name>``, one per name."""
    return [f"{prefix}{kind} {i} {_one_line(name)}" for i, name in enumerate(names)]


#: the one-number fields PLY and PCD write under their own names
_SCALARS = ("range", "intensity", "azimuth", "ring", "time", "object_index", "instance_index", "cos_incidence",
            "return_index", "return_count", "material_index", "classification")


def write_ply(path, fields: dict, object_names, *, material_names=()) -> Path:
    f, n = _checked(fields)
    dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("range", "<f4"), ("intensity", "<f4"),
                      ("azimuth", "<f4"), ("ring", "<u2"), ("time", "<f8"), ("object_index", "<i4"),
                      ("instance_index", "<i4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                      ("cos_incidence", "<f4"), ("return_index", "u1"), ("return_count", "u1"),
                      ("material_index", "<i4"), ("classification", "u1")])
    rec = np.empty(n, dtype)
    rec["x"], rec["y"], rec["z"] = f["points"].T
    rec["nx"], rec["ny"], rec["nz"] = f["normals"].T
    for k in _SCALARS:
        rec[k] = f[k]
    plytype = {"f8": "double", "f4": "float", "u2": "ushort", "i4": "int", "u1": "uchar"}
    lines = ["ply", "format binary_little_endian 1.0", "comment written by hybrid_raycast (sensor scan)"]
    lines += _table("object", object_names, "comment ") + _table("material", material_names, "comment ")
    lines.append(f"element vertex {n}")
    for name in dtype.names:
        lines.append(f"property {plytype[dtype[name].str[1:]]} {name}")
    lines.append("end_header")
    # a PLY header is ASCII (plyfile.py, _PlyHeaderLines._decode, refuses other bytes): other
    # characters of a name go as escapes, \xe9, \u2013
    header = ("\n".join(lines) + "\n").encode("ascii", "backslashreplace")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(rec.tobytes())
    return Path(path)


def _one_line(name) -> str:
    return str(name).replace("\r", " ").replace("\n", " ")


def write_npz(path, fields: dict, object_names, *, material_names=()) -> Path:
    f, _ = _checked(fields)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, object_names=np.asarray([str(x) for x in object_names], dtype=str),
                     material_names=np.asarray([str(x) for x in material_names], dtype=str), **f)
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
          ("normal_y", "f4", "surface normal y"), ("normal_z", "f4", "surface normal z"),
          ("cos_incidence", "f4", "|cos| beam to surface normal"),
          ("material_index", "i4", "index into the material table"))
#: record ids of the name tables' VLRs (user id hybrid_raycast)
_OBJECT_NAMES_ID, _MATERIAL_NAMES_ID = 1, 2


def _extra_bytes_vlr() -> bytes:
    body = b""
    for name, dt, desc in _EXTRA:
        body += struct.pack("<2sBB32s4s24s24s24s24s24s32s", b"\0\0", _EB_TYPE[dt], 0, name.encode(), b"",
                            b"", b"", b"", b"", b"", desc.encode()[:32])
    return _VLR_HEADER.pack(0, b"LASF_Spec", 4, len(body), b"extra bytes") + body


def _names_vlr(names, kind: str, record_id: int) -> bytes:
    body = "\n".join(_one_line(x) for x in names).encode("utf-8")
    if len(body) > 65535:
        raise ValueError(f"{kind} names take {len(body)} bytes; a LAS VLR holds at most 65,535")
    return _VLR_HEADER.pack(0, b"hybrid_raycast", record_id, len(body), f"{kind} names, one per line".encode()) + body


def write_las(path, fields: dict, object_names, *, material_names=()) -> Path:
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
    # byte 14 of format 6 (LAS 1.4 R15 table 7): return number in bits 0-3, number of returns in 4-7
    number = np.clip(f["return_index"], 1, 15)
    rec["returns"] = number | (np.clip(f["return_count"], 1, 15) << 4)
    rec["classification"] = f["classification"]
    rec["user_data"] = np.minimum(f["ring"], 255)
    rec["gps_time"] = f["time"]
    for k in ("range", "ring", "azimuth", "object_index", "instance_index", "cos_incidence", "material_index"):
        rec[k] = f[k]
    rec["normal_x"], rec["normal_y"], rec["normal_z"] = f["normals"].T
    by_return = np.bincount(number, minlength=16)[1:]  # the header's number of points by return 1-15
    vlrs = (_extra_bytes_vlr() + _names_vlr(object_names, "object", _OBJECT_NAMES_ID)
            + _names_vlr(material_names, "material", _MATERIAL_NAMES_ID))
    if n:
        real = q * LAS_SCALE + lo
        mins, maxs = real.min(axis=0), real.max(axis=0)
    else:
        mins = maxs = np.zeros(3)
    today = datetime.date.today()
    header = struct.pack(
        "<4sHH16sBB32s32sHHHIIBHI5I3d3d6dQQIQ15Q",
        b"LASF", 0, _WKT_BIT, b"", 1, 4, b"hybrid_raycast scan", b"hybrid_raycast", today.timetuple().tm_yday, today.year,
        _HEADER_SIZE, _HEADER_SIZE + len(vlrs), 3, 6, dtype.itemsize, 0, 0, 0, 0, 0, 0,
        LAS_SCALE, LAS_SCALE, LAS_SCALE, *lo,
        maxs[0], mins[0], maxs[1], mins[1], maxs[2], mins[2],
        0, 0, 0, n, *by_return)
    assert len(header) == _HEADER_SIZE
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(vlrs)
            fh.write(rec.tobytes())
    return Path(path)


def write_pcd(path, fields: dict, object_names, *, material_names=()) -> Path:
    f, n = _checked(fields)
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("range", "<f4"),
                      ("azimuth", "<f4"), ("ring", "<u2"), ("time", "<f8"), ("object_index", "<i4"),
                      ("instance_index", "<i4"), ("normal_x", "<f4"), ("normal_y", "<f4"), ("normal_z", "<f4"),
                      ("cos_incidence", "<f4"), ("return_index", "u1"), ("return_count", "u1"),
                      ("material_index", "<i4"), ("classification", "u1")])
    rec = np.empty(n, dtype)
    rec["x"], rec["y"], rec["z"] = f["points"].T
    rec["normal_x"], rec["normal_y"], rec["normal_z"] = f["normals"].T
    for k in _SCALARS:
        rec[k] = f[k]
    kind = {"f": "F", "u": "U", "i": "I"}
    lines = ["# .PCD v0.7 - Point Cloud Data file format, written by hybrid_raycast (sensor scan)"]
    lines += _table("object", object_names, "# ") + _table("material", material_names, "# ")
    lines += ["VERSION 0.7", "FIELDS " + " ".join(dtype.names),
              "SIZE " + " ".join(str(dtype[k].itemsize) for k in dtype.names),
              "TYPE " + " ".join(kind[dtype[k].kind] for k in dtype.names),
              "COUNT " + " ".join("1" for _ in dtype.names), f"WIDTH {n}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0",
              f"POINTS {n}", "DATA binary"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(lines) + "\n").encode("utf-8"))
            fh.write(rec.tobytes())
    return Path(path)


def write_kitti(path, fields: dict, object_names=None, *, material_names=()) -> Path:
    """x, y, z, intensity as float32 (the name tables have no place in the format)."""
    f, n = _checked(fields)
    rec = np.empty((n, 4), "<f4")
    rec[:, :3] = f["points"]
    rec[:, 3] = f["intensity"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(rec.tobytes())
    return Path(path)


def write_poses(path, poses) -> Path:
    """KITTI odometry's poses file: one line per frame, the top three rows of its (4, 4)
    sensor-to-world matrix, row by row (12 numbers)."""
    lines = [" ".join(f"{x:.9e}" for x in np.asarray(m, np.float64)[:3].ravel()) for m in poses]
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="ascii") as fh:
            fh.write("".join(line + "\n" for line in lines))
    return Path(path)


_WRITERS = {"ply": write_ply, "las": write_las, "npz": write_npz, "pcd": write_pcd, "kitti": write_kitti}


def write(path, fmt: str, fields: dict, object_names, *, material_names=()) -> Path:
    """Write a scan as ``fmt`` (one of ``FORMATS``)."""
    if fmt not in _WRITERS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    return _WRITERS[fmt](path, fields, object_names, material_names=material_names)


# -- reading points (the distance command's input) -------------------------------------------

#: PLY property types (Paul Bourke's PLY format description) and their numpy codes
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


class PointFileError(ValueError):
    """A points file that cannot be read: the message names the file and what is wrong."""


def _read_ply(path: Path) -> np.ndarray:
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise PointFileError(f"{path}: not a PLY file (no 'ply' on the first line)")
        fmt, elements = None, []
        while True:
            line = fh.readline()
            if not line:
                raise PointFileError(f"{path}: the PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                if words[1] == "list":
                    elements[-1][2].append((words[-1], None))
                else:
                    elements[-1][2].append((words[2], _PLY_TYPES.get(words[1])))
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise PointFileError(f"{path}: the PLY file has no vertex element")
        if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
            raise PointFileError(f"{path}: unknown PLY format {fmt!r}")
        before = elements[:names.index("vertex")]
        _, count, props = elements[names.index("vertex")]
        if any(t is None for e in before for _, t in e[2]) or any(t is None for _, t in props):
            raise PointFileError(f"{path}: list properties before or in the vertex element are not supported")
        if not {"x", "y", "z"} <= {n for n, _ in props}:
            raise PointFileError(f"{path}: the vertex element has no x, y and z properties")
        if fmt == "ascii":
            skip = sum(e[1] for e in before)
            rows = [fh.readline() for _ in range(skip + count)][skip:]
            try:
                table = np.array([r.split()[:len(props)] for r in rows], np.float64)
            except ValueError:
                raise PointFileError(f"{path}: a vertex line is not {len(props)} numbers") from None
            if table.shape != (count, len(props)):
                raise PointFileError(f"{path}: the file ends before its {count:,} vertices")
            col = {n: i for i, (n, _) in enumerate(props)}
            return table[:, [col["x"], col["y"], col["z"]]]
        end = "<" if fmt == "binary_little_endian" else ">"
        for _, n, pr in before:
            fh.seek(n * np.dtype([(a, end + t) for a, t in pr]).itemsize, 1)
        dt = np.dtype([(a, end + t) for a, t in props])
        data = np.frombuffer(fh.read(count * dt.itemsize), dt)
        if len(data) != count:
            raise PointFileError(f"{path}: the file ends before its {count:,} vertices")
        return np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float64)


def _read_las(path: Path) -> np.ndarray:
    """LAS 1.0-1.4, any point data record format (X, Y, Z lead every record); not LAZ."""
    with open(path, "rb") as fh:
        head = fh.read(375)
        if len(head) < 227 or head[:4] != b"LASF":
            raise PointFileError(f"{path}: not a LAS file (no LASF signature)")
        minor = head[25]
        offset, = struct.unpack_from("<I", head, 96)
        fmt, length = struct.unpack_from("<BH", head, 104)
        if fmt & 0xC0:
            raise PointFileError(f"{path}: compressed LAZ is not supported: decompress it to LAS first")
        count, = struct.unpack_from("<I", head, 107)
        if minor >= 4 and len(head) >= 255 and count == 0:
            count, = struct.unpack_from("<Q", head, 247)
        scale = np.array(struct.unpack_from("<3d", head, 131))
        shift = np.array(struct.unpack_from("<3d", head, 155))
        fh.seek(offset)
        raw = fh.read(count * length)
    if len(raw) < count * length or length < 12:
        raise PointFileError(f"{path}: the file ends before its {count:,} points")
    rec = np.frombuffer(raw, np.dtype({"names": ["X", "Y", "Z"], "formats": ["<i4"] * 3, "offsets": [0, 4, 8],
                                       "itemsize": length}), count)
    return np.stack([rec["X"], rec["Y"], rec["Z"]], axis=1) * scale + shift


def read_points(path) -> np.ndarray:
    """(N, 3) float64 points from a PLY (ascii or binary; its vertex element's x, y, z), LAS
    (1.0-1.4, any point format; not LAZ), .npz (an array 'points' (N, 3), or 'x', 'y', 'z')
    or .npy ((N, 3)) file; ``PointFileError`` (a ValueError) naming the file otherwise."""
    p = Path(path)
    if not p.is_file():
        raise PointFileError(f"{p}: no such file")
    ext = p.suffix.lower()
    try:
        if ext == ".ply":
            pts = _read_ply(p)
        elif ext == ".las":
            pts = _read_las(p)
        elif ext == ".npy":
            pts = np.asarray(np.load(p, allow_pickle=False), np.float64)
        elif ext == ".npz":
            with np.load(p, allow_pickle=False) as z:
                if "points" in z.files:
                    pts = np.asarray(z["points"], np.float64)
                elif {"x", "y", "z"} <= set(z.files):
                    pts = np.stack([z["x"], z["y"], z["z"]], axis=1).astype(np.float64)
                else:
                    raise PointFileError(f"{p}: the .npz holds no 'points' array nor 'x', 'y', 'z' "
                                         f"(it has {', '.join(z.files) or 'nothing'})")
        else:
            raise PointFileError(f"{p}: unknown points format {ext or '(no extension)'}: use .ply, .las, .npz or .npy")
    except (OSError, struct.error, ValueError) as e:
        if isinstance(e, PointFileError):
            raise
        raise PointFileError(f"{p}: cannot read: {e}") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PointFileError(f"{p}: the points have shape {pts.shape}, not (N, 3)")
    return pts
