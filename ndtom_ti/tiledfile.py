"""A tiled map on disk: a folder of one map file per tile and a manifest naming them.

The tile files are ordinary map files (``mapfile``), each holding the known cells of one
tile (a cube of ``tile_cells`` cells a side on the global cell indices); the manifest
(``manifest.json``) says how the cells were shared (resolution, tile size, workers), how
many scans the tiles hold, and which file holds which tile (``tiles``, ``tile_ids``). A checkpoint
writes new tile files under new names, then the manifest (atomically), then removes the
files the old manifest named: a reader, or a run resumed after a crash, sees one
consistent set.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import NoReturn

import numpy as np

from . import mapfile
from .atomic import atomic_write
from .mapfile import MapFileError

MANIFEST = "manifest.json"
FORMAT = "ndtom-tiled"
VERSION = 1


def is_tiled(path: str | Path) -> bool:
    """Whether ``path`` is a tiled map's folder (it holds a manifest)."""
    p = Path(path)
    return p.is_dir() and (p / MANIFEST).is_file()


def not_tiled(path: str | Path) -> str:
    """Why the folder ``path`` is not read as a map."""
    return f"{path} is a folder without a {MANIFEST}: neither a map file nor a tiled map's folder"


def tile_name(tile: tuple[int, int, int], scans: int) -> str:
    """The file of tile ``tile`` (its indices) in a checkpoint of ``scans`` scans."""
    return f"tile_{tile[0]}_{tile[1]}_{tile[2]}-scan{scans}.ndtom"


def write_manifest(folder: str | Path, info: dict, tiles: list[tuple[str, tuple[int, int, int]]]) -> Path:
    """Write the manifest of ``folder`` (atomically) naming ``tiles`` ((file, tile indices)
    each), then delete the tile files it no longer names. ``info``: resolution, tile_cells,
    tile_size, workers, scans, complete."""
    folder = Path(folder)
    old = set(read_manifest(folder)["tiles"]) if is_tiled(folder) else set()
    tiles = sorted(tiles)
    doc = {
        "format": FORMAT,
        "version": VERSION,
        **info,
        "tiles": [name for name, _ in tiles],
        "tile_ids": [[int(x) for x in t] for _, t in tiles],
        # each file's payload digest: a tile file of another run (or checkpoint) is refused
        "tile_sha256": [mapfile.read_header(folder / name)["payload_sha256"] for name, _ in tiles],
    }
    text = json.dumps(doc, indent=1, sort_keys=True).encode()
    path = atomic_write(folder / MANIFEST, lambda fh: fh.write(text))
    for name in old - set(doc["tiles"]):
        (folder / name).unlink(missing_ok=True)
    return path


