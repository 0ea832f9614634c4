"""The payload of map files of versions 4-7: the snapshot's arrays, compressed (losslessly
up to version 6; version 7 rounds the Gaussians, on request).

Raw arrays took ~17.5 bytes a known cell, mostly cell indices and log-odds of free space.
Here each array becomes one to three zstd frames, back to back in the array table's order:

- cell indices (``occ_index``, ``g_index``, rows sorted): packed into int64 keys
  (:mod:`.cellkeys`; ``lo`` and ``span`` in the table), stored as the differences of
  consecutive keys, the first key's counted from -1, so every difference is >= 1. Most are
  small (neighbouring cells of a column): ``delta8`` holds each as one byte, 0 where it does
  not fit, and ``delta64`` those that did not fit (<i8), in order.
- every other array: its raw bytes (``raw``: log-odds repeat as whole values, which zstd
  finds as matches), or its bytes in planes (``planes``: byte b of column c of every row
  together; the similar signs and exponents of Gaussian means and the small high bytes of
  counts become runs). Bit for bit what was given.
- ``nonzero`` (version 5, the scatter matrices): a bit a row, set where the row is not all
  zero bits (``packbits``, little bit order; Gaussians of one point have a zero scatter),
  then the rows that are not, in planes. On BALM at 0.2 m (14% of records of one point) the
  scatter went from 3.71 B a known cell (raw, version 4) to 3.41.
- ``values`` (version 6, the log-odds): a byte a row, the row's entry (from 1) in a table of
  at most 255 values (the most frequent of a sample of rows, compared as 32 bits), 0 where
  the row's value is not in it; then the table; then those escaped rows' values, in order.
  Free space repeats a few thousand log-odds, 99-99.9% of known cells one of the 255 most
  frequent: on norlab at 0.2 m 0.60 B a known cell instead of 0.99 (raw), and coded and
  compressed ~2x faster. Values that do not repeat (more than 1 row in 8 escaping) are
  written raw.

What remains is the Gaussians' float64 means and scatter terms (BALM at 0.2 m: ~20.6 and
~36.5 B a record): their low six bytes are close to random (each byte plane's entropy 0.8-1.0
byte a byte), so no lossless coding of their bytes takes them much below ~6.6 B a value
(XOR or differences with the previous record, a neighbouring cell, came out larger).

Version 7 (``compact``, written only when asked for) is version 6 with the Gaussians rounded:

- ``fraction16`` (the means, relative to their cell's centre, so inside +-res/2): each as
  a 16-bit fraction of the cell, ``round((v / scale + 0.5) * 65535)``, in planes; ``scale``
  (the resolution) is in the table. A mean moves by at most res / 131070 (1.5 um at 0.2 m).
- ``float32`` (the scatter matrices): rounded to float32 (a relative 6e-8), then coded as
  ``nonzero``.

BALM at 0.2 m: the means take 6 B a record instead of ~20.5, the scatter ~19 instead of
~40; 2.95 B a known cell in all instead of 6.0 (docs/large-maps.md).

Each frame declares its decompressed size, which must equal what the table's shape needs
(checked before anything is inflated), so a file never makes the reader inflate more than
its arrays' declared size; frames carry zstd's own checksum besides the file's SHA-256.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NoReturn

import numpy as np
import zstandard

from .cellkeys import unpack

# zstd level 1: on the recordings' maps ~1.5x faster than level 3 (its default) for ~5% more bytes
LEVEL = 1
# Streams compressed at another level, by coding and stream: the scatter rows kept (their low
# bytes close to random) at level -1, ~1.7x faster for ~1% more of their bytes (BALM 0.2 m:
# 7.1 -> 4.2 ms, 4.37 -> 4.42 MB). (The means' planes at -1 grew 5%; the log-odds' 50%.)
# (The float32 scatter rows stay at level 1: 19.2 B a record against 20.5 at -1, BALM 0.3 m.)
_LEVELS = {("nonzero", 1): -1}
# The newest lossless payload (the map file's default version); encode(version=4 or 5)
# still writes those versions'.
VERSION = 6
# The compact payload: version 6 with the Gaussians rounded (``fraction16``, ``float32``).
COMPACT_VERSION = 7
NEWEST = COMPACT_VERSION
# A zstd frame cannot expand more than this (a 3-byte RLE block header stands for 128 KiB):
# a larger declared size is a lie, refused before any memory is taken for it.
_MAX_RATIO = 2**15
_INDEX = ("occ_index", "g_index")
# What each array compresses best as, by payload version (bytes of the recordings' maps).
# The reader takes "raw", "planes" or "nonzero" for any array that is not an index.
CODINGS = {
    4: {
        "occ_logodds": "raw",
        "g_n": "planes",
        "g_mean_rel": "planes",
        "g_scatter": "raw",
        "g_erased_near": "planes",
        "g_ndt_state": "raw",
    },
    5: {
        "occ_logodds": "raw",
        "g_n": "planes",
        "g_mean_rel": "planes",
        "g_scatter": "nonzero",
        "g_erased_near": "planes",
        "g_ndt_state": "raw",
    },
    6: {
        "occ_logodds": "values",
        "g_n": "planes",
        "g_mean_rel": "planes",
        "g_scatter": "nonzero",
        "g_erased_near": "planes",
        "g_ndt_state": "raw",
    },
}
CODINGS[COMPACT_VERSION] = {**CODINGS[6], "g_mean_rel": "fraction16", "g_scatter": "float32"}
CODING = CODINGS[VERSION]
# What the rounding codings store of each value: (dtype, arrays they may code).
_ROUNDED = {"fraction16": ("<u2", ("g_mean_rel",)), "float32": ("<f4", ("g_scatter",))}
_FRACTION = 65535
# The codings each version's reader takes for an array that is not an index.
_VALUE_CODINGS = {
    4: ("raw", "planes", "nonzero"),
    5: ("raw", "planes", "nonzero"),
    6: ("raw", "planes", "nonzero", "values"),
    7: ("raw", "planes", "nonzero", "values", "fraction16", "float32"),
}
# The ``values`` coding: at most this many distinct values in its table (codes 1-255; 0 escapes),
# each found by a multiplicative hash of its 32 bits into a table of 2**_HASH_BITS slots.
_VALUES = 255
_HASH_BITS = 16
_MULTIPLIERS = (0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D, 0x27D4EB2F)
# Rows looked up at a time (the chunk's hashes and codes stay in the cache).
_CHUNK_VALUES = 65536
# Left raw where more rows than this share escape the table (values of no few repeated ones).
_MAX_ESCAPES = 1 / 8

Bad = Callable[[str], NoReturn]


def _compress(raw: bytes | memoryview, level: int = LEVEL) -> bytes:
    return zstandard.ZstdCompressor(level=level, write_checksum=True, write_content_size=True).compress(raw)


def _rows(a: np.ndarray) -> np.ndarray:
    """The bytes of ``a`` as (rows, bytes of a row), no copy for a contiguous array."""
    return np.ascontiguousarray(a).view(np.uint8).reshape(len(a), a.itemsize * math.prod(a.shape[1:]))


def _planes(a: np.ndarray) -> np.ndarray:
    """Bytes of ``a`` (rows first) regrouped as (bytes of a row, rows): plane p holds byte p
    of every row."""
    r = _rows(a)
    rows, width = r.shape
    if width % 4 or not rows:
        return np.ascontiguousarray(r.T)
    # 4-byte words first, then the bytes of each word: ~1.7x faster than numpy's byte transpose
    words = np.ascontiguousarray(r.view(np.uint32).T)
    planes = np.ascontiguousarray(words.view(np.uint8).reshape(width // 4, rows, 4).transpose(0, 2, 1))
    return planes.reshape(width, rows)


def _unplane(raw: bytes, dtype: np.dtype, shape: list, rows: int) -> np.ndarray:
    """The (rows, *shape[1:]) array of ``dtype`` whose planes (:func:`_planes`) ``raw`` holds
    (numpy's byte transpose: this way round ~3x faster than through words)."""
    planes = np.frombuffer(raw, np.uint8).reshape(dtype.itemsize * math.prod(shape[1:]), rows)
    return np.ascontiguousarray(planes.T).view(dtype).reshape(rows, *shape[1:])


def _nonzero(a: np.ndarray) -> list[np.ndarray]:
    """The ``nonzero`` coding's two streams: a bit for each row that is not all zero bits
    (-0.0 is not zero here), and those rows in planes."""
    r = _rows(a)
    if r.shape[1] % 8 or not r.shape[1]:
        keep = r.any(axis=1)
        return [np.packbits(keep, bitorder="little"), _planes(r[keep])]
    words = r.view(np.uint64)  # whole words, OR-ed column by column (any(axis=1) is ~4x slower)
    bits = words[:, 0].copy()
    for c in range(1, words.shape[1]):
        bits |= words[:, c]
    keep = bits != 0
    # (rows of words, by compress: a faster gather than words[keep])
    return [np.packbits(keep, bitorder="little"), _planes(np.compress(keep, words, axis=0))]


# Rows of cell indices coded at a time: the int64 keys and differences of a chunk stay in the
# cache (~1.4x faster than whole-array passes on 4 million cells).
_CHUNK_ROWS = 65536


def _values(a: np.ndarray) -> list[np.ndarray] | None:
    """The ``values`` coding's three streams of an array of 4-byte rows: a byte a row (the
    row's value is entry code - 1 of the table; 0: the next escape), the table (<= 255
    values, the most frequent of a sample of rows) and the escaped rows in order, each
    compared as its 32 bits (NaN payloads, -0.0 kept). None where too many rows would escape.
    The log-odds of free space repeat a few thousand values, 99-99.9% of them the 255 most
    frequent: a byte a known cell compresses ~1.7x smaller than their raw bytes, and coding
    and compressing it takes about half the time."""
    bits = np.ascontiguousarray(a).reshape(-1).view(np.uint32)
    n = len(bits)
    if n == 0:
        return [np.zeros(0, np.uint8), np.zeros(0, np.uint32), np.zeros(0, np.uint32)]
    u, c = np.unique(bits[:: max(1, n // 65536)], return_counts=True)
    top = u[np.argsort(-c, kind="stable")[:_VALUES]]
    shift = 32 - _HASH_BITS
    best = None
    for mult in _MULTIPLIERS:  # the first multiplier giving the frequent values distinct slots
        slots = (top.astype(np.uint64) * mult & 0xFFFFFFFF) >> shift
        _, first = np.unique(slots, return_index=True)
        if best is None or len(first) > len(best[1]):
            best = (mult, np.sort(first), slots)
        if len(first) == len(top):
            break
    assert best is not None
    mult, keep, slots = best
    table = top[keep]  # (a value whose slot a more frequent one took escapes)
    lut = np.zeros(2**_HASH_BITS, np.uint8)
    lut[slots[keep]] = np.arange(1, len(table) + 1)
    full = np.concatenate([np.zeros(1, np.uint32), table])
    codes, escapes = np.empty(n, np.uint8), []
    rows = min(n, _CHUNK_VALUES)
    h, back, miss = np.empty(rows, np.uint32), np.empty(rows, np.uint32), np.empty(rows, bool)
    m32 = np.uint32(mult)
    for lo in range(0, n, rows):
        v = bits[lo : lo + rows]
        m = len(v)
        hh, bb, mm, cc = h[:m], back[:m], miss[:m], codes[lo : lo + m]
        np.multiply(v, m32, out=hh)
        hh >>= shift
        np.take(lut, hh, out=cc)
        np.take(full, cc, out=bb)
        np.not_equal(bb, v, out=mm)
        mm |= cc == 0  # (an empty slot gives code 0 and full[0]: an escape even where the bits are 0)
        if mm.any():
            at = np.flatnonzero(mm)
            cc[at] = 0
            escapes.append(v[at])
    esc = np.concatenate(escapes) if escapes else np.zeros(0, np.uint32)
    if len(esc) > _MAX_ESCAPES * n:
        return None
    return [codes, table, esc]


def _deltas(name: str, idx: np.ndarray) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The ``delta`` coding's two streams (``delta8``, ``delta64``) and the key bounds
    (``lo``, ``span``, as cellkeys.pack gives them) of index rows that must be sorted and
    distinct (keys strictly increasing: only then are the first and last rows' i the least
    and greatest, and the keys pack's)."""
    n = len(idx)
    if n == 0:
        return [np.zeros(0, np.uint8), np.zeros(0, np.int64)], np.zeros(3, np.int64), np.ones(3, np.int64)
    j, k = idx[:, 1], idx[:, 2]
    lo = np.array([idx[0, 0], j.min(), k.min()], np.int64)
    span = np.maximum(np.array([idx[-1, 0], j.max(), k.max()], np.int64) - lo + 1, 1)
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:
        raise ValueError(f"cell indices span {span.tolist()} cells: too wide for one int64 key")
    s1, s2 = int(span[1]), int(span[2])
    # keys (i * s1 + j) * s2 + k of the indices as they are, in int64 arithmetic that wraps:
    # their differences are those of the keys counted from lo, which fit. The first key is
    # counted from -1, so every difference is >= 1.
    first = (int(lo[0]) * s1 + int(lo[1])) * s2 + int(lo[2]) - 1
    rows = min(n, _CHUNK_ROWS)
    key = np.empty(rows + 1, np.int64)
    key[0] = (first + 2**63) % 2**64 - 2**63
    d = np.empty(rows, np.int64)
    d8, far, least = np.empty(n, np.uint8), [], []
    for a in range(0, n, rows):
        c = idx[a : a + rows]
        m = len(c)
        kk, dd = key[1 : m + 1], d[:m]
        kk[...] = c[:, 0]
        kk *= s1
        kk += c[:, 1]
        kk *= s2
        kk += c[:, 2]
        np.subtract(kk, key[:m], out=dd)
        key[0] = kk[-1]
        least.append(dd.min())
        out = d8[a : a + m]
        np.minimum(dd, 256, out=out, casting="unsafe")  # one byte each; 256 (and more) becomes the escape 0
        far.append(np.compress(out == 0, dd))  # (~2x faster than dd[out == 0])
    if min(least) < 1:
        raise ValueError(f"{name}: cells must be sorted and distinct to be written")
    return [d8, np.concatenate(far)], lo, span


def _code(name: str, a: np.ndarray, coding: str, scale: float | None) -> tuple[dict, list[np.ndarray], list[bytes]]:
    """One array's table entry (less its streams), its streams and their frames (``scale``:
    what ``fraction16`` takes fractions of, checked by encode)."""
    coded = _values(a) if coding == "values" and a.itemsize * math.prod(a.shape[1:]) == 4 else None
    if coding == "values" and coded is None:  # (rows of another size, or values that do not repeat)
        coding = "raw"
    entry: dict = {"name": name, "dtype": a.dtype.str, "shape": list(a.shape), "coding": coding}
    if coding == "delta":
        raws, lo, span = _deltas(name, a)
        entry.update(lo=lo.tolist(), span=span.tolist())
    elif coding == "nonzero":
        raws = _nonzero(a)
    elif coding == "fraction16":
        if not np.isfinite(a).all():
            raise ValueError(f"array {name!r} holds values that are not finite: it cannot be saved compact")
        assert scale is not None
        q = np.clip(np.rint((a / scale + 0.5) * _FRACTION), 0, _FRACTION)
        raws = [_planes(q.astype(_ROUNDED[coding][0]))]
        entry["scale"] = scale
    elif coding == "float32":
        with np.errstate(over="ignore"):
            f = a.astype(_ROUNDED[coding][0])
        if np.isinf(f).any() and not np.isinf(a).any():  # (a file that would not load again)
            raise ValueError(f"array {name!r} holds values past float32's range: save it without compact")
        raws = _nonzero(f)
    elif coded is not None:
        raws = coded
    else:
        raws = [_planes(a) if coding == "planes" else np.ascontiguousarray(a)]
    levels = [_LEVELS.get((coding, i), LEVEL) for i in range(len(raws))]
    return entry, raws, [_compress(r.reshape(-1).view(np.uint8).data, v) for r, v in zip(raws, levels, strict=True)]


def encode(
    arrays: dict[str, np.ndarray], version: int = VERSION, scale: float | None = None
) -> tuple[list[dict], list[bytes]]:
    """Table entries (name, dtype, shape, coding, streams) and the frames, in order, of
    ``arrays`` (name -> array of its dtype; index arrays with rows in (i, j, k) order), as
    a payload of ``version`` (4-7; 7 needs ``scale``, the resolution the means are
    fractions of)."""
    coding = CODINGS[version]
    if version == COMPACT_VERSION and not (scale is not None and math.isfinite(scale) and scale > 0):
        raise ValueError(f"a compact payload needs the resolution as its scale, got {scale!r}")
    codings = {name: "delta" if name in _INDEX else coding.get(name, "raw") for name in arrays}
    # Each array coded and compressed in a worker, the largest first: numpy's passes and zstd
    # let the GIL go, so two cores share the work; saving takes about half its CPU time.
    order = sorted(arrays, key=lambda n: -arrays[n].nbytes)
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = {name: pool.submit(_code, name, arrays[name], codings[name], scale) for name in order}
        table, blobs = [], []
        for name in arrays:  # the table and the frames in the caller's order
            entry, raws, frames = futures[name].result()
            entry["streams"] = [{"nbytes": len(f), "raw_nbytes": r.nbytes} for f, r in zip(frames, raws, strict=True)]
            table.append(entry)
            blobs.extend(frames)
    return table, blobs


def check_table(table: list[dict], payload_bytes: int, bad: Bad, version: int = VERSION) -> None:
    """The codec fields of a version-4, -5 or -6 array table (names, dtypes and shapes are
    checked by the caller): each array's coding (one ``version`` has), its streams' sizes
    consistent with its shape and with zstd, and all streams filling the payload exactly."""
    total = 0
    for e in table:
        name, shape, coding = e["name"], e["shape"], e.get("coding")
        if coding not in (("delta",) if name in _INDEX else _VALUE_CODINGS.get(version, ())):
            bad(f"array {name!r} has coding {coding!r}")
        stored = e["dtype"]
        if coding in _ROUNDED:
            stored, names = _ROUNDED[coding]
            if name not in names:
                bad(f"array {name!r} cannot have coding {coding!r}")
        if coding == "fraction16":
            scale = e.get("scale")
            if not (isinstance(scale, (int, float)) and not isinstance(scale, bool) and 0 < scale < math.inf):
                bad(f"array {name!r} has scale {scale!r}: not a positive number")
        rows, row_bytes = shape[0], math.prod(shape[1:]) * np.dtype(stored).itemsize
        want = 3 if coding == "values" else 2 if coding in ("delta", "nonzero", "float32") else 1
        streams = e.get("streams")
        if not (isinstance(streams, list) and len(streams) == want and all(isinstance(s, dict) for s in streams)):
            bad(f"array {name!r} needs {want} streams, the table has {streams!r}")
        for s in streams:
            nb, raw = s.get("nbytes"), s.get("raw_nbytes")
            if not (_int(nb) and _int(raw) and nb >= 0 and raw >= 0):
                bad(f"array {name!r} has stream sizes {nb!r} and {raw!r}: not non-negative integers")
            if raw > _MAX_RATIO * nb + 64:
                bad(f"array {name!r} declares {raw} bytes in a {nb}-byte stream: more than zstd can hold")
            total += nb
        first = streams[0]["raw_nbytes"]
        nonzero = coding in ("nonzero", "float32")
        need = rows if coding in ("delta", "values") else (rows + 7) // 8 if nonzero else rows * row_bytes
        if first != need:
            bad(f"array {name!r} of shape {shape} declares {first} bytes in its first stream")
        if nonzero:
            second = streams[1]["raw_nbytes"]
            if second > rows * row_bytes or (row_bytes and second % row_bytes):
                bad(f"array {name!r} declares {second} bytes of rows for {rows} rows of {row_bytes} bytes")
        if coding == "values":
            values, escaped = streams[1]["raw_nbytes"], streams[2]["raw_nbytes"]
            if row_bytes != 4 or values % 4 or values > 4 * _VALUES or escaped % 4 or escaped > 4 * rows:
                bad(f"array {name!r} of {row_bytes}-byte rows declares a table of {values} bytes, {escaped} escaped")
        if name in _INDEX:
            lo, span = e.get("lo"), e.get("span")
            if not (
                isinstance(lo, list)
                and isinstance(span, list)
                and len(lo) == len(span) == 3
                and all(_int(v) and abs(v) < 2**31 for v in lo)
                and all(_int(v) and 0 < v <= 2**32 for v in span)
                and math.prod(span) < 2**62
            ):
                bad(f"array {name!r} has key bounds lo {lo!r}, span {span!r}")
            if streams[1]["raw_nbytes"] % 8 or streams[1]["raw_nbytes"] > 8 * rows:
                bad(f"array {name!r} declares {streams[1]['raw_nbytes']} bytes of long differences for {rows} rows")
    if total != payload_bytes:
        bad(f"the streams hold {total} bytes, the payload {payload_bytes}")


def _int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _inflate(blob: memoryview, size: int, what: str, bad: Bad) -> bytes:
    """The ``size`` bytes a zstd frame holds, inflated only after its header says ``size``."""
    try:
        declared = zstandard.frame_content_size(blob)
    except zstandard.ZstdError as exc:
        bad(f"{what} is not a zstd frame ({exc})")
    if declared == -1:
        bad(f"{what} is a zstd frame that does not declare its size")
    if declared != size:
        bad(f"{what} holds a frame of {declared} bytes where {size} were declared")
    dobj = zstandard.ZstdDecompressor().decompressobj()
    try:
        out = dobj.decompress(blob)
    except zstandard.ZstdError as exc:
        bad(f"{what} does not decompress ({exc})")
    if len(out) != size or not dobj.eof or dobj.unused_data:
        bad(f"{what} decompresses to {len(out)} bytes with trailing data, {size} declared")
    return out


def decode(table: list[dict], payload: bytes, bad: Bad) -> dict[str, np.ndarray]:
    """The arrays of a payload whose table passed :func:`check_table` (and whose checksum
    matched). Index arrays come back with distinct rows in (i, j, k) order."""
    view, offset, out = memoryview(payload), 0, {}
    for e in table:
        name, shape, dtype = e["name"], e["shape"], np.dtype(e["dtype"])
        raws = []
        for i, s in enumerate(e["streams"]):
            raws.append(
                _inflate(view[offset : offset + s["nbytes"]], s["raw_nbytes"], f"array {name!r} stream {i}", bad)
            )
            offset += s["nbytes"]
        if e["coding"] == "raw":
            out[name] = np.frombuffer(raws[0], dtype).reshape(shape)
            continue
        if e["coding"] == "planes":
            out[name] = _unplane(raws[0], dtype, shape, shape[0])
            continue
        if e["coding"] == "fraction16":
            q = _unplane(raws[0], np.dtype(_ROUNDED["fraction16"][0]), shape, shape[0])
            out[name] = ((q / _FRACTION - 0.5) * e["scale"]).astype(dtype)
            continue
        if e["coding"] in ("nonzero", "float32"):
            stored = np.dtype(_ROUNDED["float32"][0]) if e["coding"] == "float32" else dtype
            rows = shape[0]
            bits = np.unpackbits(np.frombuffer(raws[0], np.uint8), bitorder="little")
            keep = bits[:rows].view(bool)
            n = int(np.count_nonzero(keep))
            if bits[rows:].any():
                bad(f"array {name!r} sets bits past its {rows} rows")
            row_bytes = stored.itemsize * math.prod(shape[1:])
            if len(raws[1]) != n * row_bytes:
                bad(f"array {name!r} holds {len(raws[1])} bytes of rows for {n} rows that are not zero")
            a = np.zeros(shape, dtype)
            a[np.flatnonzero(keep)] = _unplane(raws[1], stored, shape, n)
            out[name] = a
            continue
        if e["coding"] == "values":
            codes = np.frombuffer(raws[0], np.uint8)
            full = np.concatenate([np.zeros(1, np.uint32), np.frombuffer(raws[1], "<u4")])
            escaped = np.frombuffer(raws[2], "<u4")
            if len(codes) and int(codes.max()) >= len(full):
                bad(f"array {name!r} has codes past its table of {len(full) - 1} values")
            bits = full[codes]
            at = np.flatnonzero(codes == 0)
            if len(at) != len(escaped):
                bad(f"array {name!r} has {len(escaped)} escaped values for {len(at)} escapes")
            bits[at] = escaped
            out[name] = bits.view(dtype).reshape(shape)
            continue
        d = np.frombuffer(raws[0], np.uint8).astype(np.int64)
        far = d == 0
        long = np.frombuffer(raws[1], "<i8")
        if len(long) != np.count_nonzero(far):
            bad(f"array {name!r} has {len(long)} long key differences for {np.count_nonzero(far)} escapes")
        lo, span = np.array(e["lo"], np.int64), np.array(e["span"], np.int64)
        total = int(math.prod(e["span"]))
        # every difference >= 1 and every key inside the span: then no sum can overflow int64
        if len(long) and not ((long > 0) & (long <= total)).all():
            bad(f"array {name!r} has key differences outside [1, {total}]")
        d[far] = long
        keys = np.cumsum(d)
        keys -= 1
        if len(keys) and (keys[-1] >= total or keys.min() < 0):  # (a sum past int64 turns negative first)
            bad(f"array {name!r} has keys past its span {e['span']}")
        if len(keys) and (lo + span - 1 >= 2**31).any():
            bad(f"array {name!r} has key bounds past int32")
        out[name] = unpack(keys, lo, span, np.int32).reshape(shape)
    return out
