"""Property-based tests of the map reader: mutated valid files (header fields, array
shapes and lengths, values, raw bytes; the checksum recomputed where the mutation would
otherwise only trip it) either raise MapFileError or load a map that passes validation:
its cells, log-odds and Gaussians are those of the file, finite and within range, and it
saves and loads back unchanged. Never another exception, a crash or garbage.

CI runs a small number of examples; NDTOM_FUZZ_EXAMPLES=10000 runs more (the counts of
each outcome are printed with -s).
"""

from __future__ import annotations

import contextlib
import gc
import hashlib
import json
import math
import os
import struct
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from ndtom_ti import MapFileError, MapMemoryError, NdtOmMap, mapcodec
from ndtom_ti.mapfile import RAW_VERSION, read_header

EXAMPLES = int(os.environ.get("NDTOM_FUZZ_EXAMPLES", "150"))
OUTCOMES: Counter = Counter()
_PREFIX = struct.Struct("<8sIQ")


def _build_bases() -> dict[str, bytes]:
    rng = np.random.default_rng(7)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, res, occ, n_scans in (("ndtom", 0.5, True, 2), ("rndt", 0.4, False, 1), ("empty", 0.3, True, 0)):
            m = NdtOmMap(res, occupancy=occ, metadata={"source": "fuzz", "nested": {"a": [1, 2]}})
            for k in range(n_scans):
                T = np.eye(4)
                T[:3, 3] = [0.3 * k, -0.2 * k, 0.1]
                m.insert_scan(rng.normal(size=(400, 3)) * [2.0, 1.5, 0.3] + [3.0, 0.0, 0.0], T)
            out[name] = m.save(Path(tmp) / f"{name}.ndtom").read_bytes()
            # the same map in formats 5 and 4 and in the raw format of version 3 (older files must keep loading)
            out[f"{name} v5"] = m.snapshot().save(Path(tmp) / "v5.ndtom", version=5).read_bytes()
            out[f"{name} v4"] = m.snapshot().save(Path(tmp) / "v4.ndtom", version=4).read_bytes()
            out[f"{name} v7"] = m.snapshot().save(Path(tmp) / "v7.ndtom", compact=True).read_bytes()
            out[f"{name} v3"] = m.snapshot().save(Path(tmp) / "v3.ndtom", version=RAW_VERSION).read_bytes()
            del m
    gc.collect()
    return out


_BASES: dict[str, bytes] = {}


def bases() -> dict[str, bytes]:
    if not _BASES:
        _BASES.update(_build_bases())
    return _BASES


# ---------------------------------------------------------------------------- file <-> parts
def split(data: bytes) -> tuple[bytes, dict, bytes]:
    hlen = struct.unpack("<Q", data[12:20])[0]
    return data[:12], json.loads(data[20 : 20 + hlen]), data[20 + hlen :]


def join(head: bytes, header: dict, payload: bytes, *, fix_sha: bool = True) -> bytes:
    """A map file of these parts; ``fix_sha``: both checksums made to match (the payload's,
    and the header's own, last, over the format version and the header before it)."""
    if fix_sha:
        header["payload_sha256"] = hashlib.sha256(payload).hexdigest()
        header.pop("header_sha256", None)
    hb = json.dumps(header).encode()
    if fix_sha:
        digest = hashlib.sha256(head[8:12] + hb).hexdigest()
        hb = hb[:-1] + b', "header_sha256": "' + digest.encode() + b'"}'
    return head + struct.pack("<Q", len(hb)) + hb + payload


def _raise(what: str):
    raise ValueError(what)


def arrays_of(header: dict, payload: bytes, head: bytes) -> dict[str, np.ndarray]:
    if struct.unpack("<I", head[8:12])[0] >= 4:
        return {k: v.copy() for k, v in mapcodec.decode(header["arrays"], payload, _raise).items()}
    out = {}
    for e in header["arrays"]:
        a = np.frombuffer(payload, dtype=e["dtype"], count=math.prod(e["shape"]), offset=e["offset"])
        out[e["name"]] = a.reshape(e["shape"]).copy()
    return out