def read_manifest(folder: str | Path) -> dict:
    """The manifest of a tiled map's folder, checked; MapFileError when it is broken."""
    folder = Path(folder)
    path = folder / MANIFEST
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise MapFileError(f"{folder} is not a tiled map: it has no {MANIFEST}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapFileError(f"{path} cannot be read: {exc}") from None

    def bad(what: str) -> NoReturn:
        raise MapFileError(f"{path} is not a tiled map's manifest: {what}")

    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        bad(f"its format is not {FORMAT!r}")
    if doc.get("version") != VERSION:
        bad(f"version {doc.get('version')!r} (this ndtom_ti reads version {VERSION})")
    for key in ("workers", "tile_cells", "scans"):
        v = doc.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < (0 if key == "scans" else 1):
            bad(f"{key} must be a positive integer, got {v!r}")
    res = doc.get("resolution")
    if isinstance(res, bool) or not isinstance(res, (int, float)) or not math.isfinite(res) or res <= 0:
        bad(f"resolution must be a positive number, got {res!r}")
    tiles, ids = doc.get("tiles"), doc.get("tile_ids")
    if not isinstance(tiles, list) or not all(isinstance(t, str) for t in tiles):
        bad(f"tiles must be a list of file names, got {tiles!r}")
    if (
        not isinstance(ids, list)
        or len(ids) != len(tiles)
        or not all(isinstance(i, list) and len(i) == 3 and all(type(x) is int for x in i) for i in ids)
    ):
        bad(f"tile_ids must give the 3 integer indices of each tile, got {ids!r}")
    if len({tuple(i) for i in ids}) != len(ids):
        bad("tile_ids names a tile twice")
    digests = doc.get("tile_sha256")  # (manifests written before 2026-11-29 have none)
    if digests is not None and (
        not isinstance(digests, list) or len(digests) != len(tiles) or not all(isinstance(d, str) for d in digests)
    ):
        bad("tile_sha256 must give a digest for each tile file")
    for t in tiles or ():
        if Path(t).name != t or not (folder / t).is_file():
            raise MapFileError(
                f"the tiled map {folder} is incomplete: its tile file {t} is missing (the {MANIFEST} names it)"
            )
    return doc


def read_tile(folder: str | Path, doc: dict, i: int) -> tuple[dict, dict]:
    """Tile ``i`` of the manifest ``doc`` of ``folder``: (settings, cell arrays) as
    ``mapfile.read`` gives them, checked against the manifest: its digest, resolution, scans
    and points, the job's map options, and its cells inside the tile the manifest names.
    Any fault: MapFileError naming the file."""
    folder = Path(folder)
    name, tile = doc["tiles"][i], doc["tile_ids"][i]
    path = folder / name
    settings, arrays = mapfile.read(path)

    def bad(what: str) -> NoReturn:
        raise MapFileError(f"{path} does not belong to the tiled map {folder}: {what}")

    digests = doc.get("tile_sha256")
    if digests is not None and mapfile.read_header(path)["payload_sha256"] != digests[i]:
        bad(f"it is not the file its {MANIFEST} names (another run's or checkpoint's tile)")
    for what, mine, theirs in (
        ("resolution", settings["resolution"], doc["resolution"]),
        ("scans", settings["scans_inserted"], doc["scans"]),
        ("points", settings["points_inserted"], doc.get("points", settings["points_inserted"])),
    ):
        if mine != theirs:
            bad(f"it holds {what} {mine}, the {MANIFEST} {theirs}")
    job = doc.get("job") or {}
    if "config" in job and json.loads(json.dumps(settings["config"].to_dict())) != job["config"]:
        bad(f"it was mapped with other map options than the {MANIFEST}'s run")
    if "occupancy" in job and settings["occupancy_enabled"] != job["occupancy"]:
        bad(f"its occupancy setting differs from the {MANIFEST}'s run")
    md = settings["metadata"]  # the run's record in the tile (the mapping loop's metadata)
    if "recording" in job and isinstance(md.get("source"), str) and md["source"] != job["recording"]:
        bad(f"it is a map of {md['source']}, the {MANIFEST}'s run of {job['recording']}")
    options = md.get("options")
    if "selection" in job and isinstance(options, dict):
        mine = {k: v for k, v in options.items() if k not in ("max_scans", "end")}
        if json.loads(json.dumps(mine)) != job["selection"]:
            bad(f"it was mapped with another selection of scans than the {MANIFEST}'s run")
    cells = doc["tile_cells"]
    for key in ("occ_index", "g_index"):
        idx = arrays[key]
        if len(idx) and (idx.astype(np.int64) // cells != np.asarray(tile, np.int64)).any():
            bad(f"it holds cells outside tile {tuple(tile)} ({cells} cells a side), the tile the {MANIFEST} names")
    return settings, arrays


def read_tiles(folder: str | Path, doc: dict) -> Iterator[tuple[dict, dict]]:
    """Every tile of ``folder`` in turn (``read_tile``), each also checked against the first:
    the same map options, so that they make one map."""
    first: dict | None = None
    for i, name in enumerate(doc["tiles"]):
        settings, arrays = read_tile(folder, doc, i)
        if first is None:
            first = settings
        elif settings["config"] != first["config"] or settings["occupancy_enabled"] != first["occupancy_enabled"]:
            raise MapFileError(
                f"{Path(folder) / name} does not belong to the tiled map {folder}: it was mapped with other map "
                f"options than {doc['tiles'][0]}"
            )
        yield settings, arrays


_CHECKED: set = set()  # folders whose tiles were read whole and found sound, as they were then


def check_tiles(folder: str | Path, doc: dict) -> None:
    """Read every tile of ``folder`` and check it (``read_tiles``); MapFileError naming the
    first bad file. Once a folder passed, the same files (names, sizes, times) are not read
    again in this process."""
    folder = Path(folder)
    stats = tuple((n, (folder / n).stat().st_size, (folder / n).stat().st_mtime_ns) for n in doc["tiles"])
    key = (str(folder.resolve()), stats, (folder / MANIFEST).stat().st_mtime_ns)
    if key in _CHECKED:
        return
    for _ in read_tiles(folder, doc):
        pass
    _CHECKED.add(key)
