"""The essential graph's one builder (slamkit.map.graphs.essential_graph_edges, ORB-SLAM III-D and
Optimizer::OptimizeEssentialGraph) on a hand-made keyframe graph: the spanning tree, the loop edges and the
covisibility edges of weight >= theta_min, each once."""

from __future__ import annotations

from slamkit.map.graphs import (
    CovisibilityGraph,
    CovisibilityView,
    SpanningTree,
    SpanningTreeView,
    essential_graph_edges,
)


def hand_made_graph() -> tuple[CovisibilityView, SpanningTreeView]:
    """Keyframes 0..6. Covisibility weights (min_shared 15): 0-1 300, 1-2 100, 2-3 99, 3-4 150, 0-2 120, 4-5 20,
    5-6 16, 1-6 101. Spanning tree: 0 <- 1 <- 2 <- 3 <- 4 <- 5 <- 6 (each child's parent first)."""
    cov = CovisibilityGraph()
    weights = {(0, 1): 300, (1, 2): 100, (2, 3): 99, (3, 4): 150, (0, 2): 120, (4, 5): 20, (5, 6): 16, (1, 6): 101}
    for k in range(7):
        shared = {b if a == k else a: w for (a, b), w in weights.items() if k in (a, b)}
        cov.update_connections(k, shared, min_shared=15)
    tree = SpanningTree()
    tree.add(0, None)
    for k in range(1, 7):
        tree.add(k, k - 1)
    return CovisibilityView(cov), SpanningTreeView(tree)


def test_spanning_tree_loop_edges_and_strong_covisibility_each_once() -> None:
    cov, tree = hand_made_graph()
    loops = [(6, 0), (3, 3), (0, 6)]  # either orientation, a self-edge is no edge
    edges = essential_graph_edges(cov, tree, loops, theta_min=100)
    tree_edges = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 6)]
    # covisibility >= 100: 0-1 (tree), 1-2 (tree, weight exactly theta_min), 3-4 (tree), 0-2 and 1-6 (new);
    # 2-3 (99) is in only as a tree edge, 4-5 and 5-6 only as tree edges
    assert edges == sorted({*tree_edges, (0, 6), (0, 2), (1, 6)})
    assert len(edges) == len(set(edges))


def test_theta_min_selects_the_covisibility_edges() -> None:
    cov, tree = hand_made_graph()
    no_loops: list[tuple[int, int]] = []
    tree_edges = {(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 6)}
    assert essential_graph_edges(cov, tree, no_loops, theta_min=1000) == sorted(tree_edges)
    assert essential_graph_edges(cov, tree, no_loops, theta_min=102) == sorted(tree_edges | {(0, 2)})
    assert essential_graph_edges(cov, tree, no_loops, theta_min=101) == sorted(tree_edges | {(0, 2), (1, 6)})
    # theta_min at the covisibility threshold: every covisibility edge
    assert essential_graph_edges(cov, tree, no_loops, theta_min=15) == sorted(tree_edges | {(0, 2), (1, 6)})


def test_a_forest_without_covisibility_is_the_tree_plus_the_loops() -> None:
    tree = SpanningTree()
    tree.add(10, None)
    tree.add(11, 10)
    tree.add(12, 10)
    edges = essential_graph_edges(CovisibilityView(CovisibilityGraph()), SpanningTreeView(tree), [(12, 11)], 100)
    assert edges == [(10, 11), (10, 12), (11, 12)]
