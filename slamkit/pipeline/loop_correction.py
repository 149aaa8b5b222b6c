"""Correcting the map after a loop is detected (ORB-SLAM sec. VII-C/D, LoopClosing::CorrectLoop and
Optimizer::OptimizeEssentialGraph): propagate the loop's Sim3 to the current keyframe's neighbourhood,
correct their points, and optimize the essential graph in Sim3 with the loop keyframe fixed.

Each correction of the map is computed first and written after (:class:`MapMove`: ``loop_correction_move`` /
``essential_graph_move`` only read the map, ``write_map_move`` writes the result): the loop closer computes under
the map's read lock, so tracking goes on meanwhile, and holds the write lock only to write
(:func:`read_then_write`).

Poses are Sim3 here (``slamkit.geometry.sim3.Sim3``, x' = s R x + t); keyframes keep SE3 ``T_c_w``, obtained
back from a Sim3 as [R, t / s] (scale is absorbed by the map, as in ORB-SLAM).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.sim3 import Sim3
from slamkit.interfaces import MapStore
from slamkit.map.graphs import essential_graph_edges
from slamkit.pipeline.map_points import PointUpdates, refreshed_points, write_point_updates
from slamkit.problems import EssentialGraphProblem, EssentialGraphResult

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
P = TypeVar("P")
R = TypeVar("R")


def sim3_of_pose(T_c_w: F64) -> Sim3:
    """The SE3 pose T_c_w as a Sim3 with scale 1."""
    return Sim3(1.0, T_c_w[:3, :3].copy(), T_c_w[:3, 3].copy())


def pose_of_sim3(S_c_w: Sim3) -> F64:
    """Back to SE3: [R, t / s] (ORB-SLAM: the map absorbs the scale)."""
    return S_c_w.to_se3()


@dataclass
class LoopCorrection:
    """Poses of the current keyframe's neighbourhood before (``non_corrected``) and after (``corrected``) the
    loop's Sim3 is propagated; keyframe id -> S_c_w."""

    non_corrected: dict[int, Sim3]
    corrected: dict[int, Sim3]


def propagate_loop_sim3(store: MapStore, current_id: int, S_cw_corrected: Sim3) -> LoopCorrection:
    """The current keyframe and its covisible neighbours move with it: S_iw' = S_ic S_cw' where S_ic is
    taken from the poses before correction (ORB-SLAM CorrectLoop)."""
    current = store.get_keyframe(current_id)
    T_wc = sim3_of_pose(current.T_c_w).inverse()
    connected = [current_id, *store.covisibility.neighbors(current_id)]
    non_corrected: dict[int, Sim3] = {}
    corrected: dict[int, Sim3] = {}
    for kf_id in connected:
        S_iw = sim3_of_pose(store.get_keyframe(kf_id).T_c_w)
        non_corrected[kf_id] = S_iw
        corrected[kf_id] = S_cw_corrected if kf_id == current_id else (S_iw @ T_wc) @ S_cw_corrected
    return LoopCorrection(non_corrected, corrected)


@dataclass(frozen=True)
class MapMove:
    """A correction of the map, computed (under the read lock) to be written at once (under the write lock):
    keyframes ``kf_ids`` get the poses ``poses`` (T_c_w (4, 4) each), points ``point_ids`` (M,) the world
    positions ``xyz_w`` (M, 3) m, and ``refresh`` the normals and depth ranges those poses and positions give."""

    kf_ids: list[int]
    poses: list[F64]
    point_ids: I64
    xyz_w: F64
    refresh: PointUpdates


def _moved_points(store: MapStore, moves: dict[int, tuple[list[int], F64]]) -> tuple[I64, F64]:
    """moves: keyframe id -> (point ids, the (4, 4) similarity to apply to their world positions), one vectorised
    product per keyframe -> (ids (M,), new xyz_w (M, 3) m) of the listed points in the map (each listed once)."""
    ids_out: list[I64] = []
    xyz_out: list[F64] = []
    for pids, M in moves.values():
        if not pids:
            continue
        ids = np.array([p.id for p in store.get_points(pids)], np.int64)
        xyz = store.point_rows(ids, "xyz_w").reshape(-1, 3)
        ids_out.append(ids)
        xyz_out.append(xyz @ M[:3, :3].T + M[:3, 3])
    if not ids_out:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(ids_out), np.concatenate(xyz_out)


