"""Where each frame sees what another frame sees: the motion models as maps.

Three kinds, one interface. :class:`GlobalWarp` is one homography per frame
(translation and affine are special cases). :class:`LayeredWarp` is a few
homographies per frame, one per scene layer (a near object's parallax, an
object moving on its own), and a map of which layer each pixel sees: a
dense, piecewise-planar motion. :class:`FieldWarp` adds a smooth
displacement field per frame, in the frame's own pixels:

    frame t sees reference point p at q, where  q = H_t p + r_t(q)

``r_t`` is a cubic B-spline: of the row alone for a rolling shutter (each row
is read at its own time, so its displacement depends on ``q_y``), or a
tensor-product mesh over the frame for motion that varies smoothly in both
directions. The map from a frame to the reference is direct,
``p = H_t^-1 (q - r_t(q))``; the other way is a fixed-point iteration, a
contraction wherever the field's slope is well below 1.

Every map takes and returns ``(x, y)`` points. :meth:`pair` gives what the
resamplers in :mod:`geometry.resample` take: a 3x3 matrix for a global warp (OpenCV's
``warpPerspective``), an ``(h, w, 2)`` float32 map otherwise (``remap``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEGREE = 3
#: Fixed-point iterations of ``q = H p + r(q)`` at most, and the change (px)
#: at which they stop.
TO_FRAME_ITERATIONS = 20
TO_FRAME_TOL = 1e-6
#: :meth:`FieldWarp.pair` computes its maps exactly every LATTICE px at most
#: (a fifth of a field cell if less; see :meth:`FieldWarp.lattice_step`).
#: Worst error of the interpolated map, measured at 320x240 on a 1.5 px wave
#: (tests/test_trajectory.py): 0.0010 px for a 3-period rolling wobble (20 px
#: cells, step 4), 0.0023 px for a 1.5-period mesh wave (step 8), median
#: 5e-5 px -- below the 1/32 px to which OpenCV's resamplers round positions.
LATTICE = 8
#: How far (px) beyond the frame a field continues its edge cells' polynomials.
EDGE_PX = 3 * LATTICE


#: A displacement below this (px, RMS over the frame) cannot be told from zero: the accuracy
#: the motion estimate is held to (docs/limits.md, motion accuracy). A frame that moves less adds
#: nothing about k, and a burst none of whose frames moves more cannot be corrected.
STILL_PX = 0.05


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``H`` applied to ``(..., 2)`` points ``(x, y)``."""
    p = np.asarray(points, np.float64) @ H[:, :2].T + H[:, 2]
    return p[..., :2] / p[..., 2:3]


def homography_xy(H: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``H`` applied to points given as coordinate arrays ``x`` and ``y`` of any one shape."""
    den = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    return (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / den, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / den


def project(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``H`` applied to homogeneous points ``p`` of shape ``(3, N)``: their ``(2, N)`` pixel coordinates."""
    q = H @ p
    return q[:2] / q[2]


def _shifted(M: np.ndarray, region: tuple[int, int, int, int]) -> np.ndarray:
    """A map between frame pixels expressed between the pixels of ``region = (y0, x0, h, w)``."""
    y0, x0 = region[:2]
    shift = np.array([[1.0, 0, x0], [0, 1.0, y0], [0, 0, 1.0]])
    return np.linalg.inv(shift) @ M @ shift


def _grid(region: tuple[int, int, int, int]) -> np.ndarray:
    y0, x0, h, w = region
    ys, xs = np.mgrid[y0 : y0 + h, x0 : x0 + w].astype(np.float64)
    return np.stack([xs, ys], axis=-1)


@dataclass(frozen=True)
class GlobalWarp:
    """``H_t_ref`` per frame (the reference's is the identity)."""

    homographies: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.homographies)

    def matrix(self, s: int, t: int) -> np.ndarray:
        """``M_st = H_t H_s^-1``: frame s pixel -> frame t pixel."""
        return self.homographies[t] @ np.linalg.inv(self.homographies[s])

    def map_points(self, s: int, t: int, points: np.ndarray) -> np.ndarray:
        """Where frame t sees what frame s sees at ``points`` (``(..., 2)``)."""
        return apply_homography(self.matrix(s, t), points)

    def pair(self, s: int, t: int, region: tuple[int, int, int, int]) -> np.ndarray:
        """:meth:`map_points` for the pixels of ``region = (y0, x0, h, w)`` of frame s, in the region's
        coordinates, as a 3x3 matrix."""
        return _shifted(self.matrix(s, t), region)

    def conjugate(self, S: np.ndarray) -> "GlobalWarp":
        """The same motion in pixels ``c`` with ``S c`` = these pixels (a CFA plane, a reduced frame)."""
        S = np.asarray(S, np.float64)
        return GlobalWarp(np.array([np.linalg.inv(S) @ H @ S for H in self.homographies]))

    def select(self, frames) -> "GlobalWarp":
        """The motion of a subset of the frames (``H_t_ref`` stay relative to the reference, which
        may be left out)."""
        return GlobalWarp(self.homographies[list(frames)])


