"""Scene layers: a few planes that move apart, found from tracked points and labelled pixel by pixel.

A near object's parallax, or an object moving on its own, is motion no
single warp explains, and dense optical flow is too coarse for the method
(DIS errs by 0.1-1 px per pixel on these frames). A scene made of a few
rigid surfaces moves exactly as one homography per surface, each fitted to
many points to a few hundredths of a pixel; what remains is to tell which
surface each pixel sees. :func:`find_layers` takes the points the dominant
motion does not explain and splits off the layers they support (sequential
robust fits, a point joining a layer only if it follows it in every frame);
:func:`label_pixels` then gives every pixel the layer whose warp best
predicts its neighbourhood, and none where it is occluded in one of the two
frames. The result is :class:`geometry.warps.LayeredWarp`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.warps import NO_LAYER, apply_homography

#: A layer needs this many points, and this fraction of all tracked points:
#: fewer are a few bad tracks, not a surface.
MIN_POINTS = 12
MIN_FRACTION = 0.02
#: A point leaves the dominant layer when its residual under it exceeds this
#: (px) in at least half the frames where it was tracked.
OUTLIER_PX = 1.0
#: A point belongs to a secondary layer when that layer's warp predicts it
#: within this (px) in every frame where it was tracked.
MEMBER_PX = 0.5
#: A layer whose points move less than this (px, median) in every frame is
#: still on the sensor: corners of a flat area are the gain pattern's, and
#: tracking them follows the sensor, not the scene. Such a layer says
#: nothing about the gain and is dropped.
STATIC_PX = 0.5
#: Layers at most, the dominant one included.
MAX_LAYERS = 3
#: Parameters of a secondary layer's model per frame: a shift of the
#: dominant layer (in reference pixels: an object moving parallel to the
#: image plane), or a homography of its own.
LAYER_PARAMS = {"shift": 2, "homography": 8}
#: Side (px, on the labelling grid) of the window whose mean absolute
#: difference decides a pixel's layer.
WINDOW = 7
#: A pixel whose layer is not clear takes that of the nearest clear pixel
#: if it is at most this fraction as far as the nearest clear pixel of any
#: other layer.
FILL_RATIO = 0.5
#: A frame's pixel sees no layer when its best window difference exceeds
#: this many times the frame's median best difference (occluded in one of
#: the two frames, or not rigid).
NO_LAYER_RATIO = 3.0


@dataclass(frozen=True)
class Layers:
    """Secondary layers of a burst, from its tracked points.

    Attributes
    ----------
    homographies : ndarray, shape (F, L, 3, 3)
        ``H_t_ref`` of each layer, layer 0 the dominant motion given.
    members : ndarray of int, shape (N,)
        Each point's layer (0: the dominant one, or none).
    models : list of str
        Each secondary layer's model (a key of LAYER_PARAMS).
    residuals : ndarray, shape (F - 1, N)
        Each point's distance (px) from where its layer puts it, NaN where
        it was not tracked.
    params : int
        Parameters of the secondary layers per frame.
    points : ndarray, shape (N, 2)
        The reference's points.
    """

    homographies: np.ndarray
    members: np.ndarray
    models: list
    residuals: np.ndarray
    params: int
    points: np.ndarray

    @property
    def n_layers(self) -> int:
        return self.homographies.shape[1]


def find_layers(src: np.ndarray, dst: np.ndarray, base: np.ndarray, *, max_layers: int = MAX_LAYERS) -> Layers:
    """Layers that explain the points ``base`` does not.

    Parameters
    ----------
    src : ndarray, shape (N, 2)
        Points of the reference, ``(x, y)``.
    dst : ndarray, shape (F - 1, N, 2)
        Where frames 1.. see them; NaN where a point was not tracked.
    base : ndarray, shape (F, 3, 3)
        The dominant motion ``H_t_ref`` (the reference's: identity).
    """
    import cv2

    tracked = np.isfinite(dst[..., 0])
    residual = np.stack([_distances(H, src, d) for H, d in zip(base[1:], dst)])
    n_tracked = tracked.sum(0)
    outlying = (np.nan_to_num(residual) > OUTLIER_PX).sum(0)
    candidates = (n_tracked > 0) & (outlying >= 0.5 * n_tracked)
    members = np.zeros(len(src), int)
    layers, models = [np.asarray(base, np.float64)], []
    need = max(MIN_POINTS, int(np.ceil(MIN_FRACTION * len(src))))
    while candidates.sum() >= need and len(layers) < max_layers:
        t = int(np.argmax((tracked & candidates).sum(1)))  # seed where most candidates were tracked
        pick = np.flatnonzero(candidates & tracked[t])
        if len(pick) < need:
            break
        _, mask = cv2.findHomography(src[pick], dst[t, pick], cv2.USAC_ACCURATE, MEMBER_PX, maxIters=5000,
                                     confidence=0.9999)
        seed = np.zeros(len(src), bool)
        if mask is not None:
            seed[pick[mask.ravel().astype(bool)]] = True
        fit = _fit_layer(src, dst, base, seed, candidates)
        if fit is None:
            break
        H, joined, model = fit
        candidates &= ~joined
        if max(np.median(_distances(H[t], src[joined], src[joined])) for t in range(1, len(H))) < STATIC_PX:
            continue  # still on the sensor: the fixed pattern itself (tracks on a flat area), not a surface
        members[joined] = len(layers)
        layers.append(H)
        models.append(model)
    homographies = np.stack(layers, axis=1)
    return Layers(homographies, members, models, _own_residuals(homographies, members, src, dst),
                  sum(LAYER_PARAMS[m] for m in models), src)


def _own_residuals(homographies, members, src, dst) -> np.ndarray:
    """Each point's distance from where its own layer puts it, per frame ``(F - 1, N)``."""
    return np.stack([_distances(homographies[t + 1, members], src, dst[t]) for t in range(len(dst))])


def _fit_layer(src, dst, base, seed, candidates):
    """The layer the ``seed`` points start: ``(H (F, 3, 3), members, model)``, or None if too few follow it.

    Two rounds: fit on the current members, keep the candidates it predicts
    within MEMBER_PX in every frame that tracked them. The model (a shift of
    the dominant layer or a homography) has the lower GRIC, both scored with
    the noise level the better one leaves.
    """
    need = max(MIN_POINTS, int(np.ceil(MIN_FRACTION * len(src))))
    joined = seed
    for _ in range(2):
        if joined.sum() < need:
            return None
        fits = {name: _fit_model(name, src, dst, base, joined) for name in LAYER_PARAMS}
        fits = {name: H for name, H in fits.items() if H is not None}
        if not fits:
            return None
        errors = {name: np.stack([_distances(H[t + 1], src[joined], dst[t, joined]) for t in range(len(dst))])
                  for name, H in fits.items()}
        # one noise level for both: the tracking noise, as the better model sees it
        sigma2 = max(min(float(np.nanmedian(e**2)) for e in errors.values()) / (2 * np.log(2)), 1e-8)
        scores = {name: float(np.nansum(np.minimum(e**2 / sigma2, 4.0)))
                  + LAYER_PARAMS[name] * len(dst) * np.log(4 * np.isfinite(e).sum()) for name, e in errors.items()}
        model = min(scores, key=scores.get)
        H = fits[model]
        e = np.stack([_distances(H[t + 1], src, dst[t]) for t in range(len(dst))])
        joined = candidates & np.isfinite(e).any(0) & np.all(np.nan_to_num(e) < MEMBER_PX, axis=0)
    return (H, joined, model) if joined.sum() >= need else None


def _fit_model(name, src, dst, base, members):
    """A layer's ``H_t_ref`` per frame (identity for the reference), fitted robustly to ``members``
    (a seed may hold a stray point), or None if a frame has too few of them."""
    import cv2

    out = [np.eye(3)]
    for t in range(len(dst)):
        on = members & np.isfinite(dst[t, :, 0])
        if on.sum() < (8 if name == "homography" else 1):
            return None
        if name == "shift":  # H_base T(o): o the median offset in reference pixels
            back = apply_homography(np.linalg.inv(base[t + 1]), dst[t, on])
            T = np.eye(3)
            T[:2, 2] = np.median(back - src[on], axis=0)
            out.append(base[t + 1] @ T)
            continue
        _, mask = cv2.findHomography(src[on], dst[t, on], cv2.USAC_ACCURATE, MEMBER_PX, maxIters=2000,
                                     confidence=0.999)
        keep = mask.ravel().astype(bool) if mask is not None else np.zeros(on.sum(), bool)
        if keep.sum() < 8:
            return None
        H, _ = cv2.findHomography(src[on][keep], dst[t, on][keep], 0)  # least squares on the inliers
        if H is None:
            return None
        out.append(H / H[2, 2])
    return np.stack(out)


def _distances(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``|H src - dst|`` per point; ``H`` one 3x3 matrix or one per point ``(N, 3, 3)``."""
    p = np.concatenate([src, np.ones((len(src), 1))], axis=1)
    q = (H @ p.T).T if H.ndim == 2 else np.einsum("nij,nj->ni", H, p)
    return np.linalg.norm(q[:, :2] / q[:, 2:3] - dst, axis=1)


def label_pixels(smooth: list, layers: np.ndarray, members: np.ndarray, points: np.ndarray, *,
                 smoothing: float) -> np.ndarray:
    """The layer every pixel of every frame sees, on the grid of ``smooth``.

    Parameters
    ----------
    smooth : list of ndarray, shape (h, w)
        The frames, smoothed (FPN suppressed) and possibly reduced;
        ``smooth[0]`` is the reference.
    layers : ndarray, shape (F, L, 3, 3)
        Each layer's ``H_t_ref`` in the pixels of ``smooth``.
    members, points : ndarray
        Each tracked point's layer and its reference position in the pixels
        of ``smooth``: a secondary layer is only seen in patches that hold
        some of its points.
    smoothing : float
        Gaussian sigma of the smoothing, in the pixels of ``smooth``: with
        the window, it blurs where a surface ends, so pixels that close to
        another layer's get none.

    Returns
    -------
    ndarray of uint8, shape (F, h, w)
        The reference: the layer whose warps best predict the pixel's
        window, on average over the other frames that see it. Frame t: the
        layer whose warp best predicts it from the reference, among those
        the reference sees there; :data:`geometry.warps.NO_LAYER` where none
        does, or only badly.
    """
    import cv2

    n, (h, w) = len(smooth), smooth[0].shape
    margin = WINDOW // 2 + int(np.ceil(2 * smoothing))
    n_layers = layers.shape[1]
    square = np.ones((WINDOW, WINDOW), np.uint8)

    def box(a: np.ndarray) -> np.ndarray:
        """Mean of ``a`` over the best of the windows holding each pixel (shiftable windows: a pixel by a
        surface's edge is judged on a window on its own side, so the edge does not fatten the surface)."""
        return cv2.erode(cv2.blur(a, (WINDOW, WINDOW), borderType=cv2.BORDER_REFLECT), square,
                         borderType=cv2.BORDER_REFLECT)

    allowed = np.ones((n_layers, h, w), bool)  # where each layer's warp keeps the pixel in some frame
    cost = np.zeros((n_layers, h, w), np.float32)
    for layer in range(n_layers):  # mean window difference over the frames that see the pixel
        count = np.zeros((h, w), np.float32)
        for t in range(1, n):
            seen = _warp(smooth[t], layers[t, layer], (h, w))
            inside = _warp(np.ones((h, w), np.float32), layers[t, layer], (h, w), border=0.0) > 0.999
            cost[layer] += np.where(inside, box(np.abs(smooth[0] - seen)), 0.0)
            count += inside
        cost[layer] /= np.maximum(count, 1)
        if layer:
            allowed[layer] &= count > 0
    cost[~allowed] = np.inf
    labels = np.empty((n, h, w), np.uint8)
    labels[0] = _apart(_connected(_decide(cost), members, points), margin)
    for t in range(1, n):
        cost = np.full((n_layers, h, w), np.inf, np.float32)
        sees = np.zeros((n_layers, h, w), bool)
        for layer in range(n_layers):
            inverse = np.linalg.inv(layers[t, layer])
            sees[layer] = _warp(labels[0], inverse, (h, w), nearest=True, border=NO_LAYER) == layer
            cost[layer][sees[layer]] = box(np.abs(smooth[t] - _warp(smooth[0], inverse, (h, w))))[sees[layer]]
        label = _decide(cost)
        best = np.min(cost, axis=0)
        some = label != NO_LAYER
        seen = some & np.take_along_axis(sees, np.where(some, label, 0)[None].astype(np.intp), axis=0)[0]
        label[~seen] = NO_LAYER
        if seen.any():
            label[best > NO_LAYER_RATIO * np.median(best[seen])] = NO_LAYER
        labels[t] = _apart(label, margin)
    return labels


def _decide(cost: np.ndarray) -> np.ndarray:
    """Per pixel, the layer of least ``cost`` ``(L, h, w)`` where that is clear; elsewhere the layer
    clearly nearest, or :data:`geometry.warps.NO_LAYER`.

    Clear: the runner-up costs at least twice as much, and more than the
    best costs typically (the noise). Where layers cost alike -- flat
    areas -- the choice does not change the brightness a trajectory sees, so
    such a pixel takes the layer of the nearest clear pixel, if that is at
    most half as far as the nearest clear pixel of any other layer (a flat
    inside stays with its surface); between surfaces it gets none.
    """
    import cv2

    best = np.argmin(cost, axis=0).astype(np.uint8)
    if cost.shape[0] == 1:
        return best
    lowest, runner_up = np.full(cost.shape[1:], np.inf, np.float32), np.full(cost.shape[1:], np.inf, np.float32)
    for c in cost:  # the two lowest costs (a sort along a short first axis is slow)
        runner_up = np.minimum(runner_up, np.maximum(lowest, c))
        lowest = np.minimum(lowest, c)
    finite = np.isfinite(lowest)
    typical = float(np.median(lowest[finite])) if finite.any() else 0.0
    with np.errstate(invalid="ignore"):  # inf - inf where no layer sees the pixel
        clear = finite & (runner_up >= 2 * lowest) & (runner_up - lowest > typical)
    if clear.all():
        return best
    distance = np.stack([cv2.distanceTransform((~(clear & (best == layer))).astype(np.uint8), cv2.DIST_L2, 5)
                         for layer in range(cost.shape[0])])
    nearest = np.argmin(distance, axis=0)
    other = np.min(np.where(np.arange(len(distance))[:, None, None] == nearest, np.inf, distance), axis=0)
    filled = np.where(np.min(distance, axis=0) <= FILL_RATIO * other, nearest, NO_LAYER).astype(np.uint8)
    return np.where(clear, best, filled)


def _apart(labels: np.ndarray, margin: int) -> np.ndarray:
    """``labels`` with :data:`geometry.warps.NO_LAYER` within ``margin`` px of another layer's pixels."""
    import cv2

    out = labels.copy()
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1,) * 2)
    present = [v for v in np.unique(labels) if v != NO_LAYER]
    if len(present) < 2:
        return out
    for value in present:
        near = cv2.dilate((labels == value).astype(np.uint8), kernel) > 0
        out[near & (labels != value) & (labels != NO_LAYER)] = NO_LAYER
    return out


def _connected(labels: np.ndarray, members: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``labels`` with :data:`geometry.warps.NO_LAYER` on every patch of a secondary layer that holds none of
    its tracked points: a surface is where its points are, and a patch elsewhere that its warp happens
    to fit (a smooth area, an edge along the motion) is not it."""
    import cv2

    out = labels.copy()
    h, w = labels.shape
    xy = np.clip(np.rint(points).astype(int), 0, [w - 1, h - 1])
    for layer in range(1, int(members.max(initial=0)) + 1):
        _, patches = cv2.connectedComponents((labels == layer).astype(np.uint8), connectivity=8)
        own = np.unique(patches[xy[members == layer, 1], xy[members == layer, 0]])
        keep = np.isin(patches, own[own > 0])
        out[(labels == layer) & ~keep] = NO_LAYER
    return out


def _warp(image, H, shape, *, nearest: bool = False, border: float | None = None) -> np.ndarray:
    """``out[p] = image(H p)`` on a ``shape`` grid; beyond the image: reflected, or ``border``."""
    import cv2

    flags = (cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP
    mode = cv2.BORDER_REFLECT if border is None else cv2.BORDER_CONSTANT
    return cv2.warpPerspective(image, H, (shape[1], shape[0]), flags=flags, borderMode=mode,
                               borderValue=0 if border is None else border)
