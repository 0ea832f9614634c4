"""The map file: one versioned, checksummed file, written atomically.

It holds a map's settings (resolution, occupancy, config, layout, metadata, counters) and
its cell arrays (``cellstate.ARRAYS``); :class:`~ndtom_ti.snapshot.MapSnapshot` reads and
writes it.

Layout (little endian):
    8 bytes   magic  b"NDTOMTI\\n"
    4 bytes   format version (uint32)
    8 bytes   header length H (uint64)
    H bytes   header, UTF-8 JSON: settings, array table, payload length and SHA-256, and last
              its own SHA-256 (of the format version and the header without it; since 2026-11-29)
    payload   versions 4-7: each array's zstd frames, back to back (``mapcodec``; the table
              gives name, dtype, shape, coding and the frames' sizes); versions 1-3: the
              arrays' raw bytes (the table gives name, dtype, shape, offset, nbytes)
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import re
import stat
import struct
from pathlib import Path
from typing import NoReturn, TypeGuard

import numpy as np

from . import mapcodec
from .atomic import MAP_MAGIC, atomic_write, check_target
from .cellstate import ARRAYS, ROWS
from .config import N_LIMIT, MapConfig, check_resolution
from .kernels.layout import Layout

MAGIC = MAP_MAGIC  # b"NDTOMTI\n" (atomic.kept_kind knows map files by it too)
# 2: g_erased_near (version 1 files lack it: read as zeros).
# 3: g_ndt_state (earlier files lack it: read as zeros).
# 4: the arrays compressed (mapcodec): ~2-4 bytes a known cell instead of ~17.5.
# 5: scatter matrices without their rows of zeros (mapcodec's "nonzero" coding).
# 6: log-odds as a byte a cell into a table of their frequent values (mapcodec's "values").
# 7: version 6 with the Gaussians rounded (means to res / 131070, scatter to float32): written
#    only on request (``compact``), the default stays lossless.
VERSION = mapcodec.VERSION
COMPACT_VERSION = mapcodec.COMPACT_VERSION
# The last version of raw arrays; write(..., version=RAW_VERSION) still writes it.
RAW_VERSION = 3
# The versions write() writes (5, 4 and 3 for older readers).
_WRITES = (VERSION, COMPACT_VERSION, 5, 4, RAW_VERSION)
# The file's arrays are a map's cell state (ARRAYS: dtype and trailing dimensions, in file
# order; ROWS: those describing the same cells).
_COLUMNS = {name: cols for name, (_, cols) in ARRAYS.items()}
# Arrays that files of an older version may lack, by the version that added them.
_SINCE = {"g_erased_near": 2, "g_ndt_state": 3}
_PREFIX = struct.Struct("<8sIQ")
_MAX_HEADER = 64 * 2**20
_CHUNK = 16 * 2**20  # bytes hashed at a time


class MapFileError(ValueError):
    """A map file that cannot be read: truncated, corrupt, foreign or too new."""


def write(path: str | Path, settings: dict, arrays: dict, *, version: int = VERSION) -> Path:
    """Write a map's ``settings`` (as ``MapSnapshot.settings()`` gives them) and cell
    ``arrays`` (``cellstate.ARRAYS``) to ``path``, atomically; ``version=COMPACT_VERSION``
    rounds the Gaussians (about half the bytes where they are dense), ``version=RAW_VERSION``
    writes the uncompressed format that ndtom_ti before format 4 reads, ``version=4`` or
    ``5`` those formats."""
    path = check_target(path)
    if version not in _WRITES:
        raise ValueError(f"map files are written as version {', '.join(map(str, _WRITES))}, not {version}")
    hbytes, blobs = _encode(settings, arrays, version)

    def write(fh) -> None:
        fh.write(_PREFIX.pack(MAGIC, version, len(hbytes)))
        fh.write(hbytes)
        for a in blobs:
            fh.write(_bytes(a))

    atomic_write(path, write)
    return path


def _encode(s: dict, cells: dict, version: int) -> tuple[bytes, list]:
    """The header bytes and the payload's parts of a map file."""
    arrays = {name: np.ascontiguousarray(cells[name], dtype=dtype) for name, (dtype, _) in ARRAYS.items()}
    if version >= 4:
        table, blobs = mapcodec.encode(arrays, version, float(s["resolution"]))
    else:
        table, blobs, offset = [], [], 0
        for name, a in arrays.items():
            table.append(
                {"name": name, "dtype": a.dtype.str, "shape": list(a.shape), "offset": offset, "nbytes": a.nbytes}
            )
            blobs.append(a)
            offset += a.nbytes
    sha, offset = hashlib.sha256(), 0
    for a in blobs:
        sha.update(_bytes(a))
        offset += len(_bytes(a))
    header = {
        "format": "ndtom_ti map",
        "version": version,
        "resolution": s["resolution"],
        "occupancy": s["occupancy_enabled"],
        "config": s["config"].to_dict(),
        "layout": {"l1": list(s["layout"].l1), "l2": s["layout"].l2, "leaf": s["layout"].leaf},
        "scans_inserted": s["scans_inserted"],
        "points_inserted": s["points_inserted"],
        "metadata": s["metadata"],
        "arrays": table,
        "payload_bytes": offset,
        "payload_sha256": sha.hexdigest(),
    }
    body = json.dumps(header, default=_json_default).encode("utf-8")
    # The header's own checksum, last (readers of files without it, and older readers, go on
    # as before): a flipped bit in the resolution or frame_origin otherwise read as valid.
    return body[:-1] + b', "header_sha256": "' + _header_digest(version, body).encode() + b'"}', blobs


