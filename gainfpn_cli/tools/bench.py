"""``gainfpn bench``: the speed/accuracy trade, measured on simulated bursts.

Every point runs the real pipeline (read, motion, solve, write) on a burst
with known truth, in a fresh process so that its peak memory is its own
(the solver's worker processes included). Points that isolate the solver
(flow-error sensitivity, parallel efficiency) call it directly with the true
motion. Reference points in the same run: the paper's published
configuration, a flat-field calibration from as many uniformly lit frames,
and the temporal-noise floor (the true gains).
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import platform
import resource
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: The sensor of every bench burst (docs/method.md section 4).
SENSOR = "paper"


#: The hand-held motions of issue 4's accuracy target: the default shake, a 4 px shake with 0.5 degree
#: rotations, and a 25 px drift.
MOTIONS = {"shake": {}, "4 px shake": {"translation_px": 2.5, "rotation_deg": 0.5},
           "25 px drift": {"translation_px": 1.0, "rotation_deg": 0.2, "drift_px": 25.0}}
#: Bursts each motion-accuracy point of the plan scores.
MOTION_SEEDS = 8
#: Issue 4's target: RMS trajectory error (px) over the frame's background, in every frame.
MOTION_TARGET_PX = 0.05


@dataclass(frozen=True)
class BurstSpec:
    """A simulated burst: enough to make it again."""

    shape: tuple[int, int] = (240, 320)
    n_frames: int = 8
    seed: int = 1
    scene: str = "dead-leaves"
    fpn_column: float = 0.0
    supersample: int = 4
    wobble_px: float = 0.0
    distortion_px: float = 0.0
    parallax: float = 0.0  # a nearer plane over 10 % of the frame, displaced 1 + parallax times as far
    exposure_jitter: float = 0.0  # sigma of the log of each frame's exposure relative to the first
    moving_object: float = 0.0  # a disk over this fraction of the frame, moving on its own
    motion: str = "shake"  # a key of MOTIONS
    sensor: str = SENSOR  # a simulate.PRESETS name; one with a CFA is written as DNG

    @property
    def key(self) -> str:
        h, w = self.shape
        waves = f"-w{self.wobble_px:g}-d{self.distortion_px:g}" if self.wobble_px or self.distortion_px else ""
        near = f"-p{self.parallax:g}" if self.parallax else ""
        sensor = "" if self.sensor == SENSOR else f"-{self.sensor}"
        jitter = f"-e{self.exposure_jitter:g}" if self.exposure_jitter else ""
        mover = f"-o{self.moving_object:g}" if self.moving_object else ""
        motion = "" if self.motion == "shake" else f"-{self.motion}"
        return (f"{w}x{h}-f{self.n_frames}-s{self.seed}-{self.scene}-c{self.fpn_column:g}-ss{self.supersample}"
                f"{waves}{near}{jitter}{mover}{motion}{sensor}")

    @property
    def megapixels(self) -> float:
        return self.shape[0] * self.shape[1] / 1e6


@dataclass(frozen=True)
class Point:
    """One measurement: ``kind`` is pipeline, flat-field, floor, flow-error, workers or motion."""

    group: str
    label: str
    burst: BurstSpec
    kind: str = "pipeline"
    preset: str | None = None
    overrides: dict = field(default_factory=dict)
    flow_error_px: float = 0.0
    seeds: int = 1  # a motion point scores this many bursts, seeds burst.seed, burst.seed + 1, ...


def plan(quick: bool, groups: tuple[str, ...] = ()) -> list[Point]:
    """The points of a quick (CI smoke, about a minute) or full run; only those of ``groups`` if given."""
    points = _all_points(quick)
    if not groups:
        return points
    known = list(dict.fromkeys(p.group for p in points))
    unknown = sorted(set(groups) - set(known))
    if unknown:
        raise ValueError(f"unknown bench group(s) {', '.join(unknown)}; the groups are {', '.join(known)}")
    return [p for p in points if p.group in groups]


def _all_points(quick: bool) -> list[Point]:
    # dead leaves: the photograph-like scene on which the published form gives its published ratio
    base = BurstSpec(shape=(120, 160), scene="dead-leaves") if quick else BurstSpec(shape=(480, 640), scene="dead-leaves")
    points = [Point("reference", "temporal-noise floor (true gains)", base, kind="floor"),
              Point("reference", "flat field, same frame count", base, kind="flat-field"),
              Point("reference", "paper as published (5x5, bilinear)", base, preset="paper")]
    points += [Point("preset", name, base, preset=name) for name in ("fast", "balanced", "accurate")]
    if quick:
        points += [Point("block_size", f"paper, {b}x{b}", base, preset="paper", overrides={"solver.block_size": b})
                   for b in (3, 9)]
        points += [Point("flow_error", f"{e} px", base, kind="flow-error", flow_error_px=e) for e in (0.0, 0.8)]
        points += [Point("workers", "solver 1 vs 2 workers", base, kind="workers")]
        points += [Point("motion_model", "wobble 1 px, auto", dataclasses.replace(base, wobble_px=1.0))]
        points += [Point("motion_accuracy", "shake, 10 % object", dataclasses.replace(
            base, scene="procedural", n_frames=6, seed=3, moving_object=0.1), kind="motion", seeds=MOTION_SEEDS)]
        return points
    points += [Point("block_size", f"paper, {b}x{b}", base, preset="paper", overrides={"solver.block_size": b})
               for b in (1, 3, 9, 17, 33)]
    points += [Point("block_size", "global (accurate, one tile)", base, overrides={"solver.tile": 4096})]
    points += [Point("lambda", f"paper, lam {lam:g}", base, preset="paper", overrides={"solver.lam": lam})
               for lam in (1e-4, 1e-2, 1.0, 10.0)]
    points += [Point("kernel", kernel, base, overrides={"solver.interpolation": kernel})
               for kernel in ("bilinear", "cubic", "lanczos4")]
    points += [Point("frames", "3 frames, no hold-out", dataclasses.replace(base, n_frames=3),
                     overrides={"output.holdout": False})]  # with the hold-out, 3 frames are refused
    points += [Point("frames", f"{n} frames", dataclasses.replace(base, n_frames=n)) for n in (5, 16)]
    points += [Point("motion_model", model, base, overrides={"motion.model": model})
               for model in ("translation", "affine", "homography", "rolling", "mesh")]
    for wave in ("wobble", "distortion"):  # motion no single warp explains: the model choice against a forced warp
        burst = dataclasses.replace(base, **{f"{wave}_px": 1.0})
        points += [Point("motion_model", f"{wave} 1 px, {model}", burst, overrides={"motion.model": model})
                   for model in ("auto", "homography")]
    near = dataclasses.replace(base, parallax=1.0)  # a nearer plane: the layers model against one warp
    points += [Point("motion_model", f"parallax 1.0, {model}", near, overrides={"motion.model": model})
               for model in ("auto", "homography")]
    for motion in MOTIONS:  # issue 4's target, on the smoother scene (fewer corners, more pull from the FPN)
        for mover in (0.0, 0.1):
            burst = dataclasses.replace(base, scene="procedural", n_frames=6, seed=3, motion=motion, moving_object=mover)
            points.append(Point("motion_accuracy", motion + (", 10 % object" if mover else ""), burst, kind="motion",
                                seeds=MOTION_SEEDS))
    jittered = dataclasses.replace(base, exposure_jitter=0.03)  # auto-exposure / flicker: measured and divided out
    points += [Point("exposure", f"3 % exposure jitter, {mode}", jittered, overrides={"input.exposure": mode})
               for mode in ("per-frame", "fixed")]
    points += [Point("refine", "1 refinement round", base, overrides={"motion.refine_rounds": 1})]
    points += [Point("scene", "procedural (smoother)", dataclasses.replace(base, scene="procedural"))]
    points += [Point("scene", "3 % pixel + 4 % column", dataclasses.replace(base, fpn_column=0.04))]
    points += [Point("flow_error", f"{e} px", base, kind="flow-error", flow_error_px=e)
               for e in (0.0, 0.05, 0.1, 0.2, 0.4, 0.8, 1.5)]
    points += [Point("workers", "solver 1 vs 2 workers", dataclasses.replace(base, shape=(1200, 1600)),
                     kind="workers")]
    for mp, shape in ((0.3, (480, 640)), (2, (1200, 1600)), (12, (3000, 4000)), (24, (4240, 5660))):
        for preset in ("fast", "balanced"):
            points.append(Point("scaling_pixels", f"{preset}, {mp} MP", BurstSpec(shape=shape, supersample=2),
                                preset=preset))
    for n in (4, 16, 32):
        points.append(Point("scaling_frames", f"balanced, {n} frames, 2 MP",
                            BurstSpec(shape=(1200, 1600), n_frames=n, supersample=2), preset="balanced"))
    # issue 5's memory target: 12 MP x 16 frames within 4 GiB
    points.append(Point("scaling_frames", "balanced, 16 frames, 12 MP",
                        BurstSpec(shape=(3000, 4000), n_frames=16, supersample=2), preset="balanced"))
    points.append(Point("scaling_frames", "balanced, 16 frames, 12 MP, 12-bit RGGB DNG",
                        BurstSpec(shape=(3000, 4000), n_frames=16, supersample=2, sensor="raw12"), preset="balanced"))
    return points


# ---------------------------------------------------------------------------
# running


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
    from ..sim.sensor import PRESETS, with_overrides

    return with_overrides(PRESETS[spec.sensor], fpn_pixel=0.03 if spec.fpn_column else None,
                          fpn_column=spec.fpn_column or None)


def _make_burst(spec: BurstSpec, folder: Path) -> None:
    from ..sim.truth import save_burst

    burst = _simulate(spec, spec.seed)
    sensor = burst.sensor
    parameters = {**dataclasses.asdict(spec), "sensor_preset": spec.sensor, "sensor": dataclasses.asdict(sensor)}
    save_burst(burst, folder, fmt="dng" if sensor.cfa else "exr", parameters=parameters)


def _simulate(spec: BurstSpec, seed: int):
    """The burst ``spec`` describes, drawn with ``seed`` (a motion point draws several)."""
    from ..sim.motion import Shake
    from ..sim.simulate import simulate_burst

    shake = Shake(wobble_px=spec.wobble_px, distortion_px=spec.distortion_px, **MOTIONS[spec.motion])
    return simulate_burst(shape=spec.shape, n_frames=spec.n_frames, seed=seed, scene=spec.scene,
                          sensor=_sensor(spec), supersample=spec.supersample, shake=shake,
                          moving_object=spec.moving_object or (0.1 if spec.parallax else 0.0),
                          parallax=spec.parallax, exposure_jitter=spec.exposure_jitter)


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
    from ..sim.truth import load_truth

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
    from ..config import load_config
    from ..outputs import write_estimate
    from ..pipeline import estimate, load_burst
    from ..sim.evaluate import evaluate

    cfg = load_config(preset=point.preset, overrides=point.overrides)
    t0 = time.perf_counter()
    burst = load_burst([folder], cfg)
    read_s = time.perf_counter() - t0
    result = estimate(burst, cfg)
    write_estimate(result, burst, cfg, out, overwrite=True)
    total = time.perf_counter() - t0
    holdout = result.report["holdout"] or {}
    if holdout.get("passed") is False:  # the tool wrote k = 1: score what a user gets, no correction
        from ..sim.truth import load_truth

        scores = _scores(np.ones(result.k.shape[:2], np.float32), folder, load_truth(folder))
    else:
        scores = evaluate(out, folder)
    shutil.rmtree(out, ignore_errors=True)
    timings = {"read_s": read_s, **result.report["timings"], "total_s": total}
    return {**scores, "timings": timings, "motion_model": result.report["motion"]["model"],
            "holdout_passed": holdout.get("passed")}


def _scores(k: np.ndarray, folder: Path, truth) -> dict:
    """:func:`sim.evaluate.scores` of a gain map that covers every pixel."""
    from ..files import find_frames, read_frame
    from ..sim.evaluate import scores

    frame0 = read_frame(find_frames([folder])[0]).data[..., 0]
    return scores(np.asarray(k, np.float32), np.ones(frame0.shape, bool), frame0, truth)


def _flat_field_k(spec: BurstSpec) -> np.ndarray:
    """What a lab with a flat-field rig gets from as many frames: uniformly lit, averaged."""
    from ..sim.motion import Shake
    from ..sim.simulate import simulate_burst

    sensor = _sensor(spec)
    flat = simulate_burst(shape=spec.shape, n_frames=spec.n_frames, seed=spec.seed, sensor=sensor, supersample=1,
                          scene=np.full((8, 8), 0.5, np.float32), shake=Shake(translation_px=0, rotation_deg=0))
    mean = flat.frames.astype(np.float64).mean(axis=0) - sensor.black_level
    return (mean.mean() / mean).astype(np.float32)


def _frames(folder: Path) -> tuple[np.ndarray, float]:
    from ..files import find_frames, read_frame

    frames = [read_frame(p) for p in find_frames([folder])]
    return np.stack([f.data[..., 0] for f in frames]), frames[0].info.saturation


def _flow_error(point: Point, folder: Path, truth) -> dict:
    """The accurate solver with the true warps, each frame's shifted by ``flow_error_px`` RMS."""
    from ..solve.accurate import solve_accurate

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
    """The first motion estimate (the default preset's) of ``seeds`` bursts like ``spec``: each
    burst's worst frame, RMS trajectory error (px) over the pixels of the background."""
    from ..motion.estimate import estimate_motion

    worst, seconds = [], 0.0
    for seed in range(spec.seed, spec.seed + seeds):
        burst = _simulate(spec, seed)
        frames = burst.frames.astype(np.float32) - burst.sensor.black_level
        t0 = time.perf_counter()
        motion = estimate_motion(frames)
        seconds += time.perf_counter() - t0
        worst.append(max(background_rms(motion.homographies[t], burst, t) for t in range(1, len(frames))))
    return {"motion_worst_px": worst, "motion_over_target": int(np.sum(np.array(worst) > MOTION_TARGET_PX)),
            "timings": {"motion_s": seconds / seeds}}


