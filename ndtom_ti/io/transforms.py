"""Rigid-transform helpers and :class:`PoseTrack` (stamped poses with interpolation).

Quaternions are (x, y, z, w) as in ROS messages. Poses are 4x4 float64 matrices.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from .errors import RecordingError

__all__ = [
    'PoseTrack',
    'hole_text',
    'invalid_transform',
    'invert',
    'make_transform',
    'quat_to_rot',
    'rot_to_quat',
    'slerp',
]


def invalid_transform(translation: Sequence[float], rotation: Sequence[float]) -> str | None:
    """Why a recorded transform (translation, quaternion x, y, z, w) cannot be used, or None:
    NaN or Inf values, or a quaternion of zero length (a driver's unset pose). tf2 drops
    such transforms with a warning; so does a recording's reader."""
    v = np.asarray([*translation, *rotation], dtype=np.float64)
    if not np.isfinite(v).all():
        return 'NaN or Inf values'
    if np.linalg.norm(v[3:]) < 1e-12:
        return 'a zero-length quaternion'
    return None


def quat_to_rot(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """(..., 4) quaternion (x, y, z, w) -> (..., 3, 3) rotation; normalises the input."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise RecordingError('zero-length quaternion: the transform has no valid rotation')
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion (x, y, z, w) with w >= 0.

    Shepperd's method, vectorised: for each matrix the largest of 4w^2, 4x^2,
    4y^2, 4z^2 is used as the pivot so that no division by a small number occurs.
    """
    R = np.asarray(R, dtype=np.float64)
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    cand = np.stack(
        [
            np.stack([m21 - m12, m02 - m20, m10 - m01, 1 + m00 + m11 + m22], -1),  # pivot w
            np.stack([1 + m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12], -1),  # pivot x
            np.stack([m01 + m10, 1 - m00 + m11 - m22, m12 + m21, m02 - m20], -1),  # pivot y
            np.stack([m02 + m20, m12 + m21, 1 - m00 - m11 + m22, m10 - m01], -1),  # pivot z
        ],
        -2,
    )
    diag = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cand, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def make_transform(translation: Sequence[float] | np.ndarray, rotation: np.ndarray | Sequence[float]) -> np.ndarray:
    """4x4 pose from a translation and either a 3x3 rotation or a quaternion (x, y, z, w)."""
    rot = np.asarray(rotation, dtype=np.float64)
    # (numpy would broadcast a 3-vector, e.g. roll pitch yaw, or a scalar into nonsense rows)
    if rot.shape not in ((4,), (3, 3)):
        raise ValueError(
            f'rotation must be a 3x3 rotation matrix or a quaternion (x, y, z, w), got shape {rot.shape}; '
            'convert angles to one first (e.g. scipy.spatial.transform.Rotation.from_euler(...).as_quat())'
        )
    if np.shape(translation) != (3,):
        raise ValueError(f'translation must be 3 numbers (x, y, z), got shape {np.shape(translation)}')
    T = np.eye(4)
    T[:3, :3] = quat_to_rot(rot) if rot.shape == (4,) else rot
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (exact transpose of the rotation, no general inverse)."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions along the shorter arc."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:  # q and -q are the same rotation; take the short way round
        q1, dot = -q1, -dot
    if dot > 0.9999995:  # nearly identical: sin(theta) ~ 0, lerp is exact to rounding
        q = q0 + f * (q1 - q0)
    else:
        theta = np.arccos(min(dot, 1.0))
        s = np.sin(theta)
        q = (np.sin((1.0 - f) * theta) / s) * q0 + (np.sin(f * theta) / s) * q1
    return q / np.linalg.norm(q)


def hole_text(track: PoseTrack, stamp_ns: int, before: int, after: int) -> str:
    """Why a stamp in a gap of a track's poses (:meth:`PoseTrack.hole_at`) has none."""
    return (
        f'no pose at {stamp_ns / 1e9:.3f} s: it falls in a gap of {(after - before) / 1e9:.3f} s without poses '
        f'({before / 1e9:.3f} .. {after / 1e9:.3f} s, where they are {(track.spacing_ns() or 0) / 1e9:.3f} s '
        'apart as a rule): a pose interpolated across it would be a guess'
    )


class PoseTrack:
    """Time-sorted stamped poses; :meth:`at` interpolates (translation linear, rotation slerp).

    Duplicate stamps keep the last pose given. ``by_index`` marks a track whose
    "stamps" are cloud indices (a KITTI file without a stamps file): pose i belongs
    to the i-th cloud of the topic and is never interpolated.
    """

    stamps_ns: np.ndarray  # (K,) int64, strictly increasing
    poses: np.ndarray  # (K, 4, 4) float64

    def __init__(
        self, stamps_ns: npt.ArrayLike, poses: npt.ArrayLike, *, by_index: bool = False, source: str = ''
    ) -> None:
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        self._init(
            np.asarray(stamps_ns, dtype=np.int64).reshape(-1),
            poses[:, :3, 3],
            rot_to_quat(poses[:, :3, :3]),
            poses,
            by_index,
            source,
        )

    @classmethod
    def from_tq(
        cls, stamps_ns: npt.ArrayLike, translations: npt.ArrayLike, quats: npt.ArrayLike, *, source: str = ''
    ) -> PoseTrack:
        """Track from translations (K,3) and quaternions (K,4) (x, y, z, w), as stored in messages."""
        t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(quats, dtype=np.float64).reshape(-1, 4)
        n = np.linalg.norm(q, axis=1, keepdims=True)
        if np.any(n < 1e-12):
            raise RecordingError(f'{source or "pose track"}: a quaternion has zero length (no valid rotation)')
        q = q / n
        poses = np.tile(np.eye(4), (len(t), 1, 1))
        if len(t):
            poses[:, :3, :3] = quat_to_rot(q)
            poses[:, :3, 3] = t
        self = cls.__new__(cls)
        self._init(np.asarray(stamps_ns, dtype=np.int64).reshape(-1), t, q, poses, False, source)
        return self

    def _init(
        self, stamps: np.ndarray, t: np.ndarray, q: np.ndarray, poses: np.ndarray, by_index: bool, source: str
    ) -> None:
        if not (len(stamps) == len(t) == len(q) == len(poses)):
            raise ValueError(f'{len(stamps)} stamps but {len(poses)} poses')
        order = np.argsort(stamps, kind='stable')
        stamps, t, q, poses = stamps[order], t[order], q[order], poses[order]
        if len(stamps) > 1:  # keep the last of equal stamps (a later message overrides)
            keep = np.append(stamps[1:] != stamps[:-1], True)
            stamps, t, q, poses = stamps[keep], t[keep], q[keep], poses[keep]
        self.stamps_ns = stamps
        self.poses = poses
        self._t = t
        self._q = q
        self.by_index = by_index
        self.source = source
        self._spacing: int | None | bool = False  # (spacing_ns, worked out on first use)

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def __repr__(self) -> str:
        if not len(self):
            return f'PoseTrack(empty, source={self.source!r})'
        return f'PoseTrack({len(self)} poses, {self.stamps_ns[0]}..{self.stamps_ns[-1]} ns, source={self.source!r})'

    @property
    def first_ns(self) -> int:
        return int(self.stamps_ns[0])

    @property
    def last_ns(self) -> int:
        return int(self.stamps_ns[-1])

    def is_constant(self, atol: float = 1e-9) -> bool:
        """True when every pose equals the first (a "fixed pose" topic)."""
        return bool(len(self) > 0 and np.all(np.abs(self.poses - self.poses[0]) <= atol))

    def gap_ns(self, stamp_ns: int) -> int:
        """Signed distance of a stamp outside [first, last]: <0 before, >0 after, 0 inside."""
        if stamp_ns < self.stamps_ns[0]:
            return int(stamp_ns) - self.first_ns
        if stamp_ns > self.stamps_ns[-1]:
            return int(stamp_ns) - self.last_ns
        return 0

    def max_gap_ns(self) -> int | None:
        """The longest time between two poses that interpolating across is trusted: 10 times
        their usual (median) spacing, at least 1 s; None with too few poses to tell."""
        spacing = self.spacing_ns()
        return None if spacing is None else max(10**9, 10 * spacing)

    def spacing_ns(self) -> int | None:
        """The usual (median) time between two poses; None with fewer than 3 or by index."""
        if self._spacing is False:
            few = len(self) < 3 or self.by_index
            self._spacing = None if few else int(np.median(np.diff(self.stamps_ns)))
        return self._spacing

    def hole_at(self, stamp_ns: int, tolerance_ns: int = 0) -> tuple[int, int] | None:
        """(before, after): the stamps of the poses around ``stamp_ns`` where they are farther
        apart than :meth:`max_gap_ns` (poses lost, a sensor or localisation that stopped) and
        the stamp is beyond ``tolerance_ns`` of both: a pose interpolated there would be a
        guess. None elsewhere (outside [first, last] too: :meth:`at` says that)."""
        limit = self.max_gap_ns()
        s = int(stamp_ns)
        if limit is None or not self.first_ns < s < self.last_ns:
            return None
        i = int(np.searchsorted(self.stamps_ns, s, side='right')) - 1
        lo, hi = int(self.stamps_ns[i]), int(self.stamps_ns[i + 1])
        if hi - lo <= limit or min(s - lo, hi - s) <= tolerance_ns:
            return None
        return lo, hi

    def at(self, stamp_ns: int, tolerance_ns: int = 0) -> np.ndarray | None:
        """Pose at ``stamp_ns``; None outside [first - tol, last + tol].

        Within the tolerance outside the range the end pose is used (clamped, not
        extrapolated: extrapolating motion from two samples amplifies noise).
        """
        n = len(self.stamps_ns)
        if n == 0:
            return None
        s = int(stamp_ns)
        st = self.stamps_ns
        if s < st[0] - tolerance_ns or s > st[-1] + tolerance_ns:
            return None
        if s <= st[0]:
            return self.poses[0].copy()
        if s >= st[-1]:
            return self.poses[-1].copy()
        i = int(np.searchsorted(st, s, side='right')) - 1
        if st[i] == s:  # exact sample: return it untouched
            return self.poses[i].copy()
        # integer differences first: float64 ns since 1970 would lose ~100 ns
        f = float(s - st[i]) / float(st[i + 1] - st[i])
        T = np.eye(4)
        T[:3, 3] = self._t[i] + f * (self._t[i + 1] - self._t[i])
        T[:3, :3] = quat_to_rot(slerp(self._q[i], self._q[i + 1], f))
        return T
