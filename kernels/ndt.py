"""Taichi kernels of the NDT-OM update (method.md sections 2 and 3).

Per scan, in this order:
0. ``mark_gaussians`` (NDT miss model only): marks in the dense block the cells holding a
                     usable Gaussian, and the scan's hit cells.
1. ``rays``:         exact Amanatides-Woo traversal origin -> endpoint; integer count of
                     rays passing each cell: in a dense scan-local block over the scan's
                     cells (mode "dense" when it holds them all), in the tree past it
                     with a compact list of the cells touched there.
2. ``hits_count``:   points per hit cell (integer atomics), and a compact hit list.
3. ``hits_group``:   on the CPU, the points grouped by hit cell, for merge to sum each
                     cell's in their order in the scan (the map does not depend on the
                     threads); ``hits_dense`` instead of 2 and 3 when the block holds every
                     cell of the scan (the points grouped in the block). A GPU sums them by
                     float64 atomic adds instead (``hits_sum``).
4. ``merge``:        one thread per hit cell merges the scan's Gaussian into the cell's
                     record with the RCU (a new record for a cell's first points), then
                     applies eq. (12) to the cell and clears its ray count.
5. ``block_apply`` / ``apply_free``: eq. (12) once per cell that rays passed and no
                     endpoint hit, clamp, and reset of the Gaussian of a cell whose
                     log-odds fell to <= 0 (``apply_marked`` first, with the NDT miss
                     model: the summed terms of the block's marked cells).

This module holds the constants and the ti.funcs the kernels share (``device_funcs``:
closures over the process's storage, built once). The kernels are families of factories
cached per frozen config (kernels/families.py): ray traversal (kernels/trace.py), the
occupancy update (kernels/update.py), queries, export and load (kernels/io.py). Mode
switches are compiled in (``ti.static``); the map's slot, its resolution, sensor model and
Gaussian records are arguments, named or in typed groups (kernels/args.py), so nothing
recompiles per map.
"""

from types import SimpleNamespace

import taichi as ti
from taichi.lang import impl

from .layout import TILE_HASH, Storage

# Counter slots of the per-call int64 counter array.
C_HIT_CELLS = 0
C_TOUCHED = 1
C_VISITS = 2
C_ERASED = 3
C_EXPORT = 4
C_RECORDS = 5  # records in use (copied in and out by the caller)
C_BLOCK_CELLS = 6  # cells of the dense block that took the free-space update
C_HIT_PASSED = 7  # hit cells outside the block that rays also passed
C_FREE = 8  # records of erased Gaussians on the free stack (copied in and out by the caller)
C_NO_RECORD = 9  # hit cells merge left for want of a record (see merge's ``left``)
C_NDT_STILL = 10  # tree cells rays passed whose NDT miss terms all rounded to zero: not updated
C_SKIPPED = 14  # ray steps across the settled boxes (trace.settled_growth): cells passed, nothing to update
# Work queues of the queued loops (see make_queue): the next chunk to take, zero before the loop.
Q_RAYS = 11
Q_MERGE = 12
Q_APPLY = 13
COUNTERS = 16
HIT_CHUNKS = 1024  # chunks of points of hits_dense's prefix sum (Taichi runs <= 512 iterations on one thread)
# Taichi 1.7 gives each CPU thread at least this many iterations of a range-for, in one run.
TASK_ITERS = 512
# Sums that every thread adds to (visits, block cells) go to STRIPES copies of the
# counters, two 64-byte lines each, picked by the work item: one atomic counter shared by
# all threads costs ~15 ns per add on the CPU. ``total`` adds the copies up.
STRIPES = 64
CTR_SIZE = COUNTERS * (1 + STRIPES)


# Taichi's vector methods (`.all()`, `.any()`, `.dot()`, `@`) are functions that its front
# end parses and compiles again at every call site (~2-6 ms each of a first scan): written
# out where the code runs rarely or once a point. (In the per-scan loops they stay: written
# out, the ray loop ran 1.11x as long, for what LLVM made of the code around it.)
@ti.func
def inside(c, lo, hi):
    # Whether lo <= c < hi on every axis (3-vectors).
    return c[0] >= lo[0] and c[1] >= lo[1] and c[2] >= lo[2] and c[0] < hi[0] and c[1] < hi[1] and c[2] < hi[2]