@dataclass(frozen=True)
class FieldWarp:
    """Homographies plus a smooth displacement field per frame (see the module docstring).

    Attributes
    ----------
    homographies : ndarray, shape (F, 3, 3)
    coefficients : ndarray, shape (F, 2, ny, nx)
        B-spline coefficients of ``r_t``'s x and y parts over ``ny - 3`` by
        ``nx - 3`` uniform cells; ``nx == 1`` for a field of the row alone.
    shape : (int, int)
        ``(H, W)`` of the frames the field spans (its pixels: field pixels).
    to_field : ndarray, shape (3, 3)
        Maps the pixels this object speaks to field pixels (identity unless
        :meth:`conjugate` made it).
    """

    homographies: np.ndarray
    coefficients: np.ndarray
    shape: tuple[int, int]
    to_field: np.ndarray = None

    def __post_init__(self):
        if self.to_field is None:
            object.__setattr__(self, "to_field", np.eye(3))

    @property
    def n_frames(self) -> int:
        return len(self.homographies)

    def field(self, t: int, points: np.ndarray) -> np.ndarray:
        """``r_t`` at field-pixel ``points`` ``(..., 2)``."""
        return field_at(self.coefficients[t], points, self.shape)

    def _to_reference(self, t: int, q: np.ndarray) -> np.ndarray:
        return apply_homography(np.linalg.inv(self.homographies[t]), q - self.field(t, q))

    def _to_frame(self, t: int, p: np.ndarray) -> np.ndarray:
        start = apply_homography(self.homographies[t], p)
        q = start
        for _ in range(TO_FRAME_ITERATIONS):
            nxt = start + self.field(t, q)
            done = np.max(np.abs(nxt - q), initial=0.0) < TO_FRAME_TOL
            q = nxt
            if done:
                break
        return q

    def map_points(self, s: int, t: int, points: np.ndarray) -> np.ndarray:
        """Where frame t sees what frame s sees at ``points`` (``(..., 2)``)."""
        f = apply_homography(self.to_field, points)
        return apply_homography(np.linalg.inv(self.to_field), self._to_frame(t, self._to_reference(s, f)))

    def pair(self, s: int, t: int, region: tuple[int, int, int, int]) -> np.ndarray:
        """:meth:`map_points` for the pixels of ``region = (y0, x0, h, w)`` of frame s, in the region's
        coordinates: float32 ``(h, w, 2)``.

        The map is computed exactly on a lattice (:meth:`lattice_step`) and
        interpolated in between (cubic splines, as separable matrix products
        in float64): the map is smooth on that scale.
        """
        y0, x0, h, w = region
        step = self.lattice_step()
        if h < 2 * step or w < 2 * step:  # too small to gain from a lattice: exact
            return (self.map_points(s, t, _grid(region)) - [x0, y0]).astype(np.float32)
        wy, wx = _upsampling(h, step), _upsampling(w, step)
        ly, lx = (np.arange(wy.shape[1]) - 1.0) * step, (np.arange(wx.shape[1]) - 1.0) * step
        lattice = np.stack(np.meshgrid(lx, ly), axis=-1)  # one step beyond the region on every side
        moved = self.map_points(s, t, lattice + [x0, y0]) - [x0, y0] - lattice
        own = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), axis=-1)
        return (own + np.stack([wy @ moved[..., c] @ wx.T for c in (0, 1)], axis=-1)).astype(np.float32)

    def lattice_step(self) -> int:
        """The lattice step of :meth:`pair`: LATTICE px, or a fifth of a field cell (in these pixels) if less."""
        ny, nx = self.coefficients.shape[2:]
        cell = self.shape[0] / (ny - DEGREE)
        if nx > 1:
            cell = min(cell, self.shape[1] / (nx - DEGREE))
        field_per_own = np.sqrt(abs(np.linalg.det(self.to_field[:2, :2])))
        return int(np.clip(cell / field_per_own / 5, 1, LATTICE))

    def conjugate(self, S: np.ndarray) -> "FieldWarp":
        """The same motion in pixels ``c`` with ``S c`` = these pixels."""
        return FieldWarp(self.homographies, self.coefficients, self.shape, self.to_field @ np.asarray(S, np.float64))

    def select(self, frames) -> "FieldWarp":
        frames = list(frames)
        return FieldWarp(self.homographies[frames], self.coefficients[frames], self.shape, self.to_field)


