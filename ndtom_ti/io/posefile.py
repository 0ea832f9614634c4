"""Pose files: TUM (`t tx ty tz qx qy qz qw`) and KITTI (12 numbers: row-major 3x4 [R|t])."""

from __future__ import annotations

from collections.abc import Sequence
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from .errors import RecordingError
from .transforms import PoseTrack

__all__ = ['load_pose_file']

_TUM_COLS = 8
_KITTI_COLS = 12
# A stamp this large is no time in seconds (3e9 years): it is an integer of nanoseconds.
_NS_STAMPS = 10**17
_INT64_MAX = 2**63 - 1
_STAMP_UNITS = (
    'stamps are seconds (1311877813.991479) or integer nanoseconds (1311877813991479000); '
    'convert other units (microseconds, milliseconds) to seconds'
)


def _seconds_to_ns(tok: str) -> int:
    """Decimal seconds -> int ns without float rounding ('1311877813.991479' -> ...991479000)."""
    return int((Decimal(tok) * 1_000_000_000).to_integral_value())


def _stamp_ns(tok: str) -> int | None:
    """A stamp as int ns: seconds, or integer nanoseconds where it can only be that (>= 1e17);
    None when it does not fit int64 ns."""
    d = Decimal(tok)
    if d.is_nan():
        raise InvalidOperation(tok)
    if not d.copy_abs() < _NS_STAMPS:  # (before int() or arithmetic: 1e999999999 overflows them)
        return int(d) if d.copy_abs() <= _INT64_MAX and d == d.to_integral_value() else None
    ns = _seconds_to_ns(tok)
    return ns if abs(ns) <= _INT64_MAX else None


def _read_rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of the non-empty, non-comment lines; separators: spaces or commas."""
    try:
        text = path.read_text(encoding='utf-8-sig')  # (a BOM some editors write is no part of the first number)
    except UnicodeDecodeError:
        raise RecordingError(f'{path}: not a text file; a pose file is TUM or KITTI text') from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        content = line.split('#', 1)[0].replace(',', ' ').strip()
        if content:
            rows.append((lineno, content.split()))
    return rows


def _load_stamps(stamps: str | Path | Sequence[int] | np.ndarray) -> np.ndarray:
    """Stamps for a KITTI file: a text file with one time in seconds per line, or ns integers."""
    if isinstance(stamps, (str, Path)):
        p = Path(stamps)
        if not p.is_file():
            raise RecordingError(f'stamps file {p} does not exist')
        out = []
        for lineno, tok in _read_rows(p):
            if len(tok) != 1:
                raise RecordingError(f'{p}:{lineno}: expected one time stamp (seconds) per line, got {len(tok)} values')
            try:
                ns = _stamp_ns(tok[0])
            except InvalidOperation:
                raise RecordingError(f'{p}:{lineno}: {tok[0]!r} is not a number') from None
            if ns is None:
                raise RecordingError(f'{p}:{lineno}: time stamp {tok[0]} is out of range; {_STAMP_UNITS}')
            out.append(ns)
        return np.asarray(out, dtype=np.int64)
    return np.asarray(stamps, dtype=np.int64).reshape(-1)


def load_pose_file(path: str | Path, stamps: str | Path | Sequence[int] | np.ndarray | None = None) -> PoseTrack:
    """Read a TUM or KITTI pose file into a :class:`PoseTrack` of T_world_sensor.

    The format is detected from the column count of the first data line: 8 = TUM
    (``t tx ty tz qx qy qz qw``, t in seconds on the clock of the cloud header
    stamps; integers above 1e17 are read as nanoseconds), 12 = KITTI (row-major 3x4 ``[R | t]``). Lines starting with '#' and
    blank lines are skipped; commas are accepted as separators.

    KITTI lines carry no time. With ``stamps`` (a file with one time in seconds per
    line, or an array of int ns) they are stamped and interpolated like TUM poses;
    without it the track is ``by_index``: line i is the pose of the i-th cloud of
    the topic (counting every cloud, before any every/time-window selection).

    Bad lines raise RecordingError with the line number.
    """
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f'pose file {p} does not exist' if not p.exists() else f'pose file {p} is not a file')
    rows = _read_rows(p)
    if not rows:
        raise RecordingError(f'{p}: no poses (the file is empty or only comments)')
    ncols = len(rows[0][1])
    if ncols not in (_TUM_COLS, _KITTI_COLS):
        raise RecordingError(
            f'{p}:{rows[0][0]}: {ncols} columns; expected 8 (TUM: t tx ty tz qx qy qz qw) or '
            '12 (KITTI: row-major 3x4 matrix r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz)'
        )
    fmt = 'TUM' if ncols == _TUM_COLS else 'KITTI'
    values = np.empty((len(rows), ncols), dtype=np.float64)
    tum_stamps = np.empty(len(rows), dtype=np.int64)
    for i, (lineno, tok) in enumerate(rows):
        if len(tok) != ncols:
            raise RecordingError(f'{p}:{lineno}: {len(tok)} columns, but the file is {fmt} with {ncols} columns')
        for j, t in enumerate(tok):
            try:
                values[i, j] = float(t)
            except ValueError:
                raise RecordingError(f'{p}:{lineno}: {t!r} (column {j + 1}) is not a number') from None
        if not np.all(np.isfinite(values[i])):
            raise RecordingError(f'{p}:{lineno}: non-finite value (nan/inf)')
        if fmt == 'TUM':
            ns = _stamp_ns(tok[0])
            if ns is None:
                raise RecordingError(f'{p}:{lineno}: time stamp {tok[0]} is out of range; {_STAMP_UNITS}')
            tum_stamps[i] = ns
    if fmt == 'TUM':
        if stamps is not None:
            raise RecordingError(f'{p} is a TUM file: its first column holds the stamps; do not pass a stamps file')
        q = values[:, 4:8]
        norms = np.linalg.norm(q, axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > 0.01)
        if bad.size:
            i = int(bad[0])
            raise RecordingError(
                f'{p}:{rows[i][0]}: quaternion (qx qy qz qw) = {tuple(q[i])} has norm {norms[i]:.4f}, not 1; '
                'TUM lines are t tx ty tz qx qy qz qw'
            )
        return PoseTrack.from_tq(tum_stamps, values[:, 1:4], q, source=f'{p.name} (TUM)')
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = values.reshape(-1, 3, 4)
    R = poses[:, :3, :3]
    err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > 0.01) | (np.linalg.det(R) < 0))
    if bad.size:
        i = int(bad[0])
        raise RecordingError(
            f'{p}:{rows[i][0]}: the 3x3 part is not a rotation (|R R^T - I| = {err[i]:.3g}, det = '
            f'{np.linalg.det(R[i]):.3g}); KITTI lines are the row-major 3x4 matrix [R | t]'
        )
    # printed with few digits, R is slightly off orthonormal: project back with the SVD
    U, _, Vt = np.linalg.svd(R)
    poses[:, :3, :3] = U @ Vt
    if stamps is None:
        return PoseTrack(np.arange(len(rows)), poses, by_index=True, source=f'{p.name} (KITTI, by cloud index)')
    st = _load_stamps(stamps)
    if len(st) != len(rows):
        raise RecordingError(f'{p} has {len(rows)} poses but the stamps have {len(st)} entries; they must match')
    return PoseTrack(st, poses, source=f'{p.name} (KITTI)')
