"""Writing a file so that a crash never leaves a broken or half file in its place."""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_target(path: str | Path) -> Path:
    """The path ``atomic_write`` replaces: a symbolic link is followed (the file it points
    to is replaced and the link stays); an existing target that is not a regular file
    (folder, pipe, device, socket) is refused, since renaming over it would replace it."""
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"cannot write {path}: folder {directory} does not exist")
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return path
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(f"cannot write {path}: it is a folder")
    if not stat.S_ISREG(mode):
        raise OSError(f"cannot write {path}: it exists and is not a regular file (a pipe, device or socket)")
    return path


# Temporary files are ".NAME.XXXXXXXX.tmp" with NAME cut to this many bytes: a legal name of
# up to 255 bytes still gets a temporary name within the usual 255-byte limit.
_TMP_NAME_BYTES = 200
_STALE_SECONDS = 5.0  # a temporary untouched this long, and not locked, was left by a killed writer


# First bytes of recordings that an output must not replace, and what they are.
_HEADS = (
    (b"#ROSBAG", "it is a ROS1 bag"),
    (b"SQLite format 3", "it is an SQLite database (a ROS2 bag?)"),
    (b"\x89MCAP", "it is an MCAP file (a ROS2 bag?)"),
)
MAP_MAGIC = b"NDTOMTI\n"  # a map file's first bytes (mapfile.MAGIC)
MAP_KIND = "it is an ndtom map file"  # what kept_kind says of a map file


def kept_kind(path: str | Path) -> str | None:
    """Why ``path`` is something an output must never replace, as a clause ("it is a ROS1
    bag"): a recording (a bag by its first bytes, or any file of a ROS2 bag's folder) or a
    map file (MAP_KIND). None for anything else (or nothing there)."""
    path = Path(path)
    meta = path.parent / "metadata.yaml"
    try:
        if meta.is_file() and "rosbag2_bagfile_information" in meta.read_text(errors="replace")[:4096]:
            return f"it lies inside the ROS2 bag {path.parent}"
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return None
    if head.startswith(MAP_MAGIC):
        return MAP_KIND
    return next((why for start, why in _HEADS if head.startswith(start)), None)


def temp_prefix(path: Path) -> str:
    """The prefix of ``path``'s temporary files (``tempfile.mkstemp``): a dot and its name
    cut to _TMP_NAME_BYTES bytes of UTF-8 (whole characters)."""
    name = path.name.encode("utf-8", "surrogateescape")[:_TMP_NAME_BYTES].decode("utf-8", "ignore")
    return f".{name}."


def _lock(fd: int, blocking: bool) -> bool:
    """An exclusive flock on ``fd`` (True), or False where it is held or flock is missing."""
    try:
        import fcntl
    except ImportError:  # (not POSIX: no cleaning of stale temporaries)
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
    except OSError:
        return False
    return True


def _remove_stale(directory: Path, prefix: str, own: str) -> None:
    """Delete temporaries of the same target that a killed save left behind: each writer holds
    a lock on its temporary while it writes, so one that is not locked and not touched for a
    while belongs to nobody."""
    now = time.time()
    try:
        names = [n for n in os.listdir(directory) if n.startswith(prefix) and n.endswith(".tmp") and n != own]
    except OSError:
        return
    for name in names:
        if len(name) != len(prefix) + 8 + 4:  # mkstemp's 8 random characters and ".tmp"
            continue
        p = directory / name
        with contextlib.suppress(OSError):
            fd = os.open(p, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
            try:
                st = os.fstat(fd)
                if stat.S_ISREG(st.st_mode) and now - st.st_mtime > _STALE_SECONDS and _lock(fd, False):
                    os.unlink(p)
            finally:
                os.close(fd)


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], object]) -> Path:
    """Write ``path`` through ``write(fh)`` into a temporary file in the same folder,
    fsync it, then rename it over ``path``: readers see the old file or the new one.
    Symbolic links and targets that are not regular files: see ``check_target``. A save
    that succeeds removes the temporaries of the same target that killed saves left."""
    path = check_target(path)
    directory = path.parent if str(path.parent) else Path(".")
    prefix = temp_prefix(path)
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=directory)
    _lock(fd, True)  # held until the file is closed: a cleaner leaves it alone meanwhile
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
            os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the file the usual mode
            os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _remove_stale(directory, prefix, os.path.basename(tmp))
    return path
