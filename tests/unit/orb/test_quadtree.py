"""ORB-SLAM's quadtree distribution (numba) against a plain-Python transcription of DistributeOctTree."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_orb.quadtree import distribute_quadtree

_created = itertools.count()


@dataclass
class _Node:
    x0: int
    y0: int
    x1: int
    y1: int
    keys: list[int] = field(default_factory=list)
    serial: int = field(default_factory=lambda: next(_created))

    def split(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> list[_Node]:
        hx, hy = math.ceil((self.x1 - self.x0) / 2), math.ceil((self.y1 - self.y0) / 2)
        mx, my = self.x0 + hx, self.y0 + hy
        quads = [
            _Node(self.x0, self.y0, mx, my),
            _Node(mx, self.y0, self.x1, my),
            _Node(self.x0, my, mx, self.y1),
            _Node(mx, my, self.x1, self.y1),
        ]
        for k in self.keys:
            quads[(2 if y[k] >= my else 0) + (1 if x[k] >= mx else 0)].keys.append(k)
        return [q for q in quads if q.keys]


def _splittable(nd: _Node) -> bool:
    return len(nd.keys) > 1 and (nd.x1 - nd.x0 > 1 or nd.y1 - nd.y0 > 1)


def _reference(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    r: NDArray[np.float32],
    width: int,
    height: int,
    n: int,
    orbslam_stop: bool = False,
) -> list[int]:
    """ORB-SLAM's DistributeOctTree, node list and all; ties between equally full nodes go by creation order.

    orbslam_stop: stop when a round leaves the node count unchanged (ORB-SLAM) instead of when no node can be
    split (slamkit). Surplus leaves beyond n are dropped, as slamkit does: the weakest of the latest split.
    """
    last_children: list[_Node] = []
    n_ini = max(1, math.floor(width / height + 0.5))
    hx = width / n_ini
    roots = [_Node(math.ceil(hx * i), 0, min(math.ceil(hx * (i + 1)), width), height) for i in range(n_ini)]
    for k in range(len(x)):
        roots[min(int(x[k] / hx), n_ini - 1)].keys.append(k)
    nodes = [nd for nd in roots if nd.keys]

    def done(prev: int, grown: list[_Node]) -> bool:
        return len(nodes) >= n or (len(nodes) == prev if orbslam_stop else not grown)

    while True:
        prev = len(nodes)
        kept, grown = [], []
        for nd in nodes:
            if not _splittable(nd):
                kept.append(nd)
                continue
            children = last_children = nd.split(x, y)
            kept += children
            grown += [c for c in children if _splittable(c)]
        nodes = kept
        if done(prev, grown):
            break
        if len(nodes) + 3 * len(grown) > n:
            while True:
                prev = len(nodes)
                queue = sorted(grown, key=lambda c: len(c.keys))  # stable
                grown = []
                for nd in reversed(queue):
                    children = last_children = nd.split(x, y)
                    nodes.remove(nd)
                    nodes += children
                    grown += [c for c in children if _splittable(c)]
                    if len(nodes) >= n:
                        break
                if done(prev, grown):
                    break
            break
    nodes.sort(key=lambda nd: nd.serial)
    best = [max(nd.keys, key=lambda k: (r[k], -k)) for nd in nodes]
    surplus = len(nodes) - n
    if surplus > 0:
        recent = [i for i, nd in enumerate(nodes) if any(nd is c for c in last_children)]
        pool = recent if len(recent) > surplus else list(range(len(nodes)))
        drop = sorted(pool, key=lambda i: r[best[i]])[:surplus]  # stable: earlier leaf first among equals
        best = [b for i, b in enumerate(best) if i not in drop]
    return sorted(best)


def _random_corners(
    seed: int, n: int, width: int, height: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float32]]:
    rng = np.random.default_rng(seed)
    flat = rng.choice(width * height, size=n, replace=False)  # unique integer positions, like FAST's
    x, y = (flat % width).astype(np.float64), (flat // width).astype(np.float64)
    return x, y, rng.integers(7, 80, size=n).astype(np.float32)


@pytest.mark.parametrize(
    ("seed", "n_points", "width", "height", "budget"),
    [
        (0, 2000, 608, 448, 217),
        (1, 3000, 1209, 344, 434),
        (2, 500, 608, 448, 60),
        (3, 80, 200, 150, 73),
        (4, 5, 50, 50, 1),
    ],
)
def test_matches_the_reference_transcription(seed: int, n_points: int, width: int, height: int, budget: int) -> None:
    x, y, r = _random_corners(seed, n_points, width, height)
    got = distribute_quadtree(x, y, r, width, height, budget)
    assert got.tolist() == _reference(x, y, r, width, height, budget)
    # On corners spread over the image the two stopping rules agree: this is ORB-SLAM's selection.
    assert got.tolist() == _reference(x, y, r, width, height, budget, orbslam_stop=True)
    assert len(got) == min(budget, n_points)


def test_clustered_corners_do_not_crowd_out_isolated_ones() -> None:
    rng = np.random.default_rng(7)
    cluster = rng.choice(60 * 60, size=1500, replace=False)
    x = np.concatenate([(cluster % 60).astype(np.float64), [300.0, 500.0, 100.0, 550.0, 320.0]])
    y = np.concatenate([(cluster // 60).astype(np.float64), [400.0, 60.0, 300.0, 420.0, 200.0]])
    r = np.concatenate([rng.uniform(50, 100, 1500), np.full(5, 8.0)]).astype(np.float32)  # isolated: weak
    got = distribute_quadtree(x, y, r, 600, 450, 50)
    assert len(got) == 50
    assert set(range(1500, 1505)) <= set(got.tolist())


def test_corners_in_one_quadrant_are_not_collapsed_to_one() -> None:
    """All corners in the top-left quarter: ORB-SLAM's stopping rule ends after the first split (one child,
    node count unchanged) with a single keypoint; slamkit keeps splitting and fills the budget."""
    x, y, r = _random_corners(10, 150, 190, 140)  # the area is 608 x 448
    assert len(_reference(x, y, r, 608, 448, 100, orbslam_stop=True)) == 1
    got = distribute_quadtree(x, y, r, 608, 448, 100)
    assert len(got) == 100
    assert got.tolist() == _reference(x, y, r, 608, 448, 100)


def test_fewer_corners_than_budget_are_all_kept() -> None:
    x, y, r = _random_corners(8, 40, 300, 200)
    assert distribute_quadtree(x, y, r, 300, 200, 100).tolist() == list(range(40))


def test_empty_input_and_zero_budget() -> None:
    empty = np.zeros(0)
    assert distribute_quadtree(empty, empty, np.zeros(0, np.float32), 100, 100, 10).shape == (0,)
    x, y, r = _random_corners(9, 10, 100, 100)
    assert distribute_quadtree(x, y, r, 100, 100, 0).shape == (0,)


def test_duplicate_positions_terminate() -> None:
    x = np.full(20, 10.0)
    y = np.full(20, 12.0)
    r = np.arange(20, dtype=np.float32)
    assert distribute_quadtree(x, y, r, 100, 100, 5).tolist() == [19]
