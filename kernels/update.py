"""The occupancy-update family (method.md section 3): a scan's points to world cells,
hits counted and summed per cell, the RCU merge of each hit cell's Gaussian with eq. (12)
for it (``merge``), then eq. (12) once per cell that rays passed and no endpoint hit
(``block_apply`` over the dense block, ``apply_free(_all)`` over the tree), with the
reset of the Gaussian of a cell whose log-odds fell to <= 0 (<= NDT_RESET under the NDT
miss model)."""

from dataclasses import dataclass

import taichi as ti

from .args import (
    Block,
    Bound,
    GroupedHits,
    Model,
    NdtRecords,
    Nodes,
    Picked,
    Records,
    Touched,
    TreeSums,
)
from .layout import Storage
from .ndt import (
    C_BLOCK_CELLS,
    C_FREE,
    C_HIT_CELLS,
    C_HIT_PASSED,
    C_NO_RECORD,
    C_RECORDS,
    HIT_CHUNKS,
    NBR_BACK,
    NBR_COUNT,
    NBR_FRESH,
    NDT_ERASED_NEIGHBOURS,
    NDT_FRESH_FLOOR,
    NDT_RESTART,
    NDT_RESTART_CLEAR,
    NE_COUNT,
    NE_GAUSS,
    Q_APPLY,
    Q_MERGE,
    device_funcs,
    f64_1d,
    f64_2d,
    i8_1d,
    i8_3d,
    i8_4d,
    i32_1d,
    i32_2d,
    i64_1d,
    i64_2d,
    inside,
    rolled,
    u8_3d,
    u64_1d,
)
from .trace import block_type, settled_growth

HIT_CHUNK = 64  # hit cells a thread takes from merge's queue at a time
COLUMN_CHUNK = 32  # block columns a thread takes from block_apply's queue at a time


SORT_SMALL = 64  # a hit cell's points up to this many are sorted by insertion


@ti.func
def _sift_down(order: ti.template(), o, root, n):
    # order[o : o + n] as a binary max-heap: the entry at root moved down to its place.
    r = root
    while True:
        c = 2 * r + 1
        if c >= n:
            break
        if c + 1 < n:  # (nested: Taichi's `and` reads both sides)
            if order[o + c] < order[o + c + 1]:
                c += 1
        if order[o + r] >= order[o + c]:
            break
        t = order[o + r]
        order[o + r] = order[o + c]
        order[o + c] = t
        r = c


@ti.func
def cell_sums(order: ti.template(), o, cnt, pts: ti.template(), centre):
    """A hit cell's point sums relative to its centre (sum q (3), sum q q^T (6)), its
    points order[o : o + cnt] first sorted by their index in the scan: the threads that
    grouped them wrote them in any order, and float sums depend on it. Sorted, the sums
    are one sequence whatever the threads, their number, or the path that grouped them
    (hits_dense in the block, the ordered hits_sum in the tree). The threads' runs leave
    a cell's points mostly in order: insertion sort does little more than read them. A cell
    of many points (a wall close to a depth camera at a coarse resolution; 2^20 points in a
    test) may hold the threads' runs interleaved: heapsort there, O(k log k) in any order."""
    if cnt <= SORT_SMALL:
        for j in range(o + 1, o + cnt):
            v = order[j]
            k = j - 1
            while k >= o:
                if order[k] <= v:
                    break
                order[k + 1] = order[k]
                k -= 1
            order[k + 1] = v
    else:
        # A max-heap of the indices (roots cnt // 2 - 1 .. 0), then its top swapped out
        # (ends cnt - 1 .. 1): one loop, so that _sift_down is inlined once.
        s = cnt // 2 - 1
        end = cnt
        while s >= 0 or end > 1:
            root = 0
            if s >= 0:
                root = s
                s -= 1
            else:
                end -= 1
                top = order[o]
                order[o] = order[o + end]
                order[o + end] = top
            _sift_down(order, o, root, end)
    sv = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
    ss = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dt=ti.f64)
    for j in range(o, o + cnt):
        i = order[j]
        x = ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]]) - centre
        sv += x
        ss += ti.Vector([x[0] * x[0], x[0] * x[1], x[0] * x[2], x[1] * x[1], x[1] * x[2], x[2] * x[2]])
    return ti.Vector([sv[0], sv[1], sv[2], ss[0], ss[1], ss[2], ss[3], ss[4], ss[5]], dt=ti.f64)


@dataclass(frozen=True)
class MergeConfig:
    """One variant of ``merge``. grouped: the hits were grouped by hits_dense in the
    dense block or by hits_group in the tree (GroupedHits: merge sums each cell's points
    in their order in the scan; the CPU), else counted and summed in the tree by atomic
    adds (TreeSums; a GPU). Both CPU paths run the one variant, so that they compile to
    the same arithmetic: two variants of a kernel may round differently (fast math
    reassociates each as it finds it). ndt: the NDT miss model (the merge clears a
    record's miss sum and refreshes what rays read)."""

    bt: str = "u16"
    grouped: bool = False
    ndt: bool = False

    def __post_init__(self):
        block_type(self.bt)


@dataclass(frozen=True)
class FreeConfig:
    """One variant of the free-space kernels of the dense block: its dtype, and whether it
    may hold the NDT miss model's marks (mark_gaussians), which are cleared, not applied."""

    bt: str = "u16"
    ndt: bool = False

    def __post_init__(self):
        block_type(self.bt)


