"""Taichi 1.7.4's CPU memory pool made one chunk of a chosen size (README "Memory").

Sparse nodes on the CPU come from a host pool that maps chunks of
``UnifiedAllocator::default_allocator_size`` (a C++ static, 1 GiB). In Taichi 1.7.4 every
chunk after the first is handed out past its end (memory corruption or a crash), so a
map must never need a second chunk. This module sets that static before ``ti.init``, so
the first and only chunk holds the whole budget. It relies on this exact wheel's
internals, so each step is guarded: the Taichi version, the symbol found once in the
library's symbol table, the value reading exactly 1 GiB before the write, and after
``ti.init`` a new mapping of the requested size. Any guard that fails leaves Taichi as
it is and says why; the caller then keeps the budget within the 1 GiB chunk.
"""

from __future__ import annotations

import ctypes
import mmap
import os
import struct
import sys
from pathlib import Path

SYMBOL = b"_ZN6taichi4lang16UnifiedAllocator22default_allocator_sizeE"
DEFAULT_CHUNK = 1 << 30
TESTED_VERSION = (1, 7, 4)


class GuardFailed(RuntimeError):
    """The workaround cannot be applied safely here (the message says why)."""


def physical_memory() -> int:
    """Bytes of memory this process may use: physical memory, or a lower cgroup limit."""
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            total = int(text)
    return total


def _library() -> Path:
    import taichi

    found = sorted((Path(taichi.__file__).parent / "_lib" / "core").glob("taichi_python*.so"))
    if len(found) != 1:
        raise GuardFailed(f"expected one taichi_python library, found {len(found)}")
    return found[0].resolve()


