"""The commands that make and score simulated bursts: simulate, evaluate, bench."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from . import _parse_scene, _parse_size, json_option, main, overwrite_option, print_json, quiet_option, say, untouched


@main.command()
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--preset", type=click.Choice(["paper", "raw12"]), default="paper", show_default=True,
              help="Sensor: the paper's 8-bit sensor, or a 12-bit RGGB camera.")
@click.option("--frames", "n_frames", type=click.IntRange(1, 1024), default=8, help="Frames in the burst.")
@click.option("--size", default="320x240", show_default=True, callback=_parse_size, help="WIDTHxHEIGHT in pixels.")
@click.option("--format", "fmt", type=click.Choice(["exr", "dng"]), default=None,
              help="Frame files [default: exr for paper, dng for raw12].")
@click.option("--seed", type=click.IntRange(0), default=0, help="Seed of every random draw.")
@click.option("--scene", default="procedural", show_default=True, callback=_parse_scene,
              help="Built-in texture (procedural, dead-leaves) or an image file to use as the scene.")
@click.option("--fpn-pixel", type=click.FloatRange(0, 0.5), help="Sigma of the per-pixel gain.")
@click.option("--fpn-column", type=click.FloatRange(0, 0.5), help="Sigma of the per-column gain.")
@click.option("--fpn-row", type=click.FloatRange(0, 0.5), help="Sigma of the even/odd-row gain.")
@click.option("--read-noise", type=click.FloatRange(0), help="Read noise, electrons RMS.")
@click.option("--bits", type=click.IntRange(8, 16), help="ADC bits.")
@click.option("--black", type=click.IntRange(0), help="Black level, DN.")
@click.option("--cfa", type=click.Choice(["none", "RGGB", "BGGR", "GRBG", "GBRG"]), help="Colour filter array.")
@click.option("--shake", type=click.FloatRange(0), default=2.0, show_default=True, help="Sigma of translation, px.")
@click.option("--rotation", type=click.FloatRange(0), default=0.3, show_default=True, help="Sigma of rotation, deg.")
@click.option("--drift", type=click.FloatRange(0), default=0.0, show_default=True, help="Pan over the burst, px.")
@click.option("--wobble", type=click.FloatRange(0), default=0.0, show_default=True,
              help="Sigma of a rolling-shutter wobble's amplitude, px (motion no single warp explains).")
@click.option("--distortion", type=click.FloatRange(0), default=0.0, show_default=True,
              help="Sigma of a smooth 2-D distortion's amplitude, px (a stand-in for parallax).")
@click.option("--moving-object", type=click.FloatRange(0, 0.5), default=0.0, show_default=True,
              help="Fraction of the frame covered by a textured disk that moves on its own.")
@click.option("--parallax", type=click.FloatRange(0), default=0.0, show_default=True,
              help="With --moving-object: the disk is a nearer plane instead, displaced 1 + PARALLAX times as far "
                   "as the background.")
@click.option("--exposure", type=click.FloatRange(0, min_open=True), default=0.75, show_default=True,
              help="Electrons at scene value 1, as a fraction of full well.")
@click.option("--exposure-jitter", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="Sigma of the log of each frame's exposure relative to the first (auto-exposure, flicker).")
@click.option("--blur", type=click.FloatRange(0), default=0.0, show_default=True,
              help="Sigma of a Gaussian lens blur, px (0: none; the pixel's own box integration is always there).")
@click.option("--defects", type=click.FloatRange(0, 0.5), default=0.0, show_default=True,
              help="Fraction of defective photosites: 70 % hot (a dark-current offset of 5-50x their noise), 15 % dead "
                   "(no response), 15 % stuck (one reading in every frame); truth/defects.exr marks them.")
@overwrite_option
@quiet_option
def simulate(out_dir, preset, n_frames, size, fmt, seed, scene, fpn_pixel, fpn_column, fpn_row, read_noise, bits,
             black, cfa, shake, rotation, drift, wobble, distortion, moving_object, parallax, exposure, exposure_jitter,
             blur, defects, overwrite, quiet):
    """Write a synthetic burst with known gains and motion into OUT_DIR."""
    import dataclasses

    from ..sim.motion import Shake
    from ..sim.sensor import PRESETS, with_overrides
    from ..sim.truth import simulate_to

    sensor = with_overrides(PRESETS[preset], fpn_pixel=fpn_pixel, fpn_column=fpn_column, fpn_row=fpn_row,
                            read_noise_e=read_noise, adc_bits=bits, black_level=black)
    if cfa is not None:
        sensor = dataclasses.replace(sensor, cfa=None if cfa == "none" else cfa)
    if sensor.black_level >= sensor.white_level:
        raise click.BadParameter(f"black level {sensor.black_level} leaves no range below {sensor.white_level}",
                                 param_hint="--black")
    fmt = fmt or ("dng" if sensor.cfa else "exr")
    motion = Shake(translation_px=shake, rotation_deg=rotation, drift_px=drift, wobble_px=wobble,
                   distortion_px=distortion)
    if parallax and not moving_object:
        raise click.BadParameter("needs --moving-object: the nearer plane is the disk", param_hint="--parallax")
    parameters = {"seed": seed, "shape": list(size), "n_frames": n_frames, "exposure": exposure,
                  "scene": str(scene), "format": fmt, "moving_object": moving_object, "parallax": parallax,
                  "exposure_jitter": exposure_jitter,
                  "sensor": dataclasses.asdict(sensor), "shake": dataclasses.asdict(motion)}
    if defects:
        parameters["defects"] = defects
    if blur:
        parameters["blur"] = blur
    paths, plan = simulate_to(out_dir, fmt=fmt, overwrite=overwrite, scene=scene, parameters=parameters, shape=size,
                        n_frames=n_frames, sensor=sensor, shake=motion, exposure=exposure, seed=seed,
                        moving_object=moving_object, parallax=parallax, exposure_jitter=exposure_jitter,
                        defects=defects, optics_sigma_px=blur)
    untouched(plan)
    say(quiet, f"wrote {len(paths)} {fmt.upper()} frames ({size[1]}x{size[0]}) and truth/ to {out_dir}")




@main.command()
@click.argument("est_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--truth", "sim_dir", required=True, type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Directory written by `gainfpn simulate`: the burst the estimate was made from.")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Where evaluation.json goes [default: EST_DIR].")
@overwrite_option
@json_option
@quiet_option
def evaluate(est_dir, sim_dir, out_dir, overwrite, as_json, quiet):
    """Score an estimate against a simulation's truth (residual FPN, paper's MSE).

    Prints a table and writes evaluation.json. Refuses a truth that is not the
    estimate's own simulation (size, CFA, bit depth or frames differ).
    """
    import json

    from ..files import write_text
    from ..outdir import prepare, staged
    from ..sim.evaluate import evaluate as run_evaluate

    out_dir = out_dir or est_dir
    scores = run_evaluate(est_dir, sim_dir)  # a truth that is not the estimate's is refused first
    plan = prepare(out_dir, command="evaluate", names=["evaluation.json"], overwrite=overwrite, beside_inputs=True,
                   inputs=[est_dir / "gain_map.exr", est_dir / "report.json", sim_dir])
    with staged(plan) as tmp:
        write_text(tmp / "evaluation.json", json.dumps(scores, indent=1))
    untouched(plan, as_json)
    if as_json:
        print_json({**scores, "evaluation": str((out_dir / "evaluation.json").absolute())})
        return
    if quiet:
        return
    ratio = scores["mse_before"] / scores["mse_after"] if scores["mse_after"] > 0 else float("inf")
    click.echo(f"{'':24}{'before':>10}{'after':>10}")
    click.echo(f"{'gain FPN (%)':24}{scores['input_fpn_percent']:>10.2f}{scores['residual_fpn_percent']:>10.2f}")
    click.echo(f"{'MSE frame 0 (DN^2)':24}{scores['mse_before']:>10.2f}{scores['mse_after']:>10.2f}")
    defects = scores.get("defects")
    if defects:
        found = [f"{kind} {d['true']} ({d['flagged']} coded, {d['given_a_gain']} given a gain)"
                 for kind, d in defects.items() if kind != "healthy_flagged" and d["true"]]
        click.echo("over the photosites the truth calls healthy; defective in the truth: "
                   f"{', '.join(found) or 'none'}; healthy coded defective: {defects['healthy_flagged']}")
    if scores.get("plane_residual_fpn_percent"):
        click.echo("gain FPN after, by CFA plane (%): " + ", ".join(
            f"{name} {value:.2f}" if value is not None else f"{name} not estimated"
            for name, value in scores["plane_residual_fpn_percent"].items()))
    click.echo(f"MSE reduction {ratio:.1f}x (temporal-noise floor {scores['mse_floor']:.2f} DN^2), "
               f"{scores['estimated_percent']:.0f} % of pixels estimated")
    after = scores["frame_mse_after"]
    frame = scores["frame_mse_before"] / after if after > 0 else float("inf")
    if f"{frame:.1f}" != f"{ratio:.1f}":  # the pixels left unestimated change what the frame gets
        click.echo(f"over the whole frame (k = 1 where not estimated): MSE reduction {frame:.1f}x")
    if scores.get("residual_bound_percent") is not None:
        click.echo(f"no estimate from {scores['bound_frames']} frames of this sensor can leave less than "
                   f"{scores['residual_bound_percent']:.2f} % gain FPN on average (Cramer-Rao bound)")
    deciles = scores.get("confidence_deciles")
    if deciles:
        click.echo(f"confidence: k's actual error over the sigma_k it states, by tenths of sigma_k "
                   f"{min(deciles):.2f}-{max(deciles):.2f} (1 is honest)")


@main.command()
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory for results.json, results.md and the plots.")
@click.option("--quick", is_flag=True, help="A small set of points (about a minute): the CI smoke run.")
@click.option("--group", "groups", multiple=True, metavar="NAME",
              help="Only this group of points (repeatable), e.g. motion_model, preset, scaling_pixels.")
@overwrite_option
@quiet_option
def bench(out_dir, quick, groups, overwrite, quiet):
    """Measure accuracy against time and memory on simulated bursts.

    Presets, knob sweeps, the paper's published form, a flat-field
    calibration and the noise floor, scaling, parallel efficiency and
    flow-error sensitivity (see gainfpn_cli/tools/bench).
    """
    from ..outdir import prepare, staged
    from ..tools.bench import OUTPUTS, plan, run

    try:
        points = plan(quick, groups)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--group") from None
    outputs = prepare(out_dir, command="bench", names=OUTPUTS, overwrite=overwrite)
    bar = None
    if not quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=len(points), desc="bench", unit="point", leave=False, dynamic_ncols=True)
    try:
        with staged(outputs) as tmp:
            run(tmp, quick=quick, groups=groups, progress=bar.update if bar else None)
    finally:
        if bar:
            bar.close()
    untouched(outputs)
    if not quiet:
        click.echo((out_dir / "results.md").read_text())
        click.echo(f"results in {out_dir}/: results.md, results.json and plots (*.png)")