def _header_digest(version: int, body: bytes) -> str:
    return hashlib.sha256(struct.pack("<I", version) + body).hexdigest()


_HEADER_SHA = re.compile(rb', "header_sha256": "([0-9a-f]{64})"\}$')


def _bytes(a: np.ndarray | bytes) -> memoryview:
    return memoryview(a) if isinstance(a, bytes) else a.reshape(-1).view(np.uint8).data


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"metadata value {o!r} of type {type(o).__name__} cannot be stored in a map file")


def read_header(path: str | Path) -> dict:
    """The header of a map file (settings, counts) without loading the cells."""
    return _read(Path(path), header_only=True)[0]


def _read(path: Path, header_only: bool = False) -> tuple[dict, dict, int]:
    """The header, the arrays (none with ``header_only``) and the format version of a file."""
    if not path.exists():
        raise FileNotFoundError(f"no map file at {path}")
    if path.is_dir():
        raise MapFileError(f"{path} is a folder, not an ndtom_ti map file")
    with _open_regular(path) as fh:
        size = os.fstat(fh.fileno()).st_size
        prefix = fh.read(_PREFIX.size)
        if not MAGIC.startswith(prefix[:8]) or not prefix:
            raise MapFileError(f"{path} is not an ndtom_ti map file (wrong magic bytes)")
        if len(prefix) < _PREFIX.size:
            raise MapFileError(f"{path} is truncated ({size} bytes): no complete header")
        _, version, hlen = _PREFIX.unpack(prefix)
        if hlen > _MAX_HEADER or _PREFIX.size + hlen > size:
            raise MapFileError(f"{path} is truncated or corrupt: header of {hlen} bytes does not fit in {size} bytes")
        raw = fh.read(hlen)
        if version > mapcodec.NEWEST + 1000:  # no version ndtom_ti will reach: flipped bits
            raise MapFileError(f"{path} is corrupt: format version {version} is no version of this format")
        signed = _HEADER_SHA.search(raw) if version <= mapcodec.NEWEST else None
        if signed is not None and _header_digest(version, raw[: signed.start()] + b"}") != signed.group(1).decode():
            raise MapFileError(f"{path} is corrupt: header checksum mismatch")
        if version > mapcodec.NEWEST:
            raise MapFileError(
                f"{path} is map format version {version}; this ndtom_ti reads up to version "
                f"{mapcodec.NEWEST}. Upgrade ndtom_ti to read it."
            )
        if version < 1:
            raise MapFileError(f"{path} has invalid format version {version}")
        try:
            header = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MapFileError(f"{path} is corrupt: unreadable header ({exc})") from None
        except RecursionError:
            raise MapFileError(f"{path} is corrupt: unreadable header (nested too deeply)") from None
        if not isinstance(header, dict) or header.get("format") != "ndtom_ti map":
            raise MapFileError(f"{path} is corrupt: header is not an ndtom_ti map header")
        _check_header(path, header, version)
        expected = _PREFIX.size + hlen + header["payload_bytes"]
        if size < expected:
            raise MapFileError(f"{path} is truncated: {size} bytes, expected {expected}")
        if size > expected:
            raise MapFileError(f"{path} is corrupt: {size - expected} unexpected trailing bytes")
        if header_only:
            return header, {}, version
        # the checksum first, in bounded memory: a damaged file that declares gigabytes is
        # refused without holding them (then the payload is read again, checked)
        start, sha = fh.tell(), hashlib.sha256()
        while chunk := fh.read(_CHUNK):
            sha.update(chunk)
        if sha.hexdigest() != header.get("payload_sha256"):
            raise MapFileError(f"{path} is corrupt: payload checksum mismatch")
        fh.seek(start)
        payload = fh.read()
    if version >= 4:
        return header, mapcodec.decode(header["arrays"], payload, _bad(path)), version
    arrays = {}
    try:
        for entry in header["arrays"]:
            name = entry["name"]
            if name not in ARRAYS or entry["dtype"] != ARRAYS[name][0]:
                raise MapFileError(f"{path} is corrupt: unexpected array {name!r}")
            a = np.frombuffer(payload, dtype=entry["dtype"], count=int(np.prod(entry["shape"])), offset=entry["offset"])
            arrays[name] = a.reshape(entry["shape"]).copy()
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, MapFileError):
            raise
        raise MapFileError(f"{path} is corrupt: bad array table ({exc})") from None
    for name in set(ARRAYS) - set(arrays):  # (_check_header refused missing arrays of its version)
        arrays[name] = np.zeros((len(arrays["g_index"]), *_COLUMNS[name]), ARRAYS[name][0])
    return header, arrays, version


