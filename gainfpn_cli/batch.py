"""Many bursts at once: a manifest of bursts, each estimated into its own folder, and a summary.

The bursts run one after another in this process, or as tasks of a Dask
cluster (``dask.distributed``, the optional ``dask`` extra), several at a
time. Each burst's folder is written exactly as ``gainfpn estimate`` writes
it, all or nothing (:func:`io.staged_directory`), so a worker lost mid-burst
leaves no half-written results: Dask runs the burst again elsewhere, and a
re-run of the batch skips every burst whose folder is complete. A burst
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

from .errors import ConfigError, GainFPNError, InputError
from .io import remove_staging

#: Columns of summary.csv (summary.json holds the same rows).
COLUMNS = ("name", "status", "frames", "motion_model", "fpn_models", "input_fpn_pixel_percent",
           "predicted_residual_fpn_percent", "holdout_ratio", "exposure_spread_percent", "time_s", "message")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
INSTALL_HINT = "batch on a cluster needs Dask: pip install 'gainfpn[dask]' (dask[distributed])"


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
    from .config import load_yaml

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


def run_burst(job: Job, out: str | os.PathLike, *, solver_workers: int | None = None) -> dict:
    """Estimate one burst into ``out/<name>`` and return its summary row.

    A burst already done (its folder complete) is not run again. Errors of
    the burst itself (input, config, estimation) make a ``failed`` row; only
    an interrupt or a bug raises.
    """
    from .config import load_config
    from .pipeline import estimate, load_burst, write_estimate

    folder = Path(out) / job.name
    if (folder / "report.json").is_file():  # the folder is renamed into place only when complete
        report = json.loads((folder / "report.json").read_text(encoding="utf-8"))
        return {**_row(job.name, report, sum(report["timings"].values())), "status": "done earlier"}
    t0 = time.perf_counter()
    try:
        cfg = load_config(job.config, overrides={"solver.workers": solver_workers})
        burst = load_burst(job.inputs, cfg)  # as `estimate` reads its INPUTS
        result = estimate(burst, cfg)
        write_estimate(result, burst, cfg, folder, overwrite=True)
    except GainFPNError as exc:
        return {**_failed(job.name, str(exc)), "time_s": round(time.perf_counter() - t0, 2)}
    return _row(job.name, result.report, time.perf_counter() - t0)


def _failed(name: str, message: str) -> dict:
    return {**dict.fromkeys(COLUMNS), "name": name, "status": "failed", "message": message}


def _row(name: str, report: dict, seconds: float) -> dict:
    from .pipeline import exposure_spread_percent

    planes = report["planes"].values()
    pixel = [p["input_fpn_percent"]["pixel"] for p in planes if "input_fpn_percent" in p]
    holdout = report.get("holdout") or {}
    return {
        "name": name,
        "status": "done" if not report["warnings"] else "done, with warnings",
        "frames": len(report["inputs"]),
        "motion_model": report["motion"]["model"],
        "fpn_models": "/".join(sorted({p.get("fpn_model", p["method"]) for p in planes})),
        "input_fpn_pixel_percent": round(sum(pixel) / len(pixel), 3) if pixel else None,
        "predicted_residual_fpn_percent": report["predicted_residual_fpn_percent"],
        "holdout_ratio": holdout.get("residual_ratio"),
        "exposure_spread_percent": round(exposure_spread_percent(report), 3),  # divided out (0: one exposure)
        "time_s": round(seconds, 2),
        "message": "; ".join(report["warnings"]),
    }


def run_batch(jobs: list[Job], out: str | os.PathLike, *, client=None, solver_workers: int | None = None,
              progress: Callable[[dict], None] | None = None) -> list[dict]:
    """Every job into ``out/<name>``; ``client`` a Dask client to run them on (else here, in turn).

    Returns the summary rows in manifest order and writes them to
    ``out/summary.json`` and ``out/summary.csv``. ``progress(row)`` is called
    as each burst ends.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot create ({exc.strerror or exc})") from None
    if client is None:
        rows = []
        for job in jobs:
            try:
                rows.append(run_burst(job, out, solver_workers=solver_workers))
            except Exception as exc:  # noqa: BLE001 -- a bug in one burst: report it, keep the others
                rows.append(_failed(job.name, f"{type(exc).__name__}: {exc}"))
            if progress:
                progress(rows[-1])
    else:
        rows = _on_cluster(client, jobs, out, progress)
    for job in jobs:  # a worker killed while writing leaves its staging folder behind
        remove_staging(out / job.name)
    write_summary(rows, out)
    return rows


def _on_cluster(client, jobs: list[Job], out: Path, progress) -> list[dict]:
    """Each burst a Dask task (its solver on one process: a Dask worker is the unit of parallelism)."""
    # keywords through partial: Client.map's own `workers=` would restrict the tasks to a worker so named
    task = functools.partial(run_burst, out=str(out.absolute()), solver_workers=1)
    futures = client.map(task, jobs, pure=False)
    rows = []
    try:
        for job, future in zip(jobs, futures):
            try:
                rows.append(future.result())
            except Exception as exc:  # noqa: BLE001 -- a bug or a lost task: report it, keep the others
                rows.append(_failed(job.name, f"{type(exc).__name__}: {exc}"))
            if progress:
                progress(rows[-1])
    except BaseException:
        client.cancel(futures)
        raise
    return rows


def write_summary(rows: list[dict], out: Path) -> None:
    """``summary.json`` and ``summary.csv`` in ``out``, each written atomically."""
    from .io import write_text

    write_text(out / "summary.json", json.dumps(rows, indent=1))
    text = _io.StringIO()
    writer = csv.DictWriter(text, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: row.get(k) for k in COLUMNS} for row in rows)
    write_text(out / "summary.csv", text.getvalue())


def local_cluster(n_workers: int):
    """A Dask client on a cluster of ``n_workers`` local processes on loopback, one thread each and
    their native libraries single-threaded (as :mod:`parallel`'s workers: results are bit-identical)."""
    distributed = import_distributed()
    from .parallel import single_threaded_children

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
