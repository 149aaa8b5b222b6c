"""The keyframe graphs of ORB-SLAM (sec. III-D): covisibility graph, spanning tree, essential graph.

Pure bookkeeping on keyframe ids; the store holds one of each, guarded by the map's lock. Orders are
deterministic (ties broken by id) so a sequential run is reproducible bit for bit.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from slamkit.map import protocol


class CovisibilityGraph:
    """Undirected weighted graph: an edge joins two keyframes that observe at least ``min_shared`` common
    map points; its weight is the number of common points (III-D: theta = 15)."""

    def __init__(self) -> None:
        self._w: dict[int, dict[int, int]] = {}

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._w

    def add_node(self, kf_id: int) -> None:
        self._w.setdefault(kf_id, {})

    def update_connections(self, kf_id: int, shared: Mapping[int, int], min_shared: int) -> None:
        """Replace ``kf_id``'s edges from its shared-point counts with every other keyframe.

        As ORB-SLAM (KeyFrame::UpdateConnections): keep the pairs with at least ``min_shared`` points; when
        none reaches it, keep the single best so a keyframe is never isolated.
        """
        counts = {k: c for k, c in shared.items() if k != kf_id and c > 0}
        kept = {k: c for k, c in counts.items() if c >= min_shared}
        if not kept and counts:
            best = max(counts.items(), key=lambda kc: (kc[1], -kc[0]))
            kept = {best[0]: best[1]}
        for other in list(self._w.get(kf_id, {})):
            self._w.get(other, {}).pop(kf_id, None)
        self._w[kf_id] = dict(kept)
        for other, c in kept.items():
            self._w.setdefault(other, {})[kf_id] = c

    def set_edge(self, a: int, b: int, weight: int) -> None:
        """The edge a-b with ``weight`` shared points, as it was saved (a store restoring a map, MapStore.restore)."""
        self._w.setdefault(a, {})[b] = int(weight)
        self._w.setdefault(b, {})[a] = int(weight)

    def remove(self, kf_id: int) -> None:
        for other in self._w.pop(kf_id, {}):
            self._w.get(other, {}).pop(kf_id, None)

    def weight(self, a: int, b: int) -> int:
        return self._w.get(a, {}).get(b, 0)

    def neighbors(self, kf_id: int, min_weight: int = 0) -> list[int]:
        """Neighbours with weight >= min_weight, best first (ties: lower id first)."""
        edges = self._w.get(kf_id, {})
        return [k for k, c in sorted(edges.items(), key=lambda kc: (-kc[1], kc[0])) if c >= min_weight]

    def best_neighbors(self, kf_id: int, n: int) -> list[int]:
        return self.neighbors(kf_id)[:n]

    def edges(self) -> list[tuple[int, int, int]]:
        """Every edge once, as (a, b, weight) with a < b, sorted."""
        return sorted((a, b, c) for a, nb in self._w.items() for b, c in nb.items() if a < b)


class SpanningTree:
    """The spanning tree of keyframes (III-D): each new keyframe's parent is the keyframe it shares most
    points with. Keeps children sets so culling can re-parent them (ORB-SLAM KeyFrame::SetBadFlag)."""

    def __init__(self) -> None:
        self.parent: dict[int, int | None] = {}
        self.children: dict[int, set[int]] = {}

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self.parent

    def add(self, kf_id: int, parent: int | None) -> None:
        self.parent[kf_id] = parent
        self.children.setdefault(kf_id, set())
        if parent is not None:
            self.children.setdefault(parent, set()).add(kf_id)

    def change_parent(self, kf_id: int, new_parent: int) -> None:
        old = self.parent.get(kf_id)
        if old is not None:
            self.children[old].discard(kf_id)
        self.parent[kf_id] = new_parent
        self.children.setdefault(new_parent, set()).add(kf_id)

    def remove(self, kf_id: int, covisibility: CovisibilityGraph) -> None:
        """Remove a keyframe, re-attaching its children to the best-connected remaining candidate.

        Candidates start as the removed keyframe's parent; each child is attached to the candidate it shares
        the most points with, then becomes a candidate itself (ORB-SLAM's greedy re-parenting). A child with
        no covisible candidate goes to the removed keyframe's parent.
        """
        parent = self.parent.get(kf_id)
        orphans = sorted(self.children.get(kf_id, set()))
        candidates = {parent} if parent is not None else set()
        while orphans:
            best: tuple[int, int, int] | None = None  # (weight, child, candidate)
            for child in orphans:
                for cand in sorted(candidates):
                    w = covisibility.weight(child, cand)
                    if w > 0 and (best is None or (w, -child, -cand) > (best[0], -best[1], -best[2])):
                        best = (w, child, cand)
            if best is None:
                for child in orphans:
                    if parent is not None:
                        self.change_parent(child, parent)
                    else:
                        self.parent[child] = None
                break
            _, child, cand = best
            self.change_parent(child, cand)
            candidates.add(child)
            orphans.remove(child)
        if parent is not None:
            self.children.get(parent, set()).discard(kf_id)
        self.parent.pop(kf_id, None)
        self.children.pop(kf_id, None)

    def edges(self) -> list[tuple[int, int]]:
        return sorted((p, c) for c, p in self.parent.items() if p is not None)


class CovisibilityView:
    """Read-only view of a CovisibilityGraph (what a MapStore hands out as ``covisibility``)."""

    __slots__ = ("_graph",)

    def __init__(self, graph: CovisibilityGraph) -> None:
        self._graph = graph

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._graph

    def weight(self, a: int, b: int) -> int:
        return self._graph.weight(a, b)

    def neighbors(self, kf_id: int, min_weight: int = 0) -> list[int]:
        return self._graph.neighbors(kf_id, min_weight)

    def best_neighbors(self, kf_id: int, n: int) -> list[int]:
        return self._graph.best_neighbors(kf_id, n)

    def edges(self) -> list[tuple[int, int, int]]:
        return self._graph.edges()


class SpanningTreeView:
    """Read-only view of a SpanningTree (what a MapStore hands out as ``spanning_tree``)."""

    __slots__ = ("_tree",)

    def __init__(self, tree: SpanningTree) -> None:
        self._tree = tree

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._tree

    def parent(self, kf_id: int) -> int | None:
        """The keyframe's parent (None for a root or a keyframe not in the tree)."""
        return self._tree.parent.get(kf_id)

    def children(self, kf_id: int) -> list[int]:
        """The keyframe's children, sorted."""
        return sorted(self._tree.children.get(kf_id, ()))

    def edges(self) -> list[tuple[int, int]]:
        return self._tree.edges()


def essential_graph_edges(
    covisibility: protocol.CovisibilityGraphView,
    spanning_tree: protocol.SpanningTreeView,
    loop_edges: Iterable[tuple[int, int]],
    theta_min: int,
) -> list[tuple[int, int]]:
    """Edges of the essential graph (ORB-SLAM III-D, Optimizer::OptimizeEssentialGraph): the spanning tree, the
    loop-closure edges, and the covisibility edges with weight >= theta_min shared points (ORB-SLAM: 100).

    The one builder of the essential graph: loop correction (slamkit.pipeline.loop_correction) adds the new loop
    connections of the loop being closed to these. Each edge once as (a, b), a < b, sorted (keyframe ids).
    """
    edges = {(min(a, b), max(a, b)) for a, b in spanning_tree.edges()}
    edges |= {(a, b) for a, b, w in covisibility.edges() if w >= theta_min}
    edges |= {(min(a, b), max(a, b)) for a, b in loop_edges if a != b}
    return sorted(edges)
