"""Many bursts at once: a manifest of bursts, each estimated into its own folder, and a summary.

The bursts run one after another in this process, or as tasks of a Dask
cluster (``dask.distributed``, the optional ``dask`` extra), several at a
time. Each burst's folder is written exactly as ``gainfpn estimate`` writes
it, all or nothing (:func:`outdir.staged`), so a worker lost mid-burst
leaves no half-written results: Dask runs the burst again elsewhere, and a
re-run of the batch skips every burst whose stored result was made from the
same input files with the same effective config (:func:`stored_report`). A burst
that fails (bad input, no motion, ...) is reported in the summary and does
not stop the others.
"""

from __future__ import annotations

import csv
import functools
import io as _io
import json
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..errors import ConfigError, GainFPNError, InputError
from ..outdir import remove_staging
from ..report import Report

#: Columns of summary.csv (summary.json holds the same rows) and the decimals each number is rounded to.
COLUMNS = {"name": None, "status": None, "earlier": None, "frames": None, "motion_model": None, "fpn_models": None,
           "prnu_percent": 3, "prnu_pixel_percent": 3, "prnu_column_percent": 3, "prnu_row_percent": 3,
           "predicted_residual_percent": 3, "holdout_ratio": 4, "exposure_spread_percent": 3,
           "defects_hot": None, "defects_dead": None, "defects_stuck": None, "time_s": 2,
           "message": None}
SUMMARY_FILES = ("summary.csv", "summary.json")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
INSTALL_HINT = "batch on a cluster needs Dask: pip install 'gainfpn[dask]' (dask[distributed])"


@dataclass(frozen=True)
class Defaults:
    """What applies to every burst of a batch under its own config: ``--preset`` and ``-c``."""

    config: Path | None = None
    preset: str | None = None


@dataclass(frozen=True)
class Job:
    """One burst of a manifest: its name (the output folder), inputs and optional config."""

    name: str
    inputs: tuple[str, ...]
    config: Path | None = None


def load_manifest(path: str | os.PathLike) -> list[Job]:
    """The bursts of a manifest YAML: ``bursts:`` a list of ``{name, inputs, config}``.

    ``inputs`` is a path, a glob or a list of them; it and ``config`` are
    relative to the manifest's folder. Errors name the manifest and the key.
    """
    from ..config import load_yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not valid YAML (not UTF-8 text)") from None
    data = load_yaml(text, source=str(path))
    if not isinstance(data, dict) or set(data) != {"bursts"}:
        raise ConfigError(f"{path}: must be a mapping with the one key 'bursts'")
    bursts = data["bursts"]
    if not isinstance(bursts, list) or not bursts:
        raise ConfigError(f"{path}: bursts: must be a non-empty list")
    jobs, seen = [], set()
    for i, entry in enumerate(bursts):
        where = f"{path}: bursts[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: must be a mapping with name, inputs and optionally config")
        unknown = sorted(set(entry) - {"name", "inputs", "config"})
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(map(str, unknown))} (keys: name, inputs, config)")
        name = entry.get("name")
        if not isinstance(name, str) or not _NAME.match(name):
            raise ConfigError(f"{where}.name: must be a folder name of letters, digits, '.', '_' or '-', got {name!r}")
        if name in seen:
            raise ConfigError(f"{where}.name: {name!r} is used twice")
        seen.add(name)
        inputs = entry.get("inputs")
        inputs = [inputs] if isinstance(inputs, str) else inputs
        if not isinstance(inputs, list) or not inputs or not all(isinstance(s, str) and s for s in inputs):
            raise ConfigError(f"{where}.inputs: must be a path or glob, or a list of them")
        config = entry.get("config")
        if config is not None and not isinstance(config, str):
            raise ConfigError(f"{where}.config: must be the path of a YAML config")
        jobs.append(Job(name, tuple(str(path.parent / s) for s in inputs),
                        None if config is None else path.parent / config))
    return jobs


def job_config(job: Job, defaults: Defaults = Defaults(), *, solver_workers: int | None = None):
    """The burst's effective config: defaults < ``--preset`` < ``-c`` < the burst's own config."""
    from ..config import load_config

    base = load_config(defaults.config, preset=defaults.preset)
    return load_config(job.config, base=base, overrides={"solver.workers": solver_workers})


