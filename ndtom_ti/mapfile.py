"""The map file: one versioned, checksummed file, written atomically.

Layout (little endian):
    8 bytes   magic  b"NDTOMTI\\n"
    4 bytes   format version (uint32)
    8 bytes   header length H (uint64)
    H bytes   header, UTF-8 JSON: settings, array table (name, dtype, shape, offset,
              nbytes), payload length and SHA-256
    payload   the arrays' raw bytes, back to back
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .atomic import atomic_write
from .config import MapConfig

if TYPE_CHECKING:
    from .map import NdtOmMap

MAGIC = b"NDTOMTI\n"
VERSION = 1
_ARRAYS = {
    "occ_index": ("<i4", 2),
    "occ_logodds": ("<f4", 1),
    "g_index": ("<i4", 2),
    "g_n": ("<i4", 1),
    "g_mean_rel": ("<f8", 2),
    "g_scatter": ("<f8", 2),
}
_PREFIX = struct.Struct("<8sIQ")
_MAX_HEADER = 64 * 2**20


class MapFileError(ValueError):
    """A map file that cannot be read: truncated, corrupt, foreign or too new."""


def save_map(m: NdtOmMap, path: str | Path) -> Path:
    path = Path(path)
    if not (path.parent if str(path.parent) else Path(".")).is_dir():
        raise FileNotFoundError(f"cannot write {path}: folder {path.parent} does not exist")
    st = m.state()
    table, offset = [], 0
    blobs = []
    for name, (dtype, _) in _ARRAYS.items():
        a = np.ascontiguousarray(st[name], dtype=dtype)
        table.append({"name": name, "dtype": dtype, "shape": list(a.shape), "offset": offset, "nbytes": a.nbytes})
        blobs.append(a)
        offset += a.nbytes
    sha = hashlib.sha256()
    for a in blobs:
        sha.update(_bytes(a))
    header = {
        "format": "ndtom_ti map",
        "version": VERSION,
        "resolution": m.resolution,
        "occupancy": m.occupancy_enabled,
        "config": m.config.to_dict(),
        "layout": {"l1": list(m.layout.l1), "l2": m.layout.l2, "leaf": m.layout.leaf},
        "scans_inserted": m.scans_inserted,
        "points_inserted": m.points_inserted,
        "metadata": m.metadata,
        "arrays": table,
        "payload_bytes": offset,
        "payload_sha256": sha.hexdigest(),
    }
    hbytes = json.dumps(header, default=_json_default).encode("utf-8")
    def write(fh) -> None:
        fh.write(_PREFIX.pack(MAGIC, VERSION, len(hbytes)))
        fh.write(hbytes)
        for a in blobs:
            fh.write(_bytes(a))

    atomic_write(path, write)
    return path


def _bytes(a: np.ndarray) -> memoryview:
    return memoryview(a.reshape(-1).view(np.uint8))


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


def _read(path: Path, header_only: bool = False) -> tuple[dict, dict]:
    if not path.exists():
        raise FileNotFoundError(f"no map file at {path}")
    if path.is_dir():
        raise MapFileError(f"{path} is a folder, not an ndtom_ti map file")
    size = path.stat().st_size
    with open(path, "rb") as fh:
        prefix = fh.read(_PREFIX.size)
        if not MAGIC.startswith(prefix[:8]) or not prefix:
            raise MapFileError(f"{path} is not an ndtom_ti map file (wrong magic bytes)")
        if len(prefix) < _PREFIX.size:
            raise MapFileError(f"{path} is truncated ({size} bytes): no complete header")
        _, version, hlen = _PREFIX.unpack(prefix)
        if version > VERSION:
            raise MapFileError(
                f"{path} is map format version {version}; this ndtom_ti reads up to version "
                f"{VERSION}. Upgrade ndtom_ti to read it."
            )
        if version < 1:
            raise MapFileError(f"{path} has invalid format version {version}")
        if hlen > _MAX_HEADER or _PREFIX.size + hlen > size:
            raise MapFileError(f"{path} is truncated or corrupt: header of {hlen} bytes does not fit in {size} bytes")
        try:
            header = json.loads(fh.read(hlen).decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MapFileError(f"{path} is corrupt: unreadable header ({exc})") from None
        if not isinstance(header, dict) or header.get("format") != "ndtom_ti map":
            raise MapFileError(f"{path} is corrupt: header is not an ndtom_ti map header")
        expected = _PREFIX.size + hlen + int(header.get("payload_bytes", -1))
        if size < expected:
            raise MapFileError(f"{path} is truncated: {size} bytes, expected {expected}")
        if size > expected:
            raise MapFileError(f"{path} is corrupt: {size - expected} unexpected trailing bytes")
        if header_only:
            return header, {}
        payload = fh.read()
    if hashlib.sha256(payload).hexdigest() != header.get("payload_sha256"):
        raise MapFileError(f"{path} is corrupt: payload checksum mismatch")
    arrays = {}
    try:
        for entry in header["arrays"]:
            name = entry["name"]
            if name not in _ARRAYS or entry["dtype"] != _ARRAYS[name][0]:
                raise MapFileError(f"{path} is corrupt: unexpected array {name!r}")
            a = np.frombuffer(payload, dtype=entry["dtype"], count=int(np.prod(entry["shape"])), offset=entry["offset"])
            arrays[name] = a.reshape(entry["shape"]).copy()
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, MapFileError):
            raise
        raise MapFileError(f"{path} is corrupt: bad array table ({exc})") from None
    missing = set(_ARRAYS) - set(arrays)
    if missing:
        raise MapFileError(f"{path} is corrupt: arrays {sorted(missing)} missing")
    return header, arrays


def load_map(path: str | Path) -> NdtOmMap:
    from .kernels.layout import Layout
    from .map import NdtOmMap

    path = Path(path)
    header, arrays = _read(path)
    try:
        config = MapConfig.from_dict(header["config"])
        lay = header["layout"]
        layout = Layout(l1=tuple(lay["l1"]), l2=int(lay["l2"]), leaf=int(lay["leaf"]))
        m = NdtOmMap(
            float(header["resolution"]),
            occupancy=bool(header["occupancy"]),
            config=config,
            layout=layout,
            metadata=header.get("metadata") or {},
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise MapFileError(f"{path} has invalid settings: {exc}") from None
    m._load_state(arrays)
    m.scans_inserted = int(header.get("scans_inserted", 0))
    m.points_inserted = int(header.get("points_inserted", 0))
    return m