def _symbol_offset(lib: Path) -> int:
    """Offset of SYMBOL from the library's load base, read from its ELF .symtab. The file is
    mapped, not read: its symbol and string tables are ~28 MB (reading them took ~35 ms of
    ``init``)."""
    import numpy as np

    entry = np.dtype(
        [("name", "<u4"), ("info", "u1"), ("other", "u1"), ("shndx", "<u2"), ("value", "<u8"), ("size", "<u8")]
    )
    with open(lib, "rb") as fh:
        if os.fstat(fh.fileno()).st_size < 64:
            raise GuardFailed(f"{lib.name} is not a 64-bit little-endian ELF library")
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    with mm:
        eh = mm[:64]
        if eh[:4] != b"\x7fELF" or eh[4] != 2 or eh[5] != 1:
            raise GuardFailed(f"{lib.name} is not a 64-bit little-endian ELF library")
        (shoff,) = struct.unpack_from("<Q", eh, 0x28)
        shentsize, shnum, _ = struct.unpack_from("<HHH", eh, 0x3A)
        raw = mm[shoff : shoff + shentsize * shnum]
        if shentsize < 64 or len(raw) != shentsize * shnum:
            raise GuardFailed(f"{lib.name} has a truncated section table")
        # (name, type, flags, addr, offset, size, link, info, align, entsize)
        secs = [struct.unpack_from("<IIQQQQIIQQ", raw, i * shentsize) for i in range(shnum)]
        symtabs = [s for s in secs if s[1] == 2]  # SHT_SYMTAB
        if len(symtabs) != 1 or not 0 <= symtabs[0][6] < shnum:
            raise GuardFailed(f"{lib.name} has no symbol table (stripped)")
        sym, strs = symtabs[0], secs[symtabs[0][6]]
        if sym[4] + sym[5] > len(mm) or strs[4] + strs[5] > len(mm):
            raise GuardFailed(f"{lib.name}'s symbol tables lie past its end")
        offsets, i = [], mm.find(SYMBOL + b"\0", strs[4], strs[4] + strs[5])
        while i >= 0:  # a name may also end a longer string (shared string tails)
            offsets.append(i - strs[4])
            i = mm.find(SYMBOL + b"\0", i + 1, strs[4] + strs[5])
        syms = np.frombuffer(mm, entry, count=sym[5] // entry.itemsize, offset=sym[4])
        hit = syms[np.isin(syms["name"], offsets) & (syms["size"] == 8) & (syms["info"] & 0xF == 1)]  # 8-byte objects
        del syms  # (the map closes only once no array views it)
    if len(hit) != 1:
        raise GuardFailed(f"symbol UnifiedAllocator::default_allocator_size found {len(hit)} times in {lib.name}")
    # The section holding it must be writable data (SHF_WRITE), not code or read-only data.
    shndx = int(hit[0]["shndx"])
    if not (0 < shndx < shnum and secs[shndx][2] & 1):
        raise GuardFailed("UnifiedAllocator::default_allocator_size is not in a writable section")
    return int(hit[0]["value"])


def _address(lib: Path, offset: int) -> int:
    """The address of ``offset`` in the loaded library, checked to lie in one of its
    writable mappings (so reading it cannot fault)."""
    base, writable = None, []
    for line in Path("/proc/self/maps").read_text().splitlines():
        parts = line.split(maxsplit=5)
        if len(parts) == 6 and parts[5].endswith(lib.name) and Path(parts[5]).resolve() == lib:
            a, b = (int(x, 16) for x in parts[0].split("-"))
            if int(parts[2], 16) == 0 and base is None:
                base = a
            if parts[1].startswith("rw"):
                writable.append((a, b))
    if base is None:
        raise GuardFailed(f"{lib.name} is not mapped in this process")
    addr = base + offset
    if not any(a <= addr and addr + 8 <= b for a, b in writable):
        raise GuardFailed("UnifiedAllocator::default_allocator_size is not in a writable mapping of the library")
    return addr


def anonymous_mappings() -> dict[int, int]:
    """Start -> length of this process's anonymous read-write mappings."""
    out = {}
    for line in Path("/proc/self/maps").read_text().splitlines():
        parts = line.split()
        if len(parts) == 5 and parts[1].startswith("rw"):
            a, b = (int(x, 16) for x in parts[0].split("-"))
            out[a] = b - a
    return out


def chunk_size_cell() -> ctypes.c_uint64:
    """The static itself, checked: Linux x86-64/arm64, Taichi 1.7.4, found once, 1 GiB."""
    if not sys.platform.startswith("linux"):
        raise GuardFailed(f"the CPU pool can only be resized on Linux (this is {sys.platform})")
    import taichi as ti

    if tuple(ti.__version__) != TESTED_VERSION:
        raise GuardFailed(f"taichi {'.'.join(map(str, ti.__version__))} is not the tested 1.7.4")
    lib = _library()
    cell = ctypes.c_uint64.from_address(_address(lib, _symbol_offset(lib)))
    if cell.value != DEFAULT_CHUNK:
        raise GuardFailed(f"UnifiedAllocator::default_allocator_size reads {cell.value}, not 1 GiB")
    return cell


def address_space_for(size: int) -> bool:
    """Whether Linux gives this process ``size`` bytes of address space in one mapping (a
    reservation with no access: nothing is committed). Taichi's pool maps its chunk so;
    one it is refused leaves Taichi half started, which crashed the process at exit."""
    try:
        m = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS, prot=0)
    except (OSError, OverflowError, ValueError):
        return False
    m.close()
    return True


def advise_huge_pages(before: dict[int, int], least: int = DEFAULT_CHUNK) -> int:
    """Ask Linux for transparent huge pages on the pool chunk(s) Taichi mapped since
    ``before`` (anonymous mappings of at least ``least`` bytes). Nodes are handed out
    from the chunk in order and touched on first use: on 4 KiB pages every page costs a
    fault (the zero page, then a copy on the first write with a TLB shootdown to the other
    threads), and the tree walks of a scan's updates miss the TLB. Advisory: where THP is
    off, or the call is refused, nothing changes. Returns the bytes advised."""
    advice = getattr(mmap, "MADV_HUGEPAGE", None)
    if advice is None or not sys.platform.startswith("linux"):
        return 0
    libc = ctypes.CDLL(None, use_errno=True)
    libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    libc.madvise.restype = ctypes.c_int
    done = 0
    for start, length in anonymous_mappings().items():
        if start not in before and length >= least and libc.madvise(start, length, advice) == 0:
            done += length
    return done