def stored_report(folder: Path, job: Job, cfg) -> Report | None:
    """The report of ``folder``'s result if it was made from the job's inputs as they are now (paths,
    sizes, modification times) with the effective config ``cfg``; else None (run it again)."""
    from ..config import config_dict
    from ..files import find_frames, stamp

    try:
        report = Report.from_json(json.loads((folder / "report.json").read_text(encoding="utf-8")))
        recorded, dark = report.inputs, report.dark
        now = [stamp(p, digest=False) for p in find_frames(job.inputs)]
    except (OSError, ValueError, KeyError, TypeError, GainFPNError):
        return None
    if len(now) != len(recorded) or not all(a.same_file(b) for a, b in zip(now, recorded)):
        return None
    if (dark is None) != (cfg.input.dark is None):
        return None
    if dark is not None and not stamp(cfg.input.dark, digest=False).same_file(dark):
        return None
    return report if _settings(report.config) == _settings(config_dict(cfg)) else None


def _settings(config: dict) -> dict:
    """A config less what cannot change a result: the solver's process count (a cluster's bursts
    solve on one, a batch here on solver.workers; the tiling and so the result do not depend on it)."""
    return {**config, "solver": {k: v for k, v in config.get("solver", {}).items() if k != "workers"}}


def run_burst(job: Job, out: str | os.PathLike, *, defaults: Defaults = Defaults(), overwrite: bool = False,
              solver_workers: int | None = None) -> dict:
    """Estimate one burst into ``out/<name>`` and return its summary row.

    A burst whose stored result is still its inputs' and config's (:func:`stored_report`) is not
    run again unless ``overwrite``. Errors of the burst itself (input, config, estimation) make a
    ``failed`` row; only an interrupt or a bug raises.
    """
    from ..api import estimate

    folder = Path(out) / job.name
    t0 = time.perf_counter()
    try:
        cfg = job_config(job, defaults, solver_workers=solver_workers)
        report = None if overwrite else stored_report(folder, job, cfg)
        if report is not None:
            return {**_row(job.name, report, report.timings.get("total_s", 0.0)), "earlier": True}
        written = estimate(job.inputs, config=cfg).write(folder, overwrite=True)  # the batch's own folder
    except GainFPNError as exc:
        return {**_failed(job.name, str(exc)), "time_s": round(time.perf_counter() - t0, 2)}
    return _row(job.name, written.report, time.perf_counter() - t0)


def _failed(name: str, message: str) -> dict:
    return {**dict.fromkeys(COLUMNS), "name": name, "status": "failed", "earlier": False, "message": message}


def _row(name: str, report: Report, seconds: float) -> dict:
    prnu = report.prnu_percent
    row = {
        "name": name,
        "status": "rejected" if report.status == "rejected" else "done",
        "earlier": False,
        "frames": len(report.inputs),
        "motion_model": report.motion.model,
        "fpn_models": report.fpn_models,
        "prnu_percent": prnu.total,
        "prnu_pixel_percent": prnu.pixel,
        "prnu_column_percent": prnu.column,
        "prnu_row_percent": prnu.row,
        "predicted_residual_percent": report.predicted_residual_percent,
        "holdout_ratio": None if report.holdout is None else report.holdout.residual_ratio,
        "exposure_spread_percent": report.exposure_spread_percent,  # divided out (0: one exposure)
        **{f"defects_{kind}": None if report.defects is None else getattr(report.defects, kind)
           for kind in ("hot", "dead", "stuck")},
        "time_s": seconds,
        "message": "; ".join(report.warnings),
    }
    return {key: value if COLUMNS[key] is None or value is None else round(float(value), COLUMNS[key])
            for key, value in row.items()}


