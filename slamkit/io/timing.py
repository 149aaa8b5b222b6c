"""Time association shared by readers: pairing two timestamp lists, slicing IMU samples between frames."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slamkit.sensors import ImuSamples

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def associate_stamps(t_a: F64, t_b: F64, max_dt_s: float) -> tuple[I64, I64]:
    """Pair entries of two sorted timestamp lists, as TUM's associate.py does.

    Every candidate pair with |t_a - t_b| < max_dt_s is ranked by that difference and accepted greedily,
    each entry used at most once. Returns (ia, ib): (M,) indices into t_a and t_b, sorted by t_a.
    """
    cand_d: list[float] = []
    cand_a: list[int] = []
    cand_b: list[int] = []
    lo = np.searchsorted(t_b, t_a - max_dt_s, side="left")
    hi = np.searchsorted(t_b, t_a + max_dt_s, side="right")
    for i in range(t_a.shape[0]):
        for j in range(int(lo[i]), int(hi[i])):
            d = abs(float(t_a[i]) - float(t_b[j]))
            if d < max_dt_s:
                cand_d.append(d)
                cand_a.append(i)
                cand_b.append(j)
    order = np.argsort(np.asarray(cand_d), kind="stable")
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for k in order:
        a, b = cand_a[int(k)], cand_b[int(k)]
        if a in used_a or b in used_b:
            continue
        used_a.add(a)
        used_b.add(b)
        pairs.append((a, b))
    pairs.sort()
    ia = np.array([p[0] for p in pairs], dtype=np.int64)
    ib = np.array([p[1] for p in pairs], dtype=np.int64)
    return ia, ib


def imu_between(imu: ImuSamples, t_prev_s: float, t_s: float) -> ImuSamples:
    """The samples with t in (t_prev_s, t_s] (ORB-SLAM3 preintegrates these between two frames)."""
    lo = int(np.searchsorted(imu.t_s, t_prev_s, side="right"))
    hi = int(np.searchsorted(imu.t_s, t_s, side="right"))
    return ImuSamples(imu.t_s[lo:hi].copy(), imu.acc_mps2[lo:hi].copy(), imu.gyro_radps[lo:hi].copy())
