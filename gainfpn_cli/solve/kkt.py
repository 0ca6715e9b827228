"""The gain least-squares system of Lim & El Gamal and its solvers.

For a block ``B`` of reference pixels and frames ``t = 1..F`` (paper eq. 5)::

    E_B = sum_t || ([I(0) 0] - I(t) T(t)) k ||^2  +  lam * ||k - 1||^2,
    subject to 1^T k = n_R                                          (eq. 6)

``k`` holds the corrections on ``R`` (``B`` first, then every pixel the
block's trajectories touch); ``I(t)`` is diagonal with the frame-t values
along the trajectories and row ``m`` of ``T(t)`` the bilinear weights of the
four pixels around where pixel ``m`` lands.

The constrained quadratic is solved in the null space of the constraint:
``k = 1 + P z`` with ``P`` an orthonormal basis of ``{v : 1^T v = 0}`` (a
Householder reflection), so ``(P^T Q P + lam I) z = -P^T Q 1`` is symmetric
positive definite, factored by Cholesky, and its condition number is
estimated from the factor (LAPACK ``dpocon``). Pure numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp
from scipy.linalg import lapack

from ..errors import EstimationError

#: Systems with more unknowns than this use the sparse KKT path.
DENSE_MAX = 3000

OK, REGULARISED, UNESTIMATED = 0, 1, 2


@dataclass(frozen=True)
class SolveOptions:
    """Numerical safety limits of the block solves.

    Attributes
    ----------
    lam : float
        Ridge weight of ``lam * ||k - 1||^2`` (DN^2: it adds to ``Q``).
    max_condition : float
        A block whose reduced system has a larger 1-norm condition estimate
        gets an extra ridge that brings it down to this value ("regularised").
    k_range : (float, float)
        Gains outside this range are not physical; a block that produces one
        even after regularisation is marked unestimated (k = 1, confidence 0).
    """

    lam: float = 0.0
    max_condition: float = 1e4
    k_range: tuple[float, float] = (0.5, 2.0)


# ---------------------------------------------------------------------------
# one block


def solve_block(i0, it, T: Sequence, *, lam: float = 0.0) -> np.ndarray:
    """Solve paper eq. 6 for one block.

    Parameters
    ----------
    i0 : array_like, shape (n_B,)
        Frame-0 values of the block's pixels, DN.
    it : array_like, shape (F, n_B)
        Values along the trajectories in frames 1..F (interpolated where the
        displacement is not an integer), DN.
    T : sequence of F arrays or sparse matrices, shape (n_B, n_R)
        Row ``m`` of ``T[t]`` holds the (bilinear) weights of the unknowns
        that pixel ``m`` lands on in frame ``t+1``. Unknowns are ordered
        with the block first.
    lam : float, optional
        Ridge weight of ``lam * ||k - 1||^2``.

    Returns
    -------
    k : ndarray of float64, shape (n_R,)
        Corrections with ``sum(k) == n_R`` (to rounding).

    Raises
    ------
    EstimationError
        If the system is singular (the data do not determine ``k``).
    """
    i0 = np.asarray(i0, dtype=np.float64)
    it = np.asarray(it, dtype=np.float64)
    if i0.ndim != 1:
        raise ValueError(f"i0 must have shape (n_B,), got {i0.shape}")
    n_b = i0.shape[0]
    if it.ndim != 2 or it.shape[1] != n_b:
        raise ValueError(f"it must have shape (F, {n_b}), got {it.shape}")
    if len(T) != it.shape[0]:
        raise ValueError(f"T must hold one matrix per frame ({it.shape[0]}), got {len(T)}")
    n_r = T[0].shape[1] if len(T) else n_b
    if n_r < n_b or any(t.shape != (n_b, n_r) for t in T):
        raise ValueError(f"every T[t] must have shape ({n_b}, n_R) with n_R >= {n_b}")
    if lam < 0 or not np.isfinite(lam):
        raise ValueError(f"lam must be finite and non-negative, got {lam}")
    frame0 = sp.hstack([sp.diags(i0), sp.csr_matrix((n_b, n_r - n_b))]).tocsr()
    A = sp.vstack([frame0 - sp.diags(it[t]) @ sp.csr_matrix(T[t]) for t in range(len(T))]).tocsr()
    Q = (A.T @ A).toarray() if n_r <= DENSE_MAX else (A.T @ A).tocsc()
    k, status, cond = _solve_gauged(Q, lam=lam, max_condition=np.inf)
    if status == UNESTIMATED:
        raise EstimationError(f"block system is singular (condition estimate {cond:.3g}): the data do not determine k")
    return k


def _solve_gauged(Q, *, lam: float, max_condition: float, check: slice = slice(None),
                  k_range: tuple[float, float] = (-np.inf, np.inf)) -> tuple[np.ndarray, int, float]:
    """Minimise ``k^T Q k + lam ||k - 1||^2`` subject to ``sum(k) = n``.

    Returns ``(k, status, condition)``. ``status`` is OK; REGULARISED when an
    extra ridge was needed to bring the condition estimate below
    ``max_condition`` or ``k[check]`` into ``k_range``; or UNESTIMATED (then
    ``k`` is all ones). With ``max_condition = inf`` nothing is rescued: the
    system is solved as it is, or found singular.
    """
    n = Q.shape[0]
    if n < 2:
        return np.ones(n), UNESTIMATED, np.inf
    system = _SparseKKT(Q) if sp.issparse(Q) else _NullSpace(Q)
    ridge, status, cond = lam, OK, np.inf
    for attempt in range(4):
        k, cond = system.solve(ridge)
        if k is not None and cond <= max_condition and np.all(np.isfinite(k)):
            inside = (k[check] >= k_range[0]) & (k[check] <= k_range[1])
            if np.all(inside):
                return k * (n / k.sum()), status, cond
        if not np.isfinite(max_condition):
            break
        ridge += system.norm / max_condition * 100.0**attempt
        status = REGULARISED
    return np.ones(n), UNESTIMATED, cond


class _NullSpace:
    """Dense path: ``k = 1 + P z``, ``(P^T Q P + ridge I) z = -P^T Q 1`` by Cholesky."""

    def __init__(self, Q: np.ndarray):
        n = Q.shape[0]
        u = np.full(n, 1.0 / np.sqrt(n))
        u[0] += 1.0  # H = I - beta u u^T sends e_1 to -1/sqrt(n); its columns 2..n span 1-perp
        beta = 2.0 / (u @ u)
        Qu = Q @ u
        HQH = Q - beta * np.outer(u, Qu) - beta * np.outer(Qu, u) + beta * beta * (u @ Qu) * np.outer(u, u)
        self.G = HQH[1:, 1:]
        self.rhs = np.sqrt(n) * HQH[1:, 0]  # -P^T Q 1, since H 1 = -sqrt(n) e_1
        self.u, self.beta = u, beta
        self.norm = float(np.abs(self.G).sum(axis=0).max())

    def solve(self, ridge: float) -> tuple[np.ndarray | None, float]:
        G = self.G + ridge * np.eye(self.G.shape[0])
        chol, info = lapack.dpotrf(G, lower=1)
        if info != 0:
            return None, np.inf
        rcond, _ = lapack.dpocon(chol, float(np.abs(G).sum(axis=0).max()), uplo="L")
        z, _ = lapack.dpotrs(chol, self.rhs, lower=1)
        v = np.concatenate([[0.0], z])
        return 1.0 + v - self.beta * self.u * (self.u @ v), (1.0 / rcond if rcond > 0 else np.inf)


class _SparseKKT:
    """Sparse path for large blocks, by LU of the KKT system

        [[Q + ridge I, s 1], [s 1^T, 0]] [k; nu] = [ridge 1; s n]

    The constraint row is scaled by ``s = ||Q||_1 / sqrt(n)`` so that the KKT
    condition number tracks that of the reduced system (for ``Q = q I`` it is
    ``(1 + sqrt 5) / 2`` times it) instead of the ratio of ``Q``'s scale to 1.
    """

    def __init__(self, Q):
        self.Q = sp.csc_matrix(Q)
        self.norm = float(abs(self.Q).sum(axis=0).max())

    def solve(self, ridge: float) -> tuple[np.ndarray | None, float]:
        from scipy.sparse.linalg import LinearOperator, onenormest, splu

        n = self.Q.shape[0]
        s = max(self.norm, np.finfo(float).tiny) / np.sqrt(n)
        edge = sp.csc_matrix(np.full((n, 1), s))
        K = sp.bmat([[self.Q + ridge * sp.eye(n), edge], [edge.T, None]], format="csc")
        rhs = np.concatenate([np.full(n, ridge), [s * n]])
        try:
            # K's pattern is symmetric: ordered on K + K^T, with the diagonal pivot kept unless below
            # 1 % of its column's largest (threshold pivoting). The default column ordering filled a
            # 5121-row KKT of a 64x80 block 5x more (10.0 M entries of L + U against 2.0 M) and took
            # 20x the time; the solutions agree to 1e-10. Multipliers up to 100 are allowed: one
            # step of refinement, and the default (partial pivoting) if the residual stays large.
            lu = splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.01, options={"SymmetricMode": True})
            norm = float(abs(K).sum(axis=0).max())  # K is symmetric: its 1- and inf-norms agree
            x = _refined(K, norm, lu, rhs)
            if x is None:
                lu = splu(K)
                x = lu.solve(rhs)
        except RuntimeError:  # exactly singular
            return None, np.inf
        inv = LinearOperator(K.shape, matvec=lu.solve, rmatvec=lambda x: lu.solve(x, trans="T"), dtype=float)
        cond = norm * onenormest(inv)
        return x[:n], cond


#: Largest scaled residual ``|rhs - K x|_inf / (|K|_inf |x|_inf + |rhs|_inf)`` a solve by the
#: threshold-pivoted factors is kept at (after one refinement step); backward errors measured on
#: such KKT systems were 1e-16-1e-14.
REFINED_RESIDUAL = 1e-12


def _refined(K, norm: float, lu, rhs) -> np.ndarray | None:
    """``K x = rhs`` by ``lu`` and one step of iterative refinement; None if the scaled residual
    (``norm``: K's inf-norm) is above :data:`REFINED_RESIDUAL`."""
    x = lu.solve(rhs)
    x = x + lu.solve(rhs - K @ x)
    scale = norm * float(np.abs(x).max()) + float(np.abs(rhs).max())
    residual = float(np.abs(rhs - K @ x).max())
    return x if np.isfinite(residual) and residual <= REFINED_RESIDUAL * scale else None