def batch_plan(jobs: list[Job], out: Path, *, overwrite: bool = False, manifest: Path | None = None,
               defaults: Defaults = Defaults()):
    """Check ``out`` before any work (:func:`outdir.prepare`): it must not hold any burst's inputs or
    configs, and a burst's folder there that an earlier batch did not write needs ``overwrite``."""
    from ..files import find_frames
    from ..outdir import prepare, read_manifest

    inputs = [p for p in (manifest, defaults.config) if p is not None]
    for job in jobs:
        inputs += [job.config] if job.config is not None else []
        try:
            inputs += find_frames(job.inputs)
        except GainFPNError:  # reported as that burst's failure
            pass
    names = [job.name for job in jobs] + list(SUMMARY_FILES)
    ours = read_manifest(out) if out.is_dir() else {}
    foreign = [n for n in names if (out / n).exists() and ours.get(n) != "batch"]
    if foreign and not overwrite:
        raise InputError(f"{out / foreign[0]}: was not written by gainfpn batch; pass --overwrite to replace it")
    return prepare(out, command="batch", names=names, inputs=inputs, overwrite=True)


def run_batch(jobs: list[Job], out: str | os.PathLike, *, client=None, defaults: Defaults = Defaults(),
              overwrite: bool = False, manifest: Path | None = None, solver_workers: int | None = None,
              progress: Callable[[dict], None] | None = None):
    """Every job into ``out/<name>``; ``client`` a Dask client to run them on (else here, in turn).

    Returns the summary rows in manifest order (and writes them to ``out/summary.json`` and
    ``out/summary.csv``) and the output plan. ``progress(row)`` is called as each burst ends.
    """
    from ..outdir import record

    out = Path(out)
    plan = batch_plan(jobs, out, overwrite=overwrite, manifest=manifest, defaults=defaults)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot create ({exc.strerror or exc})") from None

    def done(job: Job, row: dict) -> None:
        if (out / job.name).is_dir():
            record(out, [job.name], "batch")
        if progress:
            progress(row)

    options = {"defaults": defaults, "overwrite": overwrite}
    if client is None:
        rows = []
        for job in jobs:
            try:
                rows.append(run_burst(job, out, solver_workers=solver_workers, **options))
            except Exception as exc:  # noqa: BLE001 -- a bug in one burst: report it, keep the others
                rows.append(_failed(job.name, f"{type(exc).__name__}: {exc}"))
            done(job, rows[-1])
    else:
        rows = _on_cluster(client, jobs, out, done, options)
    for job in jobs:  # a worker killed while writing leaves its staging folder behind
        remove_staging(out / job.name)
    write_summary(rows, out)
    record(out, SUMMARY_FILES, "batch")
    return rows, plan


def _on_cluster(client, jobs: list[Job], out: Path, done, options: dict) -> list[dict]:
    """Each burst a Dask task (its solver on one process: a Dask worker is the unit of parallelism)."""
    # keywords through partial: Client.map's own `workers=` would restrict the tasks to a worker so named
    task = functools.partial(run_burst, out=str(out.absolute()), solver_workers=1, **options)
    futures = client.map(task, jobs, pure=False)
    rows = []
    try:
        for job, future in zip(jobs, futures):
            try:
                rows.append(future.result())
            except Exception as exc:  # noqa: BLE001 -- a bug or a lost task: report it, keep the others
                rows.append(_failed(job.name, f"{type(exc).__name__}: {exc}"))
            done(job, rows[-1])
    except BaseException:
        client.cancel(futures)
        raise
    return rows


def write_summary(rows: list[dict], out: Path) -> None:
    """``summary.json`` and ``summary.csv`` in ``out``, each written atomically."""
    from ..files import write_text

    write_text(out / "summary.json", json.dumps(rows, indent=1))
    text = _io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: row.get(k) for k in COLUMNS} for row in rows)
    write_text(out / "summary.csv", text.getvalue())


def local_cluster(n_workers: int):
    """A Dask client on a cluster of ``n_workers`` local processes on loopback, one thread each and
    their native libraries single-threaded (as :mod:`parallel`'s workers: results are bit-identical)."""
    distributed = import_distributed()
    from ..parallel import single_threaded_children

    with single_threaded_children():  # the nannies inherit it, and pass it on to the workers they restart
        cluster = distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                           host="127.0.0.1", dashboard_address=None)
    return distributed.Client(cluster)


def connect(address: str):
    """A Dask client on the scheduler at ``address``."""
    distributed = import_distributed()
    try:
        return distributed.Client(address, timeout="10s")
    except OSError as exc:
        raise InputError(f"cannot reach the Dask scheduler at {address} ({exc})") from None


def import_distributed():
    try:
        import distributed
    except ImportError:
        raise InputError(INSTALL_HINT) from None
    return distributed
