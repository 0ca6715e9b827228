"""The commands that work on captured bursts: estimate, apply, batch."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import click

from ..errors import EXIT_REJECTED
from . import (
    _cfg,
    close,
    config_option,
    json_option,
    main,
    overwrite_option,
    preset_option,
    print_json,
    progress_bars,
    quiet_option,
    say,
    strict_option,
    untouched,
)


@main.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output directory.")
@config_option
@preset_option
@click.option("--method", type=click.Choice(["auto", "accurate", "paper", "scene"]),
              help=f"Solver method. {_cfg('solver.method')}")
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
    from ..api import estimate as run_estimate
    from ..config import load_config
    from ..files import find_frames
    from ..outputs import estimate_plan
    from ..summary import estimate_line, estimate_record

    cfg = load_config(config_path, preset=preset, overrides={
        "solver.method": method, "solver.workers": workers, "solver.block_size": block_size, "solver.lam": lam,
        "input.reference": reference, "input.dark": dark})
    estimate_plan(out_dir, find_frames(inputs), cfg, overwrite=overwrite,  # refuse before any work
                  also_read=[config_path] if config_path else [])
    progress = progress_bars(quiet)
    with contextlib.ExitStack() as stack:
        executor = None
        if scheduler:
            from ..parallel import DaskExecutor
            from ..tools.batch import connect

            executor = DaskExecutor(stack.enter_context(connect(scheduler)))
        try:
            result = run_estimate(inputs, config=cfg, progress=progress, executor=executor)
            written = result.write(out_dir, overwrite=overwrite, progress=progress)
        finally:
            close(progress)
    for warning in written.report.warnings:
        click.echo(f"Warning: {warning}", err=True)
    untouched(written.plan, as_json)
    if as_json:
        print_json(estimate_record(written.report, out_dir, untouched=written.plan.untouched))
    else:
        say(quiet, estimate_line(written.report, out_dir))
    if strict and written.report.status == "rejected":
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
    from ..tools.batch import Defaults, connect, load_manifest, local_cluster, run_batch

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
    untouched(plan, as_json)
    if as_json:
        print_json({"bursts": rows, "failed": len(failed), "rejected": len(rejected),
                     "summary": str((out_dir / "summary.csv").absolute()), "untouched": list(plan.untouched)})
    else:
        earlier = sum(bool(r["earlier"]) for r in rows)
        say(quiet, f"{len(rows) - len(failed)} of {len(rows)} bursts done ({earlier} earlier, {len(rejected)} "
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
@click.option("--repair/--no-repair", default=True, show_default=True,
              help="Replace the map's defective photosites from their healthy neighbours of the same colour.")
@overwrite_option
@json_option
@quiet_option
def apply(inputs, gain_map, out_dir, dark, repair, overwrite, as_json, quiet):
    """Correct other captures (INPUTS) with a stored gain map, as `estimate` corrects its own.

    Writes OUT/<name>.exr for each input. A map estimated with --dark has that
    dark frame subtracted first (found where its header says, or given again).
    Photosites the map marks defective are repaired unless --no-repair.
    """
    from ..outputs import apply_gain_map

    progress = progress_bars(quiet)
    try:
        written, plan = apply_gain_map(gain_map, inputs, out_dir, dark=dark, overwrite=overwrite, progress=progress,
                                       repair=repair)
    finally:
        close(progress)
    untouched(plan, as_json)
    if as_json:
        print_json({"status": "done", "gain_map": str(gain_map.absolute()), "warnings": [],
                     "outputs": [str(p.absolute()) for p in written], "untouched": list(plan.untouched)})
    else:
        say(quiet, f"corrected {len(written)} frames -> {out_dir}")


