"""ORB-SLAM's quadtree distribution of one level's corners (``DistributeOctTree``), in numba.

The level's distribution area starts as round(width / height) side-by-side nodes. Every node holding more
than one corner is split into four quadrants (empty quadrants dropped) until there are at least as many
nodes as the level's feature budget, or every node holds a single corner. When one more full round of
splits could overshoot the budget, only the most populated nodes are split, largest first, until the budget
is reached. Each final node then keeps its strongest corner, so corners are spread over the whole image
instead of piling up where texture is strongest.

Differences from ORB-SLAM, all deliberate:
- ORB-SLAM stops splitting when a round leaves the number of nodes unchanged, which is meant to detect that
  every node holds a single corner but also fires when each split of a round puts all of a node's corners
  in one quadrant; when all of a level's corners lie in one quarter of the image that leaves a single
  keypoint for the whole level. Here splitting stops when no node holds more than one corner
  (tests/unit/orb/test_quadtree.py shows the case).
- Equally populated nodes are split in creation order (latest first); ORB-SLAM orders them by memory
  address, which varies from run to run.
- The last split can leave up to three nodes beyond the budget, which ORB-SLAM keeps; here the weakest of
  them are dropped, so a level never exceeds its share.
- The initial nodes' integer bounds are rounded up instead of truncated, so that they contain exactly the
  corners assigned to them.

The node boxes live in one preallocated table and each node's corners are a slice of one permutation array
that a split partitions in place (stably, so ties resolve to the earlier corner): no allocation per node.
Nodes of one depth are disjoint and non-empty, and boxes halve at each depth, so the table needs at most
(number of corners) x (log2(longest side) + 2) rows besides the initial nodes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

# Columns of the node table.
_X0, _Y0, _X1, _Y1, _START, _END = range(6)


@njit(cache=True, nogil=True)
def _splittable(nodes: NDArray[np.int64], node: int) -> bool:
    """More than one corner in a box larger than one pixel (only duplicate positions share a pixel)."""
    if nodes[node, _END] - nodes[node, _START] < 2:
        return False
    return nodes[node, _X1] - nodes[node, _X0] > 1 or nodes[node, _Y1] - nodes[node, _Y0] > 1


@njit(cache=True, nogil=True)
def _split(
    nodes: NDArray[np.int64],
    n_nodes: int,
    node: int,
    perm: NDArray[np.int64],
    scratch: NDArray[np.int64],
    x: NDArray[np.float64],
    y: NDArray[np.float64],
) -> int:
    """Split ``node`` into its non-empty quadrants (ORB-SLAM's DivideNode), appended to the table at row
    ``n_nodes`` on. Returns the new row count. Quadrant order: top-left, top-right, bottom-left,
    bottom-right; a corner on a mid line goes right/down."""
    x0, y0, x1, y1 = nodes[node, _X0], nodes[node, _Y0], nodes[node, _X1], nodes[node, _Y1]
    start, end = nodes[node, _START], nodes[node, _END]
    mx = x0 + (x1 - x0 + 1) // 2  # ceil of the half, as ORB-SLAM
    my = y0 + (y1 - y0 + 1) // 2
    counts = np.zeros(4, dtype=np.int64)
    for k in range(start, end):
        i = perm[k]
        counts[(2 if y[i] >= my else 0) + (1 if x[i] >= mx else 0)] += 1
    fill = np.zeros(4, dtype=np.int64)
    for q in range(1, 4):
        fill[q] = fill[q - 1] + counts[q - 1]
    first = fill.copy()
    for k in range(start, end):
        i = perm[k]
        q = (2 if y[i] >= my else 0) + (1 if x[i] >= mx else 0)
        scratch[fill[q]] = i
        fill[q] += 1
    for k in range(end - start):
        perm[start + k] = scratch[k]
    for q in range(4):
        if counts[q] == 0:
            continue
        nodes[n_nodes, _X0] = mx if q & 1 else x0
        nodes[n_nodes, _X1] = x1 if q & 1 else mx
        nodes[n_nodes, _Y0] = my if q & 2 else y0
        nodes[n_nodes, _Y1] = y1 if q & 2 else my
        nodes[n_nodes, _START] = start + first[q]
        nodes[n_nodes, _END] = start + first[q] + counts[q]
        n_nodes += 1
    return n_nodes


@njit(cache=True, nogil=True)
def _by_size_desc(nodes: NDArray[np.int64], ids: NDArray[np.int64], n_points: int) -> NDArray[np.int64]:
    """``ids`` ordered by decreasing node size; among equal sizes the later-created node first (ORB-SLAM
    sorts ascending and walks the list from its end). A counting sort: sizes are at most n_points."""
    counts = np.zeros(n_points + 2, dtype=np.int64)
    for node in ids:
        counts[nodes[node, _END] - nodes[node, _START]] += 1
    for size in range(1, n_points + 2):
        counts[size] += counts[size - 1]
    ascending = np.empty(ids.shape[0], dtype=np.int64)
    for j in range(ids.shape[0] - 1, -1, -1):
        size = nodes[ids[j], _END] - nodes[ids[j], _START]
        counts[size] -= 1
        ascending[counts[size]] = ids[j]
    return ascending[::-1].copy()


@njit(cache=True, nogil=True)
def distribute_quadtree(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    response: NDArray[np.float32],
    width: int,
    height: int,
    n_target: int,
) -> NDArray[np.int64]:
    """Indices of the corners ORB-SLAM's quadtree keeps, at most ``n_target`` of them, ascending.

    x, y: (N,) integer corner coordinates relative to the distribution area's top-left corner, px, in
    [0, width) x [0, height). response: (N,) corner score. ORB-SLAM can end with a few leaves more than
    the budget (the last split makes up to four); those surplus corners are dropped so a level never
    exceeds its share.
    """
    n = x.shape[0]
    if n == 0 or n_target <= 0 or width <= 0 or height <= 0:
        return np.zeros(0, dtype=np.int64)

    n_ini = max(1, math.floor(width / height + 0.5))
    h_x = width / n_ini
    depth = math.ceil(math.log2(max(width, height, 2))) + 2
    nodes = np.empty((n_ini + n * depth, 6), dtype=np.int64)
    alive = np.zeros(nodes.shape[0], dtype=np.bool_)
    perm = np.empty(n, dtype=np.int64)
    scratch = np.empty(n, dtype=np.int64)

    # Initial nodes: corners go to column floor(x / h_x) as in ORB-SLAM; the boxes are rounded up (ORB-SLAM
    # truncates) so that they hold exactly the integer positions assigned to them.
    counts = np.zeros(n_ini, dtype=np.int64)
    column = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = min(max(int(x[i] / h_x), 0), n_ini - 1)
        column[i] = c
        counts[c] += 1
    fill = np.zeros(n_ini, dtype=np.int64)
    n_nodes = 0
    start = 0
    for c in range(n_ini):
        fill[c] = start
        if counts[c] > 0:
            nodes[n_nodes, _X0] = math.ceil(h_x * c)
            nodes[n_nodes, _Y0] = 0
            nodes[n_nodes, _X1] = width if c == n_ini - 1 else math.ceil(h_x * (c + 1))
            nodes[n_nodes, _Y1] = height
            nodes[n_nodes, _START] = start
            nodes[n_nodes, _END] = start + counts[c]
            alive[n_nodes] = True
            n_nodes += 1
        start += counts[c]
    for i in range(n):
        perm[fill[column[i]]] = i
        fill[column[i]] += 1

    n_alive = n_nodes
    grown = np.empty(nodes.shape[0], dtype=np.int64)  # splittable nodes made by the latest round
    n_grown = 0
    for node in range(n_nodes):
        if _splittable(nodes, node):
            grown[n_grown] = node
            n_grown += 1
    last_split = 0  # row of the first child of the latest split

    # Full rounds: split every splittable node, until the budget is met or nothing is left to split. As in
    # ORB-SLAM the first round always runs.
    fine_tune = False
    first_round = True
    while n_grown > 0 and n_alive < n_target:
        if not first_round and n_alive + 3 * n_grown > n_target:
            fine_tune = True  # the next full round could overshoot the budget
            break
        first_round = False
        expandable = grown[:n_grown].copy()
        n_grown = 0
        for node in expandable:
            last_split = n_nodes
            n_nodes = _split(nodes, n_nodes, node, perm, scratch, x, y)
            alive[node] = False
            n_alive += n_nodes - last_split - 1
            for child in range(last_split, n_nodes):
                alive[child] = True
                if _splittable(nodes, child):
                    grown[n_grown] = child
                    n_grown += 1

    # Fine rounds: split the most populated nodes one by one until the budget is met.
    while fine_tune and n_grown > 0 and n_alive < n_target:
        expandable = _by_size_desc(nodes, grown[:n_grown], n)
        n_grown = 0
        for node in expandable:
            last_split = n_nodes
            n_nodes = _split(nodes, n_nodes, node, perm, scratch, x, y)
            alive[node] = False
            n_alive += n_nodes - last_split - 1
            for child in range(last_split, n_nodes):
                alive[child] = True
                if _splittable(nodes, child):
                    grown[n_grown] = child
                    n_grown += 1
            if n_alive >= n_target:
                break

    # Each leaf keeps its strongest corner (the first of equals, in the leaf's stable order).
    best = np.empty(n_alive, dtype=np.int64)
    recent = np.empty(n_alive, dtype=np.bool_)
    m = 0
    for node in range(n_nodes):
        if not alive[node]:
            continue
        pick = perm[nodes[node, _START]]
        for k in range(nodes[node, _START] + 1, nodes[node, _END]):
            if response[perm[k]] > response[pick]:
                pick = perm[k]
        best[m] = pick
        recent[m] = node >= last_split
        m += 1

    # ORB-SLAM keeps the (at most three) surplus leaves; we drop the weakest corners of the latest split,
    # which lie in the densest area, so the spread is untouched (any leaves if that split made too few).
    extra = m - n_target
    if extra > 0:
        n_recent = 0
        for j in range(m):
            n_recent += recent[j]
        keep = np.ones(m, dtype=np.bool_)
        for _ in range(extra):
            weakest = -1
            for j in range(m):
                candidate = keep[j] and (recent[j] or n_recent <= extra)
                if candidate and (weakest < 0 or response[best[j]] < response[best[weakest]]):
                    weakest = j
            keep[weakest] = False
        best = best[keep]
    return np.sort(best)