def repack(header: dict, arrays: dict[str, np.ndarray], head: bytes) -> bytes:
    """Write ``arrays`` back to back with a table that describes them exactly (versions 4
    and 5: compressed as that version is; an index that cannot be coded, unsorted or
    repeated, raises)."""
    version = struct.unpack("<I", head[8:12])[0]
    if version >= 4:
        scale = header.get("resolution") if version == mapcodec.COMPACT_VERSION else None
        table, frames = mapcodec.encode({e["name"]: arrays[e["name"]] for e in header["arrays"]}, version, scale)
        header["arrays"] = table
        payload = b"".join(frames)
        header["payload_bytes"] = len(payload)
        return payload
    blobs, off = [], 0
    for e in header["arrays"]:
        a = np.ascontiguousarray(arrays[e["name"]])
        e.update(dtype=a.dtype.str, shape=list(a.shape), offset=off, nbytes=a.nbytes)
        blobs.append(a.tobytes())
        off += a.nbytes
    payload = b"".join(blobs)
    header["payload_bytes"] = len(payload)
    return payload


# ---------------------------------------------------------------------------- mutations
JSON_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([0, 1, -1, 3, 6, 2**31, 2**63, 10**30]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.lists(st.integers(min_value=-3, max_value=40), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(min_value=-3, max_value=3), max_size=3),
)


def header_paths(header: dict) -> list[tuple]:
    """Paths to every field of the header (dict keys and list positions)."""
    out: list[tuple] = []

    def walk(node, path):
        if isinstance(node, dict):
            for k, v in node.items():
                out.append((*path, k))
                walk(v, (*path, k))
        elif isinstance(node, list):
            for i, v in enumerate(node):
                out.append((*path, i))
                walk(v, (*path, i))

    walk(header, ())
    return out


def set_path(node, path: tuple, value, delete: bool) -> None:
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value


@st.composite
def mutate_header(draw, data: bytes) -> bytes:
    head, header, payload = split(data)
    paths = header_paths(header)
    path = draw(st.sampled_from(paths))
    delete = isinstance(path[-1], str) and draw(st.booleans())
    set_path(header, path, draw(JSON_VALUES), delete)
    return join(head, header, payload, fix_sha=path != ("payload_sha256",))


@st.composite
def mutate_rows(draw, data: bytes) -> bytes:
    """An array gets more or fewer rows (others unchanged); table and checksum consistent."""
    head, header, payload = split(data)
    arrays = arrays_of(header, payload, head)
    name = draw(st.sampled_from(sorted(arrays)))
    a = arrays[name]
    rows = draw(st.integers(min_value=0, max_value=len(a) + 3))
    if rows <= len(a):
        arrays[name] = a[:rows]
    else:
        extra = draw(
            st.binary(
                min_size=(rows - len(a)) * a[:1].nbytes if len(a) else 0,
                max_size=(rows - len(a)) * a[:1].nbytes if len(a) else 0,
            )
        )
        if len(a):
            arrays[name] = np.concatenate([a, np.frombuffer(extra, a.dtype).reshape(-1, *a.shape[1:])])
    return join(head, header, repack(header, arrays, head))


