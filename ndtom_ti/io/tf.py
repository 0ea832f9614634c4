"""TF tree built from tf2_msgs/TFMessage messages (/tf and /tf_static)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import RecordingError, TransformTimeError
from .transforms import PoseTrack, hole_text, invalid_transform, invert, make_transform, rot_to_quat

__all__ = ['TfBuffer', 'TfEdge', 'normalize_frame', 'stamp_ns']


def normalize_frame(frame: str) -> str:
    """tf2 ignores a leading '/' (ROS1 tf allowed '/world'); so do we."""
    return frame.lstrip('/')


def stamp_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (ROS1 'time' is read into the same type) -> int ns."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _fmt_s(ns: int) -> str:
    return f'{ns / 1e9:.3f} s'


def _fmt_T(T: np.ndarray) -> str:
    """'xyz (0.1, 0, 1.2) m, quaternion (0, 0, 0, 1)' of a transform."""
    t = ', '.join(f'{v:.4g}' for v in T[:3, 3])
    q = ', '.join(f'{v:.4g}' for v in rot_to_quat(T[:3, :3]))
    return f'xyz ({t}) m, quaternion xyzw ({q})'


def _static_option(T: np.ndarray, parent: str, child: str) -> str:
    """The ``--static-transform`` that gives ``T`` as the mount ``parent -> child``."""
    t = ' '.join(f'{v:.9g}' for v in T[:3, 3])
    q = ' '.join(f'{v:.9g}' for v in rot_to_quat(T[:3, :3]))
    return f"--static-transform '{t} {q} {parent} {child}'"


@dataclass(frozen=True)
class TfEdge:
    """One parent->child edge of the tree, as recorded."""

    parent: str
    child: str
    static: bool
    count: int  # transforms recorded for this edge
    first_ns: int | None  # None for static edges (valid for all time)
    last_ns: int | None


class TfBuffer:
    """All transforms of a recording; answers T_target_source queries at a time.

    Static edges (from /tf_static) hold for all time. Each dynamic edge is a
    :class:`PoseTrack` interpolated at the query stamp. A child has one parent
    (a tree, as tf2 requires); a conflicting second parent is ignored and noted.
    An edge recorded both on /tf_static and /tf uses the static value (valid at
    all times, so clouds before the first /tf message still get it).
    """

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}
        self._static: dict[str, np.ndarray] = {}  # child -> T_parent_child
        self._samples: dict[str, list[tuple[int, tuple[float, ...], tuple[float, ...]]]] = {}
        self._tracks: dict[str, PoseTrack] = {}
        self._static_count: dict[str, int] = {}
        self.notes: list[str] = []
        self._noted: set[tuple[str, str, str]] = set()
        # (parent, child) -> (transforms dropped: NaN/Inf or a zero quaternion, why the first)
        self.ignored: dict[tuple[str, str], tuple[int, str]] = {}
        self._given: dict[str, str] = {}  # 'parent -> child' -> note, of mounts given, not recorded (give)
        self._restatic: dict[tuple[str, str], np.ndarray] = {}  # mounts /tf_static changed -> the first value
        # (parent, child) -> ((T, count) if static, dynamic samples): a child's other parents
        self._other: dict[tuple[str, str], tuple[tuple[np.ndarray, int] | None, list]] = {}
        self._chosen: dict[str, str] = {}  # child -> note: its parent chosen by a fixed frame
        self.source_note = ''  # which TF topics these are, where a recording has several sets

    # ------------------------------------------------------------------ building
    def add(
        self,
        parent: str,
        child: str,
        stamp: int,
        translation: tuple[float, float, float],
        rotation: tuple[float, float, float, float],
        static: bool = False,
    ) -> None:
        """Add one transform T_parent_child (quaternion x, y, z, w)."""
        parent, child = normalize_frame(parent), normalize_frame(child)
        if not parent or not child or parent == child:
            self._note(('bad', parent, child), f'ignored a transform with frames {parent!r} -> {child!r}')
            return
        why = invalid_transform(translation, rotation)
        if why is not None:  # as tf2 does: the edge's other transforms still count
            n, first = self.ignored.get((parent, child), (0, why))
            self.ignored[(parent, child)] = (n + 1, first)
            self._note(
                ('invalid', parent, child),
                f'ignored transforms {parent} -> {child} with {why} (the first at {_fmt_s(int(stamp))})',
            )
            return
        known = self._parent.get(child)
        if known is not None and known != parent:
            self._note(
                ('reparent', child, parent),
                f"frame {child!r} has parent {known!r} but a transform also names {parent!r} as its "
                f"parent; kept {known!r}",
            )
            # kept aside: a fixed frame above it chooses it (choose_parent)
            held, samples = self._other.setdefault((parent, child), (None, []))
            if static:
                n = held[1] if held else 0
                self._other[(parent, child)] = (make_transform(translation, rotation), n + 1), samples
            else:
                samples.append((int(stamp), tuple(translation), tuple(rotation)))
            return
        if known is None and self._creates_cycle(parent, child):
            self._note(('cycle', parent, child), f'ignored {parent!r} -> {child!r}: it would close a loop in the tree')
            return
        self._parent[child] = parent
        if static:
            T = make_transform(translation, rotation)
            old = self._static.get(child)
            if old is not None and not np.allclose(old, T, atol=1e-6):  # a mount re-published, changed
                self._restatic.setdefault((parent, child), old)
                self._note(('restatic', parent, child), self._restatic_text(parent, child, T))
            self._static[child] = T
            self._static_count[child] = self._static_count.get(child, 0) + 1
        else:
            self._samples.setdefault(child, []).append((int(stamp), tuple(translation), tuple(rotation)))
            self._tracks.pop(child, None)
        if child in self._static and child in self._samples:
            self._note(
                ('both', parent, child),
                f'{parent} -> {child} is on both /tf_static and /tf; using the static transform',
            )

    def add_message(self, msg: Any, static: bool) -> None:
        """Add every transform of a tf2_msgs/TFMessage (or ROS1 tf/tfMessage)."""
        for tr in msg.transforms:
            v, q = tr.transform.translation, tr.transform.rotation
            self.add(
                tr.header.frame_id,
                tr.child_frame_id,
                stamp_ns(tr.header.stamp),
                (v.x, v.y, v.z),
                (q.x, q.y, q.z, q.w),
                static,
            )

    def _creates_cycle(self, parent: str, child: str) -> bool:
        f: str | None = parent
        while f is not None:
            if f == child:
                return True
            f = self._parent.get(f)
        return False

    def _note(self, key: tuple[str, str, str], text: str) -> None:
        if key not in self._noted:
            self._noted.add(key)
            self.notes.append(text)

    def give(self, parent: str, child: str, translation: Any, rotation: Any) -> None:
        """A mount the recording lacks (its /tf_static not recorded), given by the user: a
        static edge like a recorded one, said in ``run_notes``."""
        p, c = normalize_frame(parent), normalize_frame(child)
        text = f'static transform given: {p} -> {c}'
        if self._given.get(f'{p} -> {c}') and self._parent.get(c) == p:  # given again (another scans())
            self._static[c] = make_transform(translation, rotation)
            return
        known = self._parent.get(c)
        if known is not None:  # recorded: the given one replaces it (said with both values)
            if c in self._static:
                was = f'recorded {_fmt_T(self._static[c])}'
            else:
                was = f'{len(self._samples.get(c, []))} recorded transforms'
            text += (
                f', replacing the recorded {known} -> {c}: given {_fmt_T(make_transform(translation, rotation))}, {was}'
            )
            for d in (self._static, self._static_count, self._samples, self._tracks, self._parent):
                d.pop(c, None)  # type: ignore[attr-defined]
            self._restatic.pop((known, c), None)  # (its values are said above)
        self.add(p, c, 0, translation, rotation, static=True)
        self._given[f'{p} -> {c}'] = text

    def _edge_text(self, parent: str, child: str) -> str:
        if (parent, child) in self._other:
            held, samples = self._other[(parent, child)]
            n, static = (held[1], True) if held else (len(samples), False)
        else:
            static = child in self._static
            n = self._static_count[child] if static else len(self._samples.get(child, []))
        return f'{parent} -> {child} ({"static" if static else f"{n} transform" + "s" * (n != 1)})'

    def parent_notes(self, frames: list[str] | None = None) -> list[str]:
        """One line per frame with two parents (of ``frames``, or all): which edge is used and
        which ignored, and how to use the other."""
        out = []
        for parent, child in self._other:
            if (frames is not None and child not in frames) or child in self._chosen:
                continue
            kept = self._parent[child]
            out.append(
                f'frame {child!r} has two parents on TF: {self._edge_text(kept, child)} is used, '
                f'{self._edge_text(parent, child)} ignored (a frame has one parent in TF); '
                f'--fixed-frame {self.root_of(parent)} uses {parent!r}'
            )
        return out

    def choose_parent(self, fixed: str, frame: str) -> str | None:
        """Where ``frame`` reaches ``fixed`` only through a parent ignored for another (a frame
        with two parents), use that one; a note saying so, or None when nothing changed."""
        fixed, frame = normalize_frame(fixed), normalize_frame(frame)
        if self.connects(fixed, frame):
            return None
        for parent, child in list(self._other):
            if child not in self._ancestors(frame) or self._creates_cycle(parent, child):
                continue
            old = self._swap(parent, child)
            if self.connects(fixed, frame):
                self._chosen[child] = (
                    f'frame {child!r} has two parents on TF: using {parent!r} (towards the fixed frame {fixed!r}), not {old!r}'
                )
                return self._chosen[child]
            self._swap(old, child)
        return None

    def _swap(self, parent: str, child: str) -> str:
        """Make the ignored edge parent -> child the used one; the used one is set aside."""
        old = self._parent[child]
        held = (self._static.pop(child), self._static_count.pop(child)) if child in self._static else None
        self._other[(old, child)] = held, self._samples.pop(child, [])
        self._tracks.pop(child, None)
        held, samples = self._other.pop((parent, child))
        self._parent[child] = parent
        if held:
            self._static[child], self._static_count[child] = held
        if samples:
            self._samples[child] = samples
        return old

    def run_notes(self) -> list[str]:
        """What a mapping run with these transforms should say: the mounts given (``give``),
        per mount that /tf_static gave with different values, and one line per edge whose
        transforms were dropped (``add``), with their count."""
        return (
            ([self.source_note] if self.source_note else [])
            + list(self._given.values())
            + list(self._chosen.values())
            + self.parent_notes()
            + [self._restatic_text(p, c, self._static[c]) for p, c in self._restatic if c in self._static]
            + [
                f'ignored {n} transform{"s" if n != 1 else ""} {p} -> {c} with {why}{" (or other faults)" if n > 1 else ""}'
                for (p, c), (n, why) in self.ignored.items()
            ]
        )

    # ------------------------------------------------------------------ structure
    def frames(self) -> list[str]:
        return sorted(set(self._parent) | set(self._parent.values()))

    def tree(self) -> dict[str, str]:
        """child -> parent."""
        return dict(sorted(self._parent.items()))

    def roots(self) -> list[str]:
        return sorted(set(self._parent.values()) - set(self._parent))

    def root_of(self, frame: str) -> str:
        frame = normalize_frame(frame)
        while frame in self._parent:
            frame = self._parent[frame]
        return frame

    def connects(self, a: str, b: str) -> bool:
        """True when both frames are in the tree and a chain of transforms links them."""
        return a in self and b in self and self.root_of(a) == self.root_of(b)

    def mount_base(self, frame: str, stop: str = '') -> str:
        """The frame that static transforms alone fix ``frame`` to (the vehicle a lidar is
        mounted on): its parents up the tree while each edge is static, short of ``stop``;
        ``frame`` itself when no static edge leads up from it."""
        f = normalize_frame(frame)
        while f in self._static and self._parent.get(f) not in (None, normalize_frame(stop)):
            f = self._parent[f]
        return f

    def is_static(self, child: str) -> bool:
        return normalize_frame(child) in self._static

    def edges(self) -> list[TfEdge]:
        out = []
        for child, parent in sorted(self._parent.items()):
            if child in self._static:
                out.append(TfEdge(parent, child, True, self._static_count[child], None, None))
            else:
                tr = self._track(child)
                out.append(TfEdge(parent, child, False, len(tr), tr.first_ns, tr.last_ns))
        return out

    def __contains__(self, frame: str) -> bool:
        f = normalize_frame(frame)
        return f in self._parent or f in self._parent.values()

    def _ancestors(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self._parent:
            chain.append(self._parent[chain[-1]])
        return chain

    def path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Frames from source up to the common ancestor, and from target up to it.

        Raises RecordingError (naming the frames that exist) when either frame is
        unknown or the two are in different trees.
        """
        target, source = normalize_frame(target), normalize_frame(source)
        missing = [f for f in (target, source) if f not in self]
        if missing and target != source:
            raise RecordingError(
                f"frame {missing[0]!r} is not in the TF tree; frames that exist: "
                f"{', '.join(self.frames()) or '(none: the recording has no /tf or /tf_static)'}"
            )
        up_s = self._ancestors(source)
        up_t = self._ancestors(target)
        common = next((f for f in up_s if f in set(up_t)), None)
        if common is None:
            raise RecordingError(
                f"frames {target!r} and {source!r} are not connected by TF: {target!r} is in the tree rooted at "
                f"{up_t[-1]!r}, {source!r} in the tree rooted at {up_s[-1]!r}; tree (child -> parent): "
                + ', '.join(f'{c} -> {p}' for c, p in self.tree().items())
            )
        return up_s[: up_s.index(common) + 1], up_t[: up_t.index(common) + 1]

    def chain_is_static(self, target: str, source: str) -> bool:
        """True when every edge between the two frames is static (a constant transform)."""
        up_s, up_t = self.path(target, source)
        return all(f in self._static for f in up_s[:-1] + up_t[:-1])

    def chain_str(self, target: str, source: str) -> str:
        """'map -> base_link -> lidar' (target first)."""
        up_s, up_t = self.path(target, source)
        return ' -> '.join(up_t + list(reversed(up_s[:-1])))

    def dynamic_range_ns(self, target: str, source: str) -> tuple[int, int] | None:
        """Stamps where every dynamic edge of the chain has data; None if all static."""
        up_s, up_t = self.path(target, source)
        lo, hi = None, None
        for f in up_s[:-1] + up_t[:-1]:
            if f in self._static:
                continue
            tr = self._track(f)
            lo = tr.first_ns if lo is None else max(lo, tr.first_ns)
            hi = tr.last_ns if hi is None else min(hi, tr.last_ns)
        return None if lo is None or hi is None else (lo, hi)

    # ------------------------------------------------------------------ queries
    def _track(self, child: str) -> PoseTrack:
        tr = self._tracks.get(child)
        if tr is None:
            s = self._samples[child]
            tr = PoseTrack.from_tq(
                [x[0] for x in s], [x[1] for x in s], [x[2] for x in s], source=f'{self._parent[child]} -> {child}'
            )
            self._tracks[child] = tr
        return tr

    def _edge(self, child: str, stamp: int, tolerance_ns: int) -> np.ndarray:
        """T_parent_child at the stamp."""
        T = self._static.get(child)
        if T is not None:
            return T
        tr = self._track(child)
        T = tr.at(stamp, tolerance_ns)
        if T is None:
            gap = tr.gap_ns(stamp)
            where = 'before the first' if gap < 0 else 'after the last'
            raise TransformTimeError(
                f'transform {self._parent[child]} -> {child} is not available at {_fmt_s(stamp)}: that is '
                f'{abs(gap) / 1e9:.3f} s {where} of its {len(tr)} transforms '
                f'({_fmt_s(tr.first_ns)} .. {_fmt_s(tr.last_ns)}; tolerance {tolerance_ns / 1e9:.3f} s)'
                + self._mount_hint(child, tr)
            )
        hole = tr.hole_at(stamp, tolerance_ns)
        if hole is not None:  # tf2 would interpolate across it: a straight line over seconds unseen
            raise TransformTimeError(f'transform {self._parent[child]} -> {child}: {hole_text(tr, stamp, *hole)}')
        return T

    def _restatic_text(self, parent: str, child: str, last: np.ndarray) -> str:
        """A mount /tf_static gave again with another value (a calibration re-published): tf2
        keeps the last, for all time, and so does a map; the first, and how to choose."""
        first = self._restatic[(parent, child)]
        return (
            f'/tf_static gives {parent} -> {child} more than once with different values; the last is used for every '
            f'scan, as tf2 keeps it (first {_fmt_T(first)}, last {_fmt_T(last)}): '
            f'{_static_option(first, parent, child)} maps with the first'
        )

    def _mount_hint(self, child: str, tr: PoseTrack) -> str:
        """Where every transform of a /tf edge is the same (a mount published on /tf rather
        than /tf_static, once or at start-up only): how to give it for all times."""
        if not tr.is_constant(1e-9):
            return ''
        n = len(tr)
        return (
            f'. {"It has one transform" if n == 1 else f"Its {n} transforms give one value"}: a mount sent on /tf '
            f'rather than /tf_static? {_static_option(tr.poses[0], self._parent[child], child)} gives it for every time'
        )

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int, tolerance_ns: int = 0) -> np.ndarray:
        """T_target_source (4x4): maps points in ``source_frame`` into ``target_frame``.

        Goes up from the source to the common ancestor and down to the target,
        each dynamic edge interpolated at the stamp (clamped within the tolerance).
        """
        up_s, up_t = self.path(target_frame, source_frame)
        T_anc_src = np.eye(4)
        for f in up_s[:-1]:
            T_anc_src = self._edge(f, stamp_ns, tolerance_ns) @ T_anc_src
        T_anc_tgt = np.eye(4)
        for f in up_t[:-1]:
            T_anc_tgt = self._edge(f, stamp_ns, tolerance_ns) @ T_anc_tgt
        return invert(T_anc_tgt) @ T_anc_src
