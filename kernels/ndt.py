"""Taichi kernels of the NDT-OM update (method.md sections 2 and 3).

Per scan, in this order:
1. ``rays``:         exact Amanatides-Woo traversal origin -> endpoint; integer count of
                     rays passing each cell: in a dense scan-local block over the scan's
                     cells (``rays_dense`` when it holds them all), in the tree past it
                     with a compact list of the cells touched there.
2. ``hits_count``:   points per hit cell (integer atomics), and a compact hit list.
3. ``hits_sum``:     scan-local sums relative to the cell centre, one slot per hit cell.
   (``hits_dense`` instead, on the CPU when the block holds every cell of the scan: the
   points grouped by hit cell in the block, summed by merge.)
4. ``merge``:        one thread per hit cell merges the scan's Gaussian into the cell's
                     record with the RCU (a new record for a cell's first points), then
                     applies eq. (12) to the cell and clears its ray count.
5. ``block_apply(_all)`` / ``apply_free``: eq. (12) once per cell that rays passed and no
                     endpoint hit, clamp, and reset of the Gaussian of a cell whose
                     log-odds fell to <= 0.

Kernels are closures over the process's storage, built once. The map's slot, its
resolution, sensor model and Gaussian records are arguments, so nothing recompiles per
map.
"""

from types import SimpleNamespace

import numpy as np
import taichi as ti
from taichi.lang import impl

from . import launch
from .layout import Storage

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
COUNTERS = 16
HIT_CHUNKS = 1024  # chunks of points of hits_dense's prefix sum (Taichi runs <= 512 iterations on one thread)
SPREAD_K = 4  # sectors per CPU thread and per scan in the rays kernels (see spread)
# Sums that every thread adds to (visits, block cells) go to STRIPES copies of the
# counters, two 64-byte lines each, picked by the work item: one atomic counter shared by
# all threads costs ~15 ns per add on the CPU. ``total`` adds the copies up.
STRIPES = 64
CTR_SIZE = COUNTERS * (1 + STRIPES)


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
# Block entry of a cell holding a usable Gaussian (set by mark_gaussians before the rays):
# ray counts never reach it (scans of at most 65534 rays use u16 blocks).
MARK_U16 = 0xFFFF
MARK_I32 = -1

# Finite in f32 too: kernel float literals are f32, and 1e300 would become inf, which
# fast math assumes never occurs. Ray parameters that matter are <= 1.
BIG = 1.0e30
# Ray parameters t in [0, 1] of two axes' crossings closer than this are settled by
# recomputing both by division. Summing steps strays < 1e-11 even over 10^5 steps.
TIE_MARGIN = 1.0e-9

i32_2d = ti.types.ndarray(dtype=ti.i32, ndim=2)
i32_1d = ti.types.ndarray(dtype=ti.i32, ndim=1)
i64_1d = ti.types.ndarray(dtype=ti.i64, ndim=1)
f64_2d = ti.types.ndarray(dtype=ti.f64, ndim=2)
f64_1d = ti.types.ndarray(dtype=ti.f64, ndim=1)
f32_1d = ti.types.ndarray(dtype=ti.f32, ndim=1)
i8_4d = ti.types.ndarray(dtype=ti.i8, ndim=4)
i8_3d = ti.types.ndarray(dtype=ti.i8, ndim=3)
i8_1d = ti.types.ndarray(dtype=ti.i8, ndim=1)
i64_2d = ti.types.ndarray(dtype=ti.i64, ndim=2)
i32_3d = ti.types.ndarray(dtype=ti.i32, ndim=3)
u64_1d = ti.types.ndarray(dtype=ti.u64, ndim=1)


def cpu_threads() -> int:
    """Threads of Taichi's CPU range-for loops (1 on a GPU, where order does not matter)."""
    cfg = impl.current_cfg()
    return max(1, int(cfg.cpu_max_num_threads)) if cfg.arch in (ti.x64, ti.arm64) else 1


def make_spread(threads: int):
    """The ray order for ``threads`` CPU threads: ``spread(i, q, inv_q)`` is the ray that
    iteration i of n traces, with q = n // sectors and inv_q = 1 / max(q, 1).

    Taichi 1.7 splits a CPU range-for into one contiguous run of iterations per thread,
    and scans come in azimuth order, so each thread traced one side of the scan: the side
    with the longer rays kept its thread busy after the other had finished (~11% more
    visits on the hall; twice the work beside a wall). Here each thread's run covers
    SPREAD_K sectors spread all around the scan, and at any moment the threads trace
    sectors 360/threads degrees apart, so they rarely count into the same cells. A
    permutation: the counts are the same in any order.
    """
    TH = threads
    KS = SPREAD_K * TH  # sectors per thread; a multiple of TH keeps KS + 1 prime to TH
    SEC = TH * KS

    @ti.func
    def spread(i, q, inv_q):
        # The last n % SEC rays keep their place. j = i // q by a multiply and a
        # correction: an integer division costs ~40 cycles a ray.
        r = i
        if ti.static(TH > 1) and i < q * SEC:
            j = ti.cast(ti.cast(i, ti.f64) * inv_q, ti.i32)
            j += ti.select((j + 1) * q <= i, 1, 0) - ti.select(j * q > i, 1, 0)
            c = j // KS  # the thread whose run holds iteration i
            m = j - c * KS  # and how far along its run
            r = ((m * TH + c * (KS + 1)) % SEC) * q + (i - j * q)
        return r

    return spread, SEC