@ti.func
def rolled(n):
    # Keeps LLVM from unrolling the loop this is in (n >= 0 counts something, so this never
    # runs): it unrolls a small loop without calls 8x, code that each process generates
    # again from the cached kernels at its first scan. Only where that cost no time a scan
    # (hits_dense's loops and prepare's ran 3-20% longer rolled, merge's sums ~10%).
    if ti.static(on_cpu()):
        if n < 0:
            print("negative count", n)


def total(ctr, which: int) -> int:
    """A counter's value: its slot plus its striped copies."""
    return int(ctr[which] + ctr[COUNTERS + which :: COUNTERS].sum())


# The occupancy tree's per-cell i32 ``ne``: the rays that passed the cell in this scan
# (low bits, zero between scans) and whether the cell may hold a Gaussian (NE_GAUSS: set by
# a hit and by loading, cleared when eq. (12) erases it): eq. (12) walks the Gaussian index
# tree only for such cells.
NE_GAUSS = 1 << 30
NE_COUNT = NE_GAUSS - 1

# The NDT miss model (config.MapConfig.miss_model == "ndt") sums each ray's log-odds change
# of a cell holding a Gaussian as a fixed-point integer: the sum is exact and does not depend
# on the order of the threads' atomic adds. 2^-32 per ray is far below f32 log-odds' ulp.
MISS_SCALE = float(2**32)
# Block entries set by mark_gaussians before the rays of the NDT miss model: a cell holding
# a usable Gaussian (MARK), and a cell that endpoints of the scan hit (HIT: it takes the hit
# update only, so rays passing it neither count nor test its Gaussian). Ray counts never
# reach them: u16 blocks take scans of at most U16_MAX_RAYS rays, i32 counts are >= 0.
# An i32 block's mark holds the Gaussian's record r as MARK_I32 - r, so that a ray visit
# reads the record without walking the index tree (u16 entries have no room for it).
MARK_U16 = 0xFFFF
HIT_U16 = 0xFFFE
U16_MAX_RAYS = 0xFFFD
MARK_I32 = -3
HIT_I32 = -2

# Finite in f32 too: kernel float literals are f32, and 1e300 would become inf, which
# fast math assumes never occurs. Ray parameters that matter are <= 1.
BIG = 1.0e30
# Ray parameters t in [0, 1] of two axes' crossings closer than this are settled by
# recomputing both by division. Summing steps strays < 1e-11 even over 10^5 steps.
TIE_MARGIN = 1.0e-9
# NDT miss model: a Gaussian that rays lower keeps its points until its cell's log-odds falls
# to <= logit(0.2) (ohm's covariance reset threshold), not 0 as in eq. (12): a thin static
# structure that rays between the lidar's rings passed is back with its points at its next
# hit (docs/quality.md). Cells at <= 0 are free all the same.
NDT_RESET = -1.3862943611198906
# NDT miss model: a hit lifts its cell to at least logit(0.88) = 2.0 (the default clamp)
# before the hit update: rays that lowered the cell since its last hit passed beside a
# surface that the hit says is still there, as between the rings past a shelf's edge.
NDT_RESTART = 2.0
# NDT miss model: except a cell's first points in a cell that rays had held at the free
# clamp (l_min): they start from -1, so that one look at a few points (an object crossing
# an aisle) leaves it free or barely occupied for the next rays to clear, as OctoMap's hits
# add to the free evidence before them. A far floor cell grazed by rays above it is lowered
# by eq. (12) (-0.04 a pass) and seldom reaches the clamp: its first point still restarts
# from NDT_RESTART (docs/quality.md).
NDT_RESTART_CLEAR = -1.0
# NDT miss model: what a record remembers of its cell's past, in the bits of rec_nbr above
# its count of erased neighbours (NBR_COUNT).
# NBR_FRESH: its points came since rays had held the cell at the free clamp, and the cell has
# not reached the occupied clamp since. A hit then adds to max(l, NDT_FRESH_FLOOR) instead of
# restarting from NDT_RESTART: an object seen in two or three looks as it crossed an aisle
# stays as weakly occupied as its points make it, as the first look left it (OctoMap adds its
# hits to such a free past); a surface there reaches the clamp as its points come.
# NBR_BACK: a hit brought the Gaussian back after rays had made its cell free (l <= 0): a
# surface seen by some looks and passed between the lidar's rings by others, as a rack's
# board or post is. Its misses count NDT_BACK_MISS of their sum, and rays keep its points at
# any log-odds, so that its next look brings it back with them (docs/quality.md).
NBR_FRESH = 1 << 20
NBR_BACK = 1 << 21
NBR_COUNT = NBR_FRESH - 1
NDT_FRESH_FLOOR = 0.0
NDT_BACK_MISS = 0.5
# NDT miss model: a Gaussian of which this many of the 26 neighbouring cells' Gaussians were
# erased by rays since its own last points stands for its whole cell: its inverse covariance
# reads NDT_WIDE x I (m^-2), so that every ray through the cell tests as one through its
# mean, until its next points. An object that left is erased by rays through its points
# cell by cell; the few cells of it that later rays pass beside the points (a look of 1-2
# scans at 3-10 points) go with the rest, whereas a thin static structure (a rack's board or
# post, whose cells rays pass between the lidar's rings) keeps its neighbours, or is hit
# again before six of them go (docs/quality.md).
NDT_ERASED_NEIGHBOURS = 6
NDT_WIDE = 1.0e-9
WIDE_ROW = (NDT_WIDE, 0.0, 0.0, NDT_WIDE, 0.0, NDT_WIDE)

