"""Running the bench's points, each in a fresh process so that its peak memory is its own."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import platform
import resource
import shutil
import time
from pathlib import Path

import numpy as np

from .points import MOTION_TARGET_PX, MOTIONS, REFINED_TARGET_PX, BurstSpec, Point, plan
from .report import markdown, plot

#: What ``run`` writes into its folder (``--overwrite`` replaces these names only).
OUTPUTS = ("results.json", "results.md", "pareto.png", "scaling.png", "flow_error.png")


def run(out_dir: Path, *, quick: bool, groups: tuple[str, ...] = (), progress=None) -> list[dict]:
    """Run every point of :func:`plan`; write results.json, results.md and plots into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scratch = out_dir / "scratch"
    started = time.perf_counter()
    points = plan(quick, groups)
    results = []
    try:
        for spec in dict.fromkeys(p.burst for p in points):  # each burst once, in its own process
            _isolated(_make_burst, spec, scratch / spec.key)
            for point in (p for p in points if p.burst == spec):
                results.append(_isolated(_measure, point, scratch))
                if progress:
                    progress(1)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    _add_derived(results)
    summary = {"machine": _machine(), "quick": quick, "groups": list(groups), "duration_s": time.perf_counter() - started, "points": results}
    (out_dir / "results.json").write_text(json.dumps(summary, indent=1))
    (out_dir / "results.md").write_text(markdown(summary))
    plot(summary, out_dir)
    return results


def _sensor(spec: BurstSpec):
    """The bench sensor; with column FPN, 3 % pixel + the column part (docs/method.md section 4's second case)."""
    from ...sim.sensor import PRESETS, with_overrides

    return with_overrides(PRESETS[spec.sensor], fpn_pixel=0.03 if spec.fpn_column else None,
                          fpn_column=spec.fpn_column or None)


def _make_burst(spec: BurstSpec, folder: Path) -> None:
    from ...sim.truth import save_burst

    burst = _simulate(spec, spec.seed)
    sensor = burst.sensor
    parameters = {**dataclasses.asdict(spec), "sensor_preset": spec.sensor, "sensor": dataclasses.asdict(sensor)}
    save_burst(burst, folder, fmt="dng" if sensor.cfa else "exr", parameters=parameters)


def _simulate(spec: BurstSpec, seed: int):
    """The burst ``spec`` describes, drawn with ``seed`` (a motion point draws several)."""
    from ...sim.motion import Shake
    from ...sim.simulate import simulate_burst

    shake = Shake(wobble_px=spec.wobble_px, distortion_px=spec.distortion_px, **MOTIONS[spec.motion])
    sensor = _sensor(spec)
    if not spec.noise:
        sensor = dataclasses.replace(sensor, shot_noise=False, read_noise_e=0.0, adc_bits=16)
    return simulate_burst(shape=spec.shape, n_frames=spec.n_frames, seed=seed, scene=spec.scene,
                          sensor=sensor, supersample=spec.supersample, shake=shake, optics_sigma_px=spec.blur_px,
                          moving_object=spec.moving_object or (0.1 if spec.parallax else 0.0),
                          parallax=spec.parallax, exposure_jitter=spec.exposure_jitter, exposure=spec.exposure)