def prepare(f: Storage, _cfg=None) -> Bound:
    """Sensor-frame points to world points and cells, each with its status."""
    grid_lo = device_funcs(f).grid_lo
    grid_n = ti.Vector(list(f.layout.cells))
    grow_settled = settled_growth(f)

    def prepare(
        pts: ti.types.ndarray(ndim=2),  # [N, 3] sensor-frame points (f32 or f64)
        n: ti.i32,
        rot: f64_1d,  # [9] R of T_world_sensor, row-major
        trans: f64_1d,  # [3] its translation
        res: ti.f64,
        r2: f64_1d,  # [3] min_range^2, max_range^2, max_range (free rays past it if > 0)
        out_world: f64_2d,  # [N, 3]
        out_cells: i32_2d,  # [N, 3]
        status: i8_1d,  # [N] 0 hit, 1 free ray, 2 not finite, 3 out of range, 4 outside the grid, 5 at the sensor
        ocell: i32_1d,  # [3] the sensor's cell
        slot: ti.i32,  # the settled boxes (trace.settled_growth), of this map's cells:
        l_min: ti.f32,
        hmask: u8_3d,  # [reach + 1]^3 bricks of 2^3 cells around the sensor's cell: ``stamp`` where a hit falls
        stamp: ti.i32,
        reach: ti.i32,  # -1: no marks, no boxes
        sbox: i32_1d,  # out [8 * 6]
    ):
        # No atomics: the caller compacts by status (contended counters cost more).
        co = ti.Vector([ocell[0], ocell[1], ocell[2]], dt=ti.i32)
        for i in range(n):
            p = ti.Vector([ti.cast(pts[i, 0], ti.f64), ti.cast(pts[i, 1], ti.f64), ti.cast(pts[i, 2], ti.f64)])
            st = ti.i8(2)
            # Exponent bits all set: inf or NaN. (ti.math.isinf/isnan cast to f32 first,
            # which made finite points past 3.4e38 read as infinite.)
            e = ti.Vector([(ti.bit_cast(p[a], ti.u64) >> ti.u64(52)) & ti.u64(0x7FF) for a in ti.static(range(3))])
            if e[0] != ti.u64(0x7FF) and e[1] != ti.u64(0x7FF) and e[2] != ti.u64(0x7FF):
                st = ti.i8(3)
                d2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
                if d2 == 0.0:
                    # (0, 0, 0): many drivers' mark of a beam with no return (organised
                    # clouds, Livox); as a hit it would put a Gaussian where the sensor is.
                    st = ti.i8(5)
                elif d2 >= r2[0] and d2 <= r2[1]:
                    st = ti.i8(0)
                elif d2 > r2[1] and r2[2] > 0.0:
                    p = p * (r2[2] / ti.sqrt(d2))  # carve free space up to max_range
                    st = ti.i8(1)
                if st <= 1:
                    w = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
                    for a in ti.static(range(3)):
                        w[a] = rot[3 * a] * p[0] + rot[3 * a + 1] * p[1] + rot[3 * a + 2] * p[2] + trans[a]
                    cf = ti.floor(w / res)
                    if inside(cf, grid_lo.cast(ti.f64), (grid_lo + grid_n).cast(ti.f64)):
                        c = ti.Vector([0, 0, 0], dt=ti.i32)
                        for a in ti.static(range(3)):
                            out_world[i, a] = w[a]
                            c[a] = ti.cast(cf[a], ti.i32)
                            out_cells[i, a] = c[a]
                        r = c - co + reach
                        if st == 0 and r[0] >= 0 and r[1] >= 0 and r[2] >= 0:
                            if r[0] <= 2 * reach and r[1] <= 2 * reach and r[2] <= 2 * reach:
                                hmask[r[0] >> 1, r[1] >> 1, r[2] >> 1] = ti.cast(stamp, ti.u8)
                    else:
                        st = ti.i8(4)
            status[i] = st
        # The hits stamped: the sensor's settled surroundings, on one thread (waking the pool
        # would cost more than the ~0.2 ms they take).
        ti.loop_config(serialize=True)
        for _ in range(1):
            if reach >= 0:
                grow_settled(slot, co, l_min, hmask, stamp, sbox)
            else:
                for k in range(8 * 6):
                    sbox[k] = 0 if k % 6 < 3 else -1

    return Bound(
        prepare,
        (
            "pts",
            "n",
            "rot",
            "trans",
            "res",
            "r2",
            "out_world",
            "out_cells",
            "status",
            "ocell",
            "slot",
            "l_min",
            "hmask",
            "stamp",
            "reach",
            "sbox",
        ),
    )


def hits_count(f: Storage, _cfg=None) -> Bound:
    """Points per hit cell in the index tree (integer atomics), and a compact hit list."""
    F = device_funcs(f)
    hn, hslot, glm, row, at, note_leaf = f.hn, f.hslot, f.glm, F.row, F.at, F.note_leaf

    def hits_count(
        slot: ti.i32,
        cells: i32_2d,  # [N, 3] cell of each hit point
        n: ti.i32,
        hitlist: i32_2d,  # [N, 3] out: distinct hit cells
        ctr: i64_1d,  # [CTR_SIZE] counters (C_HIT_CELLS)
        gidx_regions: i8_4d,  # Nodes
        leaves: i64_2d,
    ):
        for i in range(n):
            c = row(cells, i)
            if ti.atomic_add(hn[at(slot, c)], 1) == 0:
                # Every leaf these writes allocate holds a cell's first point: count it there.
                note_leaf(glm, slot, c, gidx_regions, leaves, 1)
                s = ti.atomic_add(ctr[C_HIT_CELLS], 1)
                for a in ti.static(range(3)):
                    hitlist[s, a] = c[a]
                hslot[at(slot, c)] = ti.i32(s)

    return Bound(hits_count, ("slot", "cells", "n", "hitlist", "ctr", ("nodes", Nodes, ("gidx_regions", "leaves"))))