def _upsampling(n: int, step: int) -> np.ndarray:
    """``(n, m)`` weights interpolating pixels ``0..n-1`` from lattice points at ``(j - 1) step``, j < m.

    Cubic spline interpolation (not-a-knot): error of fourth order in
    ``step``, about ``5/384 step^4`` times the map's fourth derivative.
    """
    from scipy.interpolate import make_interp_spline

    m = (n - 1) // step + 3
    return make_interp_spline(np.arange(m) - 1.0, np.eye(m), k=3)(np.arange(n) / step)


def field_at(coefficients: np.ndarray, points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The field with B-spline ``coefficients`` ``(2, ny, nx)`` over a ``shape`` frame at ``(..., 2)`` points."""
    by = basis(points[..., 1].ravel(), shape[0], coefficients.shape[1] - DEGREE)
    if coefficients.shape[2] == 1:  # a field of the row alone
        out = by @ coefficients[:, :, 0].T
    else:
        bx = basis(points[..., 0].ravel(), shape[1], coefficients.shape[2] - DEGREE)
        out = np.stack([np.einsum("ni,ij,nj->n", by, c, bx) for c in coefficients], axis=1)
    return out.reshape(points.shape)


def basis(coords: np.ndarray, length: int, cells: int) -> np.ndarray:
    """Cubic B-spline basis on ``cells`` uniform cells over pixel centres ``-0.5 .. length - 0.5``.

    Returns dense ``(n, cells + 3)``. The edge cells' polynomials continue
    EDGE_PX beyond the frame (so that maps stay smooth across its border,
    where :meth:`FieldWarp.pair` interpolates them); farther out the field
    is constant.
    """
    from scipy.interpolate import BSpline

    step = length / cells
    knots = -0.5 + step * np.arange(-DEGREE, cells + DEGREE + 1)
    x = np.clip(np.asarray(coords, np.float64), -0.5 - EDGE_PX, length - 0.5 + EDGE_PX)
    return BSpline.design_matrix(x, knots, DEGREE, extrapolate=True).toarray()


def _transform(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """:func:`apply_homography` of ``(n, 2)`` points, in OpenCV (several times faster on many points)."""
    import cv2

    if len(points) == 0:
        return np.empty((0, 2))
    return cv2.perspectiveTransform(np.ascontiguousarray(points, np.float64).reshape(-1, 1, 2), H).reshape(-1, 2)


#: Label of a pixel no layer explains (an occlusion, a disagreement).
NO_LAYER = 255
#: Where :class:`LayeredWarp` sends a point with no trajectory: far outside
#: every frame, so the resamplers' validity checks reject it (a NaN would
#: compare False and pass).
NOWHERE = -1.0e5


@dataclass(frozen=True)
class LayeredWarp:
    """A homography per frame and scene layer, and the layer each pixel of each frame sees.

    Frame s sees at ``q`` the point ``p = H_{s,l}^-1 q`` of layer
    ``l = labels[s](q)``; frame t sees it at ``H_{t,l} p``. The point has no
    trajectory (:data:`NOWHERE`) unless the reference and frame t see layer
    ``l`` there too: it is occluded, or uncovered, in one of them.

    Attributes
    ----------
    layers : ndarray, shape (F, L, 3, 3)
        ``H_t_ref`` of each layer; layer 0 is the dominant one (the background).
    labels : ndarray of uint8, shape (F, h, w)
        The layer each frame's pixel sees (:data:`NO_LAYER`: none), on a
        grid that may be coarser than the frames'.
    to_labels : ndarray, shape (3, 3)
        Frame pixels -> ``labels`` pixels.
    to_frame : ndarray, shape (3, 3)
        The pixels this object speaks -> frame pixels (identity unless
        :meth:`conjugate` made it).
    reference_labels : ndarray of uint8, shape (h, w)
        The reference's labels (``labels[0]`` unless :meth:`select` left the
        reference out): a trajectory needs the reference to see its layer.
    """

    layers: np.ndarray
    labels: np.ndarray
    to_labels: np.ndarray
    to_frame: np.ndarray = None
    reference_labels: np.ndarray = None

    def __post_init__(self):
        if self.to_frame is None:
            object.__setattr__(self, "to_frame", np.eye(3))
        if self.reference_labels is None:
            object.__setattr__(self, "reference_labels", self.labels[0])

    @property
    def n_frames(self) -> int:
        return len(self.layers)

    @property
    def homographies(self) -> np.ndarray:
        """The dominant layer's ``H_t_ref``."""
        return self.layers[:, 0]

    def label(self, t: int | None, points: np.ndarray) -> np.ndarray:
        """The layer frame t (None: the reference) sees at frame-pixel ``points`` (nearest label pixel;
        beyond the grid: its edge)."""
        g = np.rint(_transform(self.to_labels, points)).astype(np.int64)
        h, w = self.labels.shape[1:]
        labels = self.reference_labels if t is None else self.labels[t]
        return labels[np.clip(g[..., 1], 0, h - 1), np.clip(g[..., 0], 0, w - 1)]

    def map_points(self, s: int, t: int, points: np.ndarray) -> np.ndarray:
        """Where frame t sees what frame s sees at ``points`` (``(..., 2)``); :data:`NOWHERE` if nowhere."""
        q = _transform(self.to_frame, np.asarray(points, np.float64).reshape(-1, 2))
        seen = self.label(s, q)
        out = np.full(q.shape, NOWHERE)
        for layer in range(self.layers.shape[1]):
            on = np.flatnonzero(seen == layer)
            p = _transform(np.linalg.inv(self.layers[s, layer]), q[on])
            moved = _transform(self.layers[t, layer], p)
            ok = (self.label(None, p) == layer) & (self.label(t, moved) == layer)
            out[on[ok]] = moved[ok]
        own = _transform(np.linalg.inv(self.to_frame), out)
        own[out[:, 0] == NOWHERE] = NOWHERE
        return own.reshape(np.shape(points))

    def pair(self, s: int, t: int, region: tuple[int, int, int, int]) -> np.ndarray:
        """:meth:`map_points` for the pixels of ``region = (y0, x0, h, w)`` of frame s, in the region's
        coordinates: float32 ``(h, w, 2)``."""
        y0, x0 = region[:2]
        moved = self.map_points(s, t, _grid(region).reshape(-1, 2)).reshape(region[2], region[3], 2)
        nowhere = moved[..., 0] == NOWHERE
        moved -= [x0, y0]
        moved[nowhere] = NOWHERE
        return moved.astype(np.float32)

    def conjugate(self, S: np.ndarray) -> "LayeredWarp":
        """The same motion in pixels ``c`` with ``S c`` = these pixels."""
        return LayeredWarp(self.layers, self.labels, self.to_labels, self.to_frame @ np.asarray(S, np.float64),
                           self.reference_labels)

    def select(self, frames) -> "LayeredWarp":
        """The motion of a subset of the frames (the reference's labels kept even if it is left out)."""
        frames = list(frames)
        return LayeredWarp(self.layers[frames], self.labels[frames], self.to_labels, self.to_frame,
                           self.reference_labels)