@st.composite
def mutate_shape(draw, data: bytes) -> bytes:
    """An array's bytes read with another shape (columns, dimensions, dtype)."""
    head, header, payload = split(data)
    arrays = arrays_of(header, payload, head)
    name = draw(st.sampled_from(sorted(arrays)))
    a = arrays[name]
    how = draw(st.sampled_from(["flat", "cols", "dtype", "3d"]))
    if how == "flat":
        a = a.reshape(-1)
    elif how == "cols" and a.size:
        cols = draw(st.sampled_from([c for c in (1, 2, 3, 6, 9) if a.size % c == 0]))
        a = a.reshape(-1, cols)
    elif how == "dtype":
        dt = draw(st.sampled_from(["<i4", "<f4", "<f8", "<i8", "<u2", "|i1"]))
        raw = a.tobytes()
        a = np.frombuffer(raw[: len(raw) - len(raw) % np.dtype(dt).itemsize], dt)
    elif how == "3d":
        a = a.reshape(1, *a.shape)
    arrays[name] = a
    return join(head, header, repack(header, arrays, head))


def _special(dtype: np.dtype) -> st.SearchStrategy:
    if dtype.kind == "f":
        return st.one_of(
            st.floats(allow_nan=True, allow_infinity=True, width=dtype.itemsize * 8),
            st.sampled_from([0.0, -0.0, 1e-300, 2.0, 2.0001, -2.0001, 0.2, 0.25, 0.2500001, 1e10]),
        )
    info = np.iinfo(dtype)
    edges = [v for v in (0, -1, 1, 2, int(info.min), int(info.max), 2**14, -(2**14) - 1) if info.min <= v <= info.max]
    return st.one_of(st.integers(min_value=int(info.min), max_value=int(info.max)), st.sampled_from(edges))