def hits_sum(f: Storage, _cfg=None) -> Bound:
    """Scan-local sums relative to the cell centre, one slot per hit cell, by float64
    atomic adds: in the threads' order (a GPU; the CPU groups the points, hits_group)."""
    F = device_funcs(f)
    hslot, row, at = f.hslot, F.row, F.at

    def hits_sum(
        slot: ti.i32,
        pts: f64_2d,  # [N, 3] world points
        cells: i32_2d,  # [N, 3]
        n: ti.i32,
        acc: f64_2d,  # [H, 9] out: sum q (3), sum q q^T (6), q = x - cell centre
        res: ti.f64,
    ):
        for i in range(n):
            c = row(cells, i)
            s = hslot[at(slot, c)]
            q = ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]]) - (c.cast(ti.f64) + 0.5) * res
            ti.atomic_add(acc[s, 0], q[0])
            ti.atomic_add(acc[s, 1], q[1])
            ti.atomic_add(acc[s, 2], q[2])
            ti.atomic_add(acc[s, 3], q[0] * q[0])
            ti.atomic_add(acc[s, 4], q[0] * q[1])
            ti.atomic_add(acc[s, 5], q[0] * q[2])
            ti.atomic_add(acc[s, 6], q[1] * q[1])
            ti.atomic_add(acc[s, 7], q[1] * q[2])
            ti.atomic_add(acc[s, 8], q[2] * q[2])

    return Bound(hits_sum, ("slot", "pts", "cells", "n", "acc", "res"))


def hits_group(f: Storage, _cfg=None) -> Bound:
    """The points grouped by hit cell after hits_count (the tree), for merge to sum each
    cell's in their order in the scan (cell_sums), as it sums those of hits_dense: the
    same map whatever the threads or the path (the CPU; a GPU takes hits_sum)."""
    F = device_funcs(f)
    hn, hslot, row, at = f.hn, f.hslot, F.row, F.at

    def hits_group(
        slot: ti.i32,
        hitlist: i32_2d,  # [H, 3] the scan's hit cells (hits_count)
        nh: ti.i32,
        cells: i32_2d,  # [N, 3] cells of the hits
        n: ti.i32,
        hcnt: i32_1d,  # [H] out: points per hit cell
        off: i32_1d,  # [H] out: where each hit cell's points start in ``order``
        order: i32_1d,  # [N] out: the points grouped by hit cell
        first: i32_1d,  # [HIT_CHUNKS + 1] scratch: points before each chunk of hit cells
    ):
        # Offsets by a prefix sum over chunks of hit cells, as hits_dense's; hcnt then
        # counts the points placed, back to the cell's count at the end.
        size = (nh + HIT_CHUNKS - 1) // HIT_CHUNKS
        for c in range(HIT_CHUNKS):
            k = 0
            for s in range(c * size, ti.min(nh, (c + 1) * size)):
                rolled(n)
                v = hn[at(slot, row(hitlist, s))]
                hcnt[s] = v
                k += v
            first[c + 1] = k
        ti.loop_config(serialize=True)  # (waking the pool costs more than these take)
        for _ in range(1):  # prefix sums, one thread
            first[0] = 0
            for c in range(HIT_CHUNKS):
                rolled(n)
                first[c + 1] += first[c]
        for c in range(HIT_CHUNKS):
            run = first[c]
            for s in range(c * size, ti.min(nh, (c + 1) * size)):
                rolled(n)
                off[s] = run
                run += hcnt[s]
                hcnt[s] = 0
        for i in range(n):
            rolled(n)
            s = hslot[at(slot, row(cells, i))]
            order[off[s] + ti.atomic_add(hcnt[s], 1)] = i

    return Bound(hits_group, ("slot", "hitlist", "nh", "cells", "n", "hcnt", "off", "order", "first"))