class _TreePeak:
    """Peak resident memory of this process and its descendants (the solver's workers) together, MB.

    On Linux a thread sums ``VmRSS`` over the process tree every 50 ms, and
    the result is the larger of that and this process's own exact peak.
    ``RUSAGE_CHILDREN`` cannot be used: a spawned worker is forked before it
    execs Python, and its ``ru_maxrss`` keeps the parent's size at the fork
    (measured at 12 MP: 1.2-1.8 GB reported for workers whose RSS never
    exceeded 340 MB). Elsewhere this process's peak plus its largest child's
    is reported, an over-estimate for that reason.
    """

    def __init__(self, interval: float = 0.05):
        import threading

        self._proc = Path("/proc")
        self._stop = threading.Event()
        self._peak_kb = 0
        self._thread = threading.Thread(target=self._sample, args=(interval,), daemon=True)

    def __enter__(self) -> "_TreePeak":
        if self._proc.is_dir():
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def _sample(self, interval: float) -> None:
        while not self._stop.is_set():
            self._peak_kb = max(self._peak_kb, self._tree_kb())
            self._stop.wait(interval)

    def _tree_kb(self) -> int:
        parents, rss = {}, {}
        for status in self._proc.glob("[0-9]*/status"):
            try:
                fields = dict(line.split(":", 1) for line in status.read_text().splitlines() if ":" in line)
                pid = int(status.parent.name)
                parents[pid] = int(fields["PPid"])
                rss[pid] = int(fields.get("VmRSS", "0 kB").split()[0])
            except (OSError, ValueError, KeyError):
                continue
        tree, grown = {os.getpid()}, True
        while grown:
            more = {pid for pid, parent in parents.items() if parent in tree} - tree
            grown = bool(more)
            tree |= more
        return sum(rss.get(pid, 0) for pid in tree)

    @property
    def mb(self) -> float:
        own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        if self._proc.is_dir():
            return max(own, self._peak_kb) / 1024.0
        return (own + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024.0


def _measure(point: Point, scratch: Path) -> dict:
    from ...sim.truth import load_truth

    folder = scratch / point.burst.key
    row = {"group": point.group, "label": point.label, "kind": point.kind, "preset": point.preset,
           "overrides": point.overrides, "burst": dataclasses.asdict(point.burst),
           "megapixels": point.burst.megapixels}
    with _TreePeak() as memory:
        truth = load_truth(folder)
        if point.kind == "pipeline":
            row.update(_pipeline(point, folder, scratch / "out"))
        elif point.kind == "floor":
            row.update(_scores(1.0 / truth.gain, folder, truth))
        elif point.kind == "flat-field":
            row.update(_scores(_flat_field_k(point.burst), folder, truth))
        elif point.kind == "flow-error":
            row.update(_flow_error(point, folder, truth), flow_error_px=point.flow_error_px)
        elif point.kind == "workers":
            row.update(_workers(folder))
        elif point.kind == "motion":
            row.update(_motion_accuracy(point.burst, point.seeds))
    row["peak_rss_mb"] = memory.mb
    return row


def _pipeline(point: Point, folder: Path, out: Path) -> dict:
    from ...api import estimate
    from ...config import load_config
    from ...errors import EstimationError
    from ...sim.evaluate import evaluate

    cfg = load_config(preset=point.preset, overrides=point.overrides)
    t0 = time.perf_counter()
    try:
        result = estimate(folder, config=cfg)  # read, motion, solve, as `gainfpn estimate` runs them
    except EstimationError as exc:  # refused, as `gainfpn estimate` would (a forced model the burst does not follow)
        return {"refused": str(exc)}
    report = result.write(out, overwrite=True).report
    total = time.perf_counter() - t0
    passed = None if report.holdout is None else report.holdout.passed
    if passed is False:  # the tool wrote k = 1: score what a user gets, no correction
        from ...sim.truth import load_truth

        scores = _scores(np.ones(result.k.shape[:2], np.float32), folder, load_truth(folder))
    else:
        scores = evaluate(out, folder)
    shutil.rmtree(out, ignore_errors=True)
    timings = {**report.timings, "total_s": total}
    calibrated = all(plane.confidence_calibrated for plane in report.planes.values())
    return {**scores, "timings": timings, "motion_model": report.motion.model, "holdout_passed": passed,
            "solver": None if report.solver is None else report.solver.method,
            "confidence_calibrated": calibrated}


def _scores(k: np.ndarray, folder: Path, truth) -> dict:
    """:func:`sim.evaluate.scores` of a gain map that covers every pixel."""
    from ...files import find_frames, read_frame
    from ...sim.evaluate import scores

    frame0 = read_frame(find_frames([folder])[0]).data[..., 0]
    return scores(np.asarray(k, np.float32), np.ones(frame0.shape, bool), frame0, truth)


def _flat_field_k(spec: BurstSpec) -> np.ndarray:
    """What a lab with a flat-field rig gets from as many frames: uniformly lit, averaged."""
    from ...sim.motion import Shake
    from ...sim.simulate import simulate_burst

    sensor = _sensor(spec)
    flat = simulate_burst(shape=spec.shape, n_frames=spec.n_frames, seed=spec.seed, sensor=sensor, supersample=1,
                          scene=np.full((8, 8), 0.5, np.float32), shake=Shake(translation_px=0, rotation_deg=0))
    mean = flat.frames.astype(np.float64).mean(axis=0) - sensor.black_level
    return (mean.mean() / mean).astype(np.float32)


def _frames(folder: Path) -> tuple[np.ndarray, float]:
    from ...files import find_frames, read_frame

    frames = [read_frame(p) for p in find_frames([folder])]
    return np.stack([f.data[..., 0] for f in frames]), frames[0].info.saturation


def _flow_error(point: Point, folder: Path, truth) -> dict:
    """The accurate solver with the true warps, each frame's shifted by ``flow_error_px`` RMS."""
    from ...solve.accurate import solve_accurate

    frames, saturation = _frames(folder)
    rng = np.random.default_rng(7)
    H = truth.homographies.copy()
    for t in range(1, len(H)):
        shift = np.eye(3)
        shift[:2, 2] = rng.normal(0.0, point.flow_error_px / np.sqrt(2), 2)
        H[t] = shift @ H[t]
    t0 = time.perf_counter()
    result = solve_accurate(frames, H, saturation=saturation, workers=2)
    row = _scores(result.k, folder, truth)
    row["timings"] = {"solve_s": time.perf_counter() - t0}
    return row


def _motion_accuracy(spec: BurstSpec, seeds: int) -> dict:
    """The first motion estimate (the default preset's) of ``seeds`` bursts like ``spec``, and the
    warps the scene solver refines from it against its model: each burst's worst frame, RMS
    trajectory error (px) over the pixels of the background."""
    from ...motion.estimate import estimate_motion

    worst, refined, seconds, refine_seconds = [], [], 0.0, 0.0
    for seed in range(spec.seed, spec.seed + seeds):
        burst = _simulate(spec, seed)
        frames = burst.frames.astype(np.float32) - burst.sensor.black_level
        t0 = time.perf_counter()
        motion = estimate_motion(frames)
        seconds += time.perf_counter() - t0
        worst.append(max(background_rms(motion.homographies[t], burst, t) for t in range(1, len(frames))))
        t0 = time.perf_counter()
        refined.append(max(refined_rms(frames, motion, burst)[1:]))
        refine_seconds += time.perf_counter() - t0
    return {"motion_worst_px": worst, "motion_over_target": int(np.sum(np.array(worst) > MOTION_TARGET_PX)),
            "refined_worst_px": refined, "refined_over_target": int(np.sum(np.array(refined) > REFINED_TARGET_PX)),
            "timings": {"motion_s": seconds / seeds, "refine_s": refine_seconds / seeds}}


def refined_rms(frames: np.ndarray, motion, burst) -> list[float]:
    """Each frame's RMS trajectory error (px) over the background under the first estimate's
    homographies moved as the scene solver refines ``motion`` against its model (its tiles fitted
    one by one, as a worker fits them, each tile's core scored with its own refinement), relative
    to the first frame's move (the scene's place is free); frame 0's is 0."""
    from ...geometry.resample import positions
    from ...geometry.warps import apply_homography
    from ...solve.scene import SceneOptions, prepare
    from ...solve.scenemodel import fit_tile
    from ...solve.tiling import ramp

    n_frames, h, w = frames.shape
    options = SceneOptions()
    squares, counts = np.zeros(n_frames), np.zeros(n_frames)
    for tile in prepare({"frames": frames, "motion": motion.warp}, options):
        fit = fit_tile(tile)
        th, tw = tile.frames.shape[1:]
        region = (tile.y0, tile.x0, th, tw)
        rows, cols = np.mgrid[:th, :tw]
        core = (ramp((th, tw), (tile.y0, tile.x0), (h, w), options.halo) >= 1).ravel()  # its blend weight 1
        pixels = np.stack([cols.ravel(), rows.ravel()], axis=1)[core].astype(np.float64) + [tile.x0, tile.y0]
        moves = [(fit.points[t] - positions(tile.motion.pair(t, 0, region), (th, tw)).reshape(-1, 2))[core]
                 for t in range(n_frames)]
        for t in range(1, n_frames):
            true = apply_homography(burst.homographies[0] @ np.linalg.inv(burst.homographies[t]), pixels)
            keep = _background(burst, t, true, pixels)
            first = apply_homography(motion.homographies[0] @ np.linalg.inv(motion.homographies[t]), pixels)
            error = first + moves[t] - moves[0] - true
            squares[t] += np.sum(error[keep] ** 2)
            counts[t] += keep.sum()
    return [0.0] + [float(np.sqrt(squares[t] / max(counts[t], 1))) for t in range(1, n_frames)]


def background_rms(H: np.ndarray, burst, t: int) -> float:
    """RMS distance (px) between where ``H`` and the truth put the reference's pixels in frame ``t``, over
    those that see the background there (not the moving object in either frame, and inside frame t)."""
    from ...geometry.warps import apply_homography

    h, w = burst.frames.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w]
    points = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    true = apply_homography(burst.homographies[t], points)
    keep = _background(burst, t, points, true)
    error = apply_homography(H, points[keep]) - true[keep]
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