i32_2d = ti.types.ndarray(dtype=ti.i32, ndim=2)
i32_1d = ti.types.ndarray(dtype=ti.i32, ndim=1)
i64_1d = ti.types.ndarray(dtype=ti.i64, ndim=1)
f64_2d = ti.types.ndarray(dtype=ti.f64, ndim=2)
f64_1d = ti.types.ndarray(dtype=ti.f64, ndim=1)
f32_1d = ti.types.ndarray(dtype=ti.f32, ndim=1)
i8_4d = ti.types.ndarray(dtype=ti.i8, ndim=4)
i8_3d = ti.types.ndarray(dtype=ti.i8, ndim=3)
u8_3d = ti.types.ndarray(dtype=ti.u8, ndim=3)
i8_1d = ti.types.ndarray(dtype=ti.i8, ndim=1)
i64_2d = ti.types.ndarray(dtype=ti.i64, ndim=2)
i32_3d = ti.types.ndarray(dtype=ti.i32, ndim=3)
u64_1d = ti.types.ndarray(dtype=ti.u64, ndim=1)


def cpu_threads() -> int:
    """Threads of Taichi's CPU range-for loops (1 on a GPU, where order does not matter)."""
    cfg = impl.current_cfg()
    return max(1, int(cfg.cpu_max_num_threads)) if cfg.arch in (ti.x64, ti.arm64) else 1


