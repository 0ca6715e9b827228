"""The scene solver's sampling operator ``B W_t`` (docs/method.md section 8b), stored by its
structure and applied by compiled loops.

Each reading's row is the box mean of the linear spline through the scene samples: separable, an
outer product of ``m`` vertical and ``m`` horizontal weights placed at one corner of the fine grid.
So a reading is stored as its corner and ``2 m`` weights (36 bytes at ``m = 4``) where a sparse
matrix stores ``m^2`` weights and column indices (128 bytes), and the products, which are most of
the scene solver's time, run as loops compiled by numba: on a 288 px tile of 8 frames 3.3 ms
forward and 3.7 ms back, against 13.0 and 12.3 ms for scipy's float32 CSR products (``python
docs/bench/sampling.py``, one run). Weights are float32, sums float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property, wraps

import numpy as np

#: Supports (samples a side) the compiled loops are written for: every default (a grid 2x finer than
#: a full plane: 4; than a CFA colour's photosites, or the pixel pitch itself: 3). Wider ones
#: (``solver.scene_scale`` 3 and up) go through scipy's CSR product.
COMPILED = {3, 4}


def box_spline_weights(u: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Taps ``(n, m)`` and weights: the mean over ``[u - width/2, u + width/2]`` of the linear
    spline through unit samples at the integers, for each of the ``n`` positions ``u``."""
    m = int(np.ceil(width)) + 2
    taps = np.floor(u - width / 2).astype(np.int64)[:, None] + np.arange(m)
    lo = u[:, None] - width / 2 - taps
    return taps, (_hat_integral(lo + width) - _hat_integral(lo)) / width


def _hat_integral(x: np.ndarray) -> np.ndarray:
    """``int_-inf^x max(0, 1 - |s|) ds``."""
    x = np.clip(x, -1.0, 1.0)
    return np.where(x < 0, (x + 1) ** 2 / 2, 1 - (1 - x) ** 2 / 2)


