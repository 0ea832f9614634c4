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
from pathlib import Path
from typing import NoReturn

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
    for t in tiles or ():
        if Path(t).name != t or not (folder / t).is_file():
            bad(f"tile file {t!r} is missing from {folder}")
    return doc
