"""The bench's points: which bursts, which settings, in which groups."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

#: The sensor of every bench burst (docs/method.md section 4).
SENSOR = "paper"


#: The simulator's exposure (scene value 1 = 75 % of the full well: dead leaves average 39 % of full scale).
EXPOSURE = 0.75
#: A dark burst's exposure: dead leaves and the procedural scene average 7-8 % of full scale (issue 21's 5-10 %).
DARK_EXPOSURE = 0.15

#: The hand-held motions the motion accuracy is held to (STILL_PX): the default shake, a 4 px shake with 0.5 degree
#: rotations, and a 25 px drift.
MOTIONS = {"shake": {}, "4 px shake": {"translation_px": 2.5, "rotation_deg": 0.5},
           "25 px drift": {"translation_px": 1.0, "rotation_deg": 0.2, "drift_px": 25.0}}
#: Bursts each motion-accuracy point of the plan scores.
MOTION_SEEDS = 8
#: The motion accuracy asked of every frame: RMS trajectory error (px) over the frame's background.
MOTION_TARGET_PX = 0.05
#: ... and of the warps the scene solver refines against its model (issue 22's target).
REFINED_TARGET_PX = 0.02


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
    exposure: float = EXPOSURE  # a scene value of 1 gives this fraction of the full well
    blur_px: float = 0.0  # sigma of a Gaussian lens blur
    noise: bool = True  # False: no shot or read noise and a 16-bit ADC (the model error alone)

    @property
    def key(self) -> str:
        h, w = self.shape
        waves = f"-w{self.wobble_px:g}-d{self.distortion_px:g}" if self.wobble_px or self.distortion_px else ""
        near = f"-p{self.parallax:g}" if self.parallax else ""
        sensor = "" if self.sensor == SENSOR else f"-{self.sensor}"
        jitter = f"-e{self.exposure_jitter:g}" if self.exposure_jitter else ""
        mover = f"-o{self.moving_object:g}" if self.moving_object else ""
        motion = "" if self.motion == "shake" else f"-{self.motion}"
        light = "" if self.exposure == EXPOSURE else f"-x{self.exposure:g}"
        optics = f"-b{self.blur_px:g}" if self.blur_px else ""
        clean = "" if self.noise else "-clean"
        return (f"{w}x{h}-f{self.n_frames}-s{self.seed}-{self.scene}-c{self.fpn_column:g}-ss{self.supersample}"
                f"{waves}{near}{jitter}{mover}{motion}{light}{sensor}{optics}{clean}")

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
        points += _confidence_points(scenes=("procedural",), sensors=("paper",), exposures=(DARK_EXPOSURE,),
                                     frames=(8,))
        return points
    points += [Point("block_size", f"paper, {b}x{b}", base, preset="paper", overrides={"solver.block_size": b})
               for b in (1, 3, 9, 17, 33)]
    points += [Point("block_size", "global (accurate, one tile)", base,
                     overrides={"solver.method": "accurate", "solver.tile": 4096})]
    points += [Point("lambda", f"paper, lam {lam:g}", base, preset="paper", overrides={"solver.lam": lam})
               for lam in (1e-4, 1e-2, 1.0, 10.0)]
    points += [Point("kernel", kernel, base, overrides={"solver.method": "accurate", "solver.interpolation": kernel})
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
    for motion in MOTIONS:  # on the smoother scene (fewer corners, more pull from the FPN)
        for mover in (0.0, 0.1):
            burst = dataclasses.replace(base, scene="procedural", n_frames=6, seed=3, motion=motion, moving_object=mover)
            points.append(Point("motion_accuracy", motion + (", 10 % object" if mover else ""), burst, kind="motion",
                                seeds=MOTION_SEEDS))
    jittered = dataclasses.replace(base, exposure_jitter=0.03)  # auto-exposure / flicker: measured and divided out
    points += [Point("exposure", f"3 % exposure jitter, {mode}", jittered, overrides={"input.exposure": mode})
               for mode in ("per-frame", "fixed")]
    points += _confidence_points()
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
    points += _scene_model_points(base)
    # the memory a 12 MP x 16 frame burst needs (4 GiB asked), with the scene model too
    big16 = BurstSpec(shape=(3000, 4000), n_frames=16, supersample=2)
    points.append(Point("scaling_frames", "balanced, 16 frames, 12 MP", big16, preset="balanced"))
    points.append(Point("scaling_frames", "balanced, scene solver, 16 frames, 12 MP", big16, preset="balanced",
                        overrides={"solver.method": "scene"}))
    points.append(Point("scaling_frames", "balanced, 16 frames, 12 MP, 12-bit RGGB DNG",
                        BurstSpec(shape=(3000, 4000), n_frames=16, supersample=2, sensor="raw12"), preset="balanced"))
    return points


def _confidence_points(scenes=("dead-leaves", "procedural"), sensors=("paper", "raw12"),
                       exposures=(EXPOSURE, DARK_EXPOSURE), frames=(5, 16)) -> list[Point]:
    """Is the written confidence the error k has? 240x320 bursts (RGGB planes of 120x160: the two-halves
    calibration needs 10 000 pixels a plane), sharp and soft scenes, EXR and DNG, bright and dark."""
    return [Point("confidence", f"{scene}, {sensor}, {'bright' if exposure == EXPOSURE else 'dark'}, {n} frames",
                  BurstSpec(shape=(240, 320), n_frames=n, seed=7, scene=scene, sensor=sensor, exposure=exposure))
            for scene in scenes for sensor in sensors for exposure in exposures for n in frames]


def _scene_model_points(base: BurstSpec) -> list[Point]:
    """The scene solver against the accurate one: dead leaves at 8, 16 and 32 frames, 12-bit RGGB DNG
    bursts of both scenes at 8 and 16, and noise-free bursts (the model error alone) with and without a
    1 px lens blur."""
    bursts = [(f"{n} frames", dataclasses.replace(base, n_frames=n)) for n in (8, 16, 32)]
    bursts += [(f"raw12 {scene}, {n} frames", dataclasses.replace(base, scene=scene, n_frames=n, sensor="raw12"))
               for scene in ("dead-leaves", "procedural") for n in (8, 16)]
    bursts += [(f"noise-free{', 1 px blur' if blur else ''}, {n} frames",
                dataclasses.replace(base, n_frames=n, blur_px=blur, noise=False)) for blur in (0.0, 1.0) for n in (8, 16)]
    return [Point("scene_model", f"{label}, {method}", burst, overrides={"solver.method": method})
            for label, burst in bursts for method in ("accurate", "scene")]