def background_rms(H: np.ndarray, burst, t: int) -> float:
    """RMS distance (px) between where ``H`` and the truth put the reference's pixels in frame ``t``, over
    those that see the background there (not the moving object in either frame, and inside frame t)."""
    from ..geometry.warps import apply_homography

    h, w = burst.frames.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w]
    points = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    true = apply_homography(burst.homographies[t], points)
    keep = (true[:, 0] >= 0) & (true[:, 0] <= w - 1) & (true[:, 1] >= 0) & (true[:, 1] <= h - 1)
    if burst.moving is not None:
        col, row = np.clip(np.round(true).astype(int), 0, [w - 1, h - 1]).T
        keep &= ~burst.moving[0].ravel() & ~burst.moving[t][row, col]
    error = apply_homography(H, points[keep]) - true[keep]
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


def _workers(folder: Path) -> dict:
    import cv2

    from ..sim.truth import load_truth
    from ..solve.accurate import solve_accurate

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


# ---------------------------------------------------------------------------
# reporting


def markdown(summary: dict) -> str:
    """The results as a Markdown table, one row per point."""
    m = summary["machine"]
    lines = [f"Measured by `gainfpn bench{' --quick' if summary['quick'] else ''}` in {summary['duration_s']:.0f} s "
             f"on {m['cpus']} CPUs ({m['processor']}, {m['platform']}, Python {m['python']}).", "",
             "| group | point | burst | residual FPN % (bound) | MSE before | MSE after | ratio | time s "
             "(read / motion / solve / write) | peak RSS MB |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in (r for r in summary["points"] if r["kind"] != "motion"):
        b = r["burst"]
        burst = f"{b['shape'][1]}x{b['shape'][0]}x{b['n_frames']}"
        t = r.get("timings", {})
        stages = " / ".join(f"{t[k]:.2f}" for k in ("read_s", "motion_s", "solve_s", "write_s") if k in t)
        total = t.get("total_s", t.get("solve_s"))
        time_text = f"{total:.2f}" + (f" ({stages})" if stages and "total_s" in t else "") if total else ""
        if "parallel_speedup" in r:
            time_text = ", ".join(f"{k} {v:.2f}" for k, v in t["solve_by_workers_s"].items()) + \
                f"; speed-up {r['parallel_speedup']:.2f}x"
        fmt = lambda key, spec: format(r[key], spec) if r.get(key) is not None else ""  # noqa: E731
        bound = f" ({fmt('residual_bound_percent', '.2f')})" if r.get("residual_bound_percent") is not None else ""
        lines.append(f"| {r['group']} | {r['label']} | {burst} | {fmt('residual_fpn_percent', '.2f')}{bound} | "
                     f"{fmt('mse_before', '.2f')} | {fmt('mse_after', '.2f')} | {fmt('mse_ratio', '.1f')} | "
                     f"{time_text} | {r['peak_rss_mb']:.0f} |")
    motion = [r for r in summary["points"] if r["kind"] == "motion"]
    if motion:
        lines += ["", f"Motion accuracy (first estimate, as the default preset's): each burst's worst frame, RMS "
                  f"trajectory error over the background, px; target {MOTION_TARGET_PX} px.", "",
                  "| point | burst | scene | bursts (seeds) | median | max | over target | motion s per burst |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in motion:
            b, worst = r["burst"], np.array(r["motion_worst_px"])
            lines.append(f"| {r['label']} | {b['shape'][1]}x{b['shape'][0]}x{b['n_frames']} | {b['scene']} | "
                         f"{len(worst)} ({b['seed']}-{b['seed'] + len(worst) - 1}) | {np.median(worst):.3f} | "
                         f"{worst.max():.3f} | {r['motion_over_target']} | {r['timings']['motion_s']:.2f} |")
    exponents = {r.get("fitted_time_exponent") for r in summary["points"]} - {None}
    if exponents:
        lines += ["", f"Time grows as (pixels x frames)^{exponents.pop():.2f} (balanced preset, least squares in log-log)."]
    return "\n".join(lines) + "\n"


def plot(summary: dict, out_dir: Path) -> list[Path]:
    """pareto.png, scaling.png and flow_error.png (those whose points were measured)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary["points"]
    written = []
    timed = [r for r in rows if r["kind"] == "pipeline" and r["group"] not in ("scaling_pixels", "scaling_frames")]
    if timed:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for r in timed:
            star = r["group"] in ("preset", "reference")
            ax.scatter(r["timings"]["total_s"], r["residual_fpn_percent"], marker="*" if star else "o",
                       s=120 if star else 30, color="C1" if star else "C0")
            if star:
                ax.annotate(r["label"], (r["timings"]["total_s"], r["residual_fpn_percent"]), fontsize=7,
                            xytext=(4, 4), textcoords="offset points")
        ax.set(xscale="log", xlabel="wall time, end to end (s)", ylabel="residual gain FPN (%)",
               title="accuracy against time (stars: presets and the published form)")
        _plain_log(ax.xaxis)
        for r in rows:  # reference lines, labelled at the left edge (x in axes fraction, y in data)
            if r["kind"] in ("floor", "flat-field"):
                ax.axhline(r["residual_fpn_percent"], color="grey", ls="--", lw=0.8)
                ax.text(0.01, r["residual_fpn_percent"], r["label"], transform=ax.get_yaxis_transform(), fontsize=7,
                        color="grey", va="bottom")
        written.append(_save(fig, out_dir / "pareto.png"))
    scaling = [r for r in rows if r["group"] == "scaling_pixels"]
    if scaling:
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.8))
        for preset in sorted({r["preset"] for r in scaling}):
            sel = [r for r in scaling if r["preset"] == preset]
            a1.plot([r["megapixels"] for r in sel], [r["timings"]["total_s"] for r in sel], "o-", label=preset)
            a2.plot([r["megapixels"] for r in sel], [r["peak_rss_mb"] / 1024 for r in sel], "o-", label=preset)
        a1.set(xscale="log", yscale="log", xlabel="megapixels (8 frames)", ylabel="time (s)")
        a2.set(xscale="log", xlabel="megapixels (8 frames)", ylabel="peak RSS (GiB)")
        for axis in (a1.xaxis, a1.yaxis, a2.xaxis):
            _plain_log(axis)
        a1.legend()
        written.append(_save(fig, out_dir / "scaling.png"))
    flow = [r for r in rows if r["kind"] == "flow-error"]
    if flow:
        fig, ax = plt.subplots(figsize=(6, 3.8))
        ax.plot([r["flow_error_px"] for r in flow], [r["mse_ratio"] for r in flow], "o-")
        ax.axhline(1.0, color="grey", ls="--", lw=0.8)
        ax.set(yscale="log", xlabel="injected motion error, RMS (px)", ylabel="MSE before / after",
               title="flow-error sensitivity (accurate solver, true motion + error)")
        written.append(_save(fig, out_dir / "flow_error.png"))
    return written


def _plain_log(axis) -> None:
    """A log axis labelled 1, 2, 5, 10, ... in plain numbers (the default crowds 3x10^0-style minor labels)."""
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FormatStrFormatter("%g"))
    axis.set_minor_formatter(NullFormatter())


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path
