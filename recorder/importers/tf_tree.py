"""A ROS transform tree (``/tf`` and ``/tf_static``) read back as one frame's pose in another.

Each ``TransformStamped`` gives ``T_parent_child`` (the child frame's pose in the parent frame)
at a time. Static transforms hold at all times; a moving edge is interpolated between its two
nearest samples (translation linearly, rotation by slerp) and never extrapolated. The pose of
``child`` in ``frame`` is ``inv(T_root_frame) @ T_root_child``, each factor the product of the
edges from the tree's root, and is sampled at every stamp of every moving edge on the path that
lies inside all of their time spans.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from slamreplay.recorder.errors import RecorderError

F64 = NDArray[np.float64]


@dataclass
class _Edge:
    parent: str
    stamps: list[int] = field(default_factory=list)
    translations: list[tuple[float, float, float]] = field(default_factory=list)
    quats_xyzw: list[tuple[float, float, float, float]] = field(default_factory=list)
    static: bool = False


def _matrices(t: F64, rot: Rotation) -> F64:
    m = np.zeros((len(t), 4, 4))
    m[:, :3, :3] = rot.as_matrix().reshape(-1, 3, 3)
    m[:, :3, 3] = t
    m[:, 3, 3] = 1.0
    return m


class TfTree:
    """Transforms collected from tf messages; ask for a frame's planar pose in another frame."""

    def __init__(self) -> None:
        self._edges: dict[str, _Edge] = {}
        self._parents_seen: dict[str, set[str]] = defaultdict(set)

    def add(self, parent: str, child: str, stamp_ns: int, translation: tuple[float, float, float],
            quat_xyzw: tuple[float, float, float, float], static: bool) -> None:
        """Record ``T_parent_child`` at ``stamp_ns`` (static: for all times)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        self._parents_seen[child].add(parent)
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent:
            # tf allows one parent per frame: the latest one given wins, as in tf2's buffer
            edge = self._edges[child] = _Edge(parent)
        if static:
            edge.static = True
            edge.stamps, edge.translations, edge.quats_xyzw = [stamp_ns], [translation], [quat_xyzw]
            return
        edge.stamps.append(int(stamp_ns))
        edge.translations.append(translation)
        edge.quats_xyzw.append(quat_xyzw)

    @property
    def frames(self) -> set[str]:
        """Every frame named as a parent or a child."""
        return set(self._edges) | {e.parent for e in self._edges.values()}

    def _chain(self, frame: str) -> list[str]:
        """``frame``, its parent, ..., the root."""
        chain = [frame]
        while chain[-1] in self._edges:
            nxt = self._edges[chain[-1]].parent
            if nxt in chain:
                raise RecorderError(f"the tf tree has a cycle through {nxt!r}: it is not a tree; fix the bag's /tf")
            chain.append(nxt)
        return chain

    def check_frame(self, frame: str, option: str) -> None:
        """Raise RecorderError, naming the frames there are, when ``frame`` is not in the tree."""
        if frame not in self.frames:
            known = ", ".join(sorted(self.frames)) or "none: the bag has no /tf or /tf_static messages"
            raise RecorderError(f"the tf tree has no frame {frame!r} (frames: {known}): pass {option} with one of them")

    def path(self, frame: str, child: str) -> tuple[list[str], list[str]]:
        """The frames from ``frame`` and from ``child`` up to (excluding) their common ancestor."""
        up_f, up_c = self._chain(frame), self._chain(child)
        common = next((f for f in up_c if f in up_f), None)
        if common is None:
            msg = (f"tf frames {frame!r} and {child!r} are not connected (their roots are {up_f[-1]!r} and "
                   f"{up_c[-1]!r}): the bag's /tf lacks a transform linking them")
            raise RecorderError(msg)
        return up_f[:up_f.index(common)], up_c[:up_c.index(common)]

    def planar_poses(self, frame: str, child: str, after_ns: int | None = None) -> tuple[NDArray[np.int64], F64]:
        """Stamps (m,) and planar poses (m, 3) ``[x, y, yaw]`` of ``child`` in ``frame``.

        ``after_ns``: only the stamps after it (none may be left: m = 0). Raises RecorderError when a frame
        is missing, the two are not connected, or no moving transform lies between them.
        """
        from_frame, from_child = self.path(frame, child)
        edges = [self._edges[f] for f in from_frame + from_child]
        moving = [e for e in edges if not e.static]
        if not moving:
            raise RecorderError(f"only static transforms link tf frames {frame!r} and {child!r}: no motion to record")
        lo = max(min(e.stamps) for e in moving)
        hi = min(max(e.stamps) for e in moving)
        stamps = np.unique(np.concatenate([np.asarray(e.stamps, dtype=np.int64) for e in moving]))
        stamps = stamps[(stamps >= lo) & (stamps <= hi)]
        if after_ns is not None:
            stamps = stamps[stamps > after_ns]
            if len(stamps) == 0:
                return stamps, np.zeros((0, 3))
        if len(stamps) == 0:
            raise RecorderError(f"the transforms linking tf frames {frame!r} and {child!r} never overlap in time")

        def root_from(frames: list[str]) -> F64:
            m = np.broadcast_to(np.eye(4), (len(stamps), 4, 4)).copy()
            for f in reversed(frames):  # T_root_f = T_root_parent @ T_parent_f
                m = m @ self._sample(self._edges[f], stamps)
            return m

        T = np.linalg.inv(root_from(from_frame)) @ root_from(from_child)
        yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
        return stamps, np.column_stack([T[:, 0, 3], T[:, 1, 3], yaw])

    def forget_before(self, stamp_ns: int) -> None:
        """Drop the samples of moving transforms that no pose after ``stamp_ns`` needs (a live stream's tree
        stays small): each keeps its last sample at or before it, for interpolation, and all after."""
        for edge in self._edges.values():
            if edge.static or len(edge.stamps) < 3:
                continue
            before = [s for s in edge.stamps if s <= stamp_ns]
            if not before:
                continue
            first = max(before)
            keep = [k for k, s in enumerate(edge.stamps) if s >= first]
            if len(keep) < len(edge.stamps):
                edge.stamps = [edge.stamps[k] for k in keep]
                edge.translations = [edge.translations[k] for k in keep]
                edge.quats_xyzw = [edge.quats_xyzw[k] for k in keep]

    def static_planar(self, frame: str, child: str) -> tuple[float, float, float] | None:
        """The fixed planar pose of ``child`` in ``frame`` when only static transforms link them, else None."""
        if frame == child:
            return (0.0, 0.0, 0.0)
        try:
            from_frame, from_child = self.path(frame, child)
        except RecorderError:
            return None
        edges = [self._edges[f] for f in from_frame + from_child]
        if not all(e.static for e in edges):
            return None
        one = np.array([0], dtype=np.int64)

        def root_from(frames: list[str]) -> F64:
            m = np.eye(4)[None]
            for f in reversed(frames):
                m = m @ self._sample(self._edges[f], one)
            return m

        T = (np.linalg.inv(root_from(from_frame)) @ root_from(from_child))[0]
        return float(T[0, 3]), float(T[1, 3]), math.atan2(T[1, 0], T[0, 0])

    @staticmethod
    def _sample(edge: _Edge, stamps: NDArray[np.int64]) -> F64:
        t = np.asarray(edge.translations, dtype=np.float64)
        q = np.asarray(edge.quats_xyzw, dtype=np.float64)
        if edge.static or len(edge.stamps) == 1:
            return np.broadcast_to(_matrices(t[:1], Rotation.from_quat(q[:1])), (len(stamps), 4, 4))
        s = np.asarray(edge.stamps, dtype=np.int64)
        s, first = np.unique(s, return_index=True)  # a repeated stamp: the first sample
        t, q = t[first], q[first]
        if len(s) == 1:
            return np.broadcast_to(_matrices(t, Rotation.from_quat(q)), (len(stamps), 4, 4))
        rel = (stamps - s[0]).astype(np.float64)
        knots = (s - s[0]).astype(np.float64)
        trans = np.column_stack([np.interp(rel, knots, t[:, k]) for k in range(3)])
        rot = Slerp(knots, Rotation.from_quat(q))(np.clip(rel, knots[0], knots[-1]))
        return _matrices(trans, rot)