def hits_dense(f: Storage, bt: str) -> Bound:
    """Points grouped by hit cell in the dense block, for a block holding every cell of
    the scan (on the CPU: its prefix sum runs on one thread)."""
    F = device_funcs(f)
    row = F.row
    bt_ = block_type(bt)
    bt = bt_
    b3d = ti.types.ndarray(dtype=bt_, ndim=3)

    def hits_dense(
        cells: i32_2d,  # [N, 3] cells of the hits
        n: ti.i32,
        hitlist: i32_2d,  # [N, 3] out: distinct hit cells (the first ctr[C_HIT_CELLS])
        hcnt: i32_1d,  # [N] out: points per hit cell
        off: i32_1d,  # [N] out: where each hit cell's points start in ``order``
        rank: i32_1d,  # [N] scratch: a point's rank among its cell's points
        order: i32_1d,  # [N] out: the points grouped by hit cell
        ctr: i64_1d,
        block: b3d,  # the scan's ray counts, covering every cell of the scan
        base: i32_1d,
        first: i32_1d,  # [HIT_CHUNKS + 1] scratch: first hit-list slot of each chunk
    ):
        # Points grouped by hit cell without the tree, for a block that holds every hit
        # cell (an entry holds any count or slot: at most one per ray): a hit cell's ray
        # count is dropped anyway (eq. 12), so its block entry counts the cell's points,
        # then holds its slot.
        # merge then sums each cell's points itself (no atomics per point).
        b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
        size = (n + HIT_CHUNKS - 1) // HIT_CHUNKS
        for i in range(n):
            q = row(cells, i) - b0
            block[q[0], q[1], q[2]] = ti.cast(0, bt)
        for i in range(n):
            q = row(cells, i) - b0
            rank[i] = ti.cast(ti.atomic_add(block[q[0], q[1], q[2]], ti.cast(1, bt)), ti.i32)
        # Hit-list slots by a prefix sum over chunks of points: a counter shared by the
        # threads cost a cache-line transfer per hit cell. The hit list comes out in
        # the order of the points that took rank 0 (threads decide which: the hit list's
        # order reaches no map, and merge sorts each cell's points, see cell_sums).
        for c in range(HIT_CHUNKS):
            k = 0
            for i in range(c * size, ti.min(n, (c + 1) * size)):
                if rank[i] == 0:
                    k += 1
            first[c + 1] = k
        ti.loop_config(serialize=True)  # (waking the pool costs more than these take)
        for _ in range(1):  # prefix sums, one thread
            first[0] = 0
            for c in range(HIT_CHUNKS):
                first[c + 1] += first[c]
            ctr[C_HIT_CELLS] = first[HIT_CHUNKS]
        for c in range(HIT_CHUNKS):
            s = first[c]
            for i in range(c * size, ti.min(n, (c + 1) * size)):
                if rank[i] == 0:
                    q = row(cells, i) - b0
                    for a in ti.static(range(3)):
                        hitlist[s, a] = cells[i, a]
                    hcnt[s] = ti.cast(block[q[0], q[1], q[2]], ti.i32)
                    block[q[0], q[1], q[2]] = ti.cast(s, bt)
                    s += 1
        ti.loop_config(serialize=True)
        for _ in range(1):
            run = 0
            for s in range(first[HIT_CHUNKS]):
                off[s] = run
                run += hcnt[s]
        for i in range(n):
            q = row(cells, i) - b0
            order[off[ti.cast(block[q[0], q[1], q[2]], ti.i32)] + rank[i]] = i

    return Bound(
        hits_dense,
        ("cells", "n", "hitlist", "hcnt", "off", "rank", "order", "ctr", ("block", Block, ("block", "base")), "first"),
    )