@st.composite
def mutate_value(draw, data: bytes) -> bytes:
    """One element of one array set to another value (checksum recomputed)."""
    head, header, payload = split(data)
    arrays = arrays_of(header, payload, head)
    names = sorted(n for n, a in arrays.items() if a.size)
    if not names:
        return data
    name = draw(st.sampled_from(names))
    a = arrays[name].copy()
    flat = a.reshape(-1)
    i = draw(st.integers(min_value=0, max_value=len(flat) - 1))
    flat[i] = draw(_special(a.dtype))
    if draw(st.booleans()) and name.endswith("index") and len(a) > 1:  # or copy a whole row: duplicate cells
        j = draw(st.integers(min_value=0, max_value=len(a) - 1))
        a[j] = a[i // a.shape[1]]
    arrays[name] = a
    return join(head, header, repack(header, arrays, head))


@st.composite
def mutate_bytes(draw, data: bytes) -> bytes:
    """Raw byte edits anywhere: flips, a cut, bytes inserted; optionally a fresh checksum."""
    b = bytearray(data)
    for _ in range(draw(st.integers(min_value=1, max_value=4))):
        kind = draw(st.sampled_from(["flip", "cut", "insert"]))
        pos = draw(st.integers(min_value=0, max_value=max(len(b) - 1, 0)))
        if kind == "flip" and b:
            b[pos] ^= draw(st.integers(min_value=1, max_value=255))
        elif kind == "cut":
            del b[pos : pos + draw(st.integers(min_value=1, max_value=16))]
        else:
            b[pos:pos] = draw(st.binary(min_size=1, max_size=8))
    out = bytes(b)
    if draw(st.booleans()):
        with contextlib.suppress(Exception):  # the edit broke the header: keep the raw bytes
            head, header, payload = split(out)
            header["payload_bytes"] = len(payload)
            out = join(head, header, payload)
    return out


@st.composite
def mutated_file(draw) -> tuple[str, bytes]:
    name = draw(st.sampled_from(sorted(bases())))
    data = bases()[name]
    kinds = {
        "header": mutate_header,
        "rows": mutate_rows,
        "shape": mutate_shape,
        "value": mutate_value,
        "bytes": mutate_bytes,
    }
    steps = draw(st.lists(st.sampled_from(sorted(kinds)), min_size=1, max_size=3))
    for kind in steps:
        try:
            data = draw(kinds[kind](data))
        except Exception:  # noqa: BLE001 - an earlier step broke the file beyond this one's reach
            break  # (the next step cannot parse it): test it as it is
    return "+".join(steps), data


# ---------------------------------------------------------------------------- the property
def validate(m: NdtOmMap, data: bytes, path: Path) -> None:
    """A loaded map holds what its file says, within range, and saves back unchanged."""
    head, header, payload = split(data)
    arrays = arrays_of(header, payload, head)
    cfg = m.config
    lo, hi = np.array(m.layout.lo), np.array(m.layout.hi)
    assert math.isfinite(m.resolution) and m.resolution > 0
    assert m.occupancy_enabled == header["occupancy"] and m.resolution == header["resolution"]

    k = m.known_cells()
    idx, lod = k["index"], k["logodds"]
    assert ((idx >= lo) & (idx < hi)).all()
    assert np.isfinite(lod).all() and (lod >= np.float32(cfg.logodds_min)).all()
    assert (lod <= np.float32(cfg.logodds_max)).all() and ((k["p_occ"] >= 0) & (k["p_occ"] <= 1)).all()
    # exactly the file's known cells (log-odds 0 reads as unknown), with their values
    fo, fl = arrays["occ_index"].astype(np.int64), arrays["occ_logodds"]
    keep = fl != 0
    order = np.lexsort(fo[keep].T[::-1])
    assert np.array_equal(idx, fo[keep][order])
    assert np.array_equal(lod.astype(np.float32), fl[keep][order])

    g = m.gaussians(min_points=1, min_probability=0.0)
    fg = arrays["g_index"].astype(np.int64)
    gorder = np.lexsort(fg.T[::-1])
    assert np.array_equal(g["index"], fg[gorder]) and np.array_equal(g["n"], arrays["g_n"][gorder])
    assert np.isfinite(g["mean"]).all() and np.isfinite(g["cov"]).all()
    rel = g["mean"] - m.cell_center(g["index"])
    assert (np.abs(rel) <= 0.5 * m.resolution * (1 + 1e-6) + 1e-9 * np.abs(m.cell_center(g["index"]))).all()
    assert np.allclose(g["cov"], np.swapaxes(g["cov"], 1, 2))
    if len(g["cov"]):
        ev = np.linalg.eigvalsh(g["cov"])
        assert (ev >= -1e-6 * np.maximum(np.abs(ev).max(axis=1, keepdims=True), 1e-30)).all()
    assert 0 <= len(m) <= len(g["n"])
    m.gaussians(), m.memory_report()

    back = NdtOmMap.load(m.save(path.with_name("back.ndtom")))
    a, b = m.state(), back.state()
    for key in a:
        assert a[key].shape == b[key].shape and a[key].tobytes() == b[key].tobytes(), key
    del back


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    derandomize=EXAMPLES <= 500,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
@given(case=mutated_file())
def test_mutated_map_files_raise_map_file_error_or_load_valid(case):
    kinds, data = case
    note(f"mutations: {kinds}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.ndtom"
        path.write_bytes(data)
        try:
            m = NdtOmMap.load(path)
        except MapFileError:
            try:  # the header alone may still be fine; when it is not, the same error type
                read_header(path)
            except MapFileError:
                pass
            OUTCOMES["MapFileError"] += 1
            return
        except MapMemoryError:  # a valid file bigger than the budget: a clear refusal
            OUTCOMES["MapMemoryError"] += 1
            return
        try:
            validate(m, data, path)
        finally:
            del m
            gc.collect()
        OUTCOMES["loaded and valid"] += 1


def test_base_files_load_and_validate(tmp_path):
    for name, data in bases().items():
        path = tmp_path / f"{name}.ndtom"
        path.write_bytes(data)
        m = NdtOmMap.load(path)
        validate(m, data, path)
        del m


def teardown_module(module):
    if OUTCOMES:
        print(f"\nmap file fuzz ({EXAMPLES} examples asked): {dict(OUTCOMES)}")


@pytest.mark.parametrize("name", ["ndtom", "rndt", "ndtom v7", "ndtom v5", "ndtom v4", "ndtom v3", "rndt v3"])
def test_every_single_row_cut_is_a_map_file_error(tmp_path, name):
    """Deterministic companion: each array one row short (checksum valid) is refused."""
    head, header, payload = split(bases()[name])
    for target in [e["name"] for e in header["arrays"]]:
        h = json.loads(json.dumps(header))
        arrays = arrays_of(h, payload, head)
        if not len(arrays[target]):
            continue
        arrays[target] = arrays[target][:-1]
        path = tmp_path / f"{target}.ndtom"
        path.write_bytes(join(head, h, repack(h, arrays, head)))
        with pytest.raises(MapFileError, match="rows"):
            NdtOmMap.load(path)


# ---------------------------------------------------------------------------- the codec alone
_SPECIAL = [0.0, -0.0, np.nan, -np.nan, np.inf, -np.inf, 5e-324, -5e-324, 2.2250738585072014e-308, 1.0, -1e300]
_F64 = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64), st.sampled_from(_SPECIAL))


