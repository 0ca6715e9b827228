"""The ``gainfpn`` command line: parse, load, call one pipeline function, report.

User errors (:class:`GainFPNError`) exit 1 with one line; usage errors exit 2
(click); Ctrl-C exits 130 and SIGTERM 143, after the outputs being staged are
removed; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import os
import signal
from pathlib import Path

import click

from . import __version__
from .errors import GainFPNError


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is so that staged outputs are cleaned up."""


def _raise_terminated(signum, frame):
    raise _Terminated


_UNCHANGED = object()


class _Group(click.Group):
    def invoke(self, ctx: click.Context):
        try:
            previous = signal.signal(signal.SIGTERM, _raise_terminated)
        except ValueError:  # not the main thread: signals stay as they are
            previous = _UNCHANGED
        try:
            return super().invoke(ctx)
        except GainFPNError as exc:
            raise click.ClickException(str(exc)) from None
        except KeyboardInterrupt as exc:
            name = "terminated" if isinstance(exc, _Terminated) else "interrupted"
            click.echo(f"Error: {name}; nothing was written (partial outputs removed)", err=True)
            ctx.exit(143 if isinstance(exc, _Terminated) else 130)
        finally:
            if previous is not _UNCHANGED:
                signal.signal(signal.SIGTERM, previous)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="gainfpn")
def main() -> None:
    """Measure and remove gain fixed pattern noise (PRNU) from a moving burst.

    Lim & El Gamal's method: track the scene through a hand-held burst and
    choose per-pixel gains so that corrected brightness stays constant along
    each motion trajectory.
    """
    # BLAS single-threaded (before NumPy loads it): a threaded dot product sums in an order that depends on
    # the thread count, so an in-process solve would differ in the last bits from one in a worker process
    # or on a Dask worker (measured: 78 pixels' confidence off by 1 ulp at 320x240). OpenCV's own threads
    # change no result and stay on.
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _parse_size(ctx, param, value: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"must be WIDTHxHEIGHT such as 320x240, got {value!r}") from None
    if w < 22 or h < 22:
        raise click.BadParameter(f"must be at least 22x22 (LibRaw's smallest), got {value}")
    return h, w


def _parse_scene(ctx, param, value):
    from .simulate import SCENES

    if value in SCENES:
        return value
    path = Path(value)
    if not path.is_file():
        raise click.BadParameter(f"{value!r} is neither a built-in scene ({', '.join(SCENES)}) nor an image file")
    return path


@main.command()
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--preset", type=click.Choice(["paper", "raw12"]), default="paper", show_default=True,
              help="Sensor: the paper's 8-bit sensor, or a 12-bit RGGB camera.")
@click.option("--frames", "n_frames", type=click.IntRange(1, 1024), default=8, show_default=True)
@click.option("--size", default="320x240", show_default=True, callback=_parse_size, help="WIDTHxHEIGHT in pixels.")
@click.option("--format", "fmt", type=click.Choice(["exr", "dng"]), default=None,
              help="Frame files [default: exr for paper, dng for raw12].")
@click.option("--seed", type=click.IntRange(0), default=0, show_default=True)
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
@click.option("--overwrite", is_flag=True, help="Replace the results in a non-empty OUT_DIR.")
def simulate(out_dir, preset, n_frames, size, fmt, seed, scene, fpn_pixel, fpn_column, fpn_row, read_noise, bits,
             black, cfa, shake, rotation, drift, wobble, distortion, moving_object, parallax, exposure, exposure_jitter,
             overwrite):
    """Write a synthetic burst with known gains and motion into OUT_DIR."""
    import dataclasses

    from .pipeline import simulate_to
    from .simulate import PRESETS, Shake, with_overrides

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
    paths = simulate_to(out_dir, fmt=fmt, overwrite=overwrite, scene=scene, parameters=parameters, shape=size,
                        n_frames=n_frames, sensor=sensor, shake=motion, exposure=exposure, seed=seed,
                        moving_object=moving_object, parallax=parallax, exposure_jitter=exposure_jitter)
    click.echo(f"wrote {len(paths)} {fmt.upper()} frames ({size[1]}x{size[0]}) and truth/ to {out_dir}")


def _tqdm_progress(quiet: bool):
    """The pipeline's progress hook, drawn with tqdm on stderr (nothing with --quiet)."""
    if quiet:
        return None
    from tqdm import tqdm

    bars = []

    def stage(name: str, total: int):
        for old in bars:  # one stage at a time
            old.close()
        bar = tqdm(total=total or None, desc=f"{name:>10}", unit="step", leave=False, dynamic_ncols=True)
        bars.append(bar)
        return bar.update

    stage.bars = bars
    return stage