def merge(f: Storage, cfg: MergeConfig) -> Bound:
    """One thread per hit cell: the RCU merge of the scan's Gaussian into the cell's
    record (a new record for a cell's first points), then eq. (12) for the cell."""
    F = device_funcs(f)
    lo, ne, hn, gslot, glm, olm = f.lo, f.ne, f.hn, f.gslot, f.glm, f.olm
    row, at, note_leaf, ndt_icov, Q = F.row, F.at, F.note_leaf, F.ndt_icov, F.queue
    grouped, ndt = cfg.grouped, cfg.ndt
    bt = block_type(cfg.bt)
    b3d = ti.types.ndarray(dtype=bt, ndim=3)

    @ti.func
    def hit_update(
        slot,
        c,
        cnt,
        l_hit,
        l_min,
        l_max,
        regions: ti.template(),
        leaves: ti.template(),
        block: ti.template(),
        b0,
        bsize,
        ctr: ti.template(),
        grouped: ti.template(),
        in_tree,
        first,
        state,
    ):
        # eq. (12) for a cell with endpoints: the hit update only, its ray count cleared;
        # the cell has a Gaussian record now (first: its first points). NDT miss model:
        # state is the record's NBR_FRESH / NBR_BACK bits before the hit; returns them after.
        note_leaf(olm, slot, c, regions, leaves, 0)
        l0 = lo[at(slot, c)]
        out = 0
        if ti.static(ndt):
            # NDT miss model: the cell restarts from NDT_RESTART. The misses a cell took
            # while it held no points tested no surface, and those that lowered its
            # Gaussian short of its reset passed beside a surface that the hit says is
            # still there. A cell's first points where rays had held it at the free clamp
            # restart from NDT_RESTART_CLEAR: the rays had crossed free space there; its
            # next hits add to max(l, NDT_FRESH_FLOOR) until it reaches the clamp.
            if first != 0 and l0 <= l_min:
                l0 = ti.max(l0, NDT_RESTART_CLEAR)
                out = NBR_FRESH
            elif state & NBR_FRESH != 0:
                l0 = ti.max(l0, NDT_FRESH_FLOOR)
                out = state
            else:
                out = state & NBR_BACK
                if first == 0 and l0 <= 0.0:
                    out = NBR_BACK
                l0 = ti.max(l0, NDT_RESTART)
        l1 = ti.min(ti.max(l0 + ti.cast(cnt * l_hit, ti.f32), l_min), l_max)
        lo[at(slot, c)] = l1
        if ti.static(ndt):
            if l1 >= l_max:
                out = out & NBR_BACK
        if ti.static(not grouped):
            hn[at(slot, c)] = 0
        else:
            if in_tree != 0:
                hn[at(slot, c)] = 0
        v = ne[at(slot, c)]
        ne[at(slot, c)] = NE_GAUSS
        rel = c - b0
        if (rel >= 0).all() and (rel < bsize).all():
            block[rel[0], rel[1], rel[2]] = ti.cast(0, bt)
        elif v & NE_COUNT != 0:
            ti.atomic_add(ctr[C_HIT_PASSED], 1)
        return out

    def merge(
        slot: ti.i32,
        hitlist: i32_2d,  # [H, 3] the scan's hit cells
        acc: f64_2d,  # TreeSums (not grouped)
        hcnt: i32_1d,  # GroupedHits (grouped)
        off: i32_1d,
        order: i32_1d,
        pts: f64_2d,
        in_tree: ti.i32,
        nh: ti.i32,  # hit cells to merge
        n_max: ti.i32,  # cap on a Gaussian's N (0: none)
        rec_n: i32_1d,  # Records
        rec_cell: i32_2d,
        rec_mean: f64_2d,
        rec_scat: f64_2d,
        rec_free: i32_1d,
        ctr: i64_1d,  # [CTR_SIZE]; C_RECORDS holds the records in use, C_FREE the free stack's
        l_hit: ti.f64,  # Model
        l_min: ti.f32,
        l_max: ti.f32,
        occ_regions: i8_4d,  # Nodes
        gidx_regions: i8_4d,
        leaves: i64_2d,
        block: b3d,  # Block: the scan's dense ray counts (empty: none)
        base: i32_1d,
        res: ti.f64,
        left: i32_1d,  # [H] out: hit cells (s) left untouched, all records taken
        rec_miss: i64_1d,  # NdtRecords (ndt): a hit cell takes the hit update only
        rec_icov: f64_2d,  # out: ndt_icov of the changed records
        ndt_prm: f64_1d,
        ndt_minp: ti.i32,
        rec_nbr: i32_1d,  # zeroed for the changed records
    ):
        # One thread per hit cell: the RCU merge of the scan's Gaussian, then eq. (12).
        # Records are not reserved for the worst case (every hit cell new): a cell that
        # finds none is left as it was, for the caller to grow the records and merge it.
        b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
        bsize = ti.Vector([block.shape[0], block.shape[1], block.shape[2]], dt=ti.i32)
        for wq in range(Q.span(nh, HIT_CHUNK)):
            jq = Q.first(wq, ctr, Q_MERGE)
            while jq < Q.end(nh, HIT_CHUNK):
                for s in range(Q.begin(jq, nh, HIT_CHUNK), Q.stop(jq, nh, HIT_CHUNK)):
                    c = row(hitlist, s)
                    r = gslot[at(slot, c)] - 1
                    if r < 0:
                        # A record from the free stack, else a new one. Pops only here (pushes
                        # only in eq. 12's kernels): a pop that finds it empty puts its count back.
                        k = ti.atomic_sub(ctr[C_FREE], 1) - 1
                        if k >= 0:
                            r = rec_free[ti.cast(k, ti.i32)]
                        else:
                            ti.atomic_add(ctr[C_FREE], 1)
                            r = ti.i32(ti.atomic_add(ctr[C_RECORDS], 1))
                        if r >= rec_n.shape[0]:
                            left[ti.atomic_add(ctr[C_NO_RECORD], 1)] = s
                            continue
                        if ti.static(grouped):  # hits_dense did not touch the index tree (in_tree: a no-op)
                            note_leaf(glm, slot, c, gidx_regions, leaves, 1)
                        for a in ti.static(range(3)):
                            rec_cell[r, a] = c[a]
                    # Stored here, outside the branches, so that the cell's later index-tree
                    # stores share this one's inlined node activation (Taichi inlines its
                    # allocator at every store to a sparse field it cannot prove active).
                    gslot[at(slot, c)] = r + 1
                    cnt = 0
                    if ti.static(grouped):
                        cnt = hcnt[s]
                    else:
                        cnt = hn[at(slot, c)]  # read once: each tree access walks both pointer levels
                    n = ti.cast(cnt, ti.f64)
                    sv = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
                    ss = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dt=ti.f64)
                    if ti.static(grouped):  # sums relative to the cell centre, in the scan's order
                        v = cell_sums(order, off[s], cnt, pts, (c.cast(ti.f64) + 0.5) * res)
                        sv = ti.Vector([v[0], v[1], v[2]])
                        ss = ti.Vector([v[3], v[4], v[5], v[6], v[7], v[8]])
                    else:
                        sv = ti.Vector([acc[s, 0], acc[s, 1], acc[s, 2]])
                        ss = ti.Vector([acc[s, 3], acc[s, 4], acc[s, 5], acc[s, 6], acc[s, 7], acc[s, 8]])
                    mu_y = sv / n
                    s_y = (
                        ss
                        - ti.Vector(
                            [sv[0] * sv[0], sv[0] * sv[1], sv[0] * sv[2], sv[1] * sv[1], sv[1] * sv[2], sv[2] * sv[2]]
                        )
                        / n
                    )
                    m_i = rec_n[r]
                    tot_i = m_i + cnt
                    if m_i == 0:
                        for a in ti.static(range(3)):
                            rec_mean[r, a] = mu_y[a]
                        for a in ti.static(range(6)):
                            rec_scat[r, a] = s_y[a]
                    else:
                        m = ti.cast(m_i, ti.f64)
                        tot = m + n
                        mu_x = ti.Vector([rec_mean[r, 0], rec_mean[r, 1], rec_mean[r, 2]])
                        d = mu_x - mu_y
                        w = m * n / tot
                        dd = ti.Vector([d[0] * d[0], d[0] * d[1], d[0] * d[2], d[1] * d[1], d[1] * d[2], d[2] * d[2]])
                        mu = (m * mu_x + n * mu_y) / tot
                        for a in ti.static(range(3)):
                            rec_mean[r, a] = mu[a]
                        for a in ti.static(range(6)):
                            rec_scat[r, a] = rec_scat[r, a] + s_y[a] + w * dd[a]
                    if n_max > 0 and tot_i > n_max:
                        k = ti.cast(n_max - 1, ti.f64) / ti.cast(tot_i - 1, ti.f64)
                        for a in ti.static(range(6)):
                            rec_scat[r, a] = rec_scat[r, a] * k
                        tot_i = n_max
                    rec_n[r] = tot_i
                    state = 0
                    if ti.static(ndt):  # (the paper's model reads no NDT arrays)
                        rel = c - b0
                        if not ((rel >= 0).all() and (rel < bsize).all()):
                            # The rays' sum, dropped: a hit cell takes the hit update only. (In the
                            # block the rays skipped hit cells, marked before them: no sum there.)
                            rec_miss[r] = ti.i64(0)
                        if m_i > 0:
                            state = rec_nbr[r] & (NBR_FRESH | NBR_BACK)
                        if tot_i >= ndt_minp:  # what rays read of the cell's points
                            ndt_icov(r, rec_n, rec_scat, rec_mean, ndt_prm, rec_icov)
                    first = 1 if m_i == 0 else 0
                    state = hit_update(
                        slot,
                        c,
                        cnt,
                        l_hit,
                        l_min,
                        l_max,
                        occ_regions,
                        leaves,
                        block,
                        b0,
                        bsize,
                        ctr,
                        grouped,
                        in_tree,
                        first,
                        state,
                    )
                    if ti.static(ndt):
                        rec_nbr[r] = state  # (its count of erased neighbours starts again)
                jq = Q.next(ctr, Q_MERGE)

    return Bound(
        merge,
        (
            "slot",
            "hitlist",
            ("sums", TreeSums) if not grouped else (None, TreeSums),
            ("grouped", GroupedHits) if grouped else (None, GroupedHits),
            "nh",
            "n_max",
            ("records", Records),
            "ctr",
            ("model", Model, ("l_hit", "l_min", "l_max")),
            ("nodes", Nodes),
            ("block", Block, ("block", "base")),
            "res",
            "left",
            ("ndt", NdtRecords) if ndt else (None, NdtRecords),
        ),
    )