@dataclass(frozen=True)
class Sampling:
    """The stacked ``B W_t`` of every frame: row ``i`` weighs the scene samples ``corner[i] +
    r * fw + c`` (``fw``: the fine grid's width) by ``wv[i, r] * wu[i, c]`` (rows out of view have
    zero weights at corner 0)."""

    corner: np.ndarray  # (rows,) int32
    wu: np.ndarray  # (rows, m) float32
    wv: np.ndarray  # (rows, m) float32
    fine: tuple[int, int]

    @property
    def shape(self) -> tuple[int, int]:
        return self.corner.size, self.fine[0] * self.fine[1]

    def forward(self, v: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``A v``: each reading's value of the fine scene ``v`` (into ``out`` if given)."""
        if not self._looped:
            product = (self._csr[0] @ v.astype(np.float32)).astype(np.float64)
            if out is None:
                return product
            out[:] = product
            return out
        out = np.empty(self.corner.size) if out is None else out
        loop = _forward_three if self.wu.shape[1] == 3 else _forward_four
        loop(self.corner, self.wu, self.wv, np.uint64(self.fine[1]), np.asarray(v, np.float64), out)
        return out

    def back(self, r: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``A^T r``: the readings' values ``r`` summed onto the scene samples that make them (added
        to ``out`` if given)."""
        return self._back(self.wu, self.wv, r, 1, out)

    def back_squared(self, r: np.ndarray) -> np.ndarray:
        """``(A * A)^T r``: the diagonal of ``A^T diag(r) A``."""
        return self._back(self.wu**2, self.wv**2, r, 2, None)

    @cached_property
    def _csr(self):
        """The CSR matrix, its transpose and its squared transpose (supports the loops are not written for)."""
        matrix = self.sparse()
        transpose = matrix.T.tocsr()
        squared = transpose.copy()
        squared.data **= 2
        return matrix, transpose, squared

    def sparse(self):
        """The same operator as a scipy CSR matrix (float32)."""
        import scipy.sparse as sp

        rows, width = self.wu.shape
        offsets = (np.arange(width)[:, None] * self.fine[1] + np.arange(width)).ravel()
        columns = (self.corner[:, None].astype(np.int64) + offsets).ravel()
        data = (self.wv[:, :, None] * self.wu[:, None, :]).ravel()
        keep = data != 0
        indptr = np.concatenate([[0], np.cumsum(keep.reshape(rows, -1).sum(axis=1))])
        return sp.csr_matrix((data[keep], columns[keep], indptr), shape=self.shape)

    @property
    def _looped(self) -> bool:
        """Whether the compiled loops apply: a support they are written for, on a grid at least as
        large (rows out of view read the first samples)."""
        m = self.wu.shape[1]
        return m in COMPILED and min(self.fine) >= m

    def _back(self, wu, wv, r, power: int, out) -> np.ndarray:
        if not self._looped:
            product = (self._csr[power] @ r.astype(np.float32)).astype(np.float64)
            if out is None:
                return product
            out += product
            return out
        out = np.zeros(self.shape[1]) if out is None else out
        loop = _back_three if wu.shape[1] == 3 else _back_four
        loop(self.corner, wu, wv, np.uint64(self.fine[1]), np.asarray(r, np.float64), out)
        return out


def sampling(points: list[np.ndarray], fine: tuple[int, int], scale: int, aperture: float) -> tuple[Sampling,
                                                                                                     np.ndarray]:
    """The :class:`Sampling` of every frame: row ``t * n + i`` is reading ``i`` of frame ``t``, whose
    pixel sees the first frame at ``points[t][i] = (x, y)`` (grid px); the ``fine`` scene samples
    are row-major, sample ``j`` at grid coordinate ``(j - (scale-1)/2) / scale``. Also whether each
    row's support lies inside the scene grid (the others are zero rows)."""
    fh, fw = fine
    width = scale * aperture
    m = int(np.ceil(width)) + 2
    corners, us, vs, inside = [], [], [], []
    for xy in points:
        tu, wu = np.empty(len(xy), np.int64), np.empty((len(xy), m), np.float32)
        tv, wv = np.empty_like(tu), np.empty_like(wu)
        _box_weights(scale * xy[:, 0] + (scale - 1) / 2, width, tu, wu)
        _box_weights(scale * xy[:, 1] + (scale - 1) / 2, width, tv, wv)
        seen = (tu >= 0) & (tu + m - 1 < fw) & (tv >= 0) & (tv + m - 1 < fh)
        corners.append(np.where(seen, tv * fw + tu, 0).astype(np.int32))  # out of view: zero weights
        us.append(wu)
        vs.append(np.where(seen[:, None], wv, np.float32(0)))
        inside.append(seen)
    return Sampling(np.concatenate(corners), np.concatenate(us), np.concatenate(vs), fine), np.concatenate(inside)


def compiled(function=None, *, fastmath: bool = True):
    """``function`` compiled by numba (nopython; reassociation allowed unless ``fastmath`` is False)
    on its first call, or loaded from numba's cache: numba is imported only where such a function
    runs (the scene solver, the defect search's nearest readings)."""
    if function is None:
        return lambda f: compiled(f, fastmath=fastmath)

    @wraps(function)
    def call(*args):
        return _jit(function, fastmath)(*args)

    return call


@cache
def _jit(function, fastmath: bool = True):
    from numba import njit

    return njit(cache=True, nogil=True, fastmath=fastmath)(function)


@compiled(fastmath=False)  # strict IEEE order: the same weights as box_spline_weights, bit for bit
def _box_weights(u, width, first, weights):
    """:func:`box_spline_weights` as a compiled loop: each position's first tap into ``first`` and its
    weights, rounded to float32, into ``weights`` (``(n, m)``)."""
    m = weights.shape[1]
    for i in range(u.size):
        start = np.floor(u[i] - width / 2)
        first[i] = np.int64(start)
        for k in range(m):
            lo = u[i] - width / 2 - (start + k)
            hi = min(max(lo + width, -1.0), 1.0)
            lo = min(max(lo, -1.0), 1.0)
            at_hi = (hi + 1) ** 2 / 2 if hi < 0 else 1 - (1 - hi) ** 2 / 2
            at_lo = (lo + 1) ** 2 / 2 if lo < 0 else 1 - (1 - lo) ** 2 / 2
            weights[i, k] = np.float32((at_hi - at_lo) / width)


# The loops, unrolled over a row's columns, with reassociation allowed (fastmath: forward 4.2 ms
# against 4.9 ms without on the tile of docs/bench/sampling.py, back alike). A loop over blocks of 4
# (zero-padded) for wider supports was slower than the CSR product at 6 a side (45 ms against 27 ms,
# one run), hence the CSR there. The scene's indices are unsigned (``fw`` too: pass it as np.uint64;
# corners are never negative): numba tests a signed index for a negative value to wrap it, a compare
# and a select per access, with which these loops took 1.3-1.5x as long (forward 4.6-4.9 against 3.3
# ms, back 5.3-5.5 against 3.6-3.7 ms on that tile, two runs of each alternating; the same bits).
_U1, _U2, _U3 = np.uint64(1), np.uint64(2), np.uint64(3)


@compiled
def _forward_four(corner, wu, wv, fw, v, out):
    for i in range(corner.shape[0]):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        row = np.uint64(corner[i])
        for r in range(4):
            b = wv[i, r]
            a0 += b * v[row]
            a1 += b * v[row + _U1]
            a2 += b * v[row + _U2]
            a3 += b * v[row + _U3]
            row += fw
        out[i] = wu[i, 0] * a0 + wu[i, 1] * a1 + wu[i, 2] * a2 + wu[i, 3] * a3


@compiled
def _back_four(corner, wu, wv, fw, x, out):
    for i in range(corner.shape[0]):
        u0 = wu[i, 0] * x[i]
        u1 = wu[i, 1] * x[i]
        u2 = wu[i, 2] * x[i]
        u3 = wu[i, 3] * x[i]
        row = np.uint64(corner[i])
        for r in range(4):
            b = wv[i, r]
            out[row] += b * u0
            out[row + _U1] += b * u1
            out[row + _U2] += b * u2
            out[row + _U3] += b * u3
            row += fw


@compiled
def _forward_three(corner, wu, wv, fw, v, out):
    for i in range(corner.shape[0]):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        row = np.uint64(corner[i])
        for r in range(3):
            b = wv[i, r]
            a0 += b * v[row]
            a1 += b * v[row + _U1]
            a2 += b * v[row + _U2]
            row += fw
        out[i] = wu[i, 0] * a0 + wu[i, 1] * a1 + wu[i, 2] * a2


@compiled
def _back_three(corner, wu, wv, fw, x, out):
    for i in range(corner.shape[0]):
        u0 = wu[i, 0] * x[i]
        u1 = wu[i, 1] * x[i]
        u2 = wu[i, 2] * x[i]
        row = np.uint64(corner[i])
        for r in range(3):
            b = wv[i, r]
            out[row] += b * u0
            out[row + _U1] += b * u1
            out[row + _U2] += b * u2
            row += fw