def _center_of(T_c_w: F64) -> F64:
    """(3,) m the camera centre of the pose T_c_w (4, 4), as ``KeyFrame.center_w`` computes it once the pose is
    stored (the same operations on a C-ordered float64 copy: the same bits)."""
    T = np.array(T_c_w, np.float64)
    R_cw, t = T[:3, :3], T[:3, 3]
    return np.asarray(-R_cw.T @ t)


def _move_of(
    store: MapStore, moves: dict[int, tuple[list[int], F64]], poses: dict[int, F64], refresh_ids: list[int]
) -> MapMove:
    """The MapMove of point moves ``moves`` (see _moved_points) and keyframe poses ``poses`` (id -> T_c_w, in
    writing order), with the normals and depth ranges of the points ``refresh_ids`` after both."""
    ids, xyz = _moved_points(store, moves)
    order = np.argsort(ids, kind="stable")
    refresh = refreshed_points(
        store,
        refresh_ids,
        normals=True,
        descriptors=False,
        moved=(ids[order], xyz[order]),
        centers_w={k: _center_of(T) for k, T in poses.items()},
    )
    return MapMove(list(poses), list(poses.values()), ids, xyz, refresh)


def write_map_move(store: MapStore, move: MapMove) -> None:
    """Write ``move`` to the map (the write lock): the points' positions, the keyframes' poses, then the refreshed
    normals and depth ranges."""
    store.assign_points(move.point_ids, "xyz_w", move.xyz_w)
    for k, T in zip(move.kf_ids, move.poses, strict=True):
        store.set_keyframe_pose(k, T)
    write_point_updates(store, move.refresh)


def read_then_write(store: MapStore, prepare: Callable[[], P], commit: Callable[[P], R]) -> R:
    """``commit(prepare())`` with ``prepare`` (which only reads the map) under the read lock, so tracking goes on
    meanwhile, and ``commit`` under the write lock. The caller keeps the map's other writers stopped (the loop closer:
    local mapping parked, the global BA aborted; tracking only counts visible/found points), so the map ``prepare``
    read is the one ``commit`` writes; should another writer still get in between (the store's ``write_count``, where
    it has one, moved), ``prepare`` runs again under the write lock. A store without ``write_count`` runs both
    under the write lock."""
    writes = getattr(store, "write_count", None)
    if writes is None:
        with store.write():
            return commit(prepare())
    with store.read():
        seen = store.write_count  # type: ignore[attr-defined]
        prepared = prepare()
    with store.write():
        if store.write_count != seen:  # type: ignore[attr-defined]
            prepared = prepare()
        return commit(prepared)


def loop_correction_move(store: MapStore, corr: LoopCorrection) -> tuple[MapMove, set[int]]:
    """The move of :func:`apply_loop_correction`, computed without writing (the read lock does), and the ids of the
    points it corrects."""
    done: set[int] = set()
    moves: dict[int, tuple[list[int], F64]] = {}
    for kf_id in sorted(corr.corrected):
        kf = store.get_keyframe(kf_id)
        pids = []
        for pid in kf.point_ids[kf.point_ids >= 0].tolist():
            if pid not in done and store.has_point(pid):
                pids.append(pid)
                done.add(pid)
        # p' = S_new^-1 S_old p
        moves[kf_id] = (pids, corr.corrected[kf_id].inverse().matrix() @ corr.non_corrected[kf_id].matrix())
    poses = {kf_id: pose_of_sim3(S) for kf_id, S in corr.corrected.items()}
    return _move_of(store, moves, poses, sorted(done)), done


def apply_loop_correction(store: MapStore, corr: LoopCorrection) -> set[int]:
    """Move the points seen by the corrected keyframes (each once, by the first keyframe in id order that
    sees it) and set the keyframes' poses. Returns the ids of the corrected points."""
    move, done = loop_correction_move(store, corr)
    write_map_move(store, move)
    return done


def essential_graph_problem(
    store: MapStore,
    loop_kf_id: int,
    current_id: int,
    corr: LoopCorrection,
    loop_connections: dict[int, set[int]],
    theta_min: int,
) -> tuple[EssentialGraphProblem, list[int]]:
    """The essential-graph problem of ORB-SLAM's OptimizeEssentialGraph with the loop keyframe fixed.

    Edges: the new loop connections (those other than current-loop need theta_min shared points), then the
    essential graph of the map (slamkit.map.graphs.essential_graph_edges: spanning tree, earlier loop edges,
    covisibility edges with at least theta_min shared points). Loop connections are measured from the corrected
    poses, the other edges from the poses before correction; initial values are the corrected poses.
    """
    kf_ids = store.keyframe_ids()
    initial = {k: corr.corrected.get(k, sim3_of_pose(store.get_keyframe(k).T_c_w)) for k in kf_ids}
    cov = store.covisibility
    links = [
        (i, j)
        for i, linked in sorted(loop_connections.items())
        for j in sorted(linked)
        if (i, j) == (current_id, loop_kf_id) or cov.weight(i, j) >= theta_min
    ]
    return essential_graph_over(store, initial, corr.non_corrected, {loop_kf_id}, links, theta_min)


