"""Essential-graph pose-graph optimization in Sim3 or SE3 (ORB-SLAM Optimizer::OptimizeEssentialGraph).

Vertices are S_i_w (world -> camera i with scale), updated by left perturbation S <- exp(d) S. Edge (i, j)
with measurement S_ij has error e = log(E), E = S_ij S_j_w S_i_w^-1 (g2o's EdgeSim3 with ORB-SLAM's vertex
order) and information weight * I. Perturbing both ends gives
    S_ij exp(d_j) S_jw S_iw^-1 exp(-d_i) = exp(Ad(S_ij) d_j) E exp(-d_i) = exp(Ad(S_ij) d_j - Ad(E) d_i) E,
so to first order e' = e + J_l^-1(e) (Ad(S_ij) d_j - Ad(E) d_i), J_l the left Jacobian of Sim3 at e
(ORB-SLAM's g2o differentiates numerically; this analytic form is exact).
The normal equations (7x7 blocks per vertex, sparse) are assembled with scipy.sparse and solved with SuperLU.
In the SE3 variant the scale column/row are dropped (6 dof, scales stay as given, 1 for SE3 poses).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.sparse.csgraph import reverse_cuthill_mckee

from slamkit.problems import EssentialGraphProblem, EssentialGraphResult
from slamkit_scipy.lie import sim3_ad_batch, sim3_adjoint_batch, sim3_exp_batch, sim3_inverse_batch, sim3_log_batch
from slamkit_scipy.lm import LMSettings, levenberg_marquardt

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

# Most terms of the left Jacobian's series (the remainder r^N / (N + 1)! < 1e-16 for r = |omega| + |lambda| < 3).
_JL_TERMS = 24


def edge_errors(S: F64, edge_i: I64, edge_j: I64, S_ij: F64) -> tuple[F64, F64]:
    """(E, 7) errors log(S_ij S_jw S_iw^-1) and (E, 4, 4) the error transforms E themselves."""
    Emat = S_ij @ S[edge_j] @ sim3_inverse_batch(S[edge_i])
    return sim3_log_batch(Emat), Emat


def edge_jacobians(e: F64, Emat: F64, S_ij: F64) -> tuple[F64, F64]:
    """(E, 7, 7) d e / d delta_i and d e / d delta_j (left perturbations of the two vertices)."""
    ad = sim3_ad_batch(e)
    # Left Jacobian J_l(e) = sum_n ad^n / (n + 1)! by Horner's rule (its convergence is set by |omega| and
    # |lambda|: the translation part of ad is nilpotent), then inverted in one batched call: exact even for the
    # large error of a fresh loop edge.
    # Terms: the spectral radius of ad is at most |omega| + |lambda| =: r; stop once r^N / (N + 1)! < 1e-17.
    r = float(np.max(np.linalg.norm(e[:, :3], axis=1) + np.abs(e[:, 6]), initial=0.0))
    n_terms, bound = 1, r
    while bound > 1e-17 and n_terms < _JL_TERMS:
        n_terms += 1
        bound *= r / (n_terms + 1)
    Jl = np.broadcast_to(np.eye(7), ad.shape).copy()
    for n in range(n_terms, 0, -1):
        Jl = np.eye(7) + (ad @ Jl) / (n + 1)
    Jl_inv = np.linalg.inv(Jl)
    return -Jl_inv @ sim3_adjoint_batch(Emat), Jl_inv @ sim3_adjoint_batch(S_ij)


class PoseGraphSolver:
    """LM callbacks over a validated EssentialGraphProblem."""

    def __init__(self, problem: EssentialGraphProblem) -> None:
        self.edge_i = np.asarray(problem.edge_i, dtype=np.int64)
        self.edge_j = np.asarray(problem.edge_j, dtype=np.int64)
        self.S_ij = np.asarray(problem.S_ij, dtype=np.float64)
        n_edges = self.edge_i.size
        self.w = np.ones(n_edges) if problem.weights is None else np.asarray(problem.weights, dtype=np.float64)
        self.d = 7 if problem.use_sim3 else 6
        K = problem.S_c_w.shape[0]
        self.free = np.flatnonzero(~np.asarray(problem.fixed, dtype=bool))
        vmap = np.full(K, -1, dtype=np.int64)
        vmap[self.free] = np.arange(self.free.size)
        self.fi = vmap[self.edge_i]
        self.fj = vmap[self.edge_j]
        self.n = self.d * self.free.size
        # COO pattern of the four d x d blocks (ii, ij, ji, jj) of every edge, keeping free-free blocks only.
        d = self.d
        rr = np.repeat(np.arange(d), d)
        cc = np.tile(np.arange(d), d)
        rows, cols, sel = [], [], []
        for k, (a, b) in enumerate(((self.fi, self.fi), (self.fi, self.fj), (self.fj, self.fi), (self.fj, self.fj))):
            ok = np.flatnonzero((a >= 0) & (b >= 0))
            rows.append((d * a[ok])[:, None] + rr[None, :])
            cols.append((d * b[ok])[:, None] + cc[None, :])
            sel.append(k * n_edges + ok)
        self.rows = np.concatenate(rows).ravel()
        self.cols = np.concatenate(cols).ravel()
        self.block_sel = np.concatenate(sel)
        self.on_diag = self.rows == self.cols
        # Fill-reducing order computed once from the pattern (reverse Cuthill-McKee; the essential graph is
        # a long chain with local and loop edges), then SuperLU factors the permuted matrix as it is.
        pattern = sp.csr_matrix((np.ones(self.rows.size), (self.rows, self.cols)), shape=(self.n, self.n))
        self.perm = reverse_cuthill_mckee(pattern, symmetric_mode=True).astype(np.int64)
        self.invperm = np.empty_like(self.perm)
        self.invperm[self.perm] = np.arange(self.n)
        diag = np.arange(self.n)
        rows_d = self.invperm[np.concatenate([self.rows, diag])]
        cols_d = self.invperm[np.concatenate([self.cols, diag])]
        # CSC pattern of the damped, permuted matrix built once; ``assemble`` (nnz x entries, 0/1) sums the
        # per-edge block entries (and the damping) into its data array with one sparse product per solve.
        n_entries = rows_d.size
        key = cols_d * self.n + rows_d  # CSC order: by column, then row
        uniq, slot = np.unique(key, return_inverse=True)
        self.template = sp.csc_matrix((np.zeros(uniq.size), (uniq % self.n, uniq // self.n)), shape=(self.n, self.n))
        self.template.sort_indices()
        if self.template.nnz != uniq.size or not np.array_equal(self.template.indices, uniq % self.n):
            raise AssertionError("pose graph: CSC template out of order")  # scipy keeps explicit zeros sorted
        self.assemble = sp.csr_matrix((np.ones(n_entries), (slot, np.arange(n_entries))), shape=(uniq.size, n_entries))

    def cost(self, S: F64) -> float:
        e, _ = edge_errors(S, self.edge_i, self.edge_j, self.S_ij)
        e = e[:, : self.d]
        return float(np.sum(self.w * np.einsum("ij,ij->i", e, e)))

    def linearize(self, S: F64) -> tuple[tuple[F64, F64], F64, float, float]:
        e, Emat = edge_errors(S, self.edge_i, self.edge_j, self.S_ij)
        Ji, Jj = edge_jacobians(e, Emat, self.S_ij)
        d = self.d
        e, Ji, Jj = e[:, :d], Ji[:, :d, :d], Jj[:, :d, :d]
        wJi = Ji * self.w[:, None, None]
        wJj = Jj * self.w[:, None, None]
        JiT, JjT = wJi.transpose(0, 2, 1), wJj.transpose(0, 2, 1)
        blocks = np.concatenate([JiT @ Ji, JiT @ Jj, JjT @ Ji, JjT @ Jj])  # (4E, d, d)
        data = blocks[self.block_sel].ravel()
        gi = np.einsum("eij,ej->ei", JiT, e)
        gj = np.einsum("eij,ej->ei", JjT, e)
        g = np.zeros((self.free.size, d))
        oki, okj = self.fi >= 0, self.fj >= 0
        np.add.at(g, self.fi[oki], gi[oki])
        np.add.at(g, self.fj[okj], gj[okj])
        hdiag = np.zeros(self.n)
        np.add.at(hdiag, self.rows[self.on_diag], data[self.on_diag])
        f = float(np.sum(self.w * np.einsum("ij,ij->i", e, e)))
        return (data, -g.ravel()), g.ravel(), f, float(np.max(hdiag, initial=0.0))

    def solve(self, system: tuple[F64, F64], lam: float) -> F64:
        data, neg_g = system
        A = self.template.copy()
        A.data = self.assemble @ np.concatenate([data, np.full(self.n, lam)])
        try:
            y = spla.splu(A, permc_spec="NATURAL", options={"SymmetricMode": True}).solve(neg_g[self.perm])
        except RuntimeError:  # singular factor
            return np.full(self.n, np.nan)
        out: F64 = y[self.invperm]
        return out

    def retract(self, S: F64, h: F64) -> F64:
        out = S.copy()
        xi = np.zeros((self.free.size, 7))
        xi[:, : self.d] = h.reshape(-1, self.d)
        out[self.free] = sim3_exp_batch(xi) @ S[self.free]
        return out


def optimize_essential_graph(problem: EssentialGraphProblem, settings: LMSettings) -> EssentialGraphResult:
    """Solve a validated EssentialGraphProblem (module docstring)."""
    solver = PoseGraphSolver(problem)
    S0 = np.array(problem.S_c_w, dtype=np.float64)
    out = levenberg_marquardt(
        S0, solver.linearize, solver.solve, solver.retract, solver.cost, problem.iterations, settings
    )
    return EssentialGraphResult(
        S_c_w=out.x, cost_initial=out.cost_initial, cost_final=out.cost_final, iterations=out.iterations
    )
