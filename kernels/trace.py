"""The ray-traversal family: exact Amanatides-Woo traversal of each ray origin -> endpoint
(method.md section 2), counting the rays that pass each cell; and what goes with it
(marking the cells whose Gaussians the NDT miss model tests, undoing a refused batch,
counting the nodes a scan's hits would add)."""

from dataclasses import dataclass

import taichi as ti

from .args import Block, Bound, NdtRecords, Nodes, Picked, Rays, Records, Sensor, Touched
from .layout import Storage
from .ndt import (
    BIG,
    C_SKIPPED,
    C_VISITS,
    HIT_I32,
    HIT_U16,
    MARK_I32,
    MARK_U16,
    NE_GAUSS,
    Q_RAYS,
    TIE_MARGIN,
    cpu_threads,
    device_funcs,
    f64_1d,
    f64_2d,
    i8_1d,
    i8_3d,
    i8_4d,
    i32_1d,
    i32_2d,
    i32_3d,
    i64_1d,
    i64_2d,
    rolled,
)

BLOCK_DTYPES = ("u16", "i32")


def ray_chunk(threads: int) -> int:
    """Rays a thread takes from the ray queue at a time: ~2048 / threads, from 64 to 1024,
    so a scan of 57k rays is ~28 chunks a thread from 2 to 32 threads (56 on one). On the project's
    2-core VM, two threads traced a 0.2 m hall scan faster with 1024 than with 64, one
    thread the same (docs/performance.md, the eleventh round)."""
    return max(64, min(1024, 2048 // max(1, threads)))


def block_type(bt: str):
    """Taichi dtype of the dense block: u16 halves its memory traffic and holds any count
    of a scan of at most 65534 rays (a ray passes a cell once); i32 takes larger scans."""
    if bt not in BLOCK_DTYPES:
        raise ValueError(f"block dtype must be one of {BLOCK_DTYPES}, got {bt!r}")
    return ti.u16 if bt == "u16" else ti.i32


def block_mark(bt: str) -> int:
    """Block entry of a cell holding a usable Gaussian (NDT miss model), as the i32 that
    the rays compare."""
    return MARK_U16 if bt == "u16" else MARK_I32


def block_counts(bt: str):
    """``counts(v)``: whether block entry v of a block of dtype bt (as read, or cast to
    i32) is a ray count, not one of mark_gaussians' marks."""
    if bt == "u16":

        @ti.func
        def counts(v):
            return ti.cast(v, ti.i32) < HIT_U16

    else:

        @ti.func
        def counts(v):
            return ti.cast(v, ti.i32) >= 0

    return counts


@dataclass(frozen=True)
class RaysConfig:
    """One variant of the rays kernel.

    mode: "full" counts in the dense block where it covers the cell, else in the tree;
    "dense": the block covers every cell of the scan: no bounds checks, no tree;
    "floor": the benchmark floor: the same traversal through the tree, one integer atomic
    per visited cell and nothing else.
    ndt: the NDT miss model: a visit to a cell holding a usable Gaussian (its block entry
    marked, or NE_GAUSS in the tree and enough points) adds the ray's likelihood term to
    the Gaussian's record; other visits only count.
    """

    bt: str = "u16"
    mode: str = "full"
    ndt: bool = False

    def __post_init__(self):
        block_type(self.bt)
        if self.mode not in ("full", "dense", "floor"):
            raise ValueError(f"rays mode must be full, dense or floor, got {self.mode!r}")


def rays(f: Storage, cfg: RaysConfig) -> Bound:
    F = device_funcs(f)
    ne, olm = f.ne, f.olm
    row, at, note_leaf, tally, visit, next_t = F.row, F.at, F.note_leaf, F.tally, F.visit, F.next_t
    ndt_visit, ndt_tree_visit, add_miss = F.ndt_visit, F.ndt_tree_visit, F.add_miss
    Q, SHIFT, leaf, owned, owner_spec = F.queue, F.SHIFT, F.leaf, F.owned, F.owner_spec
    mode, ndt = cfg.mode, cfg.ndt
    chunk = ray_chunk(cpu_threads())
    bt = block_type(cfg.bt)
    mark = block_mark(cfg.bt)
    counts = block_counts(cfg.bt)
    full = mode != "floor"
    b3d = ti.types.ndarray(dtype=bt, ndim=3)
    b1d = ti.types.ndarray(dtype=bt, ndim=1)

    @ti.func
    def block_visit(
        entry: ti.template(),
        near,
        slot,
        c,
        o,
        z,
        u,
        length,
        hit,
        res,
        ndt_prm: ti.template(),
        rec_icov: ti.template(),
        rec_miss: ti.template(),
    ):
        # A ray passing block entry ``entry`` (cell c): counted, or with the NDT miss model
        # its Gaussian tested (a marked entry, unless near: the last cells of a hit ray, see
        # config.MapConfig.near_cells_at) or nothing (a hit cell's entry).
        if ti.static(not ndt):
            ti.atomic_add(entry, ti.cast(1, bt))
        else:
            v = entry
            if counts(v):
                ti.atomic_add(entry, ti.cast(1, bt))
            elif ti.static(cfg.bt == "i32"):
                if v <= MARK_I32 and near == 0:  # the record is in the mark
                    add_miss(MARK_I32 - v, c, o, z, u, length, hit, res, ndt_prm, rec_icov, rec_miss)
            elif v == ti.cast(mark, bt) and near == 0:
                ndt_visit(slot, c, o, z, u, length, hit, res, ndt_prm, rec_icov, rec_miss)

    @ti.func
    def advance(
        cur: ti.template(),
        rem: ti.template(),
        tmax: ti.template(),
        li: ti.template(),
        left: ti.template(),
        step,
        tdel,
        dli,
        res,
        o,
        d,
    ):
        # One step of the traversal: the axis whose face the ray crosses next.
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
            if tmin == BIG:
                left = 0  # a free ray's last cell, visited: no face left to cross
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
                if tmax[a] == tmin and (ties == 1 or (step[a] > 0) == up) and rem[a] > 0:
                    cur[a] += step[a]
                    rem[a] -= 1
                    left -= 1
                    li += dli[a]
                    tmax[a] = next_t(cur[a], step[a], rem[a], res, o[a], d[a])

    @ti.func
    def cross_settled(
        slo, shi, ce, cur: ti.template(), rem: ti.template(), tmax: ti.template(), step, tdel, d, inv_res
    ) -> ti.i32:
        # The ray's steps through its settled box (settled_growth) taken at once, from the
        # sensor's cell: cur, rem and tmax become what the traversal reaches at the box's
        # exit. An axis's j-th crossing lies at tmax + j tdel (as the steps add it up; off
        # by ~1e-14 here, far less than TIE_MARGIN), so no divisions. Returns the steps
        # taken; -1 when the ray ends in the box (every cell it passes is settled); 0 when
        # a crossing lies within the tie margin of the exit (the ray steps through as before).
        moved = 0
        if (
            ce[0] >= slo[0]
            and ce[1] >= slo[1]
            and ce[2] >= slo[2]
            and ce[0] <= shi[0]
            and ce[1] <= shi[1]
            and ce[2] <= shi[2]
        ):
            moved = -1
        else:
            # The exit: the first crossing of a face of the box ahead of the ray.
            texit = ti.f64(BIG)
            ax = -1
            kx = 0  # the exit axis's crossings up to and through the exit face
            for a in ti.static(range(3)):
                if step[a] != 0:
                    j = shi[a] - cur[a] if step[a] > 0 else cur[a] - slo[a]
                    if j < rem[a]:
                        t = tmax[a] + ti.cast(j, ti.f64) * tdel[a]
                        if t < texit:
                            texit = t
                            ax = a
                            kx = j + 1
            ok = ax >= 0
            k = ti.Vector([0, 0, 0], dt=ti.i32)  # crossings before the exit, per axis
            for a in ti.static(range(3)):
                if ok and step[a] != 0:
                    if a == ax:
                        k[a] = kx
                    elif texit > tmax[a]:
                        k[a] = ti.cast(ti.floor((texit - tmax[a]) * ti.abs(d[a]) * inv_res), ti.i32) + 1  # / tdel
                    if k[a] > rem[a]:
                        ok = False
                    elif a != ax:
                        # The axis's own crossings clear of the exit, on either side.
                        if k[a] < rem[a] and tmax[a] + ti.cast(k[a], ti.f64) * tdel[a] <= texit + TIE_MARGIN:
                            ok = False
                        if k[a] > 0 and tmax[a] + ti.cast(k[a] - 1, ti.f64) * tdel[a] >= texit - TIE_MARGIN:
                            ok = False
            if ok:
                for a in ti.static(range(3)):
                    if step[a] != 0:
                        moved += k[a]
                        cur[a] += step[a] * k[a]
                        rem[a] -= k[a]
                        tmax[a] = tmax[a] + ti.cast(k[a], ti.f64) * tdel[a] if rem[a] > 0 else BIG
        return moved

    def rays(
        slot: ti.i32,
        pts: f64_2d,  # Rays
        cells: i32_2d,
        n_hit: ti.i32,
        n: ti.i32,
        origin: f64_1d,  # Sensor
        ocell: i32_1d,
        res: ti.f64,
        sbox: i32_1d,
        touched: i32_2d,  # Touched
        cap: ti.i64,
        ctr: i64_1d,  # [CTR_SIZE] counters (C_VISITS, C_TOUCHED)
        occ_regions: i8_4d,  # Nodes
        leaves: i64_2d,
        block: b3d,  # Block (empty: every visit counts in the tree)
        base: i32_1d,
        block1: b1d,
        bflag1: i8_1d,
        rec_n: i32_1d,  # Records (ndt)
        rec_miss: i64_1d,  # NdtRecords (ndt): out, the rays' summed miss terms
        rec_icov: f64_2d,
        ndt_prm: f64_1d,
        ndt_minp: ti.i32,
        flags: ti.i32,  # ("dense") set row flags (a second cache line a visit); else block_apply reads every row
    ):
        o = ti.Vector([origin[0], origin[1], origin[2]])
        strides = ti.Vector([block.shape[1] * block.shape[2], block.shape[2], 1], dt=ti.i32)
        b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
        bsize = ti.Vector([block.shape[0], block.shape[1], block.shape[2]], dt=ti.i32)
        co = ti.Vector([ocell[0], ocell[1], ocell[2]], dt=ti.i32)
        settled = sbox[0] <= sbox[3]  # (the sensor's cell: in all eight boxes or none)
        inv_res = 1.0 / res
        own = owner_spec(slot)
        near_cells = 0
        if ti.static(ndt):
            near_cells = ti.cast(ndt_prm[8], ti.i32)
        for wq in range(Q.span(n, chunk)):
            jq = Q.first(wq, ctr, Q_RAYS)
            while jq < Q.end(n, chunk):
                for i in range(Q.begin(jq, n, chunk), Q.stop(jq, n, chunk)):
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
                    skipped = 0
                    whole = False
                    if ti.static(full):
                        if settled:
                            # The box of the ray's octant (an axis it does not step along: either).
                            q = 6 * (
                                (1 if step[0] >= 0 else 0) + (2 if step[1] >= 0 else 0) + (4 if step[2] >= 0 else 0)
                            )
                            slo = ti.Vector([sbox[q], sbox[q + 1], sbox[q + 2]], dt=ti.i32)
                            shi = ti.Vector([sbox[q + 3], sbox[q + 4], sbox[q + 5]], dt=ti.i32)
                            skipped = cross_settled(slo, shi, ce, cur, rem, tmax, step, tdel, d, inv_res)
                            if skipped < 0:  # the whole ray: its steps (and a free ray's last cell)
                                whole = True
                                skipped = rem[0] + rem[1] + rem[2] + (1 if i >= n_hit else 0)
                                rem = ti.Vector([0, 0, 0], dt=ti.i32)
                    last_leaf = ti.Vector([-(1 << 30), 0, 0], dt=ti.i32)
                    li = (cur - b0).dot(strides)  # flat index of the current cell in the block
                    dli = step * strides
                    left = rem[0] + rem[1] + rem[2]
                    if ti.static(full):
                        # A free ray passes its last cell too: one visit more than its steps,
                        # the last one where the ray's other visits of the block or tree count
                        # (one cell's count split between the two took eq. 12 twice).
                        if i >= n_hit and not whole:
                            left += 1
                    inside = 1  # whether the ray is in the block ("dense": always)
                    # Each pass steps at least one axis towards the endpoint cell, so the loop
                    # ends exactly there after at most |ce - co|_1 passes, whatever rounding does
                    # (a free ray: one pass more, at that cell).
                    if ti.static(mode == "full"):
                        # The rays start in the block (it holds the sensor's cell) and, once
                        # out, stay out: each axis's index moves one way. So they visit the
                        # block by its flat index until they leave it, then the tree, with no
                        # bounds test a visit and neither path in the other's loop.
                        if bsize[0] == 0:
                            inside = 0
                        for a in ti.static(range(3)):
                            if cur[a] < b0[a] or cur[a] >= b0[a] + bsize[a]:
                                inside = 0  # the settled box took it past the block
                        lim = ti.Vector([-(1 << 30), -(1 << 30), -(1 << 30)], dt=ti.i32)
                        for a in ti.static(range(3)):
                            if step[a] > 0:
                                lim[a] = b0[a] + bsize[a]
                            elif step[a] < 0:
                                lim[a] = b0[a] - 1
                        last_row = -1
                        while left > 0 and inside != 0:
                            near = (i < n_hit) & (left <= near_cells)
                            # Near the sensor every ray passes: count in the dense block,
                            # applied to the tree once per cell by block_apply.
                            block_visit(
                                block1[li],
                                near,
                                slot,
                                cur,
                                o,
                                z,
                                u,
                                length,
                                i < n_hit,
                                res,
                                ndt_prm,
                                rec_icov,
                                rec_miss,
                            )
                            rr = li >> SHIFT  # a row of `leaf` cells along z
                            if rr != last_row:
                                bflag1[rr] = ti.i8(1)
                                last_row = rr
                            visits += 1
                            advance(cur, rem, tmax, li, left, step, tdel, dli, res, o, d)
                            if (cur == lim).any():
                                inside = 0
                    while left > 0:
                        near = (i < n_hit) & (left <= near_cells)  # left: |ce - cur|_1
                        if ti.static(mode == "dense"):
                            block_visit(
                                block1[li],
                                near,
                                slot,
                                cur,
                                o,
                                z,
                                u,
                                length,
                                i < n_hit,
                                res,
                                ndt_prm,
                                rec_icov,
                                rec_miss,
                            )
                            if flags != 0:
                                bflag1[li >> SHIFT] = ti.i8(1)  # rows of `leaf` cells along z
                        elif owned(own, cur) != 0:  # (a tiled map's worker: its own cells only)
                            lf = cur // leaf
                            if (lf != last_leaf).any():  # a leaf is counted when a ray enters it
                                note_leaf(olm, slot, cur, occ_regions, leaves, 0)
                                last_leaf = lf
                            if ti.static(full):
                                g = visit(slot, cur, touched, cap, ctr)
                                if ti.static(ndt) and g != 0 and near == 0:
                                    ndt_tree_visit(
                                        slot,
                                        cur,
                                        o,
                                        z,
                                        u,
                                        length,
                                        i < n_hit,
                                        res,
                                        ndt_prm,
                                        rec_n,
                                        rec_icov,
                                        rec_miss,
                                        ndt_minp,
                                    )
                            else:
                                ti.atomic_add(ne[at(slot, cur)], 1)
                        visits += 1
                        # advance(), inline: the call here cost the whole-block loop ~4% (one
                        # thread, 60 hall scans, 4 pairs: 1.82-2.07 s against 1.68-2.06).
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
                            if tmin == BIG:
                                left = 0  # a free ray's last cell, visited: no face left to cross
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
                                if tmax[a] == tmin and (ties == 1 or (step[a] > 0) == up) and rem[a] > 0:
                                    cur[a] += step[a]
                                    rem[a] -= 1
                                    left -= 1
                                    li += dli[a]
                                    tmax[a] = next_t(cur[a], step[a], rem[a], res, o[a], d[a])
                    tally(ctr, C_VISITS, i >> 5, visits)
                    if ti.static(full):
                        if skipped > 0:
                            tally(ctr, C_SKIPPED, i >> 5, skipped)
                jq = Q.next(ctr, Q_RAYS)

    ndt_fields = ("rec_miss", "rec_icov", "ndt_prm", "ndt_minp")
    ndt_part = ("ndt", NdtRecords, ndt_fields) if ndt else (None, NdtRecords, ndt_fields)
    return Bound(
        rays,
        (
            "slot",
            ("rays", Rays),
            ("sensor", Sensor),
            ("touched", Touched),
            "ctr",
            ("nodes", Nodes, ("occ_regions", "leaves")),
            ("block", Block, ("block", "base", "block1", "bflag1")),
            ("records", Records, ("rec_n",)),
            ndt_part,
            "flags",
        ),
    )


# Cells the settled box may reach from the sensor's cell on each side (even). Its hit marks
# are by 2^3-cell brick, (R + 1)^3 bytes: 275 kB stay in cache while prepare writes them
# (by cell, 2.1 MB, they cost prepare 0.3 ms more a hall scan at 0.2 m), and a brick with a
# hit holds the box back by at most one cell. At 0.2 m the hall's box reached 8 cells down
# and 15-35 sideways.
SETTLED_REACH = 64


def settled_growth(f: Storage):
    """The sensor's settled surroundings, as ``grow(slot, co, l_min, hmask, stamp, sbox)``
    (a ti.func for one thread; ``update.prepare`` runs it after stamping the scan's hits):
    eight boxes of cells, one an octant from the sensor's cell ``co``, each grown a layer at
    a time on its three outer sides while every cell of the layer is at the free clamp
    (log-odds <= l_min), holds no Gaussian (no NE_GAUSS, no record) and no endpoint of the
    scan hits it (``hmask`` holds ``stamp`` there). A ray passing such a cell changes
    nothing (eq. 12 stays at the clamp, the NDT miss model has no Gaussian to test), so the
    rays cross the box of their octant in one step (``rays``), and a blocked cell holds back
    only its octant's box. Out: ``sbox`` [8 * 6] = each box's lo xyz, hi xyz (inclusive);
    lo > hi in all eight when the sensor's own cell is not settled. The hall's boxes at
    0.2 m (~45 k cells) take ~0.2 ms."""
    lo, ne, gslot = f.lo, f.ne, f.gslot
    at = device_funcs(f).at
    R = SETTLED_REACH
    glo, ghi = f.layout.lo, f.layout.hi

    @ti.func
    def settled(slot, c, co, l_min, hmask: ti.template(), stamp) -> ti.i32:
        r = c - co + R
        s = 0
        if ti.cast(hmask[r[0] >> 1, r[1] >> 1, r[2] >> 1], ti.i32) != stamp:
            if lo[at(slot, c)] <= l_min:
                if ne[at(slot, c)] & NE_GAUSS == 0:
                    if gslot[at(slot, c)] == 0:
                        s = 1
        return s

    @ti.func
    def grow(slot, co, l_min, hmask: ti.template(), stamp, sbox: ti.template()):
        for q in range(8):
            # Octant q: axis a runs up from the sensor's cell where bit a of q is set.
            sg = ti.Vector([1 if q & 1 else -1, 1 if q & 2 else -1, 1 if q & 4 else -1], dt=ti.i32)
            ext = ti.Vector([0, 0, 0], dt=ti.i32)  # the box's cells past the sensor's, per axis
            more = ti.Vector([1, 1, 1], dt=ti.i32)  # the axes whose box may still grow
            empty = settled(slot, co, co, l_min, hmask, stamp) == 0
            if empty:
                more = ti.Vector([0, 0, 0], dt=ti.i32)
            while more[0] + more[1] + more[2] > 0:
                for a in ti.static(range(3)):
                    b, c = ti.static((a + 1) % 3, (a + 2) % 3)
                    if more[a] != 0:
                        x = co[a] + sg[a] * (ext[a] + 1)
                        ok = ext[a] < R and x >= ti.static(glo[a]) and x < ti.static(ghi[a])
                        if ok:
                            # The new layer: every cell settled (the first that is not ends the test).
                            for i in range(ext[b] + 1):
                                for j in range(ext[c] + 1):
                                    cell = co
                                    cell[a] = x
                                    cell[b] = co[b] + sg[b] * i
                                    cell[c] = co[c] + sg[c] * j
                                    if settled(slot, cell, co, l_min, hmask, stamp) == 0:
                                        ok = False
                                        break
                                if not ok:
                                    break
                        if ok:
                            ext[a] += 1
                        else:
                            more[a] = 0
            for a in ti.static(range(3)):
                far = co[a] + sg[a] * ext[a]
                sbox[6 * q + a] = ti.min(co[a], far)
                sbox[6 * q + 3 + a] = ti.max(co[a], far)
                if empty:
                    sbox[6 * q + 3 + a] = co[a] - 1

    return grow


def mark_gaussians(f: Storage, bt: str) -> Bound:
    """Before the rays of the NDT miss model: the block entries of cells holding a
    Gaussian of >= ndt_minp points get the mark (update.apply_marked applies their sums,
    block_apply clears them: their rows are flagged where it reads flags), then those of
    the scan's hit cells the hit mark (merge clears them)."""
    F = device_funcs(f)
    row, leaf, picked = F.row, F.leaf, F.picked
    mark, bt_ = block_mark(bt), block_type(bt)
    hit = HIT_U16 if bt == "u16" else HIT_I32
    b3d = ti.types.ndarray(dtype=bt_, ndim=3)

    def mark_gaussians(
        nrec: ti.i32,  # records in use
        pick: i32_1d,  # Picked: the records that may lie in the block
        npick: ti.i32,
        tail0: ti.i32,
        rec_n: i32_1d,  # Records
        rec_cell: i32_2d,
        ndt_minp: ti.i32,  # NdtRecords
        block: b3d,  # Block: the scan's zeroed ray counts
        bflag: i8_3d,
        base: i32_1d,
        cells: i32_2d,  # Rays: the endpoints' cells, hits first
        n_hit: ti.i32,
        flags: ti.i32,  # whether block_apply will read the row flags (else it reads every row)
    ):
        b0 = ti.Vector([base[0], base[1], base[2]], dt=ti.i32)
        bsize = ti.Vector([block.shape[0], block.shape[1], block.shape[2]], dt=ti.i32)
        for i in range(npick + nrec - tail0):
            rolled(nrec)
            r = picked(i, pick, npick, tail0)
            if rec_n[r] >= ndt_minp:
                rel = row(rec_cell, r) - b0
                if (rel >= 0).all() and (rel < bsize).all():
                    if ti.static(bt == "i32"):
                        block[rel[0], rel[1], rel[2]] = MARK_I32 - r
                    else:
                        block[rel[0], rel[1], rel[2]] = ti.cast(mark, bt_)
                    if flags != 0:
                        bflag[rel[0], rel[1], rel[2] // leaf] = ti.i8(1)
        for i in range(n_hit):
            rolled(n_hit)
            rel = row(cells, i) - b0
            if (rel >= 0).all() and (rel < bsize).all():
                block[rel[0], rel[1], rel[2]] = ti.cast(hit, bt_)

    return Bound(
        mark_gaussians,
        (
            "nrec",
            ("picked", Picked),
            ("records", Records, ("rec_n", "rec_cell")),
            ("ndt", NdtRecords, ("ndt_minp",)),
            ("block", Block, ("block", "bflag", "base")),
            ("rays", Rays, ("cells", "n_hit")),
            "flags",
        ),
    )


def reset_rays(f: Storage, _cfg=None) -> Bound:
    """Clears the ray counts of the touched cells (a batch refused for memory)."""
    F = device_funcs(f)
    ne, row, at = f.ne, F.row, F.at

    def reset_rays(slot: ti.i32, touched: i32_2d, nt: ti.i32):  # touched: [T, 3] cells
        for t in range(nt):
            c = row(touched, t)
            ne[at(slot, c)] = ne[at(slot, c)] & NE_GAUSS

    return Bound(reset_rays, ("slot", "touched", "nt"))


def reset_rays_all(f: Storage, _cfg=None) -> Bound:
    """reset_rays for every cell of the slot (when the touched list overflowed)."""
    ne = f.ne

    def reset_rays_all(slot: ti.i32):
        for I in ti.grouped(ne):
            if I[0] == slot:
                ne[I] = ne[I] & NE_GAUSS

    return Bound(reset_rays_all, ("slot",))


def count_new_nodes(f: Storage, dedup: bool) -> Bound:
    """Nodes the cells would allocate in each tree, each counted once. Reading never
    allocates. dedup: flag leaves in ``seen`` (False: the cells lie in distinct leaves
    already, and ``seen`` is not passed)."""
    F = device_funcs(f)
    olm, glm, row, at = f.olm, f.glm, F.row, F.at
    leaf, region = F.leaf, F.region
    grid_lo = F.grid_lo

    def count_new_nodes(
        slot: ti.i32,
        cells: i32_2d,  # [N, 3] hit cells
        n: ti.i32,
        lbase: i32_1d,  # [3] first leaf of ``seen``
        seen: i32_3d,  # zeroed flags over the cells' box of leaves (dedup)
        rbase: i32_1d,  # [3] first region of ``rseen``
        rseen: i32_3d,  # zeroed flags over the cells' box of regions
        occ_regions: i8_4d,  # Nodes
        gidx_regions: i8_4d,
        out: i64_1d,  # [4] out: new occupancy leaves, index leaves, occupancy regions, index regions
    ):
        b0 = ti.Vector([lbase[0], lbase[1], lbase[2]], dt=ti.i32)
        r0 = ti.Vector([rbase[0], rbase[1], rbase[2]], dt=ti.i32)
        for i in range(n):
            c = row(cells, i)
            lf = c // leaf
            first = True
            if ti.static(dedup):
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

    return Bound(
        count_new_nodes,
        (
            "slot",
            "cells",
            "n",
            "lbase",
            "seen",
            "rbase",
            "rseen",
            ("nodes", Nodes, ("occ_regions", "gidx_regions")),
            "out",
        ),
    )