def _close(progress) -> None:
    for bar in getattr(progress, "bars", []):
        bar.close()


@main.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output directory.")
@click.option("-c", "--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="YAML config (see configs/default.yaml).")
@click.option("--preset", type=click.Choice(["fast", "balanced", "accurate"]), help="Speed/accuracy preset.")
@click.option("--method", type=click.Choice(["accurate", "paper"]), help="Solver method.")
@click.option("--workers", type=click.IntRange(1), help="Solver processes.")
@click.option("--block-size", type=click.IntRange(1), help="Paper method: block side, px.")
@click.option("--lam", type=click.FloatRange(0), help="Ridge weight lambda.")
@click.option("--reference", type=click.IntRange(0), help="Index of the reference frame.")
@click.option("--dark", type=click.Path(exists=True, dir_okay=False), help="Master dark frame to subtract.")
@click.option("--overwrite", is_flag=True, help="Replace the results in a non-empty output directory.")
@click.option("--scheduler", metavar="ADDRESS",
              help="Solve the blocks on this Dask cluster (e.g. tcp://host:8786) instead of local processes.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
def estimate(inputs, out_dir, config_path, preset, method, workers, block_size, lam, reference, dark, overwrite,
             scheduler, quiet):
    """Estimate the gain map k from a moving burst and correct its frames.

    INPUTS are EXR or RAW files, directories or glob patterns. Writes
    gain_map.exr, corrected/, report.json, config.used.yaml and preview.png
    into OUT. Exit status: 0 on success (also when the hold-out check rejects
    the estimate and k = 1 is written, with a warning), 1 on a user error.
    """
    from .config import load_config
    from .io import check_out_dir
    from .pipeline import estimate as run_estimate
    from .pipeline import exposure_spread_percent, load_burst, write_estimate

    cfg = load_config(config_path, preset=preset, overrides={
        "solver.method": method, "solver.workers": workers, "solver.block_size": block_size, "solver.lam": lam,
        "input.reference": reference, "input.dark": dark})
    check_out_dir(out_dir, overwrite)
    progress = _tqdm_progress(quiet)
    with contextlib.ExitStack() as stack:
        if scheduler:
            from .batch import connect
            from .parallel import dask_backend

            client = stack.enter_context(connect(scheduler))
            stack.enter_context(dask_backend(client))
        try:
            burst = load_burst(inputs, cfg, progress=progress)
            result = run_estimate(burst, cfg, progress=progress)
            write_estimate(result, burst, cfg, out_dir, overwrite=overwrite, progress=progress)
        finally:
            _close(progress)
    for warning in result.warnings:
        click.echo(f"Warning: {warning}", err=True)
    r = result.report
    models = sorted({p.get("fpn_model", p["method"]) for p in r["planes"].values()})
    predicted = r["predicted_residual_fpn_percent"]
    spread = exposure_spread_percent(r)
    click.echo(f"{len(burst.paths)} frames, motion {r['motion']['model']}, FPN model {'/'.join(models)}, "
               f"{100 * r['estimated_fraction']:.0f}% of pixels estimated"
               + (f", predicted residual FPN {predicted:.2f}%" if predicted is not None else "")
               + (f", exposures differ by up to {spread:.1f}% (divided out)" if spread > 0 else "")
               + f" -> {out_dir}")


@main.command()
@click.argument("manifest", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output directory: one folder per burst, and summary.csv / summary.json.")
@click.option("--scheduler", metavar="ADDRESS", help="Run the bursts on this Dask cluster (tcp://host:8786).")
@click.option("--local-cluster", "local_workers", type=click.IntRange(1), metavar="N",
              help="Run the bursts on a Dask cluster of N local processes.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
def batch(manifest, out_dir, scheduler, local_workers, quiet):
    """Estimate every burst of MANIFEST, each into OUT/NAME, and summarise them.

    MANIFEST is YAML: `bursts:` a list of `{name: NAME, inputs: PATH_OR_GLOB,
    config: OPTIONAL_YAML}` (paths relative to the manifest). Bursts already
    done in OUT are skipped, so an interrupted batch is resumed by running
    it again. A failing burst is reported and does not stop the others.
    Without --scheduler or --local-cluster the bursts run here, one after
    another. Exit status: 0 if every burst is done, 1 if any failed.
    """
    from .batch import connect, load_manifest, local_cluster, run_batch

    if scheduler and local_workers:
        raise click.UsageError("give --scheduler or --local-cluster, not both")
    jobs = load_manifest(manifest)
    bar = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="bursts", unit="burst", leave=False, dynamic_ncols=True)
    with contextlib.ExitStack() as stack:
        client = None
        if scheduler:
            client = stack.enter_context(connect(scheduler))
        elif local_workers:
            client = local_cluster(local_workers)
            stack.callback(client.cluster.close)  # after the client (last in, first out)
            stack.enter_context(client)
        try:
            rows = run_batch(jobs, out_dir, client=client, progress=(lambda _: bar.update(1)) if bar else None)
        finally:
            if bar:
                bar.close()
    failed = [r for r in rows if r["status"] == "failed"]
    for row in failed:
        click.echo(f"Error: {row['name']}: {row['message']}", err=True)
    done = len(rows) - len(failed)
    click.echo(f"{done} of {len(rows)} bursts done ({sum(r['status'] == 'done earlier' for r in rows)} earlier), "
               f"{len(failed)} failed -> {out_dir / 'summary.csv'}")
    if failed:
        raise SystemExit(1)


@main.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("--gain-map", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="gain_map.exr written by `gainfpn estimate`.")
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--overwrite", is_flag=True, help="Replace the results in a non-empty output directory.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
def apply(inputs, gain_map, out_dir, overwrite, quiet):
    """Correct other captures (INPUTS) with a stored gain map."""
    from .pipeline import apply_gain_map

    progress = _tqdm_progress(quiet)
    try:
        count = apply_gain_map(gain_map, inputs, out_dir, overwrite=overwrite, progress=progress)
    finally:
        _close(progress)
    click.echo(f"corrected {count} frames -> {out_dir}")


@main.command()
@click.argument("out_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--truth", "sim_dir", required=True, type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Directory written by `gainfpn simulate`.")
def evaluate(out_dir, sim_dir):
    """Score an estimate against a simulation's truth (residual FPN, paper's MSE).

    Prints a table and writes OUT_DIR/evaluation.json.
    """
    import json

    from .io import write_text
    from .pipeline import evaluate as run_evaluate

    scores = run_evaluate(out_dir, sim_dir)
    write_text(out_dir / "evaluation.json", json.dumps(scores, indent=1))
    ratio = scores["mse_before"] / scores["mse_after"] if scores["mse_after"] > 0 else float("inf")
    click.echo(f"{'':24}{'before':>10}{'after':>10}")
    click.echo(f"{'gain FPN (%)':24}{scores['input_fpn_percent']:>10.2f}{scores['residual_fpn_percent']:>10.2f}")
    click.echo(f"{'MSE frame 0 (DN^2)':24}{scores['mse_before']:>10.2f}{scores['mse_after']:>10.2f}")
    click.echo(f"MSE reduction {ratio:.1f}x (temporal-noise floor {scores['mse_floor']:.2f} DN^2), "
               f"{100 * scores['estimated_fraction']:.0f}% of pixels estimated")
    if scores.get("residual_bound_percent") is not None:
        click.echo(f"no estimate from {scores['bound_frames']} frames of this sensor can leave less than "
                   f"{scores['residual_bound_percent']:.2f} % gain FPN on average (Cramer-Rao bound)")


@main.command()
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory for results.json, results.md and the plots.")
@click.option("--quick", is_flag=True, help="A small set of points (about a minute): the CI smoke run.")
@click.option("--group", "groups", multiple=True, metavar="NAME",
              help="Only this group of points (repeatable), e.g. motion_model, preset, scaling_pixels.")
@click.option("--overwrite", is_flag=True, help="Replace the results in a non-empty OUT.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def bench(out_dir, quick, groups, overwrite, quiet):
    """Measure accuracy against time and memory on simulated bursts.

    Presets, knob sweeps, the paper's published form, a flat-field
    calibration and the noise floor, scaling, parallel efficiency and
    flow-error sensitivity (see gainfpn_cli/bench.py). Plots need
    matplotlib (pip install 'gainfpn[bench]').
    """
    from .bench import plan, run
    from .io import check_out_dir, staged_directory

    try:
        points = plan(quick, groups)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--group") from None
    check_out_dir(out_dir, overwrite)
    bar = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(total=len(points), desc="bench", unit="point", leave=False, dynamic_ncols=True)
    try:
        with staged_directory(out_dir) as tmp:
            run(tmp, quick=quick, groups=groups, progress=bar.update if bar else None)
    finally:
        if bar:
            bar.close()
    click.echo((out_dir / "results.md").read_text())
    click.echo(f"results in {out_dir}/: results.md, results.json and plots (*.png)")
