"""The ``gainfpn`` command line: parse, load, call one pipeline function, report.

User errors (:class:`GainFPNError`) exit 1 with one line; usage errors exit 2
(click); Ctrl-C exits 130 and SIGTERM 143, after the outputs being staged are
removed; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import signal
import sys
from pathlib import Path

import click

from . import __version__
from .errors import GainFPNError
from .summary import EXIT_REJECTED


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


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "show_default": True})
@click.version_option(__version__, prog_name="gainfpn")
def main() -> None:
    """Measure and remove gain fixed pattern noise (PRNU) from a moving burst.

    Lim & El Gamal's method: track the scene through a hand-held burst and
    choose per-pixel gains so that corrected brightness stays constant along
    each motion trajectory.
    """


def _parse_size(ctx, param, value: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"must be WIDTHxHEIGHT such as 320x240, got {value!r}") from None
    if w < 22 or h < 22:
        raise click.BadParameter(f"must be at least 22x22 (LibRaw's smallest), got {value}")
    return h, w


def _parse_scene(ctx, param, value):
    from .sim.scenes import SCENES

    if value in SCENES:
        return value
    path = Path(value)
    if not path.is_file():
        raise click.BadParameter(f"{value!r} is neither a built-in scene ({', '.join(SCENES)}) nor an image file")
    return path


def _cfg(key: str) -> str:
    """``[default: VALUE from config KEY]`` for a flag that overrides a config key."""
    from .config import Config

    section, name = key.split(".")
    return f"[default: {getattr(getattr(Config(), section), name)} (config {key})]"


#: Presets shipped in configs/ (read from the package, so a new YAML there is a new choice).
def _presets() -> list[str]:
    from .config import preset_names

    return preset_names()


quiet_option = click.option("-q", "--quiet", is_flag=True, help="No progress bars and no summary line (warnings "
                            "and errors still go to stderr).")
json_option = click.option("--json", "as_json", is_flag=True, help="Print one JSON record on stdout instead of "
                           "the summary line.")
overwrite_option = click.option("--overwrite", is_flag=True, help="Replace gainfpn's own earlier outputs in OUT "
                                "(by name; files it did not write are never touched).")
strict_option = click.option("--strict", is_flag=True, help=f"Exit with status {EXIT_REJECTED} when the hold-out "
                             "frame rejects an estimate (k = 1 written).")
config_option = click.option("-c", "--config", "config_path",
                             type=click.Path(exists=True, dir_okay=False, path_type=Path),
                             help="YAML config (see configs/default.yaml).")
preset_option = click.option("--preset", type=click.Choice(_presets()), help="Shipped config (configs/NAME.yaml).")


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
@overwrite_option
@quiet_option
def simulate(out_dir, preset, n_frames, size, fmt, seed, scene, fpn_pixel, fpn_column, fpn_row, read_noise, bits,
             black, cfa, shake, rotation, drift, wobble, distortion, moving_object, parallax, exposure, exposure_jitter,
             overwrite, quiet):
    """Write a synthetic burst with known gains and motion into OUT_DIR."""
    import dataclasses

    from .sim.motion import Shake
    from .sim.sensor import PRESETS, with_overrides
    from .sim.truth import simulate_to

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
    paths, plan = simulate_to(out_dir, fmt=fmt, overwrite=overwrite, scene=scene, parameters=parameters, shape=size,
                        n_frames=n_frames, sensor=sensor, shake=motion, exposure=exposure, seed=seed,
                        moving_object=moving_object, parallax=parallax, exposure_jitter=exposure_jitter)
    _untouched(plan)
    _say(quiet, f"wrote {len(paths)} {fmt.upper()} frames ({size[1]}x{size[0]}) and truth/ to {out_dir}")


def _progress(quiet: bool):
    """The pipeline's progress hook, drawn with tqdm on stderr only when it is a terminal (no
    carriage-return redraws in make or CI logs) and not ``--quiet``."""
    import sys

    if quiet or not sys.stderr.isatty():
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


def _say(quiet: bool, line: str) -> None:
    if not quiet:
        click.echo(line)


def _untouched(plan, in_json: bool = False) -> None:
    """Say on stderr, as warnings are said (``--json`` records them instead), which entries of OUT
    gainfpn did not write and so left as they were."""
    if plan.untouched and not in_json:
        shown = ", ".join(plan.untouched[:5]) + (f" and {len(plan.untouched) - 5} more" if len(plan.untouched) > 5
                                                 else "")
        click.echo(f"Note: left untouched in {plan.out_dir} what gainfpn did not write: {shown}", err=True)


def _print_json(record) -> None:
    import json

    click.echo(json.dumps(record, indent=1))


@main.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output directory.")
@config_option
@preset_option
@click.option("--method", type=click.Choice(["accurate", "paper"]), help=f"Solver method. {_cfg('solver.method')}")
@click.option("--workers", type=click.IntRange(1), help=f"Solver processes. {_cfg('solver.workers')}")
@click.option("--block-size", type=click.IntRange(1), help=f"Paper method: block side, px. {_cfg('solver.block_size')}")
@click.option("--lam", type=click.FloatRange(0), help=f"Ridge weight lambda. {_cfg('solver.lam')}")
@click.option("--reference", type=click.IntRange(0), help=f"Index of the reference frame. {_cfg('input.reference')}")
@click.option("--dark", type=click.Path(exists=True, dir_okay=False), help="Master dark frame to subtract. "
              "[default: none]")
@overwrite_option
@click.option("--scheduler", metavar="ADDRESS",
              help="Solve the blocks on this Dask cluster (e.g. tcp://host:8786) instead of local processes.")
@strict_option
@json_option
@quiet_option
def estimate(inputs, out_dir, config_path, preset, method, workers, block_size, lam, reference, dark, overwrite,
             scheduler, strict, as_json, quiet):
    """Estimate the gain map k from a moving burst and correct its frames.

    INPUTS are EXR or RAW files, directories or glob patterns. Writes
    gain_map.exr, corrected/, report.json, config.used.yaml and preview.png
    into OUT. Exit status: 0 on success (also when the hold-out check rejects
    the estimate and k = 1 is written, with a warning; 3 then with --strict),
    1 on a user error.
    """
    from .config import load_config
    from .files import find_frames
    from .outputs import estimate_plan, write_estimate
    from .pipeline import estimate as run_estimate
    from .pipeline import load_burst
    from .summary import estimate_line, estimate_record

    cfg = load_config(config_path, preset=preset, overrides={
        "solver.method": method, "solver.workers": workers, "solver.block_size": block_size, "solver.lam": lam,
        "input.reference": reference, "input.dark": dark})
    estimate_plan(out_dir, find_frames(inputs), cfg, overwrite=overwrite)  # refuse before any work
    progress = _progress(quiet)
    with contextlib.ExitStack() as stack:
        if scheduler:
            from .parallel import dask_backend
            from .tools.batch import connect

            client = stack.enter_context(connect(scheduler))
            stack.enter_context(dask_backend(client))
        try:
            burst = load_burst(inputs, cfg, progress=progress)
            result = run_estimate(burst, cfg, progress=progress)
            plan = write_estimate(result, burst, cfg, out_dir, overwrite=overwrite, progress=progress)
        finally:
            _close(progress)
    for warning in result.warnings:
        click.echo(f"Warning: {warning}", err=True)
    _untouched(plan, as_json)
    if as_json:
        _print_json(estimate_record(result.report, out_dir, untouched=plan.untouched))
    else:
        _say(quiet, estimate_line(result.report, out_dir))
    if strict and result.report["status"] == "rejected":
        raise SystemExit(EXIT_REJECTED)


@main.command()
@click.argument("manifest", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output directory: one folder per burst, and summary.csv / summary.json.")
@config_option
@preset_option
@overwrite_option
@click.option("--scheduler", metavar="ADDRESS", help="Run the bursts on this Dask cluster (tcp://host:8786).")
@click.option("--local-cluster", "local_workers", type=click.IntRange(1), metavar="N",
              help="Run the bursts on a Dask cluster of N local processes.")
@strict_option
@json_option
@quiet_option
def batch(manifest, out_dir, config_path, preset, overwrite, scheduler, local_workers, strict, as_json, quiet):
    """Estimate every burst of MANIFEST, each into OUT/NAME, and summarise them.

    MANIFEST is YAML: `bursts:` a list of `{name: NAME, inputs: PATH_OR_GLOB,
    config: OPTIONAL_YAML}` (paths relative to the manifest). Each burst's
    config applies on top of --preset and -c. A burst whose stored result was
    made from the same input files (paths, sizes, modification times) with the
    same effective config is not run again, so an interrupted batch is resumed
    by running it again; --overwrite runs every burst again. A failing burst is
    reported and does not stop the others. Without --scheduler or
    --local-cluster the bursts run here, one after another. Exit status: 0 if
    every burst is done, 1 if any failed, 3 with --strict if none failed but
    the hold-out check rejected one.
    """
    from .tools.batch import Defaults, connect, load_manifest, local_cluster, run_batch

    if scheduler and local_workers:
        raise click.UsageError("give --scheduler or --local-cluster, not both")
    jobs = load_manifest(manifest)
    defaults = Defaults(config=config_path, preset=preset)
    bar = None
    if not quiet and sys.stderr.isatty():
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
            rows, plan = run_batch(jobs, out_dir, client=client, defaults=defaults, overwrite=overwrite,
                                   manifest=manifest, progress=(lambda _: bar.update(1)) if bar else None)
        finally:
            if bar:
                bar.close()
    failed = [r for r in rows if r["status"] == "failed"]
    rejected = [r for r in rows if r["status"] == "rejected"]
    for row in failed:
        click.echo(f"Error: {row['name']}: {row['message']}", err=True)
    _untouched(plan, as_json)
    if as_json:
        _print_json({"bursts": rows, "failed": len(failed), "rejected": len(rejected),
                     "summary": str((out_dir / "summary.csv").absolute()), "untouched": list(plan.untouched)})
    else:
        earlier = sum(bool(r["earlier"]) for r in rows)
        _say(quiet, f"{len(rows) - len(failed)} of {len(rows)} bursts done ({earlier} earlier, {len(rejected)} "
                    f"rejected by the hold-out check), {len(failed)} failed -> {out_dir / 'summary.csv'}")
    if failed:
        raise SystemExit(1)
    if strict and rejected:
        raise SystemExit(EXIT_REJECTED)


@main.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("--gain-map", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="gain_map.exr written by `gainfpn estimate`.")
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--dark", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="The master dark frame the map was estimated with [default: the one its header records].")
@overwrite_option
@json_option
@quiet_option
def apply(inputs, gain_map, out_dir, dark, overwrite, as_json, quiet):
    """Correct other captures (INPUTS) with a stored gain map, as `estimate` corrects its own.

    Writes OUT/<name>.exr for each input. A map estimated with --dark has that
    dark frame subtracted first (found where its header says, or given again).
    """
    from .outputs import apply_gain_map

    progress = _progress(quiet)
    try:
        written, plan = apply_gain_map(gain_map, inputs, out_dir, dark=dark, overwrite=overwrite, progress=progress)
    finally:
        _close(progress)
    _untouched(plan, as_json)
    if as_json:
        _print_json({"status": "done", "gain_map": str(gain_map.absolute()), "warnings": [],
                     "outputs": [str(p.absolute()) for p in written], "untouched": list(plan.untouched)})
    else:
        _say(quiet, f"corrected {len(written)} frames -> {out_dir}")


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

    from .files import write_text
    from .outdir import prepare, staged
    from .sim.evaluate import evaluate as run_evaluate

    out_dir = out_dir or est_dir
    scores = run_evaluate(est_dir, sim_dir)  # a truth that is not the estimate's is refused first
    plan = prepare(out_dir, command="evaluate", names=["evaluation.json"], overwrite=overwrite, beside_inputs=True,
                   inputs=[est_dir / "gain_map.exr", est_dir / "report.json", sim_dir])
    with staged(plan) as tmp:
        write_text(tmp / "evaluation.json", json.dumps(scores, indent=1))
    _untouched(plan, as_json)
    if as_json:
        _print_json({**scores, "evaluation": str((out_dir / "evaluation.json").absolute())})
        return
    if quiet:
        return
    ratio = scores["mse_before"] / scores["mse_after"] if scores["mse_after"] > 0 else float("inf")
    click.echo(f"{'':24}{'before':>10}{'after':>10}")
    click.echo(f"{'gain FPN (%)':24}{scores['input_fpn_percent']:>10.2f}{scores['residual_fpn_percent']:>10.2f}")
    click.echo(f"{'MSE frame 0 (DN^2)':24}{scores['mse_before']:>10.2f}{scores['mse_after']:>10.2f}")
    click.echo(f"MSE reduction {ratio:.1f}x (temporal-noise floor {scores['mse_floor']:.2f} DN^2), "
               f"{scores['estimated_percent']:.0f} % of pixels estimated")
    if scores.get("residual_bound_percent") is not None:
        click.echo(f"no estimate from {scores['bound_frames']} frames of this sensor can leave less than "
                   f"{scores['residual_bound_percent']:.2f} % gain FPN on average (Cramer-Rao bound)")


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
    flow-error sensitivity (see gainfpn_cli/bench.py).
    """
    from .outdir import prepare, staged
    from .tools.bench import OUTPUTS, plan, run

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
    _untouched(outputs)
    if not quiet:
        click.echo((out_dir / "results.md").read_text())
        click.echo(f"results in {out_dir}/: results.md, results.json and plots (*.png)")
