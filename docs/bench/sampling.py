"""Time the scene solver's sampling products (gainfpn_cli/solve/sampling.py) against the same
operator as scipy's float32 CSR matrix (float64 vectors in and out, as the solver calls both), in
one run:

    python docs/bench/sampling.py

A 288 px tile (a 256 px core and its halo) of 8 frames, each turned by 0.003 rad and shifted by
(1.3, -0.7) px more than the one before, for each support the solver uses (scale 2 of a full
plane: 4 samples a side; of a CFA colour: 3; scale 4: 6, which goes through the CSR product).
Prints the best of 3 runs of 20 products each, in ms, and the largest difference relative to the
largest value; then the scene's smoothness product (scenemodel.add_smoothness) on the 576 px grid of
the 2x scene, best of 3 runs of 20.
"""

from __future__ import annotations

import time

import numpy as np

from gainfpn_cli.solve.sampling import sampling
from gainfpn_cli.solve.scenemodel import add_smoothness


def best_ms(product, repeat: int = 20) -> float:
    product()
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(repeat):
            product()
        runs.append((time.perf_counter() - t0) / repeat * 1e3)
    return min(runs)


def main() -> None:
    rng = np.random.default_rng(0)
    side, n_frames = 288, 8
    ys, xs = np.mgrid[:side, :side].astype(np.float64)
    for scale, aperture in ((2, 1.0), (2, 0.5), (4, 1.0)):
        fine = (scale * side, scale * side)
        points = []
        for t in range(n_frames):
            angle, shift = 0.003 * t, (1.3 * t, -0.7 * t)
            x = np.cos(angle) * xs - np.sin(angle) * ys + shift[0]
            y = np.sin(angle) * xs + np.cos(angle) * ys + shift[1]
            points.append(np.column_stack([x.ravel(), y.ravel()]))
        A, _ = sampling(points, fine, scale, aperture)
        print(f"scale {scale}, aperture {aperture} ({A.wu.shape[1]} samples a side, {A.shape[0]} readings): "
              + compared(A, rng))
    fine = (2 * side, 2 * side)
    v, out = rng.standard_normal(fine[0] * fine[1]), np.zeros(fine[0] * fine[1])
    print(f"smoothness on {fine[0]}x{fine[1]}: {best_ms(lambda: add_smoothness(v, fine, 0.5, out)):.2f} ms")


def compared(A, rng) -> str:
    """The compiled products of ``A`` against its CSR matrix's, timed, and their differences."""
    matrix = A.sparse()
    transpose = matrix.T.tocsr()
    v, r = rng.standard_normal(A.shape[1]), rng.standard_normal(A.shape[0])

    def csr_forward():
        return (matrix @ v.astype(np.float32)).astype(np.float64)

    def csr_back():
        return (transpose @ r.astype(np.float32)).astype(np.float64)

    forward_error = np.abs(A.forward(v) - csr_forward()).max() / np.abs(csr_forward()).max()
    back_error = np.abs(A.back(r) - csr_back()).max() / np.abs(csr_back()).max()
    return (f"forward {best_ms(lambda: A.forward(v)):.2f} ms (CSR {best_ms(csr_forward):.2f}), "
            f"back {best_ms(lambda: A.back(r)):.2f} ms (CSR {best_ms(csr_back):.2f}); "
            f"differences {forward_error:.1e} / {back_error:.1e}")

if __name__ == "__main__":
    main()