def essential_graph_over(
    store: MapStore,
    initial: Mapping[int, Sim3],
    before: Mapping[int, Sim3],
    fixed: set[int],
    new_links: list[tuple[int, int]],
    theta_min: int,
) -> tuple[EssentialGraphProblem, list[int]]:
    """The essential-graph problem (ORB-SLAM OptimizeEssentialGraph) over every keyframe of the map, ``initial``
    their Sim3 poses (keyframe id -> S_c_w; every keyframe of the map), ``fixed`` the ones held.

    Edges: ``new_links`` (a loop's or a merge's new connections) measured from the ``initial`` poses, then the
    essential graph of the map (slamkit.map.graphs.essential_graph_edges: spanning tree, loop edges, covisibility
    edges with at least theta_min shared points) measured from the poses ``before`` the correction where given, else
    from ``initial``; an edge is inserted once, first wins."""
    kf_ids = store.keyframe_ids()
    row = {k: i for i, k in enumerate(kf_ids)}
    init = [initial[k] for k in kf_ids]
    measured = [before.get(k, init[row[k]]) for k in kf_ids]
    edges: dict[tuple[int, int], list[Sim3]] = {}

    def add(i: int, j: int, source: list[Sim3]) -> None:
        if i != j and i in row and j in row:
            edges.setdefault((min(i, j), max(i, j)), source)

    for i, j in new_links:
        add(i, j, init)
    for a, b in essential_graph_edges(store.covisibility, store.spanning_tree, store.loop_edges(), theta_min):
        add(a, b, measured)
    pairs = sorted(edges)
    S_ij = (
        np.stack([(edges[i, j][row[i]] @ edges[i, j][row[j]].inverse()).matrix() for i, j in pairs])
        if pairs
        else np.zeros((0, 4, 4))
    )
    problem = EssentialGraphProblem(
        S_c_w=np.stack([s.matrix() for s in init]),
        fixed=np.array([k in fixed for k in kf_ids]),
        edge_i=np.array([row[i] for i, _ in pairs], np.int64),
        edge_j=np.array([row[j] for _, j in pairs], np.int64),
        S_ij=S_ij,
        # stereo/RGB-D maps: SE3 (ORB-SLAM2 OptimizeEssentialGraph with bFixScale keeps every scale at 1)
        use_sim3=not any(store.get_keyframe(k).features.bf > 0.0 for k in kf_ids),
    )
    return problem, kf_ids


def essential_graph_move(
    store: MapStore, problem: EssentialGraphProblem, result: EssentialGraphResult, kf_ids: list[int]
) -> MapMove:
    """The move of :func:`apply_essential_graph`, computed without writing (the read lock does)."""
    row = {k: i for i, k in enumerate(kf_ids)}
    by_ref: dict[int, list[int]] = {}
    for pid in store.point_ids():
        point = store.get_point(pid)
        ref = point.ref_kf_id if point.ref_kf_id in row else min(point.observations, default=-1)
        if ref in row:
            by_ref.setdefault(ref, []).append(pid)
    optimized = [Sim3.from_matrix(S) for S in result.S_c_w]
    moves: dict[int, tuple[list[int], F64]] = {}
    for ref, pids in by_ref.items():
        moves[ref] = (pids, optimized[row[ref]].inverse().matrix() @ problem.S_c_w[row[ref]])
    poses = {k: pose_of_sim3(optimized[row[k]]) for k in kf_ids}
    return _move_of(store, moves, poses, store.point_ids())


def apply_essential_graph(
    store: MapStore, problem: EssentialGraphProblem, result: EssentialGraphResult, kf_ids: list[int]
) -> None:
    """Set every keyframe's pose from the optimized Sim3 and move each point with its reference keyframe:
    p' = S_new^-1 S_before p (ORB-SLAM OptimizeEssentialGraph's final step)."""
    write_map_move(store, essential_graph_move(store, problem, result, kf_ids))
