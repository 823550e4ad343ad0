"""``packpilot`` command line: simulate, replay, report.

Every user-facing error (bad config, bad log, bad CAN frame) is a :class:`PackPilotError`:
printed as one line on stderr with exit code 2, never a traceback.
"""

from __future__ import annotations

import datetime
import json
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer

from packpilot.control.registry import REGISTRY
from packpilot.errors import PackPilotError

if TYPE_CHECKING:
    from packpilot.config import ScenarioConfig
    from packpilot.contract.record import Result

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="PackPilot: battery management for multi-battery packs.",
    pretty_exceptions_enable=False,
)
replay_app = typer.Typer(no_args_is_help=True, help="Replay a CSV log through a control method.")
app.add_typer(replay_app, name="replay")

T = TypeVar("T")


def _guard(fn: Callable[[], T]) -> T:
    """Run a command: a user-facing error is one line and exit code 2. Warnings raised on the
    way (a NumPy overflow on absurd input) are held back: shown after a command that works,
    dropped when a clean error says what was wrong, so that error stays one line."""
    with warnings.catch_warnings(record=True) as held:
        try:
            result = fn()
        except PackPilotError as err:
            typer.echo(f"error: {err}", err=True)
            raise typer.Exit(code=2) from None
        except OSError as err:  # an output path in a missing directory, a read-only file, ...
            where = f"{err.filename}: " if err.filename else ""
            typer.echo(f"error: {where}{err.strerror or err}", err=True)
            raise typer.Exit(code=2) from None
    for w in held:
        warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return result


def _json_default(o: Any) -> Any:
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


@app.command()
def simulate(
    config: Annotated[Path, typer.Argument(help="scenario TOML file")],
    db: Annotated[Path | None, typer.Option(help="record telemetry to this SQLite file")] = None,
    trace_csv: Annotated[Path | None, typer.Option(help="write the per-step trace as CSV")] = None,
    plot: Annotated[Path | None, typer.Option(help="write a PNG of V, I, SOC, T")] = None,
    report: Annotated[
        Path | None, typer.Option(help="write a self-contained HTML report of the run")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the metrics as JSON")] = False,
    duration: Annotated[float | None, typer.Option(help="override sim.duration_s")] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="no progress bar")] = False,
    can_interface: Annotated[
        str | None, typer.Option(help="charger over CAN: python-can interface (virtual, socketcan)")
    ] = None,
    can_channel: Annotated[str | None, typer.Option(help="CAN channel, e.g. can0")] = None,
    can_log: Annotated[Path | None, typer.Option(help="log CAN frames to .blf or .asc")] = None,
) -> None:
    """Run a closed-loop simulation of a scenario."""

    def go() -> None:
        from packpilot.config import load_config
        from packpilot.sim.runner import Runner

        cfg = load_config(config)
        if can_interface or can_channel or can_log:
            cfg = _with_can(cfg, can_interface, can_channel, can_log)
        cfg = _with_duration(cfg, duration)
        _check_outputs(db=db, trace_csv=trace_csv, plot=plot, report=report, can_log=can_log)
        progress = False if no_progress or as_json else None
        started = datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")
        if db is not None:
            from packpilot.io.telemetry import SQLiteRecorder

            with SQLiteRecorder(db) as recorder:
                build = lambda: Runner(cfg, recorder=recorder, progress=progress)  # noqa: E731
                result = _named(config, build).run()
        else:
            result = _named(config, lambda: Runner(cfg, progress=progress)).run()
        if trace_csv is not None:
            from packpilot.io.telemetry import trace_to_csv

            trace_to_csv(result, trace_csv)
        if plot is not None:
            from packpilot.report.plots import plot_run

            plot_run(result, plot)
        if report is not None:
            _write_report(result, report, cfg.model_dump(mode="json"), config, db, started)
        if as_json:
            typer.echo(json.dumps(result.metrics, default=_json_default))
        else:
            _print_metrics(result.metrics)

    _guard(go)


def _with_duration(cfg: ScenarioConfig, duration: float | None) -> ScenarioConfig:
    """``--duration`` validated as ``sim.duration_s`` is (``--duration 0`` / ``-5`` were
    tracebacks when the override bypassed the model)."""
    if duration is None:
        return cfg
    return _revalidated(cfg, "sim", {"duration_s": duration}, "--duration")