@st.composite
def codec_arrays(draw) -> dict[str, np.ndarray]:
    """Arrays of every name the codec knows, of one row count per group: sorted distinct
    cells, float64 values of any bits (NaN with payloads, -0.0, infinities, subnormals),
    rows of the scatter all zero or zero but for one -0.0."""

    def cells(n: int) -> np.ndarray:
        base = draw(st.sampled_from([0, -(2**31) + 1, 2**31 - 2**20 - 1, -12345]))  # (the key bounds: |lo| < 2**31)
        rows = draw(st.sets(st.tuples(st.integers(0, 2**20), st.integers(0, 300), st.integers(0, 300)), max_size=n))
        return (np.array(sorted(rows), np.int64).reshape(-1, 3) + base).astype(np.int32)

    occ = cells(draw(st.integers(0, 40)))
    g = cells(draw(st.integers(0, 40)))
    k, n = len(occ), len(g)

    def f64(shape) -> np.ndarray:
        a = np.array(draw(st.lists(_F64, min_size=math.prod(shape), max_size=math.prod(shape))), np.float64)
        bits = a.view(np.uint64)
        bits ^= np.array(draw(st.lists(st.integers(0, 7), min_size=a.size, max_size=a.size)), np.uint64)  # NaN payloads
        return a.reshape(shape)

    scatter = f64((n, 6))
    for r in range(n):
        how = draw(st.sampled_from(["values", "zeros", "minus zero"]))
        if how != "values":
            scatter[r] = 0.0
        if how == "minus zero":
            scatter[r, draw(st.integers(0, 5))] = -0.0
    ints = st.integers(-(2**31), 2**31 - 1)
    return {
        "occ_index": occ,
        "occ_logodds": np.array(draw(st.lists(st.floats(width=32, allow_nan=True), min_size=k, max_size=k)), "<f4"),
        "g_index": g,
        "g_n": np.array(draw(st.lists(ints, min_size=n, max_size=n)), "<i4"),
        "g_mean_rel": f64((n, 3)),
        "g_scatter": scatter,
        "g_erased_near": np.array(draw(st.lists(ints, min_size=n, max_size=n)), "<i4"),
        "g_ndt_state": np.array(draw(st.lists(st.integers(0, 255), min_size=n, max_size=n)), "|u1"),
    }


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    derandomize=EXAMPLES <= 500,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(arrays=codec_arrays(), version=st.sampled_from([4, 5, mapcodec.VERSION]))
def test_codec_round_trip_is_bit_for_bit(arrays, version):
    """Whatever bits the arrays hold, encode then decode gives them back exactly (dtype,
    shape and every byte, NaN payloads and -0.0 included), in every compressed version."""
    table, frames = mapcodec.encode(arrays, version)
    assert [e["name"] for e in table] == list(arrays)
    assert {e["name"]: e["coding"] for e in table if e["name"] in mapcodec.CODING} == mapcodec.CODINGS[version]
    payload = b"".join(frames)
    mapcodec.check_table(table, len(payload), _raise, version)
    back = mapcodec.decode(table, payload, _raise)
    for name, a in arrays.items():
        b = back[name]
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name


@settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=EXAMPLES <= 500)
@given(
    arrays=codec_arrays(),
    scale=st.sampled_from([0.05, 0.2, 0.3, 1.0, 7.5]),
    where=st.lists(st.floats(-0.5, 0.5), min_size=1, max_size=120),
    terms=st.lists(st.floats(-1e6, 1e6, width=64) | st.sampled_from([0.0, -0.0, 1e-300, 5e-324]), min_size=1),
)
def test_compact_codec_rounds_within_its_bounds(arrays, scale, where, terms):
    """Format 7: every array but the Gaussians' means and scatter bit for bit; each mean
    (inside its cell, +-scale/2, the cell's edges among them) within scale / 131070 and still
    inside; each scatter term its float32 rounding (zero rows, -0.0 and subnormals too)."""
    n = len(arrays["g_index"])
    arrays["g_mean_rel"] = np.resize(np.array(where + [-0.5, 0.5]) * scale, (n, 3))
    scatter = np.resize(np.array(terms, np.float64), (n, 6))
    scatter[np.all(arrays["g_scatter"].view(np.uint64) == 0, axis=1)] = 0.0  # the strategy's rows of zeros
    arrays["g_scatter"] = scatter
    table, frames = mapcodec.encode(arrays, mapcodec.COMPACT_VERSION, scale)
    payload = b"".join(frames)
    mapcodec.check_table(table, len(payload), _raise, mapcodec.COMPACT_VERSION)
    back = mapcodec.decode(table, payload, _raise)
    for name, a in arrays.items():
        b = back[name]
        assert a.dtype == b.dtype and a.shape == b.shape, name
        if name == "g_mean_rel":
            assert (np.abs(b - a) <= scale / 131070 * (1 + 1e-9)).all() and (np.abs(b) <= scale / 2).all()
        elif name == "g_scatter":
            assert b.tobytes() == a.astype(np.float32).astype(np.float64).tobytes()
        else:
            assert a.tobytes() == b.tobytes(), name


def test_compact_codec_refuses_what_it_cannot_round():
    """Means that are not finite, scatter past float32's range, or no scale: a ValueError
    before anything is written (a file that would not load again is never made)."""
    good = {"g_mean_rel": np.zeros((2, 3)), "g_scatter": np.ones((2, 6))}
    for arrays, text in (
        ({**good, "g_mean_rel": np.array([[0.0, np.nan, 0.0], [0.0, 0.0, 0.0]])}, "not finite"),
        ({**good, "g_scatter": np.full((2, 6), 1e39)}, "float32's range"),
    ):
        with pytest.raises(ValueError, match=text):
            mapcodec.encode(arrays, mapcodec.COMPACT_VERSION, 0.2)
    for scale in (None, 0.0, float("nan")):
        with pytest.raises(ValueError, match="needs the resolution"):
            mapcodec.encode(good, mapcodec.COMPACT_VERSION, scale)