def as_warp(motion) -> GlobalWarp | FieldWarp | LayeredWarp:
    """A warp object from a warp object or an ``(F, 3, 3)`` array of homographies."""
    if isinstance(motion, (GlobalWarp, FieldWarp, LayeredWarp)):
        return motion
    H = np.asarray(motion, np.float64)
    if H.ndim != 3 or H.shape[1:] != (3, 3) or not np.all(np.isfinite(H)):
        raise ValueError(f"homographies must be finite with shape (F, 3, 3), got {H.shape}")
    return GlobalWarp(H)


def positions_from_homography(H: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Position in frame t of every reference pixel, for ``H = H_t_ref``.

    Returns
    -------
    ndarray of float64, shape (H, W, 2)
        ``[..., 0]`` = x, ``[..., 1]`` = y in frame t's pixel coordinates.
    """
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise ValueError(f"H must be a finite 3x3 matrix, got shape {H.shape}")
    h, w = shape
    ys, xs = np.arange(h, dtype=np.float64)[:, None], np.arange(w, dtype=np.float64)[None, :]  # broadcast, no grids
    den = (H[2, 0] * xs + H[2, 2]) + H[2, 1] * ys
    out = np.empty((h, w, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide((H[0, 0] * xs + H[0, 2]) + H[0, 1] * ys, den, out=out[..., 0])
        np.divide((H[1, 0] * xs + H[1, 2]) + H[1, 1] * ys, den, out=out[..., 1])
    out[~np.isfinite(out)] = np.nan  # points sent to infinity have no position
    return out


def positions_from_flow(flow_xy: np.ndarray) -> np.ndarray:
    """Position in the moving frame of every reference pixel: ``p + flow``."""
    flow_xy = np.asarray(flow_xy, dtype=np.float64)
    if flow_xy.ndim != 3 or flow_xy.shape[2] != 2:
        raise ValueError(f"flow_xy must have shape (H, W, 2), got {flow_xy.shape}")
    h, w = flow_xy.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([xs + flow_xy[..., 0], ys + flow_xy[..., 1]], axis=-1)




def trajectory_rms(H_est: np.ndarray, H_true: np.ndarray, shape: tuple[int, int], step: int = 4) -> float:
    """RMS distance (px) between where two homographies send the reference's pixels."""
    h, w = shape
    ys, xs = np.mgrid[0:h:step, 0:w:step].astype(np.float64)
    p = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    return float(np.sqrt(np.mean(np.sum((project(H_est, p) - project(H_true, p)) ** 2, axis=0))))