def _with_can(
    cfg: ScenarioConfig, interface: str | None, channel: str | None, log: Path | None
) -> ScenarioConfig:
    """The ``[can]`` section with the command line's ``--can-*`` options, validated."""
    update = {
        k: v
        for k, v in (("interface", interface), ("channel", channel), ("log", log))
        if v is not None
    }
    return _revalidated(cfg, "can", {k: str(v) for k, v in update.items()}, "--can-*")


def _revalidated(
    cfg: ScenarioConfig, section: str, update: dict[str, Any], option: str
) -> ScenarioConfig:
    """``cfg`` with ``update`` merged into ``[section]``, through the section's model."""
    from pydantic import ValidationError

    from packpilot.config.base import fmt_error
    from packpilot.errors import ConfigError

    current = getattr(cfg, section)
    data = {**(current.model_dump() if current is not None else {}), **update}
    try:
        return cfg.model_validate({**cfg.model_dump(), section: data})
    except ValidationError as err:
        raise ConfigError(fmt_error(option, err)) from None


def _check_outputs(**paths: Path | None) -> None:
    """Every output of ``simulate`` checked before the run, named by its flag."""
    from packpilot.io.outputs import check_output

    suffixes = {
        "plot": (".png", ".svg", ".pdf"),
        "report": (".html", ".htm"),
        "can_log": (".blf", ".asc"),
    }
    for name, path in paths.items():
        if path is not None:
            check_output(path, f"--{name.replace('_', '-')}", suffixes.get(name, ()))


def _named(config: Path, build: Callable[[], T]) -> T:
    """Errors found while building a run from ``config`` (checks against the pack's cells)
    name the file, as the config formatter's do."""
    from packpilot.errors import ConfigError

    try:
        return build()
    except ConfigError as err:
        if str(config) in str(err):
            raise
        raise ConfigError(f"{config}: {err}") from None


def _write_report(
    result: Result, out: Path, cfg: dict[str, Any], config: Path, db: Path | None, started: str
) -> None:
    """HTML report of an in-memory run; run facts from the database row when one was written."""
    import dataclasses

    from packpilot.report.html import RunInfo, run_info_from_db, write_report

    if db is not None and result.run_id is not None:
        info = run_info_from_db(db, result.run_id)
        info = dataclasses.replace(info, source=f"{config} (recorded in {db})")
    else:
        info = RunInfo.from_config(
            cfg,
            status="ok",
            started_at=started,
            finished_at=datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds"),
            source=str(config),
        )
    write_report(result, out, info)


def _print_metrics(m: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="run summary", show_header=True)
    table.add_column("metric")
    table.add_column("value", justify="right")
    for k, v in m.items():
        if isinstance(v, float):
            text = f"{v:.4g}"
        elif isinstance(v, list):
            text = ", ".join(f"{x:.4g}" if isinstance(x, float) else str(x) for x in v)
        else:
            text = str(v)
        table.add_row(k, text)
    Console().print(table)


