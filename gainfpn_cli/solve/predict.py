"""The scene each photosite of a plane sees in each frame of a burst, predicted from the other
frames along the motion, for the defect search (:mod:`solve.defects`).

Two predictions, each best for its use:

* :func:`scene_along`: every frame brought onto the reference's grid, the median taken over the
  frames and brought back onto each frame's grid. Quiet (a median of all the frames), but
  interpolated twice: on an aliased plane (a colour of a mosaic, sampled every other photosite)
  it misses sharp edges by tens of percent. It measures the readings' noise and tests for dead
  and stuck photosites.
* :func:`nearest_along`: for each photosite in frame ``t``, the mean of the readings of the two
  photosites of other frames that lie nearest the scene point (not interpolated: across an edge
  an interpolation mixes both sides), never the photosite itself. Noisier (two readings), but
  closer on an aliased plane: noise-free 240x320 raw12 bursts of 8 frames (`python
  docs/bench/defects.py predict`), the mean relative error of every plane 7.0-8.7 % -> 3.1-3.8 %
  (dead leaves) and 1.7-1.8 % -> 1.0-1.1 % (procedural). It finds hot photosites whose offset the
  median's error hides, and turns away dead and dim ones the median's error fakes.
"""

from __future__ import annotations

import numpy as np

from ..geometry.resample import sample, valid_samples
from .sampling import compiled
from .stacks import each_strip, nan_median

#: Interpolation of the frames onto the reference's grid and of the median scene back.
KERNEL = "cubic"
#: Fewest frames seeing a point of the reference's grid for their median to predict it.
MIN_SEEN = 4
#: Fewest good neighbours (of 8) whose median predicts a photosite where the frames do not.
MIN_NEIGHBOURS = 3
#: Readings of other frames averaged by :func:`nearest_along`. On the bench's bursts
#: (docs/bench/defects.py) 1, 2 and 3 found as many hot photosites within 4 %; 1 flagged 11 more
#: healthy ones over 80 defect-free bursts of 6 and 7 frames, 3 two more.
NEAREST = 2
#: Other frames searched for them, at most (the nearest in the burst's order): each costs a pass
#: over the plane per frame. On the 16-frame raw12 bursts of docs/bench/defects.py 4 found 64 / 83 %
#: of the hot photosites (dead leaves / procedural), 8 67 / 84 %, 15 (all) 69 / 84 %.
CANDIDATES = 8


def scene_along(frames, good, warp, *, threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x, valid, from_frames`` ``(F, H, W)``: the scene each photosite sees in each frame, where
    it is known, and where it is predicted from the other frames: the median of the frames on the
    reference's grid brought back, or at the borders (fewer than :data:`MIN_SEEN` frames on the
    point) the median of the 8 neighbours in the frame. ``good(t, frames[t])`` gives frame ``t``'s
    usable readings (a frame at a time: a mask of the stack would be another 192 MB at 12 MP x
    16 frames); ``warp.pair(s, t, region)`` maps frame ``s``'s pixels into frame ``t``. The median
    runs on ``threads`` threads."""
    n_frames, h, w = frames.shape
    region = (0, 0, h, w)
    on_ref = np.full((n_frames, h, w), np.nan, np.float32)
    for t in range(n_frames):
        M, frame = warp.pair(0, t, region), frames[t]  # (frames may divide each frame as it is taken)
        ok = valid_samples(good(t, frame), M, (h, w), kernel=KERNEL)
        on_ref[t][ok] = sample(frame, M, (h, w), kernel=KERNEL)[ok]
    seen = np.isfinite(on_ref).sum(axis=0) >= MIN_SEEN
    scene = np.where(seen, nan_median(on_ref, threads=threads), 0).astype(np.float32)  # all-NaN points: not known
    del on_ref
    x = np.empty(frames.shape, np.float32)
    valid = np.empty(frames.shape, bool)
    from_frames = np.empty(frames.shape, bool)
    for t in range(n_frames):
        M = warp.pair(t, 0, region)
        x[t] = sample(scene, M, (h, w), kernel=KERNEL)
        from_frames[t] = known = valid_samples(seen, M, (h, w), kernel=KERNEL)
        frame = frames[t]
        readable = good(t, frame)
        valid[t] = readable & known
        border = np.nonzero(~known)  # the 8 neighbours' median only where the frames do not see the point
        around, count = ring_median(frame, readable, border)
        x[t][border] = np.nan_to_num(around)
        valid[t][border] = readable[border] & (count >= MIN_NEIGHBOURS)  # edges of the frame have 3 or 5
    return x, valid, from_frames


def nearest_along(frames, good, warp, *, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``x, valid`` ``(F, H, W)``: each photosite's scene in each frame ``t`` as the mean of the
    :data:`NEAREST` good readings, among up to :data:`CANDIDATES` other frames, of the photosites
    nearest the point (one a frame, as read: not interpolated), and where it is so predicted and the
    photosite's own reading is good. A frame whose nearest photosite to the point is the predicted
    photosite itself (no motion there) does not predict it: a defect would predict its own reading.
    ``good`` and ``warp`` as :func:`scene_along`'s. Each frame's rows are searched a strip at a time
    on ``threads`` threads (:func:`stacks.each_strip`; the compiled search releases the GIL)."""
    n_frames, h, w = frames.shape
    region = (0, 0, h, w)
    x = np.zeros(frames.shape, np.float32)
    valid = np.zeros(frames.shape, bool)
    for t in range(n_frames):
        distance = np.full((NEAREST, h, w), np.inf, np.float32)  # squared, ascending
        value = np.zeros((NEAREST, h, w), np.float32)
        for s in _candidates(t, n_frames):
            M, frame = warp.pair(t, s, region), np.ascontiguousarray(frames[s], np.float32)
            homography = M.shape == (3, 3)
            H = np.asarray(M if homography else np.eye(3), np.float64)
            moved = np.ascontiguousarray(np.empty((0, 0, 2)) if homography else M, np.float32)
            usable = np.ascontiguousarray(good(s, frame))

            def offer(rows):  # run at once: this candidate's arrays
                _keep_nearest(H, moved, frame, usable, distance, value, rows.start, rows.stop)

            each_strip(offer, frames.shape, threads=threads)
        known = np.isfinite(distance[-1])
        x[t] = np.where(known, value.mean(axis=0), 0.0)
        valid[t] = known & good(t, frames[t])
    return x, valid