_FREE_PARTS = (("model", Model, ("l_free", "l_min", "l_max")), ("records", Records, ("rec_n", "rec_free")), "ctr")


def apply_marked(f: Storage, _cfg=None) -> Bound:
    """The NDT miss model's summed change of the cells of the dense block that held a
    usable Gaussian and took no endpoint (marked by mark_gaussians), one thread per record,
    before block_apply (which clears the marks): their sums are the only ones of cells in
    the block left after merge."""
    F = device_funcs(f)
    row, free_update, take_miss, tally, erased_beside = F.row, F.free_update, F.take_miss, F.tally, F.erased_beside
    picked = F.picked
    ndt_reset = F.ndt_reset

    def apply_marked(
        slot: ti.i32,
        nrec: ti.i32,  # records in use
        pick: i32_1d,  # Picked: the records that may lie in the block (those mark_gaussians read)
        npick: ti.i32,
        tail0: ti.i32,
        l_min: ti.f32,  # Model
        l_max: ti.f32,
        rec_n: i32_1d,  # Records
        rec_cell: i32_2d,
        rec_free: i32_1d,
        ctr: i64_1d,
        shape: i32_1d,  # [3] the block's shape in cells
        base: i32_1d,  # [3] cell index of its first cell
        rec_miss: i64_1d,  # NdtRecords: the rays' sums, those of the block's cells consumed here
        rec_icov: f64_2d,  # out: erased_beside's (ndt.py), with rec_nbr
        ndt_minp: ti.i32,
        rec_nbr: i32_1d,
    ):
        b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
        bsize = ti.Vector([shape[0], shape[1], shape[2]], dt=ti.i32)
        for i in range(npick + nrec - tail0):
            r = picked(i, pick, npick, tail0)
            if rec_miss[r] != 0:  # (the tree's are apply_free's)
                c = row(rec_cell, r)
                rel = c - b0
                if (rel >= 0).all() and (rel < bsize).all():
                    erased = free_update(
                        slot,
                        c,
                        take_miss(r, rec_miss, rec_nbr),
                        NE_GAUSS,
                        l_min,
                        l_max,
                        ndt_reset(r, rec_nbr),
                        rec_n,
                        ctr,
                        rec_free,
                    )
                    if erased != 0:
                        erased_beside(slot, c, rec_n, rec_nbr, rec_icov, ndt_minp)
                    tally(ctr, C_BLOCK_CELLS, r >> 6, 1)

    return Bound(
        apply_marked,
        (
            "slot",
            "nrec",
            ("picked", Picked),
            ("model", Model, ("l_min", "l_max")),
            ("records", Records, ("rec_n", "rec_cell", "rec_free")),
            "ctr",
            "shape",
            "base",
            ("ndt", NdtRecords, ("rec_miss", "rec_icov", "ndt_minp", "rec_nbr")),
        ),
    )


