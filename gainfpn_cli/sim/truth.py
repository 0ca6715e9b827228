"""Simulated bursts on disk: frames plus a ``truth/`` folder.

Layout of a simulation directory::

    frame_000.exr ...            (or frame_000.dng ...)
    truth/gain.exr               channel Y: the true gain a
    truth/ideal.exr              channel Y: noise-free, FPN-free frame 0, DN after black
    truth/homographies.json      H_t_ref per frame, and the conventions
    truth/defects.exr            channel defect: defective photosites by kind (solve.defects.KINDS), with --defects
    truth/simulation.json        every parameter needed to make the burst again (and the exposures drawn)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from .. import __version__
from ..errors import InputError
from ..files import ATTR_CFA, ATTR_SATURATION, read_exr_planes, write_exr, write_text
from ..outdir import OutputPlan, prepare, staged
from .dng import write_dng
from .scenes import read_scene
from .sensor import Sensor
from .simulate import Burst, simulate_burst

FORMATS = ("exr", "dng")


def check_format(sensor: Sensor, fmt: str) -> None:
    """Raise :class:`InputError` if frames of ``sensor`` cannot be stored as ``fmt``."""
    if fmt not in FORMATS:
        raise ValueError(f"fmt must be one of {FORMATS}, got {fmt!r}")
    if fmt == "dng" and sensor.cfa is None:
        raise InputError("DNG output needs a colour filter array (give --cfa, e.g. RGGB)")
    if fmt == "dng" and sensor.adc_bits not in (8, 10, 12, 16):
        raise InputError(f"DNG output supports 8, 10, 12 or 16-bit data, not {sensor.adc_bits}-bit")


def save_burst(
    burst: Burst,
    out_dir: str | Path,
    *,
    fmt: str = "exr",
    parameters: Mapping[str, Any] | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[Path]:
    """Write a burst's frames and truth into ``out_dir``; return the frame paths.

    EXR frames hold float32 DN after black level, with the saturation level
    and CFA layout as header attributes; DNG frames hold the raw counts with
    black and white levels in their tags.
    """
    sensor = burst.sensor
    check_format(sensor, fmt)
    out_dir = Path(out_dir)
    truth_dir = out_dir / "truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for t, counts in enumerate(burst.frames):
        path = out_dir / f"frame_{t:03d}.{fmt}"
        if fmt == "dng":
            write_dng(path, counts, bits=sensor.adc_bits, cfa=sensor.cfa, black=[sensor.black_level] * 4,
                      white=sensor.white_level)
        else:
            metadata: dict[str, Any] = {ATTR_SATURATION: float(burst.saturation), "gainfpn:version": __version__}
            if sensor.cfa:
                metadata[ATTR_CFA] = sensor.cfa
            write_exr(path, {"Y": counts.astype(np.float32) - sensor.black_level}, metadata=metadata)
        paths.append(path)
        if progress:
            progress(1)
    write_exr(truth_dir / "gain.exr", {"Y": burst.gain})
    write_exr(truth_dir / "ideal.exr", {"Y": burst.ideal[0]})
    if burst.defects is not None:
        write_exr(truth_dir / "defects.exr", {"defect": burst.defects.astype(np.float32)})
    write_text(
        truth_dir / "homographies.json",
        json.dumps(
            {
                "convention": "H_t_ref maps reference-frame (frame 0) pixel (x, y) to frame t; pixel centres at integers",
                "H_t_ref": burst.homographies.tolist(),
            },
            indent=1,
        ),
    )
    drawn = {} if burst.exposures is None else {"exposures": burst.exposures.tolist()}  # relative to frame 0
    write_text(truth_dir / "simulation.json", json.dumps({"version": __version__, **(parameters or {}), **drawn},
                                                         indent=1))
    return paths


@dataclass(frozen=True)
class Truth:
    """What a simulation directory knows: the true gain, ideal frame 0, motion, and the defective
    photosites by kind (None if it has none)."""

    gain: np.ndarray
    ideal: np.ndarray
    homographies: np.ndarray
    parameters: dict
    defects: np.ndarray | None = None


def load_truth(sim_dir: str | Path) -> Truth:
    """Read ``sim_dir/truth``; raise :class:`InputError` when it is incomplete."""
    truth_dir = Path(sim_dir) / "truth"
    if not truth_dir.is_dir():
        raise InputError(f"{sim_dir}: no truth/ folder (is this a directory written by `gainfpn simulate`?)")
    gain, _ = read_exr_planes(truth_dir / "gain.exr")
    ideal, _ = read_exr_planes(truth_dir / "ideal.exr")
    try:
        motion = json.loads((truth_dir / "homographies.json").read_text(encoding="utf-8"))
        parameters = json.loads((truth_dir / "simulation.json").read_text(encoding="utf-8"))
        homographies = np.asarray(motion["H_t_ref"], dtype=np.float64)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"{truth_dir}: unreadable truth ({exc})") from None
    defects = None
    if (truth_dir / "defects.exr").exists():
        defects = read_exr_planes(truth_dir / "defects.exr")[0]["defect"].astype(np.uint8)
    return Truth(gain=gain["Y"], ideal=ideal["Y"], homographies=homographies, parameters=parameters, defects=defects)


def hot_offset_z(burst: Burst, sensor: Sensor, where: np.ndarray, scene_error: np.ndarray | None = None) -> np.ndarray:
    """How plainly the burst shows each photosite ``where``'s offset: the mean of its readings
    minus the truth ``a x_t`` over the offset's standard error with the scene known (``y_t = a x_t
    + b``, shot, read and rounding noise; the gain ``a`` unknown with the sensor's pixel FPN as
    prior, ``N(1, fpn^2)``). Along a flat trajectory this is the offset over (level x FPN): an
    offset there reads as a gain; a trajectory across an edge tells them apart. At z >= 6 a
    detector that knew the scene would find 98 % of the hot photosites above a threshold that
    flags 1e-4 of the healthy ones. ``scene_error`` ``(F, H, W)``: the scene known only to within it
    (each reading's variance raised by the square of its gain times it there)."""
    x = burst.ideal[:, where].astype(np.float64)  # the reading a gain of 1 gives, DN
    a = burst.gain[where].astype(np.float64)
    var = (a * x / sensor.dn_per_e + sensor.read_noise_e**2) * sensor.dn_per_e**2 + 1 / 12.0
    if scene_error is not None:
        var += (a * scene_error[:, where].astype(np.float64)) ** 2
    offset = np.mean(burst.frames[:, where].astype(np.float64) - sensor.black_level - a * x, axis=0)
    w = 1 / var
    xx, xb, bb = (w * x * x).sum(0) + 1 / sensor.fpn_pixel**2, (w * x).sum(0), w.sum(0)
    return offset / np.sqrt(xx / (xx * bb - xb**2))


def response_z(burst: Burst, sensor: Sensor, where: np.ndarray) -> np.ndarray:
    """How plainly each photosite ``where``'s readings differ from a healthy one's with the scene
    known: the square root of their chi-square about the best healthy response ``a x_t`` (shot,
    read and rounding noise; the gain ``a`` with the sensor's pixel FPN as prior, ``N(1, fpn^2)``).
    A healthy photosite's is about ``sqrt(T)`` for ``T`` frames; a dead or stuck one's is small
    where the scene along its trajectory is near black or near its stuck reading. At 8 frames a
    detector that knew the scene and flagged 1e-4 of the healthy photosites would flag those above
    5.6 (chi-square's 1 - 1e-4 quantile with 8 degrees of freedom, 31.8)."""
    x = burst.ideal[:, where].astype(np.float64)
    y = burst.frames[:, where].astype(np.float64) - sensor.black_level
    w = 1 / ((x / sensor.dn_per_e + sensor.read_noise_e**2) * sensor.dn_per_e**2 + 1 / 12.0)
    prior = 1 / sensor.fpn_pixel**2
    a = ((w * x * y).sum(0) + prior) / ((w * x * x).sum(0) + prior)
    return np.sqrt((w * (y - a * x) ** 2).sum(0) + prior * (a - 1) ** 2)


def residual_bound_percent(truth: Truth, mask: np.ndarray, n_frames: int) -> float | None:
    """The residual gain FPN (percent, as :func:`metrics.residual_fpn_percent`) below which no
    estimate from ``n_frames`` frames of this simulation can go on average over ``mask``:
    :func:`metrics.gain_bound` with the simulated sensor's noise and its pixel FPN as the prior,
    every frame as bright as the ideal frame 0. None if the parameters do not give the sensor."""
    from ..metrics import gain_bound, mixture_spread

    try:
        sensor = Sensor(**truth.parameters["sensor"])
    except (KeyError, TypeError):
        return None
    sigma = gain_bound(truth.ideal[mask] / sensor.dn_per_e, n_frames=n_frames, read_noise_e=sensor.read_noise_e,
                       dn_per_e=sensor.dn_per_e, shot_noise=sensor.shot_noise, prior=sensor.fpn_pixel)
    return 100.0 * mixture_spread(sigma)


def simulate_to(out_dir: Path, *, fmt: str, overwrite: bool = False, scene: str | Path = "procedural",
                parameters: dict | None = None, **burst_options) -> tuple[list[Path], OutputPlan]:
    """Simulate a burst (see :func:`sim.simulate.simulate_burst`) and save it, all or nothing; return the
    frames written and the output plan.

    ``scene`` is a built-in scene's name or the path of an image.
    """
    check_format(burst_options["sensor"], fmt)
    names = [f"frame_{t:03d}.{fmt}" for t in range(burst_options["n_frames"])] + ["truth"]
    plan = prepare(out_dir, command="simulate", names=names, inputs=[scene] if isinstance(scene, Path) else [],
                   overwrite=overwrite)
    if isinstance(scene, Path):
        scene = read_scene(scene)
    burst = simulate_burst(scene=scene, **burst_options)
    with staged(plan) as tmp:
        paths = save_burst(burst, tmp, fmt=fmt, parameters=parameters)
    return [out_dir / p.relative_to(tmp) for p in paths], plan