@app.command()
def report(
    db: Annotated[Path, typer.Argument(help="telemetry SQLite file (simulate --db)")],
    out: Annotated[Path, typer.Option(help="HTML file to write")],
    run_id: Annotated[int | None, typer.Option(help="run to report (default: latest)")] = None,
) -> None:
    """Write a self-contained HTML report (plots inline, no network) of a recorded run."""

    def go() -> None:
        from packpilot.report.html import report_from_db

        path = report_from_db(db, out, run_id)
        typer.echo(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")

    _guard(go)


def _replay(method: str, log: Path, config: Path | None, out: Path | None, as_json: bool) -> None:
    def go() -> None:
        from packpilot.config import load_section

        replay = REGISTRY[method].replay
        assert replay is not None
        result = replay.function()(log, load_section(config, method))
        if out is not None:
            result.write_csv(out)
        if as_json:
            typer.echo(json.dumps(result.summary, default=_json_default))
        elif out is None:
            import csv

            writer = csv.writer(sys.stdout)
            writer.writerow(result.columns)
            writer.writerows(result.rows)

    _guard(go)


LogArg = Annotated[Path, typer.Argument(help="CSV log to replay")]
ConfigOpt = Annotated[Path | None, typer.Option(help="TOML file with the method's section")]
OutOpt = Annotated[Path | None, typer.Option(help="write the output table as CSV")]
JsonOpt = Annotated[bool, typer.Option("--json", help="print the summary as JSON")]


def _replay_command(method: str, help_text: str) -> None:
    """``packpilot replay METHOD``: one command per registered replay adapter."""

    def command(
        log: LogArg, config: ConfigOpt = None, out: OutOpt = None, as_json: JsonOpt = False
    ) -> None:
        _replay(method, log, config, out, as_json)

    replay_app.command(method, help=help_text)(command)


for _entry in REGISTRY.values():
    if _entry.replay is not None:
        _replay_command(_entry.name, _entry.replay.help)


@app.command()
def campaign(
    config: Annotated[Path, typer.Argument(help="scenario TOML file")],
    runs: Annotated[int, typer.Option(help="number of runs (run indices 0..N-1)")],
    spread: Annotated[
        str | None,
        typer.Option(help="parameter spreads, e.g. capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35"),
    ] = None,
    seed: Annotated[int, typer.Option(help="campaign seed (run i draws from [seed, i])")] = 0,
    scheduler: Annotated[
        str | None,
        typer.Option(help="auto | processes | threads | sync | a Dask address tcp://host:8786"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Parquet result file (default CONFIG_campaign.parquet)")
    ] = None,
    resume: Annotated[bool, typer.Option(help="keep finished runs, compute the rest")] = False,
    workers: Annotated[int | None, typer.Option(help="local workers (default: cores)")] = None,
    batch: Annotated[int | None, typer.Option(help="runs per task (default: automatic)")] = None,
    max_runs: Annotated[
        int | None, typer.Option(help="compute at most this many runs now (finish with --resume)")
    ] = None,
    duration: Annotated[float | None, typer.Option(help="override sim.duration_s")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the summary as JSON")] = False,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="no progress bar")] = False,
) -> None:
    """Monte-Carlo campaign: N closed-loop runs over parameter spreads (Dask), to Parquet."""

    def go() -> None:
        from packpilot import campaign as cp
        from packpilot.config import load_config

        cfg = _with_duration(load_config(config), duration)
        target = out if out is not None else Path(f"{config.stem}_campaign.parquet")
        _check_outputs(out=target)
        show = not (as_json or no_progress) and sys.stdout.isatty()
        try:
            with cp.rich_progress(show) as progress:
                report = cp.run_campaign(
                    cfg,
                    runs,
                    target,
                    spreads=spread,
                    seed=seed,
                    scheduler=scheduler,
                    workers=workers,
                    batch=batch,
                    resume=resume,
                    limit=max_runs,
                    on_progress=progress,
                )
        except KeyboardInterrupt:
            typer.echo(
                f"interrupted: finished runs kept; rerun with --resume --out {target}", err=True
            )
            raise typer.Exit(code=130) from None
        png = cp.plot_histograms(report.table, target.with_suffix(".png"))
        if as_json:
            typer.echo(json.dumps(cp.report_to_dict(report, png), default=_json_default))
        else:
            cp.print_summary(report)
            typer.echo(
                f"wrote {report.out} ({report.table.num_rows} runs)" + (f", {png}" if png else "")
            )

    _guard(go)


@app.command()
def dashboard(
    config: Annotated[Path, typer.Argument(help="scenario TOML file")],
    host: Annotated[str, typer.Option(help="address to listen on")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port (0: any free port)")] = 8765,
    speed: Annotated[
        float, typer.Option(help="simulated seconds per wall second (0: as fast as possible)")
    ] = 10.0,
    db: Annotated[Path | None, typer.Option(help="also record telemetry to this SQLite")] = None,
    duration: Annotated[float | None, typer.Option(help="override sim.duration_s")] = None,
) -> None:
    """Run a scenario and watch it live in a browser (Ctrl-C stops)."""

    def go() -> None:
        import contextlib

        from packpilot.config import load_config
        from packpilot.errors import ConfigError
        from packpilot.sim.runner import Runner
        from packpilot.web.app import Dashboard

        if speed < 0 or speed != speed:
            raise ConfigError(f"--speed {speed}: must be >= 0 (0 = as fast as possible)")
        if not 0 <= port <= 65535:
            raise ConfigError(f"--port {port}: must be 0..65535")
        cfg = _with_duration(load_config(config), duration)
        if db is not None:
            _check_outputs(db=db)
        runner = _named(config, lambda: Runner(cfg, progress=False))
        name = cfg.pack.name if "name" in cfg.pack.model_fields_set else config.stem
        dash = Dashboard(runner, scenario=name, speed=speed, db=db, host=host, port=port)
        typer.echo(f"dashboard for {name} on {dash.url}  (Ctrl-C to stop)", err=True)
        dash.start()
        with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C / SIGTERM: the normal way out
            dash.serve()
        st = dash.live.status()
        why = f": {st['error']}" if st["error"] and st["state"] == "error" else ""
        typer.echo(f"run {st['state']} at t = {st['t_s']:.1f} s{why}", err=True)

    _guard(go)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
