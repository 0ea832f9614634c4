"""One scan's update of a map (method.md sections 2 and 3): validation, the memory plan,
ray tracing (one pass with a dense block near the sensor, or batches under memory
pressure), hits, the RCU merge and eq. (12). The kernels are those of kernels/families.py;
``UpdatePlan`` holds the choices that change speed only: every plan gives the same map,
cell for cell."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np

from .kernels.args import Block, GroupedHits, Model, Picked, Rays, Sensor, Touched, TreeSums
from .kernels.ndt import (
    C_BLOCK_CELLS,
    C_ERASED,
    C_FREE,
    C_HIT_CELLS,
    C_HIT_PASSED,
    C_NDT_STILL,
    C_NO_RECORD,
    C_RECORDS,
    C_SKIPPED,
    C_TOUCHED,
    C_VISITS,
    CTR_SIZE,
    HIT_CHUNKS,
    Q_MERGE,
    Q_RAYS,
    U16_MAX_RAYS,
    total,
)
from .kernels.trace import SETTLED_REACH, RaysConfig
from .kernels.update import FreeConfig, MergeConfig
from .record_index import MIN_RECORDS, NO_PICK
from .scaninput import as_points, as_pose, cell_box
from .slot import MapSlot

# Dense scan-local ray counts over the scan's cell box, at most this many cells (2 or 4 B):
# counting there is several times cheaper than in the sparse tree. Past it the block keeps
# the part nearest the sensor, where rays are densest, and the rest counts in the tree.
BLOCK_CELLS = 1 << 25
TOUCHED_START = 1 << 20
# The settled boxes (trace.settled_growth) of a scan that has none: lo > hi in each octant.
NO_BOX = np.tile(np.array([0, 0, 0, -1, -1, -1], np.int32), 8)
ROW_FLAGS = ("auto", "always", "never")


@dataclass
class ScanReport:
    """What one ``insert_scan`` did."""

    points_in: int = 0
    points_used: int = 0  # endpoints inserted as hits
    free_rays: int = 0  # rays past max_range carved as free space (max_range_mode="free")
    dropped_nonfinite: int = 0
    dropped_range: int = 0  # closer than min_range, or past max_range with mode "drop"
    dropped_outside_grid: int = 0
    dropped_no_return: int = 0  # at the sensor itself, (0, 0, 0): drivers' mark of a beam with no return
    cells_hit: int = 0
    cells_passed: int = 0  # distinct cells rays passed without an endpoint: free-space updates
    ray_cell_visits: int = 0
    # ray steps across the sensor's settled surroundings, not visited: cells there are at the
    # free clamp with no Gaussian, where a pass changes nothing (UpdatePlan.settled_box)
    ray_cells_crossed: int = 0
    gaussians_erased: int = 0
    ray_batches: int = 0  # batches the rays were traced in under memory pressure (0: one pass)
    seconds: float = 0.0
    # [gaussians_erased, 3] i32: the cells whose Gaussians rays erased (left out of as_dict)
    erased_cells: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32), repr=False)

    def as_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if k != "erased_cells"}


@dataclass
class UpdatePlan:
    """How a map's updates run. Speed only: any plan gives the same map, cell for cell.

    block_cells: most cells of the dense ray-count block around the sensor (0: count
        every ray visit in the sparse tree).
    u16_rays: scans of at most this many rays count in 16 bits on the CPU (a ray passes
        a cell once; 65534 and 65535 are the NDT miss model's marks), at most 65533; larger
        scans, or 0 (the default), in 32 bits. 16-bit counts were no faster on the hall at
        0.2 m (a whole scan 1.02x the time of 32-bit ones, paired in one process), and one
        block type means one set of kernels to compile where a recording's scans straddle
        65533 points.
    row_flags: for a block that holds the whole scan: "auto" flags the rows rays enter
        when the last scan made few visits per block cell, "always", or "never" (every
        row is read).
    one_pass: False traces every scan in batches through the tree, as under memory
        pressure.
    touched_rows: rows of the list of tree cells a scan's rays touch (doubled past a
        scan that overflows it; that scan visits every cell of the map instead).
    index_records: from this many Gaussian records on, the NDT miss model reads only
        those whose cells may lie in the scan's block, found by place (record_index);
        below it, every record (0: always by place).
    settled_box: on the CPU, the rays cross the sensor's settled surroundings (a box of
        cells at the free clamp with no Gaussian and no hit of the scan, where a pass
        changes nothing: trace.settled_growth) in one step instead of cell by cell.
    """

    block_cells: int = BLOCK_CELLS
    u16_rays: int = 0
    row_flags: str = "auto"
    one_pass: bool = True
    touched_rows: int = TOUCHED_START
    index_records: int = MIN_RECORDS
    settled_box: bool = True

    def __setattr__(self, name: str, value: Any) -> None:
        if name in ("one_pass", "settled_box") and not isinstance(value, bool):
            raise ValueError(f"{name} must be True or False, got {value!r}")
        if name == "row_flags" and value not in ROW_FLAGS:
            raise ValueError(f"row_flags must be one of {ROW_FLAGS}, got {value!r}")
        if name in ("block_cells", "u16_rays", "touched_rows", "index_records") and (
            isinstance(value, bool) or int(value) != value or int(value) < (1 if name == "touched_rows" else 0)
        ):
            raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
        if name == "u16_rays" and int(value) > U16_MAX_RAYS:
            raise ValueError(f"u16_rays must be at most {U16_MAX_RAYS} (16-bit ray counts), got {value!r}")
        super().__setattr__(name, value)


@dataclass
class PreparedRays:
    """A validated scan: world endpoints and their cells, hits first, then free rays."""

    world: np.ndarray  # [N, 3] f64
    cells: np.ndarray  # [N, 3] i32
    n_hit: int
    origin: np.ndarray  # [3] f64 sensor origin
    ocell: np.ndarray  # [3] i64 its cell
    report: ScanReport
    box: tuple[np.ndarray, np.ndarray] | None  # the cells' bounding box
    one_pass: bool  # the whole scan fits the memory budget at once
    hit_nodes: tuple[np.ndarray, np.ndarray] | None  # (nodes the hits add, hit cells) when batched
    mine: np.ndarray | None = None  # a tiled map's worker: which hits lie in its cells (else all)
    sbox: np.ndarray = field(default_factory=lambda: NO_BOX)  # the settled boxes (trace.settled_growth)

    @cached_property
    def own_hits(self) -> tuple[np.ndarray, np.ndarray, int]:
        """(world, cells, count) of the hits this map merges: the worker's own, in scan order."""
        if self.mine is None:
            return self.world, self.cells, self.n_hit
        return self.world[: self.n_hit][self.mine], self.cells[: self.n_hit][self.mine], int(self.mine.sum())