def _candidates(t: int, n_frames: int) -> list[int]:
    """The other frames nearest ``t`` in the burst's order, at most :data:`CANDIDATES`."""
    others = sorted((s for s in range(n_frames) if s != t), key=lambda s: (abs(s - t), s))
    return others[:CANDIDATES]


@compiled(fastmath=False)  # IEEE order: the same ranking on every machine
def _keep_nearest(H, moved, frame, good, distance, value, first, last):
    """Offer the readings of another ``frame`` to the ascending lists ``distance`` (squared, from
    each pixel's position there to the photosite nearest it) and ``value`` ``(NEAREST, h, w)``, in
    place, in the rows ``first`` to ``last`` (excluded): at each pixel, that photosite's reading
    where it is ``good`` and not the pixel itself. The positions are ``moved`` ``(h, w, 2)``, or
    where that is empty, the homography ``H`` of each pixel ``(x, y)``."""
    nearest, h, w = distance.shape
    fh, fw = frame.shape
    mapped = moved.shape[0] > 0
    for i in range(first, last):
        den, nx, ny = H[2, 1] * i + H[2, 2], H[0, 1] * i + H[0, 2], H[1, 1] * i + H[1, 2]
        for j in range(w):
            if mapped:
                px, py = moved[i, j, 0], moved[i, j, 1]
            else:
                q = 1.0 / (den + H[2, 0] * j)
                px, py = (nx + H[0, 0] * j) * q, (ny + H[1, 0] * j) * q
            if not (-0.5 <= px < fw - 0.5 and -0.5 <= py < fh - 0.5):  # (and not NaN)
                continue
            c, r = int(px + 0.5), int(py + 0.5)  # (non-negative: truncation is the floor)
            if (c == j and r == i) or not good[r, c]:
                continue
            d = np.float32((px - c) ** 2 + (py - r) ** 2)
            if not d < distance[nearest - 1, i, j]:
                continue
            k = nearest - 1
            while k > 0 and d < distance[k - 1, i, j]:  # the farther ones move down a place
                distance[k, i, j] = distance[k - 1, i, j]
                value[k, i, j] = value[k - 1, i, j]
                k -= 1
            distance[k, i, j] = d
            value[k, i, j] = frame[r, c]


def ring_median(values: np.ndarray, known: np.ndarray, at: tuple[np.ndarray, np.ndarray]):
    """Median of the ``known`` neighbours among the 8 of each pixel ``at`` (row and column
    indices; NaN where none is known), and their count."""
    padded = np.pad(np.where(known, values, np.nan), 1, mode="constant", constant_values=np.nan)
    rows, columns = at[0] + 1, at[1] + 1
    ring = np.stack([padded[rows + dy, columns + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
    return nan_median(ring), np.isfinite(ring).sum(axis=0)