def _logodds(kind: str, n: int = 300_000) -> np.ndarray:
    """float32 rows as the ``values`` coding meets them: a few hundred repeated values (more
    than its table holds), rare others (0.0, -0.0, NaN payloads among them), or all distinct."""
    rng = np.random.default_rng(5)
    if kind == "distinct":
        return rng.standard_normal(n).astype("<f4")
    common = (np.arange(400, dtype=np.float32) * np.float32(-0.04)).astype("<f4")
    a = common[np.minimum(rng.geometric(0.02, n) - 1, 399)]
    bits = a.view(np.uint32)
    rare = rng.choice(n, n // 50, replace=False)
    bits[rare] = rng.integers(0, 2**32, len(rare), dtype=np.uint64).astype(np.uint32)
    bits[rare[:8]] = [0, 0x80000000, 0x7FC00001, 0xFFC00002, 0x7F800000, 0, 0x80000000, 1]
    return a


@pytest.mark.parametrize("kind", ["repeated", "distinct"])
def test_codec_values_coding_is_bit_for_bit_or_left_raw(kind):
    """Log-odds of a few hundred repeated values take a byte a row through the table (those
    it cannot hold, 0.0 and -0.0 and NaN payloads among them, escape bit for bit); values
    that do not repeat are left raw, never larger than format 5."""
    a = _logodds(kind)
    arrays = {"occ_logodds": a}
    table, frames = mapcodec.encode(arrays)
    payload = b"".join(frames)
    mapcodec.check_table(table, len(payload), _raise)
    assert mapcodec.decode(table, payload, _raise)["occ_logodds"].tobytes() == a.tobytes()
    v5 = sum(s["nbytes"] for s in mapcodec.encode(arrays, 5)[0][0]["streams"])
    if kind == "distinct":
        assert table[0]["coding"] == "raw" and len(payload) == v5
    else:
        codes, values, escaped = table[0]["streams"]
        assert table[0]["coding"] == "values" and values["raw_nbytes"] == 4 * 255
        assert len(a) // 50 < escaped["raw_nbytes"] // 4 < len(a) // 8  # the rare ones, and values past the table
        assert len(payload) < 0.8 * v5, (len(payload), v5)


def test_codec_leaves_out_rows_of_zero_scatter():
    """Format 5 stores a scatter row of zeros as one bit: a million Gaussians of one point
    (zero scatter) cost a few hundred bytes of scatter, where format 4 held their zeros."""
    n = 10**6
    scatter = np.zeros((n, 6))
    scatter[::1000] = np.random.default_rng(1).random((n // 1000 + (n % 1000 > 0), 6))
    scatter[7, 3] = -0.0  # not zero bits: kept
    arrays = {"g_scatter": scatter}
    sizes = {v: sum(s["nbytes"] for s in mapcodec.encode(arrays, v)[0][0]["streams"]) for v in (4, mapcodec.VERSION)}
    table, frames = mapcodec.encode(arrays)
    back = mapcodec.decode(table, b"".join(frames), _raise)["g_scatter"]
    assert back.tobytes() == scatter.tobytes()
    assert sizes[mapcodec.VERSION] < 60 * 1001 + 1000, sizes  # the kept rows (~48 B each) and the bits
    assert sizes[mapcodec.VERSION] < sizes[4], sizes


@pytest.mark.parametrize("name", ["ndtom", "ndtom v7", "ndtom v3"])
def test_a_flipped_bit_in_the_header_is_corruption(tmp_path, name):
    """The header's own checksum: a bit flipped in the resolution (0.3 -> 0.7 read as valid,
    the map scaled 2.3x) or in the version is refused; a file without it (written before it
    existed) reads as before."""
    data = bases()[name]
    hlen = struct.unpack("<Q", data[12:20])[0]
    header = data[20 : 20 + hlen]
    at = header.index(b'"resolution": ') + len(b'"resolution": ')
    for pos, bit in ((20 + at, 0x04), (8, 0x01)):  # a digit of the resolution; the version's lowest bit
        bad = bytearray(data)
        bad[pos] ^= bit
        path = tmp_path / "bad.ndtom"
        path.write_bytes(bytes(bad))
        with pytest.raises(MapFileError, match="header checksum mismatch"):
            NdtOmMap.load(path)
        with pytest.raises(MapFileError, match="header checksum mismatch"):
            read_header(path)
    head, h, payload = split(data)
    h.pop("header_sha256")
    old = tmp_path / "old.ndtom"
    old.write_bytes(join(head, h, payload, fix_sha=False))
    assert "header_sha256" not in read_header(old) and NdtOmMap.load(old).scans_inserted > 0
