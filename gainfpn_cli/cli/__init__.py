"""The ``gainfpn`` command line: parse, load, call one pipeline function, report.

User errors (:class:`GainFPNError`) exit 1 with one line; usage errors exit 2
(click); Ctrl-C exits 130 and SIGTERM 143, after the outputs being staged are
removed; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import click

from .. import __version__
from ..errors import EXIT_REJECTED, GainFPNError


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
    from ..sim.scenes import SCENES

    if value in SCENES:
        return value
    path = Path(value)
    if not path.is_file():
        raise click.BadParameter(f"{value!r} is neither a built-in scene ({', '.join(SCENES)}) nor an image file")
    return path


def _cfg(key: str) -> str:
    """``[default: VALUE from config KEY]`` for a flag that overrides a config key."""
    from ..config import Config

    section, name = key.split(".")
    return f"[default: {getattr(getattr(Config(), section), name)} (config {key})]"


#: Presets shipped in configs/ (read from the package, so a new YAML there is a new choice).
def _presets() -> list[str]:
    from ..config import preset_names

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


def progress_bars(quiet: bool):
    """The pipeline's progress hook, drawn with tqdm on stderr only when it is a terminal (no
    carriage-return redraws in make or CI logs) and not ``--quiet``."""

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


def close(progress) -> None:
    for bar in getattr(progress, "bars", []):
        bar.close()


def say(quiet: bool, line: str) -> None:
    if not quiet:
        click.echo(line)


def untouched(plan, in_json: bool = False) -> None:
    """Say on stderr, as warnings are said (``--json`` records them instead), which entries of OUT
    gainfpn did not write and so left as they were."""
    if plan.untouched and not in_json:
        shown = ", ".join(plan.untouched[:5]) + (f" and {len(plan.untouched) - 5} more" if len(plan.untouched) > 5
                                                 else "")
        click.echo(f"Note: left untouched in {plan.out_dir} what gainfpn did not write: {shown}", err=True)


def print_json(record) -> None:
    import json

    click.echo(json.dumps(record, indent=1))


from . import burst_commands, sim_commands  # noqa: E402,F401 (registers the commands on main)