def make_kernels(f: Storage) -> SimpleNamespace:
    """Build (once) and return the kernels bound to the storage ``f``."""
    if f.kernels is not None:
        return f.kernels
    lo, ne, olm = f.lo, f.ne, f.olm
    gslot, hn, hslot, glm = f.gslot, f.hn, f.hslot, f.glm
    L = f.layout
    leaf = L.leaf
    region = L.region
    grid_lo = ti.Vector(list(L.lo))
    grid_n = ti.Vector(list(L.cells))
    occ_l1, gidx_l1 = f.l1_nodes
    occ_l2, gidx_l2 = f.l2_nodes
    # The kernels of every scan get a lighter call (launch.py); queries keep Taichi's.
    fast = launch.Launcher if launch.enabled() else (lambda k: k)

    @ti.func
    def row(a: ti.template(), i) -> ti.types.vector(3, ti.i32):
        return ti.Vector([a[i, 0], a[i, 1], a[i, 2]], dt=ti.i32)

    @ti.func
    def at(slot, c) -> ti.types.vector(4, ti.i32):
        return ti.Vector([slot, c[0], c[1], c[2]], dt=ti.i32)

    @ti.func
    def note_leaf(mark: ti.template(), slot, c, regions: ti.template(), leaves: ti.template(), which: ti.template()):
        # Called before a cell is written: counts the leaf (and region) it creates.
        b = at(slot, c // leaf)
        if mark[b] == 0:
            if ti.atomic_or(mark[b], 1) == 0:
                ti.atomic_add(leaves[slot, which], 1)
                r = (c - grid_lo) // region
                regions[slot, r[0], r[1], r[2]] = ti.i8(1)

    @ti.kernel
    def prepare(
        pts: ti.types.ndarray(ndim=2),  # [N, 3] sensor-frame points (f32 or f64)
        n: ti.i32,
        rot: f64_1d,  # [9] R of T_world_sensor, row-major
        trans: f64_1d,  # [3] its translation
        res: ti.f64,
        r2: f64_1d,  # [3] min_range^2, max_range^2, max_range (free rays past it if > 0)
        out_world: f64_2d,  # [N, 3]
        out_cells: i32_2d,  # [N, 3]
        status: i8_1d,  # [N] 0 hit, 1 free ray, 2 not finite, 3 out of range, 4 outside the grid
    ):
        # No atomics: the caller compacts by status (contended counters cost more).
        for i in range(n):
            p = ti.Vector([ti.cast(pts[i, 0], ti.f64), ti.cast(pts[i, 1], ti.f64), ti.cast(pts[i, 2], ti.f64)])
            st = ti.i8(2)
            # Exponent bits all set: inf or NaN. (ti.math.isinf/isnan cast to f32 first,
            # which made finite points past 3.4e38 read as infinite.)
            e = ti.Vector([(ti.bit_cast(p[a], ti.u64) >> ti.u64(52)) & ti.u64(0x7FF) for a in ti.static(range(3))])
            if not (e == ti.u64(0x7FF)).any():
                st = ti.i8(3)
                d2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
                if d2 >= r2[0] and d2 <= r2[1]:
                    st = ti.i8(0)
                elif d2 > r2[1] and r2[2] > 0.0:
                    p = p * (r2[2] / ti.sqrt(d2))  # carve free space up to max_range
                    st = ti.i8(1)
                if st <= 1:
                    w = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
                    for a in ti.static(range(3)):
                        w[a] = rot[3 * a] * p[0] + rot[3 * a + 1] * p[1] + rot[3 * a + 2] * p[2] + trans[a]
                    cf = ti.floor(w / res)
                    if (cf >= grid_lo.cast(ti.f64)).all() and (cf < (grid_lo + grid_n).cast(ti.f64)).all():
                        for a in ti.static(range(3)):
                            out_world[i, a] = w[a]
                            out_cells[i, a] = ti.cast(cf[a], ti.i32)
                    else:
                        st = ti.i8(4)
            status[i] = st

    @ti.kernel
    def hits_count(
        slot: ti.i32,
        cells: i32_2d,  # [N, 3] cell of each hit point
        n: ti.i32,
        hitlist: i32_2d,  # [N, 3] out: distinct hit cells
        ctr: i64_1d,  # [CTR_SIZE]
        regions: i8_4d,  # [L1] index-tree regions in use
        leaves: i64_2d,  # [2] leaf counts
    ):
        for i in range(n):
            c = row(cells, i)
            if ti.atomic_add(hn[at(slot, c)], 1) == 0:
                # Every leaf these writes allocate holds a cell's first point: count it there.
                note_leaf(glm, slot, c, regions, leaves, 1)
                s = ti.atomic_add(ctr[C_HIT_CELLS], 1)
                for a in ti.static(range(3)):
                    hitlist[s, a] = c[a]
                hslot[at(slot, c)] = ti.i32(s)

    @ti.kernel
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

    spread, SEC = make_spread(cpu_threads())

    @ti.func
    def free_update(slot, c, dl, g, l_min, l_max, rec_n: ti.template(), ctr: ti.template(),
                    rec_free: ti.template()):  # fmt: skip
        # eq. (12) (or the NDT miss model) for a cell that rays passed and no endpoint hit:
        # dl is its log-odds change; reset of its Gaussian (g: NE_GAUSS set) at l <= 0: its
        # record goes on the free stack for the next new Gaussian of any cell, so records
        # follow the Gaussians alive, not all ever made.
        l = ti.min(ti.max(lo[at(slot, c)] + dl, l_min), l_max)
        lo[at(slot, c)] = l
        if l <= 0.0 and g != 0:
            r = gslot[at(slot, c)] - 1
            if r >= 0:
                if rec_n[r] > 0:
                    # Mean and scatter are overwritten by the next first merge.
                    rec_n[r] = 0
                    ti.atomic_add(ctr[C_ERASED], 1)
                    gslot[at(slot, c)] = 0
                    rec_free[ti.cast(ti.atomic_add(ctr[C_FREE], 1), ti.i32)] = r
            # Nothing left to erase: later passes skip the index tree until a hit sets it.
            ne[at(slot, c)] = ne[at(slot, c)] & NE_COUNT

    @ti.func
    def take_miss(r, rec_miss: ti.template()) -> ti.f32:
        # The NDT miss model's summed change of record r's cell, consumed.
        v = rec_miss[r]
        rec_miss[r] = ti.i64(0)
        return ti.cast(ti.cast(v, ti.f64) * (1.0 / MISS_SCALE), ti.f32)

    @ti.func
    def free_update_tree(slot, c, l_free, l_min, l_max, rec_n: ti.template(), ctr: ti.template(),
                         rec_free: ti.template(), rec_miss: ti.template(), ndt_minp):  # fmt: skip
        # Hit cells were updated by merge, which cleared their ray count: skipped. With the
        # NDT miss model (ndt_minp > 0) a cell whose Gaussian has >= ndt_minp points takes
        # the rays' summed likelihood terms instead of the count's.
        v = ne[at(slot, c)]
        k = v & NE_COUNT
        if k > 0:
            g = v & NE_GAUSS
            ne[at(slot, c)] = g
            dl = ti.cast(k * l_free, ti.f32)
            if ndt_minp > 0 and g != 0:
                r = gslot[at(slot, c)] - 1
                if r >= 0 and rec_n[r] >= ndt_minp:
                    dl = take_miss(r, rec_miss)
            free_update(slot, c, dl, g, l_min, l_max, rec_n, ctr, rec_free)

    @ti.func
    def block_cell(slot, c, v, new_leaf, l_free, l_min, l_max, rec_n: ti.template(), ctr: ti.template(),
                   regions: ti.template(), leaves: ti.template(), rec_free: ti.template(), rec_miss: ti.template(),
                   mark) -> ti.i32:  # fmt: skip
        # eq. (12) for a cell of the dense block that v rays passed (v == mark: a cell
        # holding a Gaussian, which takes the NDT miss model's sum); new_leaf: the first
        # such cell of its tree leaf in this pass, which counts the leaf if it creates it.
        # Returns 1 if the cell changed.
        if new_leaf:
            note_leaf(olm, slot, c, regions, leaves, 0)
        changed = 1
        if v == mark:
            dl = take_miss(gslot[at(slot, c)] - 1, rec_miss)
            if dl != 0.0:
                free_update(slot, c, dl, NE_GAUSS, l_min, l_max, rec_n, ctr, rec_free)
            else:
                changed = 0
        else:
            free_update(slot, c, ti.cast(v * l_free, ti.f32), ne[at(slot, c)] & NE_GAUSS, l_min, l_max, rec_n, ctr,
                        rec_free)  # fmt: skip
        return changed

    @ti.func
    def add_miss(r, c, o, z, u, length, hit, res, prm: ti.template(), rec_icov: ti.template(),
                 rec_miss: ti.template()):  # fmt: skip
        # The ray's NDT miss term added to record r's sum (terms that round to zero add nothing).
        v = ndt_miss(r, c, o, z, u, length, hit, res, prm, rec_icov)
        if v != 0:
            ti.atomic_add(rec_miss[r], v)

    @ti.func
    def ndt_visit(slot, c, o, z, u, length, hit, res, prm: ti.template(), rec_icov: ti.template(),
                  rec_miss: ti.template()):  # fmt: skip
        # A ray passing a cell of the block marked as holding a usable Gaussian.
        add_miss(gslot[at(slot, c)] - 1, c, o, z, u, length, hit, res, prm, rec_icov, rec_miss)

    @ti.func
    def ndt_tree_visit(slot, c, o, z, u, length, hit, res, prm: ti.template(), rec_n: ti.template(),
                       rec_icov: ti.template(), rec_miss: ti.template(), ndt_minp):  # fmt: skip
        # A ray passing a cell of the tree that may hold a Gaussian (NE_GAUSS).
        r = gslot[at(slot, c)] - 1
        if r >= 0 and rec_n[r] >= ndt_minp:
            add_miss(r, c, o, z, u, length, hit, res, prm, rec_icov, rec_miss)

    @ti.func
    def ndt_floor(s0, s1, s2, s3, s4, s5, prm: ti.template()) -> ti.f64:
        # Variance added on every axis of a Gaussian (xx xy xz yy yz zz) before it is
        # inverted: a share prm[2] of its trace always (flat ones stay invertible), and for
        # a line-like Gaussian (middle eigenvalue l2 < prm[3] x the largest l3: one scan
        # line across the cell) prm[4] x (prm[3] l3 - l2) / prm[3] more, so that it stands
        # for the surface the line samples.
        tr = s0 + s3 + s5
        out = prm[2] * tr + 1e-12
        # l2 < rho l3 needs c2 = l1 l2 + l1 l3 + l2 l3 <= (2 rho + rho^2) tr^2: the
        # eigenvalues are worked out only then.
        c2 = s0 * s3 + s0 * s5 + s3 * s5 - s1 * s1 - s2 * s2 - s4 * s4
        if c2 <= (2.0 * prm[3] + prm[3] * prm[3]) * tr * tr:
            q = tr / 3.0
            p2 = (s0 - q) ** 2 + (s3 - q) ** 2 + (s5 - q) ** 2 + 2.0 * (s1 * s1 + s2 * s2 + s4 * s4)
            if p2 > 1e-30 * q * q:
                p = ti.sqrt(p2 / 6.0)
                b0, b3, b5 = (s0 - q) / p, (s3 - q) / p, (s5 - q) / p
                b1, b2, b4 = s1 / p, s2 / p, s4 / p
                hdet = 0.5 * (b0 * (b3 * b5 - b4 * b4) - b1 * (b1 * b5 - b4 * b2) + b2 * (b1 * b4 - b3 * b2))
                phi = ti.acos(ti.min(ti.max(hdet, -1.0), 1.0)) / 3.0
                l3 = q + 2.0 * p * ti.cos(phi)
                l1 = q + 2.0 * p * ti.cos(phi + 2.0943951023931957)
                l2 = 3.0 * q - l1 - l3
                out += prm[4] * ti.max(0.0, prm[3] * l3 - l2) / prm[3]
        return out

    @ti.func
    def ndt_icov(r, rec_n: ti.template(), rec_scat: ti.template(), rec_mean: ti.template(), prm: ti.template(),
                 rec_icov: ti.template()):  # fmt: skip
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
        eps = ndt_floor(s0, s1, s2, s3, s4, s5, prm)
        a00, a11, a22 = s0 + eps, s3 + eps, s5 + eps
        c00 = a11 * a22 - s4 * s4
        c01 = s2 * s4 - s1 * a22
        c02 = s1 * s4 - s2 * a11
        c11 = a00 * a22 - s2 * s2
        c12 = s1 * s2 - a00 * s4
        c22 = a00 * a11 - s1 * s1
        det = a00 * c00 + s1 * c01 + s2 * c02
        rec_icov[r, 0] = c00 / det
        rec_icov[r, 1] = c01 / det
        rec_icov[r, 2] = c02 / det
        rec_icov[r, 3] = c11 / det
        rec_icov[r, 4] = c12 / det
        rec_icov[r, 5] = c22 / det
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
        # min_points, prior variance of a cell with fewer points (ndt_icov)].
        centre = (c.cast(ti.f64) + 0.5) * res
        oc = o - centre
        i0, i1, i2, i3, i4, i5 = rec_icov[r, 0], rec_icov[r, 1], rec_icov[r, 2], rec_icov[r, 3], rec_icov[r, 4], rec_icov[r, 5]
        inv = ti.Matrix([[i0, i1, i2], [i1, i3, i4], [i2, i4, i5]], dt=ti.f64)
        mu = ti.Vector([rec_icov[r, 6], rec_icov[r, 7], rec_icov[r, 8]])
        a = inv @ u
        # x_ML on the ray's line, kept on the segment the ray travelled.
        t = ti.min(ti.max(a.dot(mu - oc) / a.dot(u), 0.0), length)
        e = oc + t * u - mu
        m2 = e.dot(inv @ e)
        out = ti.i64(0)
        # Past m2 = 48, |logit(p)| < 4 eta exp(-24) < 2^-33: the term rounds to zero.
        if m2 < 48.0:
            p_n = ti.exp(-0.5 * m2)
            p_z = ti.f64(0.0)
            if hit:
                w = oc + t * u - (z - centre)
                p_z = ti.exp(-w.dot(w) * prm[1])
            p = 0.5 - prm[0] * p_n * (1.0 - p_z)
            out = ti.cast(ti.round(ti.log(p / (1.0 - p)) * MISS_SCALE), ti.i64)
        return out

    def block_kernels(bt):
        """The kernels that read or write the scan's dense ray-count block, for block
        dtype ``bt``: u16 halves its memory traffic and holds any count of a scan of at
        most 65535 rays (a ray passes a cell once); i32 takes larger scans."""
        b3d = ti.types.ndarray(dtype=bt, ndim=3)
        b1d = ti.types.ndarray(dtype=bt, ndim=1)
        bits = 16 if bt == ti.u16 else 32
        mark = MARK_U16 if bt == ti.u16 else MARK_I32  # as the i32 that block_cell compares

        @ti.func
        def hit_update(slot, c, cnt, l_hit, l_min, l_max, regions: ti.template(), leaves: ti.template(),
                       block: ti.template(), b0, bsize, ctr: ti.template(), dense_hits):  # fmt: skip
            # eq. (12) for a cell with endpoints: the hit update only, its ray count cleared;
            # the cell has a Gaussian record now.
            note_leaf(olm, slot, c, regions, leaves, 0)
            lo[at(slot, c)] = ti.min(ti.max(lo[at(slot, c)] + ti.cast(cnt * l_hit, ti.f32), l_min), l_max)
            if dense_hits == 0:
                hn[at(slot, c)] = 0
            v = ne[at(slot, c)]
            ne[at(slot, c)] = NE_GAUSS
            rel = c - b0
            if (rel >= 0).all() and (rel < bsize).all():
                block[rel[0], rel[1], rel[2]] = ti.cast(0, bt)
            elif v & NE_COUNT != 0:
                ti.atomic_add(ctr[C_HIT_PASSED], 1)

        @ti.kernel
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
            # the order of the cells' first points.
            for c in range(HIT_CHUNKS):
                k = 0
                for i in range(c * size, ti.min(n, (c + 1) * size)):
                    if rank[i] == 0:
                        k += 1
                first[c + 1] = k
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
            for _ in range(1):
                run = 0
                for s in range(first[HIT_CHUNKS]):
                    off[s] = run
                    run += hcnt[s]
            for i in range(n):
                q = row(cells, i) - b0
                order[off[ti.cast(block[q[0], q[1], q[2]], ti.i32)] + rank[i]] = i

        @ti.kernel
        def merge(
            slot: ti.i32,
            hitlist: i32_2d,  # [H, 3]
            acc: f64_2d,  # [H, 9]
            nh: ti.i32,
            n_max: ti.i32,  # 0: no cap
            rec_n: i32_1d,  # [C] records: points
            rec_cell: i32_2d,  # [C, 3] records: cell index
            rec_mean: f64_2d,  # [C, 3] records: mean minus cell centre
            rec_scat: f64_2d,  # [C, 6] records: scatter xx xy xz yy yz zz
            ctr: i64_1d,  # [CTR_SIZE]; C_RECORDS holds the records in use
            l_hit: ti.f64,
            l_min: ti.f32,
            l_max: ti.f32,
            regions: i8_4d,  # [slots, L1] occupancy-tree regions in use
            leaves: i64_2d,
            block: b3d,  # the scan's dense ray counts (see rays)
            base: i32_1d,
            use_block: ti.i32,
            hcnt: i32_1d,  # [H] points per hit cell, from hits_dense (dense_hits != 0)
            gregions: i8_4d,  # [slots, L1] index-tree regions in use
            dense_hits: ti.i32,  # 1: hits grouped by hits_dense, 0: counted and summed in the tree
            pts: f64_2d,  # [N, 3] world points of the hits (dense_hits)
            order: i32_1d,  # [N] (dense_hits)
            off: i32_1d,  # [H] (dense_hits)
            res: ti.f64,
            rec_free: i32_1d,  # [C] stack of free records (ctr[C_FREE] of them)
            left: i32_1d,  # [H] out: hit cells (s) left untouched, all records taken
            rec_miss: i64_1d,  # [C] NDT miss sums of this scan: a hit cell takes the hit update only
            rec_icov: f64_2d,  # [C, 9] out (ndt != 0): ndt_icov of the changed records
            prm: f64_1d,  # [7] NDT miss model parameters (see ndt_miss)
            ndt: ti.i32,  # points a cell needs for the NDT miss model (the map passes 1; 0: the paper's model)
        ):
            # One thread per hit cell: the RCU merge of the scan's Gaussian, then eq. (12).
            # Records are not reserved for the worst case (every hit cell new): a cell that
            # finds none is left as it was, for the caller to grow the records and merge it.
            b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
            bsize = ti.Vector([block.shape[0], block.shape[1], block.shape[2]], dt=ti.i32) * use_block
            for s in range(nh):
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
                    if dense_hits != 0:  # hits_count did not touch the index tree
                        note_leaf(glm, slot, c, gregions, leaves, 1)
                    gslot[at(slot, c)] = r + 1
                    for a in ti.static(range(3)):
                        rec_cell[r, a] = c[a]
                cnt = 0
                if dense_hits != 0:
                    cnt = hcnt[s]
                else:
                    cnt = hn[at(slot, c)]  # read once: each tree access walks both pointer levels
                n = ti.cast(cnt, ti.f64)
                sv = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
                ss = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dt=ti.f64)
                if dense_hits != 0:  # sums relative to the cell centre, as hits_sum's
                    centre = (c.cast(ti.f64) + 0.5) * res
                    for j in range(off[s], off[s] + cnt):
                        i = order[j]
                        x = ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]]) - centre
                        sv += x
                        ss += ti.Vector([x[0] * x[0], x[0] * x[1], x[0] * x[2], x[1] * x[1], x[1] * x[2], x[2] * x[2]])
                else:
                    sv = ti.Vector([acc[s, 0], acc[s, 1], acc[s, 2]])
                    ss = ti.Vector([acc[s, 3], acc[s, 4], acc[s, 5], acc[s, 6], acc[s, 7], acc[s, 8]])
                mu_y = sv / n
                s_y = ss - ti.Vector(
                    [sv[0] * sv[0], sv[0] * sv[1], sv[0] * sv[2], sv[1] * sv[1], sv[1] * sv[2], sv[2] * sv[2]]
                ) / n
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
                if ndt != 0:  # (the paper's model passes no NDT arrays)
                    rec_miss[r] = ti.i64(0)
                    if tot_i >= ndt:  # what rays read of the cell's points
                        ndt_icov(r, rec_n, rec_scat, rec_mean, prm, rec_icov)
                    # A cell's first points: the misses it took while it held none tested no
                    # surface, so its log-odds restarts from 0 if they had lowered it.
                    if m_i == 0 and lo[at(slot, c)] < 0.0:
                        lo[at(slot, c)] = 0.0
                hit_update(slot, c, cnt, l_hit, l_min, l_max, regions, leaves, block, b0, bsize, ctr, dense_hits)

        def make_rays(mode: str, flags: bool = True, ndt: bool = False):
            # "full": counts in the dense block where it covers the cell, else in the tree.
            # "dense": the block covers every cell of the scan: no bounds checks, no tree;
            # with flags=False no row flags either (a second cache line per visit), for
            # blocks that rays fill densely: block_apply_all then reads every cell.
            # "floor": the benchmark floor: the same traversal through the tree, one integer
            # atomic per visited cell and nothing else.
            # ndt: the NDT miss model: a visit to a cell holding a usable Gaussian (its block
            # entry marked, or NE_GAUSS in the tree and enough points) adds the ray's
            # likelihood term to the Gaussian's record; other visits only count.
            full = mode != "floor"
            @ti.kernel
            def rays(
                slot: ti.i32,
                pts: f64_2d,  # [N, 3] world endpoints
                cells: i32_2d,  # [N, 3] endpoint cells
                n_hit: ti.i32,  # rays [0, n_hit) end in a hit; the rest are free rays
                n: ti.i32,
                origin: f64_1d,  # [3] world sensor origin
                ocell: i32_1d,  # [3] its cell
                res: ti.f64,
                touched: i32_2d,  # [cap, 3] out: cells touched for the first time this scan
                cap: ti.i64,
                ctr: i64_1d,  # [CTR_SIZE]
                regions: i8_4d,  # [slots, L1] occupancy-tree regions in use
                leaves: i64_2d,  # [slots, 2]
                block: b3d,  # [Bx, By, Bz] dense ray counts around the sensor (full only)
                bflag: i8_3d,  # [Bx, By, Bz/leaf] rows of the block that rays entered
                base: i32_1d,  # [3] cell index of block[0, 0, 0]
                block1: b1d,  # the same block and flags, flat ("dense" steps a flat index)
                bflag1: i8_1d,
                use_block: ti.i32,
                rec_n: i32_1d,  # [C] Gaussian records (ndt): points
                rec_icov: f64_2d,  # [C, 9] inverse regularised covariance and mean (see ndt_icov)
                rec_miss: i64_1d,  # [C] out: summed log-odds changes, fixed point (MISS_SCALE)
                prm: f64_1d,  # [7] eta, 1 / (2 sigma_s^2), covariance floors (ndt_floor), min_points, prior (ndt_icov)
                ndt_minp: ti.i32,  # points a Gaussian needs for the NDT miss model
            ):
                o = ti.Vector([origin[0], origin[1], origin[2]])
                strides = ti.Vector([block.shape[1] * block.shape[2], block.shape[2], 1], dt=ti.i32)
                b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
                bsize = ti.Vector([block.shape[0], block.shape[1], block.shape[2]], dt=ti.i32) * use_block
                co = ti.Vector([ocell[0], ocell[1], ocell[2]], dt=ti.i32)
                q = n // SEC
                inv_q = 1.0 / ti.cast(ti.max(q, 1), ti.f64)
                for it in range(n):
                    i = spread(it, q, inv_q)
                    ce = row(cells, i)
                    z = ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]])
                    d = z - o
                    length = d.norm()  # the NDT miss model's (dead code without it)
                    u = d / length
                    cur = co
                    step = ti.Vector([0, 0, 0], dt=ti.i32)
                    rem = ti.Vector([0, 0, 0], dt=ti.i32)
                    tmax = ti.Vector([BIG, BIG, BIG], dt=ti.f64)
                    tdel = ti.Vector([BIG, BIG, BIG], dt=ti.f64)
                    for a in ti.static(range(3)):
                        diff = ce[a] - co[a]
                        if diff != 0:
                            step[a] = 1 if diff > 0 else -1
                            rem[a] = ti.abs(diff)
                            face = co[a] + 1 if diff > 0 else co[a]
                            tmax[a] = (ti.cast(face, ti.f64) * res - o[a]) / d[a]
                            tdel[a] = res / ti.abs(d[a])
                    visits = 0
                    last_leaf = ti.Vector([-(1 << 30), 0, 0], dt=ti.i32)
                    li = (co - b0).dot(strides)  # flat index of the current cell in the block
                    dli = step * strides
                    left = rem[0] + rem[1] + rem[2]
                    # Each pass steps at least one axis towards the endpoint cell, so the loop
                    # ends exactly there after at most |ce - co|_1 passes, whatever rounding does.
                    while left > 0:
                        rel = cur - b0
                        if ti.static(mode == "dense"):
                            if ti.static(ndt) and block1[li] == ti.cast(mark, bt):
                                ndt_visit(slot, cur, o, z, u, length, i < n_hit, res, prm, rec_icov, rec_miss)
                            else:
                                ti.atomic_add(block1[li], ti.cast(1, bt))
                            if ti.static(flags):
                                bflag1[li >> SHIFT] = ti.i8(1)  # rows of `leaf` cells along z
                        elif ti.static(full) and (rel >= 0).all() and (rel < bsize).all():
                            # Near the sensor every ray passes: count in the dense block,
                            # applied to the tree once per cell by block_apply.
                            if ti.static(ndt) and block[rel[0], rel[1], rel[2]] == ti.cast(mark, bt):
                                ndt_visit(slot, cur, o, z, u, length, i < n_hit, res, prm, rec_icov, rec_miss)
                            else:
                                ti.atomic_add(block[rel[0], rel[1], rel[2]], ti.cast(1, bt))
                            lb = ti.Vector([rel[0], rel[1], rel[2] // leaf])  # a row of `leaf` cells
                            if (lb != last_leaf).any():
                                bflag[lb[0], lb[1], lb[2]] = ti.i8(1)
                                last_leaf = lb
                        else:
                            lf = cur // leaf
                            if (lf != last_leaf).any():  # a leaf is counted when a ray enters it
                                note_leaf(olm, slot, cur, regions, leaves, 0)
                                last_leaf = lf
                            if ti.static(full):
                                g = visit(slot, cur, touched, cap, ctr)
                                if ti.static(ndt) and g != 0:
                                    ndt_tree_visit(slot, cur, o, z, u, length, i < n_hit, res, prm, rec_n, rec_icov,
                                                   rec_miss, ndt_minp)  # fmt: skip
                            else:
                                ti.atomic_add(ne[at(slot, cur)], 1)
                        visits += 1
                        # One axis crosses first by a clear margin (the common case): step it,
                        # advancing its crossing parameter by addition.
                        first = -1
                        if tmax[0] + TIE_MARGIN < tmax[1] and tmax[0] + TIE_MARGIN < tmax[2]:
                            first = 0
                        elif tmax[1] + TIE_MARGIN < tmax[0] and tmax[1] + TIE_MARGIN < tmax[2]:
                            first = 1
                        elif tmax[2] + TIE_MARGIN < tmax[0] and tmax[2] + TIE_MARGIN < tmax[1]:
                            first = 2
                        if first >= 0:
                            for a in ti.static(range(3)):
                                if a == first:
                                    cur[a] += step[a]
                                    rem[a] -= 1
                                    left -= 1
                                    li += dli[a]
                                    tmax[a] = tmax[a] + tdel[a] if rem[a] > 0 else BIG
                        else:
                            # Near a tie: the crossings recomputed by division, as the decision
                            # the margin stands in for (the sums stray far less than it).
                            for a in ti.static(range(3)):
                                tmax[a] = next_t(cur[a], step[a], rem[a], res, o[a], d[a])
                            tmin = ti.min(tmax[0], tmax[1], tmax[2])
                            ties = 0
                            up = False
                            for a in ti.static(range(3)):
                                if tmax[a] == tmin:
                                    ties += 1
                                    if step[a] > 0:
                                        up = True
                            # An exact tie (the segment crosses an edge or corner): axes stepping
                            # up move first, so the cell holding the crossing point is visited.
                            for a in ti.static(range(3)):
                                if tmax[a] == tmin and (ties == 1 or (step[a] > 0) == up):
                                    cur[a] += step[a]
                                    rem[a] -= 1
                                    left -= 1
                                    li += dli[a]
                                    tmax[a] = next_t(cur[a], step[a], rem[a], res, o[a], d[a])
                    if ti.static(full) and i >= n_hit:  # a free ray passes its last cell too
                        if ti.static(mode == "dense"):  # li is the endpoint cell's now
                            if ti.static(ndt) and block1[li] == ti.cast(mark, bt):
                                ndt_visit(slot, ce, o, z, u, length, False, res, prm, rec_icov, rec_miss)
                            else:
                                ti.atomic_add(block1[li], ti.cast(1, bt))
                            if ti.static(flags):
                                bflag1[li >> SHIFT] = ti.i8(1)
                        else:
                            note_leaf(olm, slot, ce, regions, leaves, 0)
                            g = visit(slot, ce, touched, cap, ctr)
                            if ti.static(ndt) and g != 0:
                                ndt_tree_visit(slot, ce, o, z, u, length, False, res, prm, rec_n, rec_icov, rec_miss,
                                               ndt_minp)  # fmt: skip
                        visits += 1
                    tally(ctr, C_VISITS, i >> 5, visits)

            return rays

        @ti.kernel
        def block_apply(
            slot: ti.i32,
            block: b3d,  # [Bx, By, Bz] ray counts, zeroed here
            bflag: i8_3d,  # [Bx, By, Bz/leaf] rows entered, zeroed here
            base: i32_1d,  # [3]
            l_free: ti.f64,
            l_min: ti.f32,
            l_max: ti.f32,
            rec_n: i32_1d,
            ctr: i64_1d,
            regions: i8_4d,
            leaves: i64_2d,
            rec_free: i32_1d,
            rec_miss: i64_1d,  # [C] NDT miss sums of marked cells, consumed here
        ):
            # eq. (12) for the cells of the dense block, straight from their counts (hit cells
            # were zeroed by merge). One leaf of the tree per iteration, so its cells are
            # updated together (the block is leaf-aligned).
            b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
            for bi, bj, kb in ti.ndrange(block.shape[0] // leaf, block.shape[1] // leaf, block.shape[2] // leaf):
                cells = 0
                for ii, jj in ti.ndrange(leaf, leaf):
                    i, j = bi * leaf + ii, bj * leaf + jj
                    if bflag[i, j, kb] != 0:
                        bflag[i, j, kb] = ti.i8(0)
                        for kk in range(leaf):
                            k = kb * leaf + kk
                            v = ti.cast(block[i, j, k], ti.i32)
                            if v != 0:
                                block[i, j, k] = ti.cast(0, bt)
                                cells += block_cell(slot, b0 + ti.Vector([i, j, k]), v, cells == 0, l_free, l_min, l_max,
                                                    rec_n, ctr, regions, leaves, rec_free, rec_miss, mark)  # fmt: skip
                if cells > 0:
                    tally(ctr, C_BLOCK_CELLS, bi * (block.shape[1] // leaf) + bj, cells)

        lanes = 64 // bits  # block entries per 64-bit word
        mask = (1 << bits) - 1

        @ti.kernel
        def block_apply_all(
            slot: ti.i32,
            words: u64_1d,  # the block, flat, as 64-bit words: ray counts, zeroed here
            shape: i32_1d,  # [3] its shape in cells
            base: i32_1d,
            l_free: ti.f64,
            l_min: ti.f32,
            l_max: ti.f32,
            rec_n: i32_1d,
            ctr: i64_1d,
            regions: i8_4d,
            leaves: i64_2d,
            rec_free: i32_1d,
            rec_miss: i64_1d,
        ):
            # block_apply for a block the rays filled densely (no row flags): every column
            # of cells along z read in memory order, a word of `lanes` cells at a time, so
            # the empty cells (most of them) cost one test per word. Little-endian: lane 0
            # is the word's first cell.
            b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
            wz = shape[2] // lanes  # a multiple of the leaf size: whole words
            for i, j in ti.ndrange(shape[0], shape[1]):
                cells = 0
                last = -1
                col = (i * shape[1] + j) * wz
                for kw in range(wz):
                    w = words[col + kw]
                    if w != 0:
                        words[col + kw] = ti.u64(0)
                        for lane in ti.static(range(lanes)):
                            v = ti.cast((w >> ti.u64(bits * lane)) & ti.u64(mask), ti.i32)
                            if v != 0:
                                k = kw * lanes + lane
                                cells += block_cell(slot, b0 + ti.Vector([i, j, k]), v, k >> SHIFT != last, l_free, l_min,
                                                    l_max, rec_n, ctr, regions, leaves, rec_free, rec_miss, mark)  # fmt: skip
                                last = k >> SHIFT
                if cells > 0:
                    tally(ctr, C_BLOCK_CELLS, (i * shape[1] + j) >> 3, cells)

        @ti.kernel
        def mark_gaussians(
            nrec: ti.i32,
            rec_n: i32_1d,  # [C] records: points
            rec_cell: i32_2d,  # [C, 3] records: cell index
            ndt_minp: ti.i32,
            block: b3d,  # [Bx, By, Bz] the scan's zeroed ray counts
            bflag: i8_3d,  # [Bx, By, Bz/leaf] row flags
            base: i32_1d,  # [3]
        ):
            # Before the rays of the NDT miss model: the block entries of cells holding a
            # Gaussian of >= ndt_minp points get the mark (their rows flagged, so that
            # block_apply visits and clears them).
            b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
            bsize = ti.Vector([block.shape[0], block.shape[1], block.shape[2]], dt=ti.i32)
            for r in range(nrec):
                if rec_n[r] >= ndt_minp:
                    rel = row(rec_cell, r) - b0
                    if (rel >= 0).all() and (rel < bsize).all():
                        block[rel[0], rel[1], rel[2]] = ti.cast(mark, bt)
                        bflag[rel[0], rel[1], rel[2] // leaf] = ti.i8(1)

        return SimpleNamespace(
            mark_gaussians=fast(mark_gaussians),
            hits_dense=fast(hits_dense),
            merge=fast(merge),
            rays=fast(make_rays("full")),
            rays_dense=fast(make_rays("dense")),
            rays_dense_unflagged=fast(make_rays("dense", flags=False)),
            ndt_rays=fast(make_rays("full", ndt=True)),
            ndt_rays_dense=fast(make_rays("dense", ndt=True)),
            ndt_rays_dense_unflagged=fast(make_rays("dense", flags=False, ndt=True)),
            block_apply=fast(block_apply),
            block_apply_all=fast(block_apply_all),
            rays_floor=fast(make_rays("floor")),
        )

    by_dtype = {np.dtype(np.uint16): block_kernels(ti.u16), np.dtype(np.int32): block_kernels(ti.i32)}

    @ti.kernel
    def apply_free(
        slot: ti.i32,
        touched: i32_2d,  # [T, 3]
        nt: ti.i32,
        l_free: ti.f64,
        l_min: ti.f32,
        l_max: ti.f32,
        rec_n: i32_1d,
        ctr: i64_1d,
        rec_free: i32_1d,  # [C] stack of free records (ctr[C_FREE] of them)
        rec_miss: i64_1d,  # [C] NDT miss sums, consumed here
        ndt_minp: ti.i32,  # 0: the paper's eq. (12) for every cell
    ):
        for t in range(nt):
            free_update_tree(slot, row(touched, t), l_free, l_min, l_max, rec_n, ctr, rec_free, rec_miss, ndt_minp)

    @ti.kernel
    def apply_free_all(slot: ti.i32, l_free: ti.f64, l_min: ti.f32, l_max: ti.f32, rec_n: i32_1d, ctr: i64_1d,
                       rec_free: i32_1d, rec_miss: i64_1d, ndt_minp: ti.i32):  # fmt: skip
        # Fallback when the touched list overflowed: visit every known cell.
        for I in ti.grouped(ne):
            if I[0] == slot and ne[I] & NE_COUNT > 0:
                free_update_tree(slot, ti.Vector([I[1], I[2], I[3]]), l_free, l_min, l_max, rec_n, ctr, rec_free, rec_miss,
                                 ndt_minp)  # fmt: skip

    @ti.kernel
    def ndt_refresh(nrec: ti.i32, rec_n: i32_1d, rec_scat: f64_2d, rec_mean: f64_2d, prm: f64_1d, rec_icov: f64_2d):
        # ndt_icov of every record (after a load: merge keeps them current afterwards).
        for r in range(nrec):
            if rec_n[r] > 0:
                ndt_icov(r, rec_n, rec_scat, rec_mean, prm, rec_icov)

    @ti.kernel
    def count_new_nodes(
        slot: ti.i32,
        cells: i32_2d,
        n: ti.i32,
        lbase: i32_1d,  # [3] first leaf of ``seen``
        seen: i32_3d,  # zeroed flags over the cells' box of leaves
        dedup: ti.i32,  # 0: the cells lie in distinct leaves already (``seen`` unused)
        rbase: i32_1d,  # [3] first region of ``rseen``
        rseen: i32_3d,  # zeroed flags over the cells' box of regions
        occ_regions: i8_4d,
        gidx_regions: i8_4d,
        out: i64_1d,  # [4] new occupancy leaves, index leaves, occupancy regions, index regions
    ):
        # Nodes the cells would allocate in each tree, each counted once. Reading never
        # allocates.
        b0 = ti.Vector([lbase[0], lbase[1], lbase[2]], dt=ti.i32)
        r0 = ti.Vector([rbase[0], rbase[1], rbase[2]], dt=ti.i32)
        for i in range(n):
            c = row(cells, i)
            lf = c // leaf
            first = True
            if dedup != 0:
                q = lf - b0
                first = ti.atomic_or(seen[q[0], q[1], q[2]], 1) == 0
            if first:
                b = at(slot, lf)
                if olm[b] == 0:
                    ti.atomic_add(out[0], 1)
                if glm[b] == 0:
                    ti.atomic_add(out[1], 1)
                r = (c - grid_lo) // region
                q = r - r0
                if ti.atomic_or(rseen[q[0], q[1], q[2]], 1) == 0:
                    if occ_regions[slot, r[0], r[1], r[2]] == 0:
                        ti.atomic_add(out[2], 1)
                    if gidx_regions[slot, r[0], r[1], r[2]] == 0:
                        ti.atomic_add(out[3], 1)

    @ti.kernel
    def reset_rays(slot: ti.i32, touched: i32_2d, nt: ti.i32):
        for t in range(nt):
            c = row(touched, t)
            ne[at(slot, c)] = ne[at(slot, c)] & NE_GAUSS

    @ti.kernel
    def reset_rays_all(slot: ti.i32):
        for I in ti.grouped(ne):
            if I[0] == slot:
                ne[I] = ne[I] & NE_GAUSS

    # ---- queries, export, load -------------------------------------------------------

    @ti.kernel
    def query(slot: ti.i32, cells: i32_2d, n: ti.i32, out: f32_1d):
        for i in range(n):
            out[i] = lo[at(slot, row(cells, i))]

    @ti.kernel
    def count_known(slot: ti.i32, ctr: i64_1d):
        for I in ti.grouped(lo):
            if I[0] == slot and lo[I] != 0.0:
                ti.atomic_add(ctr[C_EXPORT], 1)

    @ti.kernel
    def export_known(slot: ti.i32, idx: i32_2d, val: f32_1d, ctr: i64_1d):
        for I in ti.grouped(lo):
            if I[0] == slot and lo[I] != 0.0:
                k = ti.atomic_add(ctr[C_EXPORT], 1)
                for a in ti.static(range(3)):
                    idx[k, a] = I[a + 1]
                val[k] = lo[I]

    @ti.kernel
    def load_known(slot: ti.i32, idx: i32_2d, val: f32_1d, n: ti.i32, regions: i8_4d, leaves: i64_2d):
        for k in range(n):
            c = row(idx, k)
            note_leaf(olm, slot, c, regions, leaves, 0)
            lo[at(slot, c)] = val[k]

    @ti.kernel
    def load_slots(slot: ti.i32, rec_cell: i32_2d, n: ti.i32, regions: i8_4d, occ_regions: i8_4d, leaves: i64_2d):
        for r in range(n):
            c = row(rec_cell, r)
            note_leaf(glm, slot, c, regions, leaves, 1)
            gslot[at(slot, c)] = r + 1
            note_leaf(olm, slot, c, occ_regions, leaves, 0)
            ne[at(slot, c)] = ne[at(slot, c)] | NE_GAUSS

    @ti.kernel
    def count_leaf_cells(ctr: i64_2d):
        # Independent check of the leaf counters (tests): cells of active leaves per slot.
        for I in ti.grouped(lo):
            ti.atomic_add(ctr[I[0], 0], 1)
        for I in ti.grouped(gslot):
            ti.atomic_add(ctr[I[0], 1], 1)

    @ti.kernel
    def clear_slot(slot: ti.i32):
        # Bottom-up: leaves (L2 cells) first, then the L2 blocks, so every node goes back
        # to Taichi's free lists.
        for i, j, k in ti.ndrange(L.l1[0], L.l1[1], L.l1[2]):
            for l1, l2 in ti.static(((occ_l1, occ_l2), (gidx_l1, gidx_l2))):
                if ti.is_active(l1, [slot, i, j, k]):
                    for a, b, c in ti.ndrange(L.l2, L.l2, L.l2):
                        p = [slot, i * L.l2 + a, j * L.l2 + b, k * L.l2 + c]
                        if ti.is_active(l2, p):
                            ti.deactivate(l2, p)
                    ti.deactivate(l1, [slot, i, j, k])

    f.kernels = SimpleNamespace(
        prepare=fast(prepare),
        hits_count=fast(hits_count),
        hits_sum=fast(hits_sum),
        block=by_dtype,  # by the block's numpy dtype
        rays_floor=by_dtype[np.dtype(np.int32)].rays_floor,
        apply_free=fast(apply_free),
        apply_free_all=fast(apply_free_all),
        ndt_refresh=ndt_refresh,
        reset_rays=fast(reset_rays),
        count_new_nodes=count_new_nodes,
        reset_rays_all=reset_rays_all,
        query=query,
        count_known=count_known,
        export_known=export_known,
        load_known=load_known,
        load_slots=load_slots,
        count_leaf_cells=count_leaf_cells,
        clear_slot=clear_slot,
    )
    return f.kernels