def make_queue(threads: int, cpu: bool = True):
    """The work queue of a loop over n items in chunks of ``chunk`` (a SimpleNamespace of
    ti.funcs). Taichi 1.7 splits a CPU range-for into one fixed, contiguous run per thread
    (its pass make_cpu_multithreaded_range_for), so a thread the OS starts late, or one
    whose run holds the longer rays, leaves the others idle at the loop's end. Here every
    thread instead takes the next chunk from a shared counter until none is left::

        for w in range(q.span(n, chunk)):
            j = q.first(w, ctr, Q_X)
            while j < q.end(n, chunk):
                for i in range(q.begin(j, n, chunk), q.stop(j, n, chunk)):
                    ...  # item i
                j = q.next(ctr, Q_X)

    Chunks are taken alternately from the first and the second half of the items, so that
    threads working at the same moment are half a scan apart (scans come in azimuth order)
    and rarely count into the same cells. On a GPU (cpu False) it is the plain loop: one
    thread per item. The counter slot must be zero before the loop. Every item is taken
    exactly once, in any order: what the loops sum is order-free.
    """
    TH = max(1, threads)

    @ti.func
    def span(n, chunk):
        # Iterations of the outer loop: one run of TASK_ITERS per thread, whose first starts the queue.
        out = n
        if ti.static(cpu):
            out = TASK_ITERS * TH
        return out

    @ti.func
    def end(n, chunk):
        # Chunk numbers run to an even count (the halves' order), past the last chunk on CPU.
        out = n
        if ti.static(cpu):
            out = 2 * ((n + 2 * chunk - 1) // (2 * chunk))
        return out

    @ti.func
    def first(w, ctr: ti.template(), q: ti.template()):
        out = w
        if ti.static(cpu):
            out = 1 << 30
            if w % TASK_ITERS == 0:
                out = ti.cast(ti.atomic_add(ctr[q], 1), ti.i32)
        return out

    @ti.func
    def next(ctr: ti.template(), q: ti.template()):
        out = 1 << 30
        if ti.static(cpu):
            out = ti.cast(ti.atomic_add(ctr[q], 1), ti.i32)
        return out

    @ti.func
    def begin(j, n, chunk):
        out = j
        if ti.static(cpu):
            half = (n + 2 * chunk - 1) // (2 * chunk)  # chunks in the first half
            out = ((j >> 1) + (j & 1) * half) * chunk
        return out

    @ti.func
    def stop(j, n, chunk):
        out = j + 1
        if ti.static(cpu):
            out = ti.min(n, begin(j, n, chunk) + chunk)
        return out

    return SimpleNamespace(span=span, end=end, first=first, next=next, begin=begin, stop=stop)


def on_cpu() -> bool:
    return impl.current_cfg().arch in (ti.x64, ti.arm64)


def device_funcs(f: Storage) -> SimpleNamespace:
    """The ti.funcs the kernel families share, bound to the storage ``f`` (built once)."""
    if getattr(f, "funcs", None) is not None:
        return f.funcs
    lo, ne, olm = f.lo, f.ne, f.olm
    gslot = f.gslot
    L = f.layout
    leaf = L.leaf
    region = L.region
    grid_lo = ti.Vector(list(L.lo))

    @ti.func
    def row(a: ti.template(), i) -> ti.types.vector(3, ti.i32):
        return ti.Vector([a[i, 0], a[i, 1], a[i, 2]], dt=ti.i32)

    @ti.func
    def picked(i, pick: ti.template(), npick, tail0) -> ti.i32:
        # The i-th record of a Picked (args.py): pick[:npick], then tail0 on.
        r = tail0 + i - npick
        if i < npick:
            r = pick[i]
        return r

    @ti.func
    def at(slot, c) -> ti.types.vector(4, ti.i32):
        return ti.Vector([slot, c[0], c[1], c[2]], dt=ti.i32)

    tiles = f.tiles
    h0, h1, h2 = TILE_HASH

    @ti.func
    def owner_spec(slot) -> ti.types.vector(3, ti.i64):
        # Map ``slot``'s owner (layout.TileOwner: tile size in cells, workers, this worker),
        # read once a kernel: owned() tests it per cell.
        return ti.Vector([tiles[slot, 0], tiles[slot, 1], tiles[slot, 2]], dt=ti.i64)

    @ti.func
    def owned(spec, c) -> ti.i32:
        # 1 when the map of owner_spec ``spec`` updates cell c: always, unless it is one
        # worker's part of a tiled map (the hash of TileOwner.owners, in int64).
        ok = 1
        if spec[1] > 1:
            t = c // ti.cast(spec[0], ti.i32)  # floor division on integers, as numpy's
            h = (ti.cast(t[0], ti.i64) * h0) ^ (ti.cast(t[1], ti.i64) * h1) ^ (ti.cast(t[2], ti.i64) * h2)
            ok = ti.i32(h % spec[1] == spec[2])
        return ok

    @ti.func
    def note_leaf(mark: ti.template(), slot, c, regions: ti.template(), leaves: ti.template(), which: ti.template()):
        # Called before a cell is written: counts the leaf (and region) it creates.
        b = at(slot, c // leaf)
        if mark[b] == 0:
            if ti.atomic_or(mark[b], 1) == 0:
                ti.atomic_add(leaves[slot, which], 1)
                r = (c - grid_lo) // region
                regions[slot, r[0], r[1], r[2]] = ti.i8(1)

    @ti.func
    def tally(ctr: ti.template(), which: ti.template(), key, v):
        ti.atomic_add(ctr[COUNTERS * (1 + (key & (STRIPES - 1))) + which], v)

    @ti.func
    def visit(slot, c, touched: ti.template(), cap, ctr: ti.template()) -> ti.i32:
        # Counts a ray passing cell c in the tree; returns the cell's NE_GAUSS bit.
        v = ti.atomic_add(ne[at(slot, c)], 1)
        if v & NE_COUNT == 0:
            t = ti.atomic_add(ctr[C_TOUCHED], 1)
            if t < cap:
                for a in ti.static(range(3)):
                    touched[t, a] = c[a]
        return v & NE_GAUSS

    @ti.func
    def next_t(c, step, rem, res, o, d):
        # Ray parameter of the next cell face on one axis (BIG once the axis is done).
        face = c + 1 if step > 0 else c
        return (ti.cast(face, ti.f64) * res - o) / d if rem > 0 else BIG

    SHIFT = leaf.bit_length() - 1  # leaf is a power of two

    queue = make_queue(cpu_threads(), on_cpu())

    @ti.func
    def free_update(
        slot, c, dl, g, l_min, l_max, l_reset, rec_n: ti.template(), ctr: ti.template(), rec_free: ti.template()
    ):
        # eq. (12) (or the NDT miss model) for a cell that rays passed and no endpoint hit:
        # dl is its log-odds change; reset of its Gaussian (g: NE_GAUSS set) at l <= l_reset
        # (eq. 12: 0; NDT miss model: NDT_RESET): its record goes on the free stack for the
        # next new Gaussian of any cell, so records follow the Gaussians alive, not all ever made.
        # Returns 1 when it erased a Gaussian.
        l = ti.min(ti.max(lo[at(slot, c)] + dl, l_min), l_max)
        lo[at(slot, c)] = l
        # A reset leaves nothing to erase: later passes skip the index tree until a hit
        # sets NE_GAUSS again. Stored beside lo, not in the branch: a store there inlines
        # Taichi's node allocator once more (one thread per cell here, no race).
        reset = l <= l_reset and g != 0
        v = ne[at(slot, c)]
        if reset:
            v &= NE_COUNT
        ne[at(slot, c)] = v
        erased = 0
        if reset:
            r = gslot[at(slot, c)] - 1
            if r >= 0:
                if rec_n[r] > 0:
                    erased = 1
                    # Mean and scatter are overwritten by the next first merge.
                    rec_n[r] = 0
                    ti.atomic_add(ctr[C_ERASED], 1)
                    gslot[at(slot, c)] = 0
                    rec_free[ti.cast(ti.atomic_add(ctr[C_FREE], 1), ti.i32)] = r
        return erased

    grid_hi = ti.Vector(list(L.hi))

    @ti.func
    def erased_beside(slot, c, rec_n: ti.template(), rec_nbr: ti.template(), rec_icov: ti.template(), minp):
        # NDT miss model: rays erased the Gaussian of cell c. Each of its 26 neighbours that
        # holds one counts it; at NDT_ERASED_NEIGHBOURS since its own last points, the
        # neighbour's rows read as NDT_WIDE (see there) until its next points.
        # A loop, not unrolled: 26 inlined copies of the tree lookups made every kernel that
        # erases compile for seconds, and erasing is rare.
        for q in range(27):
            nb = c + ti.Vector([q // 9 - 1, (q // 3) % 3 - 1, q % 3 - 1], dt=ti.i32)
            if q != 13:
                if inside(nb, grid_lo, grid_hi):
                    r = gslot[at(slot, nb)] - 1
                    # (a count already past the threshold stays there: the state bits above it)
                    if r >= 0 and rec_n[r] >= minp and rec_nbr[r] & NBR_COUNT < NDT_ERASED_NEIGHBOURS:
                        # Threads that saw 5 at once may add past 6: each add that did takes
                        # itself back, so the count ends at min(6, its sum) in any order (it
                        # is saved), and the one add that reached 6 widens.
                        k = (ti.atomic_add(rec_nbr[r], 1) & NBR_COUNT) + 1
                        if k == NDT_ERASED_NEIGHBOURS:
                            wide(r, rec_icov)
                        elif k > NDT_ERASED_NEIGHBOURS:
                            ti.atomic_sub(rec_nbr[r], 1)

    @ti.func
    def wide(r, rec_icov: ti.template()):
        # Record r's inverse covariance as NDT_WIDE x I (its mean stays).
        for a in ti.static(range(6)):  # xx xy xz yy yz zz
            rec_icov[r, a] = ti.f64(WIDE_ROW[a])  # (a bare literal would be f32)

    @ti.func
    def take_miss(r, rec_miss: ti.template(), rec_nbr: ti.template()) -> ti.f32:
        # The NDT miss model's summed change of record r's cell, consumed (NBR_BACK: a share).
        v = rec_miss[r]
        rec_miss[r] = ti.i64(0)
        k = 1.0 / MISS_SCALE
        if rec_nbr[r] & NBR_BACK != 0:
            k *= NDT_BACK_MISS
        return ti.cast(ti.cast(v, ti.f64) * k, ti.f32)

    @ti.func
    def ndt_reset(r, rec_nbr: ti.template()) -> ti.f32:
        # Log-odds at which rays erase record r's points: never for NBR_BACK.
        return NDT_RESET if rec_nbr[r] & NBR_BACK == 0 else -BIG

    @ti.func
    def free_update_tree(
        slot,
        c,
        l_free,
        l_min,
        l_max,
        rec_n: ti.template(),
        ctr: ti.template(),
        rec_free: ti.template(),
        rec_miss: ti.template(),
        ndt_minp,
        ndt: ti.template(),
        rec_nbr: ti.template(),
        rec_icov: ti.template(),
    ):
        # Hit cells were updated by merge, which cleared their ray count: skipped. With the
        # NDT miss model (ndt) a cell whose Gaussian has >= ndt_minp points takes the rays'
        # summed likelihood terms instead of the count's.
        v = ne[at(slot, c)]
        k = v & NE_COUNT
        if k > 0:
            g = v & NE_GAUSS
            ne[at(slot, c)] = g
            dl = ti.cast(k * l_free, ti.f32)
            l_reset = 0.0
            if ti.static(ndt) and g != 0:
                r = gslot[at(slot, c)] - 1
                if r >= 0 and rec_n[r] >= ndt_minp:
                    dl = take_miss(r, rec_miss, rec_nbr)
                    l_reset = ndt_reset(r, rec_nbr)
                    if dl == 0.0:  # not a free-space update (as a marked cell of the block)
                        ti.atomic_add(ctr[C_NDT_STILL], 1)
            erased = free_update(slot, c, dl, g, l_min, l_max, l_reset, rec_n, ctr, rec_free)
            if ti.static(ndt):
                if erased != 0:
                    erased_beside(slot, c, rec_n, rec_nbr, rec_icov, ndt_minp)

    @ti.func
    def block_cell(
        slot,
        c,
        v,
        new_leaf,
        l_free,
        l_min,
        l_max,
        rec_n: ti.template(),
        ctr: ti.template(),
        regions: ti.template(),
        leaves: ti.template(),
        rec_free: ti.template(),
    ):
        # eq. (12) for a cell of the dense block that v rays passed; new_leaf: the first
        # such cell of its tree leaf in this pass, which counts the leaf if it creates it.
        # (Cells marked for the NDT miss model were applied and cleared by apply_marked.)
        if new_leaf:
            note_leaf(olm, slot, c, regions, leaves, 0)
        free_update(
            slot, c, ti.cast(v * l_free, ti.f32), ne[at(slot, c)] & NE_GAUSS, l_min, l_max, 0.0, rec_n, ctr, rec_free
        )

    @ti.func
    def add_miss(r, c, o, z, u, length, hit, res, prm: ti.template(), rec_icov: ti.template(), rec_miss: ti.template()):
        # The ray's NDT miss term added to record r's sum (terms that round to zero add nothing).
        v = ndt_miss(r, c, o, z, u, length, hit, res, prm, rec_icov)
        if v != 0:
            ti.atomic_add(rec_miss[r], v)

    @ti.func
    def ndt_visit(
        slot, c, o, z, u, length, hit, res, prm: ti.template(), rec_icov: ti.template(), rec_miss: ti.template()
    ):
        # A ray passing a cell of the block marked as holding a usable Gaussian.
        add_miss(gslot[at(slot, c)] - 1, c, o, z, u, length, hit, res, prm, rec_icov, rec_miss)

    @ti.func
    def ndt_tree_visit(
        slot,
        c,
        o,
        z,
        u,
        length,
        hit,
        res,
        prm: ti.template(),
        rec_n: ti.template(),
        rec_icov: ti.template(),
        rec_miss: ti.template(),
        ndt_minp,
    ):
        # A ray passing a cell of the tree that may hold a Gaussian (NE_GAUSS).
        r = gslot[at(slot, c)] - 1
        if r >= 0 and rec_n[r] >= ndt_minp:
            add_miss(r, c, o, z, u, length, hit, res, prm, rec_icov, rec_miss)

    @ti.func
    def ndt_floor(s0, s1, s2, s3, s4, s5, n, prm: ti.template()) -> ti.f64:
        # Variance added on every axis of a Gaussian (xx xy xz yy yz zz) before it is
        # inverted: a share prm[2] of its trace always (flat ones stay invertible), and for
        # a line-like Gaussian (middle eigenvalue l2 < prm[3] x the largest l3: one scan
        # line across the cell) prm[4] x (prm[3] l3 - l2) / prm[3] more, so that it stands
        # for the surface the line samples; times min(1, prm[7] / n) for n points, since a
        # line that stays a line as points join it is a thin structure, not one look at a face.
        tr = s0 + s3 + s5
        out = prm[2] * tr + 1e-12
        # Eigenvalues of every Gaussian: no cheaper invariant tells a line from a plane at
        # prm[3] = 0.5 (a bound on c2 = l1 l2 + l1 l3 + l2 l3 skips none, as c2 <= tr^2 / 3).
        q = tr / 3.0
        p2 = (s0 - q) ** 2 + (s3 - q) ** 2 + (s5 - q) ** 2 + 2.0 * (s1 * s1 + s2 * s2 + s4 * s4)
        if p2 > 1e-30 * q * q:
            # l3, the largest root of det(x I - S) = x^3 - tr x^2 + c2 x - det, by Newton's
            # method from q + 2 p >= l3: from above it converges without overshoot (f is
            # convex past q), and 4 steps give the widening to ~1e-11 of l3 (no inverse
            # cosine and cosines, which cost ~3x more, even in f32).
            c2 = s0 * s3 + s0 * s5 + s3 * s5 - s1 * s1 - s2 * s2 - s4 * s4
            dt = s0 * (s3 * s5 - s4 * s4) - s1 * (s1 * s5 - s4 * s2) + s2 * (s1 * s4 - s3 * s2)
            x = q + 2.0 * ti.sqrt(p2 / 6.0)
            for _ in ti.static(range(4)):
                fx = ((x - tr) * x + c2) * x - dt
                dfx = (3.0 * x - 2.0 * tr) * x + c2
                if dfx > 0.0:
                    x -= fx / dfx
            # l1 + l2 = tr - l3, l1 l2 = det / l3.
            sm = tr - x
            l2 = 0.5 * (sm + ti.sqrt(ti.max(sm * sm - 4.0 * dt / x, 0.0)))
            out += prm[4] * ti.min(1.0, prm[7] / n) * ti.max(0.0, prm[3] * x - l2) / prm[3]
        return out

    @ti.func
    def ndt_icov(
        r,
        rec_n: ti.template(),
        rec_scat: ti.template(),
        rec_mean: ti.template(),
        prm: ti.template(),
        rec_icov: ti.template(),
    ):
        # What a ray visit reads of record r, in one row: the inverse of its regularised
        # covariance (xx xy xz yy yz zz) and a copy of its mean (relative to the cell
        # centre). Computed when its points change (merge) or the map is loaded.
        k = 1.0 / ti.max(ti.cast(rec_n[r], ti.f64) - 1.0, 1.0)
        s0, s1, s2 = rec_scat[r, 0] * k, rec_scat[r, 1] * k, rec_scat[r, 2] * k
        s3, s4, s5 = rec_scat[r, 3] * k, rec_scat[r, 4] * k, rec_scat[r, 5] * k
        if ti.cast(rec_n[r], ti.f64) < prm[5]:
            # Fewer than min_points points: their mean, and a prior of prm[6] on every axis
            # (a point stands for a small patch; rays must pass near it to clear it).
            s0 += prm[6]
            s3 += prm[6]
            s5 += prm[6]
        eps = ndt_floor(s0, s1, s2, s3, s4, s5, ti.cast(rec_n[r], ti.f64), prm)
        a00, a11, a22 = s0 + eps, s3 + eps, s5 + eps
        c00 = a11 * a22 - s4 * s4
        c01 = s2 * s4 - s1 * a22
        c02 = s1 * s4 - s2 * a11
        c11 = a00 * a22 - s2 * s2
        c12 = s1 * s2 - a00 * s4
        c22 = a00 * a11 - s1 * s1
        k_det = 1.0 / (a00 * c00 + s1 * c01 + s2 * c02)
        rec_icov[r, 0] = c00 * k_det
        rec_icov[r, 1] = c01 * k_det
        rec_icov[r, 2] = c02 * k_det
        rec_icov[r, 3] = c11 * k_det
        rec_icov[r, 4] = c12 * k_det
        rec_icov[r, 5] = c22 * k_det
        for a in ti.static(range(3)):
            rec_icov[r, 6 + a] = rec_mean[r, a]

    @ti.func
    def ndt_miss(r, c, o, z, u, length, hit, res, prm: ti.template(), rec_icov: ti.template()) -> ti.i64:
        # The NDT miss model (Saarinen et al., IJRR 2013, eqs. 22-24) for one ray o -> z
        # passing cell c, whose Gaussian (record r, as at the scan's start) it tests: the
        # ray's point of highest likelihood x_ML, p = 0.5 - eta p(x_ML|N) (1 - p(x_ML|z)),
        # and the log-odds change logit(p), in fixed point. Coordinates relative to the
        # cell centre keep f64 exact enough far from the origin. u, length: the ray's unit
        # direction and length. prm: [eta, 1 / (2 sigma_s^2), covariance floors (ndt_floor),
        # min_points, prior variance of a cell with fewer points (ndt_icov), line points
        # (ndt_floor)].
        centre = (c.cast(ti.f64) + 0.5) * res
        oc = o - centre
        i0, i1, i2, i3, i4, i5 = (
            rec_icov[r, 0],
            rec_icov[r, 1],
            rec_icov[r, 2],
            rec_icov[r, 3],
            rec_icov[r, 4],
            rec_icov[r, 5],
        )
        mu = ti.Vector([rec_icov[r, 6], rec_icov[r, 7], rec_icov[r, 8]])
        # inv @ u and the dot products written out, in the order of Taichi's `@` and `dot`.
        a = ti.Vector(
            [i0 * u[0] + i1 * u[1] + i2 * u[2], i1 * u[0] + i3 * u[1] + i4 * u[2], i2 * u[0] + i4 * u[1] + i5 * u[2]]
        )
        # x_ML on the ray's line, kept on the segment the ray travelled.
        g = mu - oc
        t = ti.min(
            ti.max((a[0] * g[0] + a[1] * g[1] + a[2] * g[2]) / (a[0] * u[0] + a[1] * u[1] + a[2] * u[2]), 0.0), length
        )
        e = oc + t * u - mu
        b = ti.Vector(
            [i0 * e[0] + i1 * e[1] + i2 * e[2], i1 * e[0] + i3 * e[1] + i4 * e[2], i2 * e[0] + i4 * e[1] + i5 * e[2]]
        )
        m2 = e[0] * b[0] + e[1] * b[1] + e[2] * b[2]
        out = ti.i64(0)
        # Past m2 = 48, |logit(p)| < 4 eta exp(-24) < 2^-33: the term rounds to zero.
        if m2 < 48.0:
            p_n = ti.exp(-0.5 * m2)
            p_z = ti.f64(0.0)
            if hit:
                w = oc + t * u - (z - centre)
                p_z = ti.exp(-(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) * prm[1])
            p = 0.5 - prm[0] * p_n * (1.0 - p_z)
            out = ti.cast(ti.round(ti.log(p / (1.0 - p)) * MISS_SCALE), ti.i64)
        return out

    f.funcs = SimpleNamespace(
        owned=owned,
        owner_spec=owner_spec,
        leaf=leaf,
        region=region,
        grid_lo=grid_lo,
        SHIFT=SHIFT,
        queue=queue,
        row=row,
        picked=picked,
        at=at,
        note_leaf=note_leaf,
        tally=tally,
        visit=visit,
        next_t=next_t,
        free_update=free_update,
        erased_beside=erased_beside,
        wide=wide,
        take_miss=take_miss,
        ndt_reset=ndt_reset,
        free_update_tree=free_update_tree,
        block_cell=block_cell,
        add_miss=add_miss,
        ndt_visit=ndt_visit,
        ndt_tree_visit=ndt_tree_visit,
        ndt_floor=ndt_floor,
        ndt_icov=ndt_icov,
        ndt_miss=ndt_miss,
    )
    return f.funcs