def block_apply(f: Storage, cfg: FreeConfig) -> Bound:
    """eq. (12) for the cells of the dense block, straight from their counts (hit cells were
    zeroed by merge; marked cells took their sums in apply_marked); block and row flags are
    zero afterwards. ``flagged``: the rays flagged the rows they entered (a block they left
    mostly empty) and only those are read; else every row is, a word of cells at a time.
    One kernel for both, so a recording whose scans fill the block more or less densely
    compiles it once."""
    F = device_funcs(f)
    block_cell, tally, SHIFT, Q, leaf = F.block_cell, F.tally, F.SHIFT, F.queue, F.leaf
    owned, owner_spec = F.owned, F.owner_spec
    ndt = cfg.ndt
    bits = 16 if cfg.bt == "u16" else 32
    lanes = 64 // bits  # block entries per 64-bit word
    row_words = leaf // lanes  # words per row of `leaf` cells along z (one row flag)
    mask = (1 << bits) - 1
    ones = sum(1 << (bits * i) for i in range(lanes))  # lowest bit of every lane
    highs = ones << (bits - 1)  # highest bit of every lane

    def block_apply(
        slot: ti.i32,
        words: u64_1d,  # the block, flat, as 64-bit words: ray counts, zeroed here
        bflag: i8_3d,  # rows entered (read when flagged), zeroed here
        shape: i32_1d,  # [3] its shape in cells
        base: i32_1d,  # [3] cell index of its first cell
        flagged: ti.i32,
        l_free: ti.f64,  # Model
        l_min: ti.f32,
        l_max: ti.f32,
        rec_n: i32_1d,  # Records
        rec_free: i32_1d,
        ctr: i64_1d,
        occ_regions: i8_4d,  # Nodes
        leaves: i64_2d,
    ):
        # Every column of cells along z in memory order, a row of `leaf` cells at a time (skipped
        # unless flagged when the rays flagged rows), a word of `lanes` cells at a time, so the
        # empty cells (most of them) cost one test per word. Little-endian: lane 0 is the word's
        # first cell.
        b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
        own = owner_spec(slot)
        wz = shape[2] // lanes  # a multiple of the leaf size: whole rows
        ncol = shape[0] * shape[1]
        for wq in range(Q.span(ncol, COLUMN_CHUNK)):
            jq = Q.first(wq, ctr, Q_APPLY)
            while jq < Q.end(ncol, COLUMN_CHUNK):
                for ij in range(Q.begin(jq, ncol, COLUMN_CHUNK), Q.stop(jq, ncol, COLUMN_CHUNK)):
                    i, j = ij // shape[1], ij % shape[1]
                    cells = 0
                    last = -1
                    col = ij * wz
                    for kb in range(wz // row_words):
                        read = True
                        if flagged != 0:
                            read = bflag[i, j, kb] != 0
                            if read:
                                bflag[i, j, kb] = ti.i8(0)
                        if read:
                            # A row's words tested at once: most rows hold no count.
                            seen = ti.u64(0)
                            for kr in ti.static(range(row_words)):
                                seen |= words[col + kb * row_words + kr]
                            read = seen != 0
                        if read:
                            # The words a loop (eight inlined block_cells took 0.9 s of a first
                            # scan to compile; a loop over every lane cost ~15% of this kernel's time).
                            for kr in range(row_words):
                                kw = kb * row_words + kr
                                w = words[col + kw]
                                if w != 0:
                                    words[col + kw] = ti.u64(0)
                                    # A word lies in one tile (tiles are whole leaves): a tiled map's
                                    # worker clears other workers' cells without applying them.
                                    mine = owned(own, b0 + ti.Vector([i, j, kw * lanes]))
                                    if ti.static(ndt and bits == 32):
                                        # The marks (negative; hit marks were cleared by merge)
                                        # dropped from the whole word at once: their lanes' sign bits.
                                        top = w & ti.u64(highs)
                                        w &= ~((top >> ti.u64(bits - 1)) * ti.u64(mask))
                                    elif ti.static(ndt):
                                        # The marks (all bits set; hit marks were cleared by merge)
                                        # dropped from the whole word at once: t has a zero lane
                                        # exactly there, and no count makes t - ones borrow into a
                                        # lane's top bit.
                                        t = ~w
                                        top = (t - ti.u64(ones)) & ~t & ti.u64(highs)
                                        w &= ~((top >> ti.u64(bits - 1)) * ti.u64(mask))
                                    if mine == 0:
                                        w = ti.u64(0)
                                    # The word's counted lanes, lowest first, through one block_cell:
                                    # each inlined copy holds Taichi's node allocator, inlined at each
                                    # store to a sparse field (half the kernel's code to generate).
                                    while w != 0:
                                        lane = lanes - 1
                                        for q in ti.static(range(lanes - 2, -1, -1)):
                                            if (w >> ti.u64(bits * q)) & ti.u64(mask) != 0:
                                                lane = q
                                        sh = ti.u64(bits * lane)
                                        v = ti.cast((w >> sh) & ti.u64(mask), ti.i32)
                                        w &= ~(ti.u64(mask) << sh)
                                        k = kw * lanes + lane
                                        block_cell(
                                            slot,
                                            b0 + ti.Vector([i, j, k]),
                                            v,
                                            k >> SHIFT != last,
                                            l_free,
                                            l_min,
                                            l_max,
                                            rec_n,
                                            ctr,
                                            occ_regions,
                                            leaves,
                                            rec_free,
                                        )
                                        cells += 1
                                        last = k >> SHIFT
                    if cells > 0:
                        tally(ctr, C_BLOCK_CELLS, ij >> 3, cells)
                jq = Q.next(ctr, Q_APPLY)

    return Bound(
        block_apply,
        (
            "slot",
            "words",
            "bflag",
            "shape",
            "base",
            "flagged",
            *_FREE_PARTS,
            ("nodes", Nodes, ("occ_regions", "leaves")),
        ),
    )


def apply_free(f: Storage, ndt: bool) -> Bound:
    """eq. (12) for the cells of the tree that rays touched and no endpoint hit."""
    F = device_funcs(f)
    row, free_update_tree = F.row, F.free_update_tree

    def apply_free(
        slot: ti.i32,
        touched: i32_2d,  # Touched: [T, 3] cells
        nt: ti.i32,  # the first nt of them
        l_free: ti.f64,  # Model
        l_min: ti.f32,
        l_max: ti.f32,
        rec_n: i32_1d,  # Records
        rec_free: i32_1d,
        ctr: i64_1d,
        rec_miss: i64_1d,  # NdtRecords (ndt): miss sums, consumed here
        ndt_minp: ti.i32,
        rec_nbr: i32_1d,  # out: erased_beside's (ndt.py), with rec_icov
        rec_icov: f64_2d,
    ):
        for t in range(nt):
            free_update_tree(
                slot,
                row(touched, t),
                l_free,
                l_min,
                l_max,
                rec_n,
                ctr,
                rec_free,
                rec_miss,
                ndt_minp,
                ndt,
                rec_nbr,
                rec_icov,
            )

    return Bound(
        apply_free,
        (
            "slot",
            ("touched", Touched, ("touched",)),
            "nt",
            *_FREE_PARTS,
            ("ndt", NdtRecords, ("rec_miss", "ndt_minp", "rec_nbr", "rec_icov"))
            if ndt
            else (None, NdtRecords, ("rec_miss", "ndt_minp", "rec_nbr", "rec_icov")),
        ),
    )


def apply_free_all(f: Storage, ndt: bool) -> Bound:
    """apply_free over every cell of the slot: the fallback when the touched list overflowed."""
    F = device_funcs(f)
    ne, free_update_tree = f.ne, F.free_update_tree

    def apply_free_all(
        slot: ti.i32,
        l_free: ti.f64,  # Model
        l_min: ti.f32,
        l_max: ti.f32,
        rec_n: i32_1d,  # Records
        rec_free: i32_1d,
        ctr: i64_1d,
        rec_miss: i64_1d,  # NdtRecords (ndt)
        ndt_minp: ti.i32,
        rec_nbr: i32_1d,
        rec_icov: f64_2d,
    ):
        for I in ti.grouped(ne):
            if I[0] == slot and ne[I] & NE_COUNT > 0:
                free_update_tree(
                    slot,
                    ti.Vector([I[1], I[2], I[3]]),
                    l_free,
                    l_min,
                    l_max,
                    rec_n,
                    ctr,
                    rec_free,
                    rec_miss,
                    ndt_minp,
                    ndt,
                    rec_nbr,
                    rec_icov,
                )

    return Bound(
        apply_free_all,
        (
            "slot",
            *_FREE_PARTS,
            ("ndt", NdtRecords, ("rec_miss", "ndt_minp", "rec_nbr", "rec_icov"))
            if ndt
            else (None, NdtRecords, ("rec_miss", "ndt_minp", "rec_nbr", "rec_icov")),
        ),
    )


def ndt_refresh(f: Storage, _cfg=None) -> Bound:
    """ndt_icov of every record (after a load: merge keeps them current afterwards), or
    the wide rows of those with NDT_ERASED_NEIGHBOURS neighbours erased."""
    ndt_icov, wide = device_funcs(f).ndt_icov, device_funcs(f).wide

    def ndt_refresh(
        nrec: ti.i32,  # records in use
        rec_n: i32_1d,  # Records
        rec_mean: f64_2d,
        rec_scat: f64_2d,
        rec_icov: f64_2d,  # NdtRecords: out
        ndt_prm: f64_1d,
        rec_nbr: i32_1d,
    ):
        for r in range(nrec):
            if rec_n[r] > 0:
                ndt_icov(r, rec_n, rec_scat, rec_mean, ndt_prm, rec_icov)
                if rec_nbr[r] & NBR_COUNT >= NDT_ERASED_NEIGHBOURS:
                    wide(r, rec_icov)

    return Bound(
        ndt_refresh,
        (
            "nrec",
            ("records", Records, ("rec_n", "rec_mean", "rec_scat")),
            ("ndt", NdtRecords, ("rec_icov", "ndt_prm", "rec_nbr")),
        ),
    )


def erased_near(f: Storage, _cfg=None) -> Bound:
    """The NDT miss model's erased-neighbour rule for Gaussians erased in another worker's
    cells of a tiled map (its last scan): each neighbour here that holds one counts them, as
    erased_beside counts the erasures of this map's own cells during its free-space pass."""
    F = device_funcs(f)
    row, erased_beside = F.row, F.erased_beside

    def erased_near(
        slot: ti.i32,
        cells: i32_2d,  # [N, 3] the cells whose Gaussians were erased
        n: ti.i32,
        rec_n: i32_1d,  # Records
        ndt_minp: ti.i32,  # NdtRecords
        rec_nbr: i32_1d,
        rec_icov: f64_2d,
    ):
        for i in range(n):
            erased_beside(slot, row(cells, i), rec_n, rec_nbr, rec_icov, ndt_minp)

    return Bound(
        erased_near,
        (
            "slot",
            "cells",
            "n",
            ("records", Records, ("rec_n",)),
            ("ndt", NdtRecords, ("ndt_minp", "rec_nbr", "rec_icov")),
        ),
    )