def read(path: str | Path) -> tuple[dict, dict]:
    """The map file at ``path``: its settings (as ``MapSnapshot.settings()`` gives them)
    and its cell arrays, sorted by cell; every fault of the file is a MapFileError."""
    path = Path(path)
    header, arrays, version = _read(path)
    try:
        config = MapConfig.from_dict(header["config"])
        lay = header["layout"]
        layout = Layout(l1=tuple(lay["l1"]), l2=int(lay["l2"]), leaf=int(lay["leaf"]))
        layout.validate()
        # files need not list cells sorted; snapshots do
        # (the codec of version 4 yields cells sorted and distinct: no need to check again)
        ordered = version >= 4
        for first, order in _check_values(path, arrays, layout, config, header["resolution"], ordered).items():
            for name in ROWS[first]:
                arrays[name] = arrays[name][order]
        settings = {
            "resolution": float(header["resolution"]),
            "occupancy_enabled": bool(header["occupancy"]),
            "config": config,
            "layout": layout,
            "metadata": header.get("metadata") or {},
            "scans_inserted": header["scans_inserted"],
            "points_inserted": header["points_inserted"],
        }
    except MapFileError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise MapFileError(f"{path} has invalid settings: {exc}") from None
    return settings, arrays


def _open_regular(path: Path):
    """``path`` opened for reading, refused unless it is a regular file (opening a FIFO
    without O_NONBLOCK would wait for a writer)."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise MapFileError(f"{path} is not a regular file (a pipe, device or socket), not an ndtom_ti map file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _bad(path: Path):
    def bad(what: str) -> NoReturn:
        raise MapFileError(f"{path} is corrupt: {what}")

    return bad


def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_header(path: Path, header: dict, version: int) -> None:
    """Every header field the reader and ``ndtom info`` use, by type and range, and the
    array table against itself: all arrays present once, each with its dtype, its number
    of columns and the bytes its shape needs, inside the payload, not overlapping, and
    arrays that describe the same cells of one length. Any fault: MapFileError."""

    def bad(what: str) -> NoReturn:
        raise MapFileError(f"{path} is corrupt: {what}")

    pb = header.get("payload_bytes")
    if not _is_int(pb) or pb < 0:
        bad(f"payload_bytes must be a non-negative integer, got {pb!r}")
    sha = header.get("payload_sha256")
    if not isinstance(sha, str) or len(sha) != 64:
        bad("payload_sha256 is not a SHA-256 hex digest")
    for key in ("scans_inserted", "points_inserted"):
        if not _is_int(header.get(key)) or header[key] < 0:
            bad(f"{key} must be a non-negative integer, got {header.get(key)!r}")
    try:
        check_resolution(header.get("resolution"))
    except (TypeError, ValueError) as exc:
        bad(str(exc))
    if not isinstance(header.get("occupancy"), bool):
        bad(f"occupancy must be true or false, got {header.get('occupancy')!r}")
    if not isinstance(header.get("config"), dict):
        bad("config is not a table of map options")
    try:  # the one check of settings (MapConfig's), here too: `ndtom info` reads the header alone
        MapConfig.from_dict(header["config"]).check_at(header["resolution"])
    except (TypeError, ValueError) as exc:
        bad(f"invalid map options: {exc}")
    if header.get("metadata") is not None and not isinstance(header["metadata"], dict):
        bad("metadata is not a table")
    lay = header.get("layout")
    if not (
        isinstance(lay, dict)
        and isinstance(lay.get("l1"), list)
        and len(lay["l1"]) == 3
        and all(_is_int(v) and v > 0 for v in [*lay["l1"], lay.get("l2"), lay.get("leaf")])
    ):
        bad(f"layout must hold l1 (3 positive integers), l2 and leaf (positive integers), got {lay!r}")
    table = header.get("arrays")
    if not isinstance(table, list):
        bad("the array table is not a list")
    rows, spans = {}, []
    for entry in table:
        name = entry.get("name") if isinstance(entry, dict) else None
        if not isinstance(name, str) or name not in ARRAYS:
            bad(f"unexpected array {name!r}")
        if name in rows:
            bad(f"array {name!r} appears twice")
        dtype = ARRAYS[name][0]
        if entry.get("dtype") != dtype:
            bad(f"array {name!r} has dtype {entry.get('dtype')!r}, expected {dtype!r}")
        shape, cols = entry.get("shape"), _COLUMNS[name]
        if not (
            isinstance(shape, list)
            and len(shape) == 1 + len(cols)
            and all(_is_int(n) and n >= 0 for n in shape)
            and tuple(shape[1:]) == cols
        ):
            bad(f"array {name!r} has shape {shape!r}, expected [rows{''.join(f', {c}' for c in cols)}]")
        rows[name] = shape[0]
        if version >= 4:  # the codec's fields: checked below, for the whole table
            continue
        nbytes, offset = math.prod(shape) * np.dtype(dtype).itemsize, entry.get("offset")
        if entry.get("nbytes") != nbytes or isinstance(entry.get("nbytes"), bool):
            bad(f"array {name!r} of shape {shape} needs {nbytes} bytes, the table says {entry.get('nbytes')!r}")
        if not _is_int(offset) or offset < 0 or offset + nbytes > pb:
            bad(f"array {name!r} (offset {offset!r}, {nbytes} bytes) lies outside the {pb}-byte payload")
        spans.append((offset, offset + nbytes, name))
    missing = {name for name in set(ARRAYS) - set(rows) if _SINCE.get(name, 1) <= version}
    if missing:
        bad(f"arrays {sorted(missing)} missing")
    if version >= 4:
        mapcodec.check_table(table, pb, bad, version)
    spans.sort()
    for (_, end, a), (start, _, b) in itertools.pairwise(spans):
        if start < end:
            bad(f"arrays {a!r} and {b!r} overlap in the payload")
    for first, names in ROWS.items():
        for name in names:
            if name in rows and rows[name] != rows[first]:
                bad(f"array {name!r} has {rows[name]} rows but {first!r} has {rows[first]}")


def _check_values(path: Path, arrays: dict, layout, config: MapConfig, resolution: float, ordered: bool) -> dict:
    """Cell values a map can hold, before any kernel sees them: cells inside the grid and
    each listed once, log-odds finite and inside the clamps, Gaussians of at least one
    point whose mean lies in its cell and whose scatter is finite and positive
    semi-definite. Any fault: MapFileError. Returns, for "occ_index" and "g_index" when
    their cells are not listed in order (i, j, k), the permutation that sorts them."""

    def bad(what: str) -> NoReturn:
        raise MapFileError(f"{path} is corrupt: {what}")

    if not math.isfinite(resolution * 2.0 * max(layout.cells)):
        bad(f"resolution {resolution} m makes the grid's extent overflow")
    lo, hi = np.array(layout.lo, np.int64), np.array(layout.hi, np.int64)
    unsorted = {}
    for name in ("occ_index", "g_index"):
        idx = arrays[name].astype(np.int64)
        if len(idx) == 0:
            continue
        if ((idx < lo) | (idx >= hi)).any():
            bad(f"{name} holds cells outside the grid of {layout.cells} cells")
        if ordered:
            continue
        n = (hi - lo).tolist()
        key = ((idx[:, 0] - lo[0]) * n[1] + (idx[:, 1] - lo[1])) * n[2] + (idx[:, 2] - lo[2])
        if not (np.diff(key) > 0).all():  # written sorted: cheap check first
            if len(np.unique(key)) != len(key):
                bad(f"{name} lists a cell twice")
            unsorted[name] = np.argsort(key)
    lod = arrays["occ_logodds"]
    if len(lod) and not (
        np.isfinite(lod).all()
        and (lod >= np.float32(config.logodds_min)).all()
        and (lod <= np.float32(config.logodds_max)).all()
    ):
        bad(f"occ_logodds holds values that are not finite or outside [{config.logodds_min}, {config.logodds_max}]")
    gn, mean, s = arrays["g_n"], arrays["g_mean_rel"], arrays["g_scatter"]
    if len(gn) == 0:
        return unsorted
    if (gn < 1).any():
        bad("g_n holds Gaussians of fewer than one point")
    if (gn > N_LIMIT).any():  # a map's updates cap N there: more points would wrap the kernels' int32
        bad(f"g_n holds Gaussians of more than {N_LIMIT} points")
    half = 0.5 * resolution * (1.0 + 1e-6)
    if not (np.isfinite(mean).all() and (np.abs(mean) <= half).all()):
        bad("g_mean_rel holds means that are not finite or outside their cells")
    if not np.isfinite(s).all():
        bad("g_scatter holds values that are not finite")
    xx, xy, xz, yy, yz, zz = (s[:, i] for i in range(6))
    top = gn.astype(np.float64) * resolution**2 * (1.0 + 1e-6)
    ok = (xx >= -1e-12) & (yy >= -1e-12) & (zz >= -1e-12) & (xx <= top) & (yy <= top) & (zz <= top)
    with np.errstate(over="ignore", invalid="ignore"):  # huge values: NaN compares false, refused
        scale = xx + yy + zz
        tol = 1e-6 * scale * scale
        det = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
        ok &= (xx * yy - xy * xy >= -tol) & (xx * zz - xz * xz >= -tol) & (yy * zz - yz * yz >= -tol)
        ok &= det >= -1e-6 * scale**3
    if not ok.all():
        bad("g_scatter holds a scatter matrix that is not positive semi-definite or exceeds its cell")
    if (arrays["g_erased_near"] < 0).any():
        bad("g_erased_near holds negative counts")
    if (arrays["g_ndt_state"] > 3).any():
        bad("g_ndt_state holds values other than 0-3")
    return unsorted