def _background(burst, t: int, reference: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Which of the point pairs ``reference`` (x, y in the reference) and ``seen`` (where frame ``t``
    sees them) lie inside both frames and on the background in both (not the moving object)."""
    h, w = burst.frames.shape[1:]
    keep = np.ones(len(reference), bool)
    for xy in (reference, seen):
        keep &= (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
    if burst.moving is not None:
        for frame, xy in ((0, reference), (t, seen)):
            col, row = np.clip(np.round(xy).astype(int), 0, [w - 1, h - 1]).T
            keep &= ~burst.moving[frame][row, col]
    return keep


def _workers(folder: Path) -> dict:
    import cv2

    from ...sim.truth import load_truth
    from ...solve.accurate import solve_accurate

    truth = load_truth(folder)
    frames, saturation = _frames(folder)
    times = {}
    threads = cv2.getNumThreads()
    for name, workers, cv_threads in (("1 worker, 1 thread", 1, 1), ("1 worker, OpenCV threads", 1, threads),
                                      ("2 workers", 2, threads)):
        cv2.setNumThreads(cv_threads)  # the workers themselves always run OpenCV single-threaded
        t0 = time.perf_counter()
        solve_accurate(frames, truth.homographies, saturation=saturation, workers=workers)
        times[name] = time.perf_counter() - t0
    cv2.setNumThreads(threads)
    return {"timings": {"solve_by_workers_s": times},
            "parallel_speedup": times["1 worker, 1 thread"] / times["2 workers"]}


def _isolated(fn, *args):
    """``fn(*args)`` in a fresh process, so that its peak memory is its own.

    On an interrupt or SIGTERM the process is terminated at once, and it
    stops its own solver workers first (:func:`_call_and_send`).
    """
    context = multiprocessing.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    process = context.Process(target=_call_and_send, args=(send, fn, args))
    process.start()
    send.close()
    try:
        ok, value = receive.recv()
        process.join()
    except EOFError:
        process.join()
        raise RuntimeError(f"the bench process for {fn.__name__} died (exit status {process.exitcode})") from None
    except BaseException:
        process.terminate()
        process.join()
        raise
    if not ok:
        raise value
    return value


def _call_and_send(send, fn, args) -> None:
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt  # unwinds through parallel.map_ordered, which terminates its workers

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the bench parent terminates this process
    try:
        send.send((True, fn(*args)))
    except KeyboardInterrupt:  # terminated: the parent is already stopping
        pass
    except Exception as exc:
        send.send((False, exc))


def _add_derived(results: list[dict]) -> None:
    for row in results:
        if "mse_after" in row:
            row["mse_ratio"] = row["mse_before"] / max(row["mse_after"], 1e-12)
        if "frame_mse_after" in row:
            row["frame_mse_ratio"] = row["frame_mse_before"] / max(row["frame_mse_after"], 1e-12)
    scaling = [r for r in results if r["group"] == "scaling_pixels" and r.get("preset") == "balanced"]
    if len(scaling) >= 2:
        x = np.log([r["megapixels"] * r["burst"]["n_frames"] for r in scaling])
        y = np.log([r["timings"]["total_s"] for r in scaling])
        exponent = float(np.polyfit(x, y, 1)[0])
        for r in scaling:
            r["fitted_time_exponent"] = exponent


def _machine() -> dict:
    import os

    return {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
            "processor": platform.processor() or platform.machine()}