class RayTracer:
    """The rays of one map's scans (owned by :class:`ScanUpdate`): the dense ray-count block
    near the sensor (its box, its buffers, the empty blocks), the list of tree cells rays
    touch, and the ray kernels' driver, in one pass or in batches under memory pressure."""

    def __init__(
        self, *, slot: MapSlot, plan: UpdatePlan, ctr: np.ndarray, resolution: float, ndt: bool, arch: str, l_min: float
    ):
        self.st, self.slot, self.k = slot.storage, slot.index, slot.kernels
        self.records, self.budget, self.plan = slot.records, slot.budget, plan
        self.resolution, self.ndt, self.arch = resolution, ndt, arch
        self.l_min = l_min  # the free clamp: cells there take nothing from passing rays
        self.layout = slot.layout
        self.sbox = NO_BOX  # the last scan's settled boxes
        self.no_marks = np.zeros((1, 1, 1), np.uint8)  # prepare's marks when there is no settled box
        self.ctr = ctr  # the update's counters
        self.block_density = 0.0  # ray visits per cell of the last scan's dense block
        self.batches = 0  # ray batches of the last scan (0: one pass)
        # The records the NDT miss model's kernels read this scan (those the block may hold).
        self.picked = Picked(pick=NO_PICK, npick=0, tail0=0)
        self.touched = np.empty((0, 3), np.int32)  # plan.touched_rows is at least 1
        self.sync_touched()
        self.empty = {
            bt: Block.of(np.zeros((0, 0, 0), dt), np.zeros((0, 0, 0), np.int8), np.zeros(3, np.int32))
            for bt, dt in (("u16", np.uint16), ("i32", np.int32))
        }

    def sync_touched(self) -> None:
        """(Re)allocate the touched list to ``plan.touched_rows`` rows when that changed."""
        if self.plan.touched_rows != len(self.touched):
            self.touched = np.empty((self.plan.touched_rows, 3), np.int32)
            self.touched_group = Touched(touched=self.touched, cap=len(self.touched))

    def trace(self, mode: str, p: PreparedRays):
        """Run the ray kernel of ``mode`` ("full" or "floor") over all rays, in batches
        when memory is tight. Returns the dense block they counted in (a Block), whether
        the rays set its row flags, and whether it holds every cell of the scan; or None."""
        st, slot, k, ctr = self.st, self.slot, self.k, self.ctr
        dense = p.one_pass and mode == "full"  # the floor counts in the tree only
        # 16-bit counts on the CPU only: NVIDIA GPUs have no 16-bit atomics.
        bt = "u16" if self.arch == "cpu" and len(p.world) <= self.plan.u16_rays else "i32"
        ndt = mode == "full" and self.ndt
        blk = self.block_for(self.block_box(p) if dense else None, p.ocell, bt)
        self.sbox = p.sbox if mode == "full" else NO_BOX
        common = {
            "slot": slot,
            "sensor": Sensor(origin=p.origin, ocell=p.ocell.astype(np.int32), res=self.resolution, sbox=self.sbox),
            "touched": self.touched_group,
            "ctr": ctr,
            "nodes": self.budget.nodes,
            "block": blk,
            "records": self.records.group,
        }
        if ndt:
            common["ndt"] = self.records.ndt_group
        cfg = RaysConfig(bt=bt, mode="full" if mode == "full" else "floor", ndt=ndt)
        world, cells, n_hit, n = p.world, p.cells, p.n_hit, len(p.world)
        self.batches = 0
        if p.one_pass:
            box = p.box
            assert box is not None  # the scan has rays
            lo, hi = np.minimum(box[0], p.ocell), np.maximum(box[1], p.ocell)
            flagged, whole = True, False
            base = blk.base
            if dense and (base <= lo).all() and (base + np.array(blk.block.shape) > hi).all():
                whole = True
                # The block covers every cell of the scan. Row flags pay off only where
                # rays leave most rows empty: the last scan made few visits per block cell
                # (measured on the hall: flags lose by 6% at 0.37 visits/cell, 15% at 1.15).
                # Either way the same kernels run: a guess that turns costs no compile.
                rf = self.plan.row_flags
                flagged = self.block_density < 0.2 if rf == "auto" else rf == "always"
                cfg = RaysConfig(bt=bt, mode="dense", ndt=ndt)
            scan_rays = Rays(pts=world, cells=cells, n_hit=n_hit, n=n)
            # The Gaussians the rays test are those of the scan's start: merge runs after them.
            if ndt and blk.block.size:
                _, own_cells, own_n = p.own_hits  # hit marks are cleared by merge: its hits only
                # The records apply_marked reads too: merge's new ones hold no sums.
                self.picked = self.records.in_box(base, base + np.array(blk.block.shape) - 1, self.plan.index_records)
                k.mark_gaussians(bt)(
                    nrec=self.records.count,
                    picked=self.picked,
                    records=self.records.group,
                    ndt=self.records.ndt_group,
                    block=blk,
                    rays=Rays(pts=world, cells=own_cells, n_hit=own_n, n=own_n),
                    flags=int(flagged),
                )
            ctr[Q_RAYS] = 0
            k.rays(cfg)(rays=scan_rays, flags=int(flagged), **common)
            st.note_usage()
            if not (dense and blk.block.size):
                return None
            self.block_density = total(ctr, C_VISITS) / blk.block.size  # the only rays kernel of the update
            return blk, flagged, whole
        # Hits first, then free rays, each by azimuth: batches stay spatially compact.
        d = world - p.origin
        az = np.arctan2(d[:, 1], d[:, 0])
        order = np.concatenate([np.argsort(az[:n_hit]), n_hit + np.argsort(az[n_hit:])])
        ws, cs = world[order], cells[order]
        budget = self.budget
        rays = k.rays(cfg)
        pending = [(0, n)]
        # Nodes the hits write after the rays (merge): an upper bound, counted again exactly
        # when a batch does not fit, as the rays may have made some of them already.
        hits, hit_cells = p.hit_nodes or (np.zeros(4, np.int64), cells[:0])
        fresh = True
        while pending:
            a, b = pending.pop()
            bound = budget.scan_bound(cs[a:b], 0, p.ocell, tight=True, rays=True)
            fits = budget.fits(bound + hits)
            if not fits and not fresh:
                hits, fresh = budget.new_hit_nodes(hit_cells), True
                fits = budget.fits(bound + hits)
            if fits:
                # No dense block here: its cells would reach the tree outside this batch's bound.
                ctr[Q_RAYS] = 0
                rays(
                    flags=1,
                    rays=Rays(
                        pts=np.ascontiguousarray(ws[a:b]),
                        cells=np.ascontiguousarray(cs[a:b]),
                        n_hit=max(0, min(n_hit - a, b - a)),
                        n=b - a,
                    ),
                    **common,
                )
                st.note_usage()
                self.batches += 1
                fresh = len(hit_cells) == 0
            elif b - a > 1:
                mid = (a + b) // 2
                pending += [(mid, b), (a, mid)]
            else:
                nt = int(ctr[C_TOUCHED])
                if nt <= len(self.touched):
                    k.reset_rays()(slot=slot, touched=self.touched, nt=nt)
                else:
                    k.reset_rays_all()(slot=slot)
                # The leaves these rays made hold nothing now: give them back for later scans.
                from .kernels.release import release_empty_leaves

                release_empty_leaves(st, slot)
                refused = budget.refusal(bound + hits)  # said of the pool as the rays left it
                raise refused  # nothing of this scan is kept
        return None

    def hit_marks(self) -> tuple[np.ndarray, int, int]:
        """(marks, stamp, reach) for ``prepare`` to stamp a scan's hits near the sensor in
        and grow the settled boxes from (trace.settled_growth): on the CPU, for a map that
        updates all its cells (a tiled map's worker knows only its own); else (a stand-in,
        0, -1): no boxes."""
        st = self.st
        if self.arch != "cpu" or self.layout.owner is not None or not self.plan.settled_box:
            return self.no_marks, 0, -1
        side = SETTLED_REACH + 1  # bricks of 2^3 cells
        if st.hmask_buf.shape != (side,) * 3:
            st.hmask_buf = np.zeros((side,) * 3, np.uint8)
            st.hmask_stamp = 0
        elif st.hmask_stamp == 255:  # a byte's stamps used up: cleared once every 255 scans
            st.hmask_buf[:] = 0
            st.hmask_stamp = 0
        st.hmask_stamp += 1  # unique to this scan among the storage's maps since the last clear
        return st.hmask_buf, st.hmask_stamp, SETTLED_REACH

    def block_box(self, p: PreparedRays):
        """The cell box the dense block should cover: the scan's, or, when that is larger
        than the block can be, the box of all but its farthest 0.1% of points on each axis.
        A few stray far points (a real recording: 0.1% of them 25-160 m away) otherwise
        spread the block over 9x the cells, which cost a scan 3x its median; their rays
        count in the tree past the block."""
        box = p.box
        if box is None:
            return None
        leaf = self.layout.leaf
        lo, hi = np.minimum(box[0], p.ocell) // leaf, np.maximum(box[1], p.ocell) // leaf + 1
        if int(np.prod(hi - lo)) * leaf**3 <= self.plan.block_cells:
            return box
        q = np.quantile(p.cells, [0.001, 0.999], axis=0, method="inverted_cdf")
        return q[0].astype(np.int64), q[1].astype(np.int64)

    def block_for(self, box, ocell: np.ndarray, bt: str = "i32") -> Block:
        """The dense ray-count block (dtype ``bt``) of a scan: the leaf-aligned box of its
        cells and the sensor, trimmed on its far sides to ``plan.block_cells`` cells
        (empty with no ``box``)."""
        leaf = self.layout.leaf
        limit = self.plan.block_cells
        if box is None or limit < leaf**3:
            return self.empty[bt]
        dtype = np.uint16 if bt == "u16" else np.int32
        oleaf = ocell // leaf
        lo = np.minimum(box[0] // leaf, oleaf)  # in leaves
        hi = np.maximum(box[1] // leaf, oleaf) + 1
        while int(np.prod(hi - lo)) * leaf**3 > limit:
            a = int(np.argmax(hi - lo))
            cut = max(1, int(hi[a] - lo[a]) // 8)
            if hi[a] - oleaf[a] - 1 >= oleaf[a] - lo[a]:  # trim the side farther from the sensor
                hi[a] = max(hi[a] - cut, oleaf[a] + 1)
            else:
                lo[a] = min(lo[a] + cut, oleaf[a])
        shape = tuple(int(x) * leaf for x in hi - lo)
        n = shape[0] * shape[1] * shape[2]
        st = self.st
        words = -(-n * np.dtype(dtype).itemsize // 4)  # the buffer is int32, viewed as dtype
        if words > len(st.block_buf):
            st.block_buf = np.zeros(max(words, min(len(st.block_buf) * 5 // 4, BLOCK_CELLS)), np.int32)
        if n // leaf > len(st.bflag_buf):
            st.bflag_buf = np.zeros(max(n // leaf, min(len(st.bflag_buf) * 5 // 4, BLOCK_CELLS // leaf)), np.int8)
        block = st.block_buf.view(dtype)[:n].reshape(shape)
        bflag = st.bflag_buf[: n // leaf].reshape(shape[0], shape[1], shape[2] // leaf)
        return Block.of(block, bflag, (lo * leaf).astype(np.int32))


class ScanUpdate:
    """Runs the updates of one map (in its :class:`~ndtom_ti.slot.MapSlot` ``slot``)."""

    def __init__(self, *, slot: MapSlot, plan: UpdatePlan, config, resolution: float, occupancy: bool, arch: str):
        self.st, self.slot, self.k = slot.storage, slot.index, slot.kernels
        self.records, self.budget, self.plan = slot.records, slot.budget, plan
        self.config, self.resolution, self.occupancy, self.arch = config, resolution, occupancy, arch
        self.ndt = bool(config.ndt_misses)
        self.layout = slot.layout
        self.owner = self.layout.owner  # a tiled map's worker: the cells it updates
        self.glo = np.array(self.layout.lo, np.int64)
        self.ghi = np.array(self.layout.hi, np.int64)
        self.ctr = np.zeros(CTR_SIZE, np.int64)
        self.chunks = np.empty(HIT_CHUNKS + 1, np.int32)  # hits_dense's scratch
        self.model = Model(
            l_hit=config.l_hit, l_free=config.l_free, l_min=float(config.logodds_min), l_max=float(config.logodds_max)
        )
        # The rays: the dense block, the touched list, one pass or batches.
        self.tracer = RayTracer(
            slot=slot,
            plan=plan,
            ctr=self.ctr,
            resolution=resolution,
            ndt=self.ndt,
            arch=arch,
            l_min=float(np.float32(config.logodds_min)),
        )
        self._tree_ready = False  # compile_tree_path done

    def _ndt_kw(self) -> dict:
        return {"ndt": self.records.ndt_group} if self.ndt else {}

    def count_erased_near(self, cells: np.ndarray) -> None:
        """The NDT miss model's erased-neighbour rule for Gaussians erased outside this
        map's cells (a tiled map: another worker's last scan), before the next scan."""
        if self.ndt and len(cells):
            c = np.ascontiguousarray(cells, np.int32).reshape(-1, 3)
            self.k.erased_near()(
                slot=self.slot, cells=c, n=len(c), records=self.records.group, ndt=self.records.ndt_group
            )

    # ------------------------------------------------------------------ preparation

    def prepare(self, points: Any, T_world_sensor: Any) -> PreparedRays:
        """Validate a scan and turn it into world endpoints and their cells (hits first,
        then free rays), reserving the pool memory the update may need."""
        pts = as_points(points)
        T = as_pose(T_world_sensor)
        cfg = self.config
        res = self.resolution
        rep = ScanReport(points_in=len(pts))

        origin = np.ascontiguousarray(T[:3, 3])
        ocell = np.floor(origin / res).astype(np.int64)
        if ((ocell < self.glo) | (ocell >= self.ghi)).any():
            lo, hi = self.glo * res, self.ghi * res
            raise ValueError(
                f"sensor origin {origin.tolist()} is outside the map grid "
                f"[{lo.tolist()}, {hi.tolist()}] m; use a coarser resolution or a larger Layout, or give "
                "poses relative to a point near the sensor's path (`ndtom map` shifts a recording whose "
                "first pose is that far itself)"
            )

        n = len(pts)
        world = np.empty((n, 3), np.float64)
        cells = np.empty((n, 3), np.int32)
        status = np.empty(n, np.int8)
        free_at = cfg.max_range if cfg.max_range_mode == "free" else 0.0
        r2 = np.array([cfg.min_range**2, cfg.max_range**2, free_at])
        hmask, stamp, reach = self.tracer.hit_marks() if n else (self.tracer.no_marks, 0, -1)
        sbox = NO_BOX.copy()  # prepare grows them (none when it does not run)
        if n:
            self.k.prepare()(
                pts=pts,
                n=n,
                rot=np.ascontiguousarray(T[:3, :3]).reshape(-1),
                trans=origin,
                res=res,
                r2=r2,
                out_world=world,
                out_cells=cells,
                status=status,
                ocell=ocell.astype(np.int32),
                slot=self.slot,
                l_min=self.tracer.l_min,
                hmask=hmask,
                stamp=stamp,
                reach=reach,
                sbox=sbox,
            )
        cnt = np.bincount(status, minlength=6) if n else np.zeros(6, np.int64)
        n_hit, n_free = int(cnt[0]), int(cnt[1])
        if n_hit + n_free < n:
            hit = status == 0
            if n_free:
                free = status == 1
                world = np.concatenate([world[hit], world[free]])
                cells = np.concatenate([cells[hit], cells[free]])
            else:
                world, cells = world[hit], cells[hit]
        elif n_free:  # nothing dropped, but hits must come first
            order = np.argsort(status, kind="stable")
            world, cells = world[order], cells[order]
        rep.dropped_nonfinite, rep.dropped_range, rep.dropped_outside_grid = int(cnt[2]), int(cnt[3]), int(cnt[4])
        rep.dropped_no_return = int(cnt[5])
        rep.points_used = n_hit
        rep.free_rays = n_free
        box = cell_box(cells) if len(cells) else None

        # Memory: the whole scan in one pass when its bound fits; otherwise the hits must
        # fit and the rays are traced in batches, each checked against exact counts.
        budget = self.budget
        bound = budget.scan_bound(cells, n_hit, ocell, box=box)
        one_pass = self.plan.one_pass and budget.fits(bound)
        hit_nodes = None
        if not one_pass:
            # The index tree takes only hit cells: count its new nodes exactly and retry.
            new = budget.new_hit_nodes(cells[:n_hit])
            bound[2:] = new[2:]
            one_pass = self.plan.one_pass and budget.fits(bound)
            if not one_pass:
                budget.reserve(new)
                # What the hits write after the batched rays: each batch must leave room for it.
                hit_nodes = (new, cells[:n_hit])
        # A tiled map's worker traces every ray but merges only the hits in its cells.
        mine = self.owner.owned(cells[:n_hit]) if self.owner is not None else None
        return PreparedRays(world, cells, n_hit, origin, ocell, rep, box, one_pass, hit_nodes, mine, sbox)

    # ------------------------------------------------------------------ rays

    def traverse_only(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """The benchmark floor (NdtOmMap.traverse_only)."""
        t0 = time.perf_counter()
        self.tracer.sync_touched()
        p = self.prepare(points, T_world_sensor)
        self.ctr[:] = 0
        if len(p.world):
            self.tracer.trace("floor", p)
        rep = p.report
        rep.ray_cell_visits = total(self.ctr, C_VISITS)
        rep.seconds = time.perf_counter() - t0
        return rep

    # ------------------------------------------------------------------ the update

    def insert_guarded(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """``insert``, leaving the shared scratch clean when it raises (the caller holds
        the storage's lock)."""
        try:
            rep = self.insert(points, T_world_sensor)
            if not self._tree_ready:
                self._tree_ready = True
                self.compile_tree_path()  # what a later scan may switch to, compiled at the first
            return rep
        except BaseException:
            # Interrupted between kernels (Ctrl-C) or refused: keep the shared block and
            # the NDT miss sums zero.
            self.st.block_buf[:] = 0
            self.st.bflag_buf[:] = 0
            self.records.clear_miss()
            raise

    def compile_tree_path(self) -> None:
        """Compile the kernels of the tree path by calling them on no work: rays past the
        dense block, hits counted and summed in the tree, eq. (12) over the touched list.
        Kernels compile at their first call, and a scan whose box the block holds whole
        needs none of these; a later scan with a few far points (a real recording: 0.1%
        of them 25-160 m away) or under memory pressure does, and waited 2.4 s for them
        (15x the median scan, BALM at 0.2 m)."""
        k, ctr, slot, recs = self.k, self.ctr, self.slot, self.records
        bt = "u16" if self.arch == "cpu" and self.plan.u16_rays > 0 else "i32"
        pts, cells = np.zeros((0, 3), np.float64), np.zeros((0, 3), np.int32)
        none = Rays(pts=pts, cells=cells, n_hit=0, n=0)
        sensor = Sensor(origin=np.zeros(3), ocell=np.zeros(3, np.int32), res=self.resolution, sbox=NO_BOX)
        blk, nodes, ndt = self.tracer.empty[bt], self.budget.nodes, self._ndt_kw()
        keep = ctr.copy()  # the queues' counters move
        k.rays(RaysConfig(bt=bt, mode="full", ndt=self.ndt))(
            slot=slot,
            rays=none,
            sensor=sensor,
            touched=self.tracer.touched_group,
            ctr=ctr,
            nodes=nodes,
            block=blk,
            records=recs.group,
            flags=1,
            **ndt,
        )
        hitlist = np.zeros((1, 3), np.int32)
        k.hits_count()(slot=slot, cells=cells, n=0, hitlist=hitlist, ctr=ctr, nodes=nodes)
        hits = self._tree_sums(hitlist, 0, pts, cells, 0)
        k.merge(MergeConfig(bt=bt, grouped=self.arch == "cpu", ndt=self.ndt))(
            slot=slot,
            hitlist=hitlist,
            **hits,
            nh=0,
            n_max=int(self.config.n_max),
            records=recs.group,
            ctr=ctr,
            model=self.model,
            nodes=nodes,
            block=blk,
            res=self.resolution,
            left=np.zeros(1, np.int32),
            **ndt,
        )
        k.apply_free(self.ndt)(
            slot=slot, touched=self.tracer.touched_group, nt=0, model=self.model, records=recs.group, ctr=ctr, **ndt
        )
        ctr[:] = keep

    def _tree_sums(self, hitlist, nh: int, world, cells, n_hit: int) -> dict:
        """merge's hits after hits_count: on the CPU each cell's points grouped
        (hits_group), which merge sums in their order in the scan as it sums those of
        hits_dense, so that the map depends neither on the threads nor on the path; on
        a GPU their sums by float64 atomic adds (hits_sum)."""
        k, slot = self.k, self.slot
        if self.arch != "cpu":
            acc = np.zeros((nh, 9), np.float64)
            k.hits_sum()(slot=slot, pts=world, cells=cells, n=n_hit, acc=acc, res=self.resolution)
            return {"sums": TreeSums(acc=acc)}
        hcnt, off, order = (np.empty(max(x, 1), np.int32) for x in (nh, nh, n_hit))
        k.hits_group()(
            slot=slot, hitlist=hitlist, nh=nh, cells=cells, n=n_hit, hcnt=hcnt, off=off, order=order, first=self.chunks
        )
        return {"grouped": GroupedHits(hcnt=hcnt, off=off, order=order, pts=world, in_tree=1)}

    def insert(self, points: Any, T_world_sensor: Any) -> ScanReport:
        t0 = time.perf_counter()
        self.tracer.sync_touched()
        p = self.prepare(points, T_world_sensor)
        rep, world, cells, n_hit = p.report, p.world, p.cells, p.n_hit
        n = len(world)
        cfg, res = self.config, self.resolution
        k, ctr, slot, recs, nodes, model = self.k, self.ctr, self.slot, self.records, self.budget.nodes, self.model
        ctr[:] = 0
        ctr[C_FREE] = recs.nfree
        dense = None
        if self.occupancy and n:
            dense = self.tracer.trace("full", p)  # may refuse
        blk, flagged, whole = dense if dense is not None else (self.tracer.empty["i32"], True, False)
        bt = "u16" if blk.block.dtype == np.uint16 else "i32"
        world, cells, n_hit = p.own_hits  # (each cell's points keep their order: the same sums)
        hitlist = np.empty((max(n_hit, 1), 3), np.int32)
        nh = 0
        # Points per hit cell counted in the block (no tree walks) when it holds them all; on
        # the CPU only (its prefix sum runs on one thread). On the CPU merge sums each cell's
        # points in their order in the scan on either path (the same map, bit for bit).
        grouped = self.arch == "cpu"
        if n_hit:
            if whole and grouped:
                hcnt, off, order = np.empty(n_hit, np.int32), np.empty(n_hit, np.int32), np.empty(n_hit, np.int32)
                k.hits_dense(bt)(
                    cells=cells,
                    n=n_hit,
                    hitlist=hitlist,
                    hcnt=hcnt,
                    off=off,
                    rank=np.empty(n_hit, np.int32),
                    order=order,
                    ctr=ctr,
                    block=blk,
                    first=self.chunks,
                )
                nh = int(ctr[C_HIT_CELLS])
                hits = {"grouped": GroupedHits(hcnt=hcnt, off=off, order=order, pts=world, in_tree=0)}
            else:
                k.hits_count()(slot=slot, cells=cells, n=n_hit, hitlist=hitlist, ctr=ctr, nodes=nodes)
                nh = int(ctr[C_HIT_CELLS])
                hits = self._tree_sums(hitlist, nh, world, cells, n_hit)
            left, todo = np.empty(nh, np.int32), nh
            merge = k.merge(MergeConfig(bt=bt, grouped=grouped, ndt=self.ndt))
            while True:
                cap = recs.capacity
                ctr[C_RECORDS], ctr[C_NO_RECORD], ctr[Q_MERGE] = recs.count, 0, 0
                merge(
                    slot=slot,
                    hitlist=hitlist,
                    **hits,
                    nh=todo,
                    n_max=int(cfg.n_max),
                    records=recs.group,
                    ctr=ctr,
                    model=model,
                    nodes=nodes,
                    block=blk,
                    res=res,
                    left=left,
                    **self._ndt_kw(),
                )
                # At once, like the record count: an update cut short later must not hand
                # out the records merge took from the free stack again.
                nfree, count = recs.nfree, recs.count
                recs.count, recs.nfree = min(int(ctr[C_RECORDS]), cap), int(ctr[C_FREE])
                recs.taken(nfree, count)
                todo = int(ctr[C_NO_RECORD])
                if not todo:
                    break
                recs.grow_for(nh)
                s = np.sort(left[:todo])
                hitlist = hitlist[s]
                g, t = hits.get("grouped"), hits.get("sums")
                if isinstance(g, GroupedHits):
                    hits = {"grouped": replace(g, hcnt=g.hcnt[s], off=g.off[s])}
                elif isinstance(t, TreeSums):
                    hits = {"sums": TreeSums(acc=t.acc[s])}
        merged_free = int(ctr[C_FREE])  # records erased from here on go on the free stack
        if dense is not None:
            block, marked = blk.block, self.ndt and blk.block.size > 0
            shape = np.array(block.shape, np.int32)
            if marked:  # the sums of the marked cells (block_apply clears their marks)
                k.apply_marked()(
                    slot=slot,
                    nrec=recs.count,
                    picked=self.tracer.picked,
                    model=model,
                    records=recs.group,
                    ctr=ctr,
                    shape=shape,
                    base=blk.base,
                    ndt=recs.ndt_group,
                )
            k.block_apply(FreeConfig(bt=bt, ndt=marked))(
                slot=slot,
                words=block.reshape(-1).view(np.uint64),
                bflag=blk.bflag,
                shape=shape,
                base=blk.base,
                flagged=int(flagged),
                model=model,
                records=recs.group,
                ctr=ctr,
                nodes=nodes,
            )
        if self.occupancy and n:
            nt = int(ctr[C_TOUCHED])
            if 0 < nt <= len(self.tracer.touched):
                k.apply_free(self.ndt)(
                    slot=slot,
                    touched=self.tracer.touched_group,
                    nt=nt,
                    model=model,
                    records=recs.group,
                    ctr=ctr,
                    **self._ndt_kw(),
                )
            elif nt:
                k.apply_free_all(self.ndt)(slot=slot, model=model, records=recs.group, ctr=ctr, **self._ndt_kw())
                self.plan.touched_rows = 2 * nt
                self.tracer.sync_touched()
            rep.cells_passed = nt - int(ctr[C_HIT_PASSED]) - int(ctr[C_NDT_STILL]) + total(ctr, C_BLOCK_CELLS)
        self.st.note_usage()
        rep.cells_hit = nh
        rep.ray_cell_visits = total(ctr, C_VISITS)
        rep.ray_cells_crossed = total(ctr, C_SKIPPED)
        rep.gaussians_erased = int(ctr[C_ERASED])
        rep.ray_batches = self.tracer.batches
        recs.nfree = int(ctr[C_FREE])
        rep.erased_cells = recs.cell[recs.free[merged_free : recs.nfree]]
        rep.seconds = time.perf_counter() - t0
        return rep
