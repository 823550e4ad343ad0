"""``packpilot`` command line: simulate, replay, report.

Every user-facing error (bad config, bad log, bad CAN frame) is a :class:`PackPilotError`:
printed as one line on stderr with exit code 2, never a traceback.

Exit codes: 0 done; 2 a user error (one ``error: ...`` line); 3 ``simulate --fail-on`` found an
alarm of a listed category (the run itself completed and its outputs were written); 130
interrupted (Ctrl-C).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer

if __name__ == "__main__":  # ``python -m packpilot.cli``: decide before any kernel is imported
    from packpilot.coldstart import prepare

    prepare(sys.argv[1:])

from packpilot.coldstart import begin
from packpilot.control.registry import REGISTRY
from packpilot.errors import PackPilotError

if TYPE_CHECKING:
    from packpilot.config import ScenarioConfig
    from packpilot.contract.record import Result
    from packpilot.sim.verdict import Verdict

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="PackPilot: battery management for multi-battery packs.",
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain help: "[seed, i]" is text, not markup; nothing is cut
)
replay_app = typer.Typer(
    no_args_is_help=True,
    help="Replay a log: a CSV or flight log through a control method (protection, sequencing,"
    " equalization, flight), or a CAN frame log through the whole BMS (can).",
    rich_markup_mode=None,
)
app.add_typer(replay_app, name="replay")
calibrate_app = typer.Typer(
    no_args_is_help=True,
    help="Derive a control method's configuration from a cell set.",
    rich_markup_mode=None,
)
app.add_typer(calibrate_app, name="calibrate")

T = TypeVar("T")

EXIT_USER_ERROR = 2
EXIT_FAIL_ON = 3
"""``simulate --fail-on``: an alarm of a listed category (for CI)."""
EXIT_INTERRUPTED = 130
"""Ctrl-C, as a shell reports SIGINT (128 + 2)."""


def _version_callback(value: bool) -> None:
    if value:
        import importlib.metadata

        try:
            version = importlib.metadata.version("packpilot")
        except importlib.metadata.PackageNotFoundError:
            version = "unknown"
        typer.echo(f"packpilot {version}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            help="print the version and exit",
            callback=_version_callback,
            is_eager=True,
        ),
    ] = False,
) -> None:
    """PackPilot: battery management for multi-battery packs."""


def scenario_path(config: Path) -> Path:
    """The scenario file ``config`` names: a path, or an example's name (``uav_mission``
    finds ``examples/uav_mission.toml`` here, in the source tree or among the installed
    examples), so the README's commands work from anywhere."""
    if config.exists() or config.suffix or len(config.parts) > 1:
        return config
    for folder in _example_dirs():
        candidate = folder / f"{config.name}.toml"
        if candidate.is_file():
            return candidate
    import difflib

    from packpilot.errors import ConfigError

    names = sorted({p.stem for d in _example_dirs() for p in d.glob("*.toml")})
    close = difflib.get_close_matches(config.name, names, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    known = f"; examples: {', '.join(names)}" if names else ""
    raise ConfigError(f"{config}: no such file, and no example of that name{hint}{known}")


def _example_dirs() -> list[Path]:
    """Where named examples are looked up: ./examples, the source tree's (an editable
    install), then the ones a wheel installs under ``<prefix>/share/packpilot/examples``."""
    import packpilot

    here = Path("examples")
    checkout = Path(packpilot.__file__).resolve().parents[2] / "examples"
    installed = Path(sys.prefix) / "share" / "packpilot" / "examples"
    return [d for d in (here, checkout, installed) if d.is_dir()]


def _guard(fn: Callable[[], T], announce: bool | None = None) -> T:
    """Run a command: a user-facing error is one line and exit code 2; Ctrl-C is exit code
    130 without a traceback. Warnings raised on the way (a NumPy overflow on absurd input) are
    held back: shown after a command that works, dropped when a clean error says what was
    wrong, so that error stays one line. Compiling kernels (the first run on a machine) is
    said on stderr with a heartbeat when ``announce`` (default: stderr is a terminal)."""
    from packpilot.buildclock import announce_compiles
    from packpilot.coldstart import reporting

    if announce is None:
        announce = sys.stderr.isatty()
    with warnings.catch_warnings(record=True) as held:
        try:
            with reporting(sys.stderr):  # interpreted first run: the background compile
                if announce:
                    with announce_compiles(sys.stderr):
                        result = fn()
                else:
                    result = fn()
        except PackPilotError as err:
            typer.echo(f"error: {err}", err=True)
            raise typer.Exit(code=EXIT_USER_ERROR) from None
        except KeyboardInterrupt:  # Ctrl-C while loading or compiling: no traceback either
            typer.echo("interrupted", err=True)
            raise typer.Exit(code=EXIT_INTERRUPTED) from None
        except OSError as err:  # an output path in a missing directory, a read-only file, ...
            where = f"{err.filename}: " if err.filename else ""
            typer.echo(f"error: {where}{err.strerror or err}", err=True)
            raise typer.Exit(code=EXIT_USER_ERROR) from None
    for w in held:
        warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return result


def _json_default(o: Any) -> Any:
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


FAIL_ON_HELP = (
    "exit with code 3 when the run had an alarm of one of these categories (comma-separated):"
    " trip, fault, unsupplied, overdischarge, crosscharge, limit, refused, crosscurrent,"
    " reserve, unknown"
)


@app.command()
def simulate(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, or an example's name")],
    db: Annotated[Path | None, typer.Option(help="record telemetry to this SQLite file")] = None,
    trace_csv: Annotated[Path | None, typer.Option(help="write the per-step trace as CSV")] = None,
    plot: Annotated[Path | None, typer.Option(help="write a PNG of V, I, SOC, T")] = None,
    report: Annotated[
        Path | None, typer.Option(help="write a self-contained HTML report of the run")
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="print the verdict and the metrics as JSON")
    ] = False,
    duration: Annotated[float | None, typer.Option(help="override sim.duration_s")] = None,
    progress: Annotated[
        bool | None,
        typer.Option(
            "--progress/--no-progress",
            help="progress on stderr (default: a bar when stderr is a terminal)",
            show_default=False,
        ),
    ] = None,
    can_interface: Annotated[
        str | None, typer.Option(help="charger over CAN: python-can interface (virtual, socketcan)")
    ] = None,
    can_channel: Annotated[str | None, typer.Option(help="CAN channel, e.g. can0")] = None,
    can_log: Annotated[Path | None, typer.Option(help="log CAN frames to .blf or .asc")] = None,
    fail_on: Annotated[str | None, typer.Option(help=FAIL_ON_HELP)] = None,
) -> None:
    """Run a closed-loop simulation of a scenario.

    Exit codes: 0 done, 2 bad input, 3 --fail-on matched, 130 interrupted (Ctrl-C).
    """

    def go() -> int:
        from packpilot.sim.verdict import parse_fail_on

        path = scenario_path(config)
        categories = parse_fail_on(fail_on) if fail_on is not None else []
        cfg = _with_can(_load(path, duration), can_interface, can_channel, can_log)
        _check_outputs(db=db, trace_csv=trace_csv, plot=plot, report=report, can_log=can_log)
        started = datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")
        result = _run_interruptible(cfg, path, db, progress, (report, plot, trace_csv))
        with _saying("writing the outputs and the verdict", bool(progress)):
            _write_outputs(result, cfg.model_dump(mode="json"), path, trace_csv, plot, report,
                           db, started)  # fmt: skip
            summary = _summary(result, cfg.model_dump(mode="json"), as_json)
        return _emit_summary(summary, as_json, categories)

    code = _guard(go, announce=progress)
    if code:
        raise typer.Exit(code=code)


@contextlib.contextmanager
def _saying(label: str, on: bool, every_s: float = 1.5) -> Iterator[None]:
    """``label ...`` on stderr, repeated with the time spent every ``every_s`` until the block
    ends (``--progress``: ``make demo`` never leaves its reader in silence)."""
    if not on:
        yield
        return
    t0 = time.perf_counter()
    print(f"{label} ...", file=sys.stderr, flush=True)
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(every_s):
            print(f"{label} ... ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def _load(path: Path, duration: float | None) -> ScenarioConfig:
    """The scenario, with ``--duration`` applied (validated as ``sim.duration_s`` is)."""
    from packpilot.config import load_config

    return _with_duration(load_config(path), duration)


def _with_can(
    cfg: ScenarioConfig, interface: str | None, channel: str | None, log: Path | None
) -> ScenarioConfig:
    """The ``--can-*`` options applied; refused when there is nothing for CAN to carry (no
    charger) or the interface is not one python-can knows, before the run starts."""
    if not (interface or channel or log):
        return cfg
    from packpilot.errors import ConfigError

    if not cfg.charger.present:
        raise ConfigError(
            "--can-*: this scenario has no charger ([charger] present = false); the CAN link"
            " only carries the charger's setpoints and status"
        )
    if interface is not None:
        import can

        known = sorted(can.interfaces.VALID_INTERFACES)
        if interface not in known:
            raise ConfigError(
                f"--can-interface {interface!r}: not a python-can interface; one of"
                f" {', '.join(known)}"
            )
    update = {
        k: str(v)
        for k, v in (("interface", interface), ("channel", channel), ("log", log))
        if v is not None
    }
    return _revalidated(cfg, "can", update, "--can-*")


def _run_interruptible(
    cfg: ScenarioConfig,
    path: Path,
    db: Path | None,
    progress: bool | None,
    outputs: tuple[Path | None, ...] = (),
) -> Result:
    """The run; Ctrl-C ends it with a message and exit code 130 (a ``--db`` run is stamped
    ``interrupted``, with every sample up to that point). The message names the ``outputs``
    (report, plot, CSV) that were asked for and are therefore not written."""
    from packpilot.sim.runner import Runner

    with _saying("building the pack and the BMS", bool(progress)):
        runner = _named(path, lambda: Runner(cfg, progress=progress))
    begin()  # a first run: interpreted, compiling in the background (its input now checked)
    try:
        if db is None:
            return runner.run()
        from packpilot.io.telemetry import SQLiteRecorder

        with SQLiteRecorder(db) as recorder:
            runner.recorder = recorder
            return runner.run()
    except KeyboardInterrupt:
        t_s = runner.steps_done * cfg.sim.dt_s
        kept = f"; {db} holds the run up to there, status 'interrupted'" if db else ""
        typer.echo(f"interrupted at t = {t_s:.1f} s{kept}", err=True)
        missing = [str(p) for p in outputs if p is not None]
        if missing:
            typer.echo(f"not written: {', '.join(missing)} (the run did not finish)", err=True)
        raise typer.Exit(code=EXIT_INTERRUPTED) from None


def _write_outputs(
    result: Result, cfg: dict[str, Any], path: Path, trace_csv: Path | None, plot: Path | None,
    report: Path | None, db: Path | None, started: str,
) -> None:  # fmt: skip
    if trace_csv is not None:
        from packpilot.io.telemetry import trace_to_csv

        trace_to_csv(result, trace_csv)
    if plot is not None:
        from packpilot.report.plots import plot_run

        plot_run(result, plot)
    if report is not None:
        _write_report(result, report, cfg, path, db, started)


def _summary(result: Result, cfg: dict[str, Any], as_json: bool) -> Any:
    """The verdict and the metrics (compiling the kernels reported apart from wall_time_s)."""
    from packpilot.sim.verdict import run_verdict

    verdict = run_verdict(result, cfg)
    metrics = {**result.metrics, "build_time_s": result.build_time_s}
    return verdict, metrics


def _emit_summary(summary: Any, as_json: bool, categories: list[str]) -> int:
    """Print the verdict, the alarms and the metrics; the exit code ``--fail-on`` asks for."""
    from packpilot.sim.verdict import fail_on

    verdict, metrics = summary
    if as_json:
        out = {"verdict": verdict.as_dict(), **metrics}
        typer.echo(json.dumps(out, default=_json_default))
    else:
        _print_verdict(verdict)
        _print_metrics(metrics)
    hits = fail_on(verdict, categories)
    if hits:
        typer.echo(f"fail-on: {', '.join(hits)} (exit code {EXIT_FAIL_ON})", err=True)
        return EXIT_FAIL_ON
    return 0


def _with_duration(cfg: ScenarioConfig, duration: float | None) -> ScenarioConfig:
    """``--duration`` validated as ``sim.duration_s`` is (``--duration 0`` / ``-5`` were
    tracebacks when the override bypassed the model)."""
    if duration is None:
        return cfg
    return _revalidated(cfg, "sim", {"duration_s": duration}, "--duration")


PERIOD_RANGE_S = (1e-4, 10.0)
"""A BMS period on the command line: the range of ``sim.dt_s`` (0.1 ms to 10 s)."""
MAX_RUN_ID = 2**63 - 1
"""Largest run id SQLite can hold (a signed 64-bit integer; 2^63 raised OverflowError)."""
DRONECAN_NODE_IDS = (1, 127)
"""DroneCAN node ids a node may take (0 is anonymous, 7 bits)."""
MAX_SPEED = 1e6
"""Fastest ``--speed`` (simulated s per wall s; 0 = as fast as possible)."""


def check_option(option: str, value: float | None, lo: float, hi: float, unit: str = "") -> None:
    """A numeric option within ``lo..hi`` (NaN and inf fail), else one line naming it
    (``run --duration nan`` ran 0 steps and exited 0; ``--node-id 200`` was accepted)."""
    if value is None:
        return
    from packpilot.errors import ConfigError

    if not lo <= value <= hi:
        ends = "..".join(f"{x:g}" if isinstance(x, float) else str(x) for x in (lo, hi))
        raise ConfigError(f"{option} {value!r}: must be {ends}{unit}")


def _check_duration(duration: float | None) -> None:
    """``--duration`` of a run that has no scenario duration to validate it against."""
    from packpilot.config.base import MAX_TIME_S

    check_option("--duration", duration, 1e-4, MAX_TIME_S, " s")


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


def _print_verdict(verdict: Verdict) -> None:
    """The verdict and the alarms table, first: what a reader must not miss."""
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    style = {"OK": "bold green", "WARNING": "bold yellow"}.get(verdict.word, "bold red")
    con = Console()
    con.print(Text.assemble("verdict: ", (verdict.word, style)))
    if not verdict.alarms:
        return
    table = Table(title="alarms", show_header=True)
    for col in ("first at (s)", "battery", "severity", "cause", "cleared"):
        table.add_column(col, justify="right" if col.startswith("first") else "left")
    for a in verdict.alarms:
        cleared = f"yes ({a.cleared_t_s:.1f} s)" if a.cleared_t_s is not None else "no"
        times = f" ×{a.count}" if a.count > 1 else ""
        table.add_row(
            f"{a.t_s:.1f}", a.battery or "pack", a.severity.label,
            Text(f"{a.kind}: {a.cause}{times}"), cleared,
        )  # fmt: skip
    con.print(table)


def _metric_text(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return ", ".join(_metric_text(x) for x in v)
    if isinstance(v, dict):
        return ", ".join(f"{k} {_metric_text(x)}" for k, x in v.items()) or "none"
    return str(v)


def _print_metrics(m: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    table = Table(title="run summary", show_header=True)
    table.add_column("metric")
    table.add_column("value", justify="right")
    for k, v in m.items():
        table.add_row(k, Text(_metric_text(v)))  # Text: a value is never read as markup
    Console().print(table)


@calibrate_app.command("protection")
def calibrate_protection_cmd(
    cell: Annotated[
        str, typer.Option(help="shipped cell set (uav_5ah, ...) or a packpilot-cell/1 JSON file")
    ],
    soc_floor: Annotated[
        float, typer.Option(help="SOC the cells must keep when the allowance is used up")
    ] = 0.02,
    parallel: Annotated[int, typer.Option(help="cells in parallel per group")] = 1,
    min_temp: Annotated[
        float | None,
        typer.Option(help="corner of the coldest band, degC (default: the set's lowest)"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="TOML file to write (default: standard output)")
    ] = None,
) -> None:
    """Cut-off per (current, temperature) cell from the cell set's OCV and resistance tables:
    OCV at the floor (plus the charge the allowance may draw) minus I x R at the cell's worst
    corner; writes a [protection] section (docs/discharge_protection.md, "Calibrated table")."""

    def go() -> None:
        from packpilot.model.cell import load_parameter_file, load_parameter_set
        from packpilot.model.cell.calibrate import calibrate_protection, to_toml
        from packpilot.model.cell.params import PARAMETER_SETS

        check_option("--parallel", parallel, 1, 64)
        check_option("--min-temp", min_temp, -100.0, 100.0, " degC")
        params = load_parameter_set(cell) if cell in PARAMETER_SETS else load_parameter_file(cell)
        cfg, cells = calibrate_protection(params, soc_floor, parallel=parallel, min_temp_c=min_temp)
        header = (
            f"packpilot calibrate protection --cell {cell} --soc-floor {soc_floor:g} "
            f"--parallel {parallel}"
            + ("" if min_temp is None else f" --min-temp {min_temp:g}")
            + "\ncut-off = OCV(s_c, T) - I (R0 + R1)(T, I, s_c) at each cell's worst corner,"
            "\ns_c = floor + I t_max / (3600 Q); t_max from the source's table"
        )
        text = to_toml(cfg, cells, header)
        if out is None:
            typer.echo(text, nl=False)
        else:
            out.write_text(text, encoding="utf-8")
            typer.echo(f"wrote {out} ({len(cells)} cells)")

    _guard(go)


@app.command()
def report(
    db: Annotated[Path, typer.Argument(help="telemetry SQLite file (simulate --db)")],
    out: Annotated[
        Path | None,
        typer.Option(help="HTML file to write (default: next to DB, run.sqlite -> run.html)"),
    ] = None,
    run_id: Annotated[int | None, typer.Option(help="run to report (default: latest)")] = None,
    can_log: Annotated[
        Path | None,
        typer.Option(help="CAN log (.blf/.asc) for the CAN section (default: the run's can.log)"),
    ] = None,
) -> None:
    """Write a self-contained HTML report (interactive charts inline, no network) of a recorded
    run."""

    def go() -> None:
        from packpilot.report.html import report_from_db

        check_option("--run-id", run_id, 1, MAX_RUN_ID)
        target = out if out is not None else default_report_path(db, run_id)
        path = report_from_db(db, target, run_id, can_log)
        typer.echo(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")

    _guard(go)


@app.command("plan-join")
def plan_join(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, or an example's name")],
    soc: Annotated[str, typer.Option(help="pack SOCs to tabulate, comma-separated")] = (
        "0.2,0.5,0.8"
    ),
    temp: Annotated[
        str | None,
        typer.Option(help="temperatures (degC), comma-separated (default: 0 and the ambient)"),
    ] = None,
    switch_a: Annotated[
        float | None,
        typer.Option(help="the switch's peak current rating (A; default: battery limits only)"),
    ] = None,
    load_a: Annotated[
        float, typer.Option(help="current the other batteries carry meanwhile (A; < 0 charging)")
    ] = 0.0,
    as_json: Annotated[bool, typer.Option("--json", help="print the rows as JSON")] = False,
) -> None:
    """The join planner as a designer's table: for each battery about to join the others,
    the admissible voltage difference (above / below the bus) and the predicted peak current
    at the supervisor's fixed join_limit_v (docs/power.md)."""

    def go() -> None:
        from packpilot.sim.power import join_table

        cfg = _load(scenario_path(config), None)
        socs = _floats("--soc", soc, 0.0, 1.0)
        temps = _floats("--temp", temp, -60.0, 100.0) if temp is not None else None
        check_option("--switch-a", switch_a, 1e-3, 1e6, " A")
        check_option("--load-a", load_a, -1e5, 1e5, " A")
        rows = join_table(cfg, socs, temps, switch_a if switch_a is not None else float("inf"),
                          load_a)  # fmt: skip
        if as_json:
            typer.echo(json.dumps(rows, default=_json_default))
            return
        typer.echo(f"{cfg.pack.name}: admissible dV at which a battery may join (its switch"
                   " and every battery within its current limits), the others at rest"
                   f" carrying {load_a:g} A")  # fmt: skip
        typer.echo(f"{'battery':>8} {'SOC':>5} {'T degC':>6} {'R loop':>8} {'dV up':>7} "
                   f"{'dV down':>7} {'peak at':>8} {'':>9} {'half s':>7}")  # fmt: skip
        for r in rows:
            fixed = f"{r['fixed_dv_v']:g} V"
            typer.echo(f"{r['battery']:>8} {r['soc']:>5.2f} {r['temp_c']:>6.1f} "
                       f"{float(r['r_loop_ohm']) * 1e3:>6.1f}mO {r['dv_up_v']:>6.3f}V "
                       f"{r['dv_down_v']:>6.3f}V {fixed:>8} {r['peak_at_fixed_a']:>7.1f}A "
                       f"{r['half_s']:>7.2f}")  # fmt: skip

    _guard(go)


def _floats(option: str, text: str, lo: float, hi: float) -> tuple[float, ...]:
    """A comma-separated list of numbers within ``lo..hi``, else one line naming the option."""
    from packpilot.errors import ConfigError

    try:
        values = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"{option} {text!r}: not a comma-separated list of numbers") from None
    if not values:
        raise ConfigError(f"{option} {text!r}: give at least one number")
    for v in values:
        check_option(option, v, lo, hi)
    return values


def default_report_path(db: Path, run_id: int | None) -> Path:
    """``run.sqlite`` -> ``run.html`` (``run_3.html`` for ``--run-id 3``), beside the file."""
    return db.with_name(db.stem + (f"_{run_id}" if run_id is not None else "") + ".html")


def _print_summary(summary: dict[str, Any], as_json: bool) -> None:
    from packpilot.replay.common import summary_lines

    if as_json:
        typer.echo(json.dumps(summary, default=_json_default))
    else:
        for line in summary_lines(summary):
            typer.echo(line)


def _replay(
    method: str, log: Path, config: Path | None, out: Path | None, as_json: bool,
    options: Any,
) -> None:  # fmt: skip
    def go() -> None:
        from packpilot.replay.config import load_replay_config

        replay = REGISTRY[method].replay
        assert replay is not None
        if out is not None and str(out) != "-":
            _check_outputs(out=out)
        run: Callable[..., Any] = replay.function()  # (log, config, options)
        result = run(log, load_replay_config(config, method), options)
        if out is not None and str(out) == "-":
            import csv

            writer = csv.writer(sys.stdout)
            writer.writerow(result.columns)
            writer.writerows(result.rows)
            return
        if out is not None:
            result.write_csv(out)
        _print_summary(result.summary, as_json)
        if out is not None and not as_json:
            typer.echo(f"wrote {out} ({len(result.rows)} rows)")

    _guard(go)


LogArg = Annotated[
    Path, typer.Argument(help="log: CSV (simulate --trace-csv, import), .ulg, .bin, .log, .tlog")
]
ConfigOpt = Annotated[
    Path | None,
    typer.Option(help="TOML with the method's section, or a replay's --json output"),
]
OutOpt = Annotated[
    Path | None, typer.Option(help="write the per-row output table as CSV ('-': to stdout)")
]
JsonOpt = Annotated[bool, typer.Option("--json", help="print the summary as JSON")]
BatteryOpt = Annotated[
    str | None, typer.Option(help="battery of a multi-battery log (its column prefix, e.g. A)")
]
AssumeTempOpt = Annotated[
    float | None,
    typer.Option(help="temperature (degC) to assume when the log has none; stated in the output"),
]
CellsOpt = Annotated[
    int | None,
    typer.Option(help="series cells, for a log with neither cell voltages nor a cell count"),
]


def _replay_command(method: str, help_text: str) -> None:
    """``packpilot replay METHOD``: one command per registered replay adapter."""

    def command(
        log: LogArg, config: ConfigOpt = None, out: OutOpt = None, as_json: JsonOpt = False,
        battery: BatteryOpt = None, assume_temp_c: AssumeTempOpt = None, cells: CellsOpt = None,
    ) -> None:  # fmt: skip
        from packpilot.replay.common import LogOptions

        _replay(method, log, config, out, as_json, LogOptions(battery, assume_temp_c, cells))

    replay_app.command(method, help=help_text)(command)


def _replay_help(name: str, fallback: str) -> str:
    """The replay module's own help (its column vocabulary), else the registry's."""
    import importlib

    module = importlib.import_module(f"packpilot.replay.{name}")
    return str(getattr(module, "HELP", fallback))


for _entry in REGISTRY.values():
    if _entry.replay is not None:
        _replay_command(_entry.name, _replay_help(_entry.name, _entry.replay.help))


@replay_app.command("flight")
def replay_flight_cmd(
    log: LogArg,
    report: Annotated[
        Path | None, typer.Option(help="write the HTML report 'what PackPilot would have done'")
    ] = None,
    config: Annotated[
        Path | None, typer.Option(help="TOML with [protection] and [sequencing] sections")
    ] = None,
    as_json: JsonOpt = False,
    assume_temp_c: AssumeTempOpt = None,
    cells: CellsOpt = None,
    parallel: Annotated[
        str | None,
        typer.Option(help="two batteries of the log that were in parallel, e.g. A,B "
                     "(otherwise every battery is independent)"),
    ] = None,
) -> None:
    """What PackPilot would have done on a recorded flight: every battery through discharge
    protection and, for two batteries the user says were in parallel (--parallel A,B), the
    pair through parallel discharge sequencing. What the log lacks is listed, never filled
    in silently."""

    def go() -> None:
        from packpilot.replay.common import LogOptions
        from packpilot.replay.config import load_replay_config
        from packpilot.replay.flight import replay_flight
        from packpilot.report.flight import write_flight_page

        if report is not None:
            _check_outputs(report=report)
        prot = load_replay_config(config, "protection", other_method_ok=True)
        seq = load_replay_config(config, "sequencing", other_method_ok=True)
        from packpilot.errors import InputError

        pair = None
        if parallel is not None:
            parts = [p.strip() for p in parallel.split(",")]
            if len(parts) != 2 or not all(parts):
                raise InputError(f"--parallel {parallel!r}: give two battery names, e.g. A,B")
            pair = (parts[0], parts[1])
        fr = replay_flight(log, prot, seq, LogOptions(None, assume_temp_c, cells), pair)  # type: ignore[arg-type]
        _print_summary(fr.summary, as_json)
        if report is not None:
            write_flight_page(fr, report)  # the run report's zoomable charts
            if not as_json:
                typer.echo(f"wrote {report}")

    _guard(go)


@app.command("import")
def import_cmd(
    log: Annotated[Path, typer.Argument(help="flight log: .ulg, .bin, .log, .tlog")],
    out: Annotated[Path, typer.Option(help="CSV to write (PackPilot's log columns)")],
    assume_temp_c: AssumeTempOpt = None,
    cells: CellsOpt = None,
) -> None:
    """Convert a flight log's battery data to a CSV that every `packpilot replay` reads: per
    battery A, B, ... the columns <name>_voltage_v, _current_a, _temp_c, _min_cell_v, ... as
    `simulate --trace-csv` names them. What the log lacks is printed and left out."""

    def go() -> None:
        from packpilot.io.flightlog import read_flight_log

        _check_outputs(out=out)
        table = read_flight_log(log).table(cells=cells, assume_temp_c=assume_temp_c)
        table.write_csv(out)
        for note in table.notes:
            typer.echo(f"note: {note}", err=True)
        for what in table.assumed:
            typer.echo(f"assumed: {what}", err=True)
        typer.echo(f"wrote {out} ({table.n_rows} rows, columns {', '.join(table.columns)})")

    _guard(go)


# --- packpilot fit (issue 27) ------------------------------------------------------------


@app.command("fit")
def fit_cmd(
    logs: Annotated[
        list[Path], typer.Argument(help="flight logs (.ulg, .bin, .log, .tlog) of one battery type")
    ],
    out: Annotated[
        Path | None, typer.Option(help="cell set to write (.json, what [pack] cell accepts)")
    ] = None,
    report: Annotated[Path | None, typer.Option(help="write the validation report (.html)")] = None,
    battery: BatteryOpt = None,
    cells: CellsOpt = None,
    chemistry: Annotated[
        str, typer.Option(help="shipped set whose OCV, thermal data and limits are the template")
    ] = "uav_5ah",
    train_share: Annotated[
        float, typer.Option(help="share of each log's samples to fit on; the rest tests the fit")
    ] = 0.6,
    validate: Annotated[
        str,
        typer.Option(
            help="time: fit on the first part of each log, test on the rest; flights: leave "
            "one flight out (>= 3 flights in the logs given; docs/fit.md)"
        ),
    ] = "time",
    series_ohm: Annotated[
        float,
        typer.Option(
            min=0.0,
            help="the logged battery's leads, connectors and current shunt up to the logger's "
            "voltage sensor (Ohm, whole battery; measured): taken out of the fitted R0 as "
            "series_ohm, which heats no cell. The logs cannot tell it; 0: not split (flagged)",
        ),
    ] = 0.0,
    as_json: JsonOpt = False,
) -> None:
    """Fit a cell model to flight logs (capacity, initial SOC per log, R0, R1/tau1, a second
    RC pair where resolved) on the first part of each log, test it on the rest, and say
    whether it is usable, with each parameter's uncertainty and what cannot be identified."""

    def go() -> None:
        import json

        from packpilot.model.cell import load_parameter_set
        from packpilot.model.fit.cellset import cellset_dict, whatif_assumptions
        from packpilot.model.fit.validate import fit_and_validate
        from packpilot.replay.fitlogs import profiles_from_logs
        from packpilot.report.fit_report import write_fit_report

        if out is not None:
            from packpilot.io.outputs import check_output

            check_output(out, "--out", (".json",))
        if report is not None:
            _check_outputs(report=report)
        base = load_parameter_set(chemistry)
        profiles, notes = profiles_from_logs(list(logs), cells, battery)
        v = fit_and_validate(profiles, base.ocv_soc, base.ocv_table_v, train_share=train_share,
                             mode=validate)  # fmt: skip
        name = out.stem if out is not None else "fitted"
        data = cellset_dict(v, name, chemistry, profiles[0].series_cells, series_ohm)
        data["notes"]["logs"] = notes
        if out is not None:
            out.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
        if report is not None:
            write_fit_report(
                v, ", ".join(p.name for p in profiles), report,
                whatif_assumptions(v, profiles[0].series_cells, series_ohm),
            )  # fmt: skip
        summary = {k: data["notes"][k] for k in ("verdict", "reasons", "not_identifiable",
                                                 "assumptions", "notes", "validation")}  # fmt: skip
        summary["parameters"] = {
            k: {"value": p["value"], "unit": p["unit"], "rel_uncertainty": p["rel_uncertainty"]}
            for k, p in data["notes"]["parameters"].items()
        }
        summary["window"] = data["notes"]["window"]
        summary["fit_cpu_s"] = data["notes"]["fit_cpu_s"]
        _print_summary(summary, as_json)
        for path in (out, report):
            if path is not None and not as_json:
                typer.echo(f"wrote {path}")

    _guard(go)


fleet_app = typer.Typer(
    help="Battery health across flights: one record per flight per battery (SQLite), one row "
    "per battery with its trend and flags.",
    no_args_is_help=True,
)
app.add_typer(fleet_app, name="fleet")
FleetDb = Annotated[Path, typer.Option(help="the fleet's SQLite file")]


@fleet_app.command("add")
def fleet_add_cmd(
    logs: Annotated[list[Path], typer.Argument(help="flight logs (.ulg, .bin, .log, .tlog)")],
    db: FleetDb = Path("fleet.sqlite"),
    label: Annotated[
        str | None, typer.Option(help="the battery's label, when the log has no serial number")
    ] = None,
    battery: BatteryOpt = None,
    cells: CellsOpt = None,
) -> None:
    """Fit each flight of each battery and keep one record per flight per battery."""

    def go() -> None:
        from packpilot.replay.fleet import add_logs

        for line in add_logs(db, list(logs), label, cells, battery):
            typer.echo(line)

    _guard(go)


@fleet_app.command("report")
def fleet_report_cmd(
    db: FleetDb = Path("fleet.sqlite"),
    r0_rise: Annotated[float, typer.Option(help="flag R0 up by more than this share")] = 0.20,
    fade: Annotated[float, typer.Option(help="flag capacity down by more than this share")] = 0.10,
    spread_rise: Annotated[
        float, typer.Option(help="flag cell spread up by more than this (V)")
    ] = 0.020,
    as_json: JsonOpt = False,
) -> None:
    """One row per battery: flights, R0 first vs recent, capacity and cell-spread change, flags."""

    def go() -> None:
        from packpilot.replay.fleet import report

        rows = report(db, r0_rise, fade, spread_rise)
        if as_json:
            typer.echo(json.dumps(rows))
            return
        for r in rows:
            flags = "; ".join(r["flags"]) or "no flag"  # type: ignore[arg-type]
            typer.echo(
                f"{r['battery']}: {r['flights']} flights, R0 {r['r0_first_mohm']:.2f} -> "
                f"{r['r0_recent_mohm']:.2f} mOhm ({r['r0_change_pct']:+.0f} %), lowest cell "
                f"{r['lowest_cell_v']:.2f} V"
                + (f", cell spread {r['cell_spread_first_mv']:.0f} -> "
                   f"{r['cell_spread_recent_mv']:.0f} mV" if r.get("cell_spread_flights") else "")
                + f": {flags}"
            )  # fmt: skip

    _guard(go)


# --- end packpilot fit ----------------------------------------------------------------------


@app.command()
def campaign(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, or an example's name")],
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
    fail_on: Annotated[str | None, typer.Option(help=CAMPAIGN_FAIL_ON_HELP)] = None,
    plot: Annotated[
        Path | None, typer.Option(help="also write histograms of every varying column (.png)")
    ] = None,
) -> None:
    """Monte-Carlo campaign: N closed-loop runs over parameter spreads (Dask), to Parquet.

    Exit codes: 0 done, 2 bad input, 3 --fail-on matched in some run, 130 interrupted.
    """

    def go() -> int:
        from packpilot import campaign as cp
        from packpilot.sim.verdict import parse_fail_on

        categories = parse_fail_on(fail_on) if fail_on is not None else []
        if plot is not None and plot.suffix.lower() != ".png":
            from packpilot.errors import InputError

            raise InputError(f"--plot {plot}: the histograms are a PNG; give a .png name")
        path = scenario_path(config)
        target = out if out is not None else Path(f"{path.stem}_campaign.parquet")
        check_campaign_out(target)
        _check_outputs(out=target)
        cfg = _load(path, duration)
        show = not (as_json or no_progress) and sys.stdout.isatty()
        try:
            with cp.rich_progress(show) as bar:
                progress = _warn_identical(runs if spread is None else 0, bar)
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
            typer.echo(cp.interrupted_note(target, runs), err=True)
            _exit_now(EXIT_INTERRUPTED)
        png = cp.plot_histograms(report.table, plot) if plot is not None else None
        if as_json:
            typer.echo(json.dumps(cp.report_to_dict(report, png), default=_json_default))
        else:
            cp.print_summary(report)
            typer.echo(
                f"wrote {report.out} ({report.table.num_rows} runs)" + (f", {png}" if png else "")
            )
        hits = cp.fail_on_runs(report.table, categories)
        if hits:
            said = ", ".join(f"{c} in {n} run(s)" for c, n in hits.items())
            typer.echo(f"fail-on: {said} (exit code {EXIT_FAIL_ON})", err=True)
            return EXIT_FAIL_ON
        return 0

    code = _guard(go)
    if code:
        raise typer.Exit(code=code)


def _exit_now(code: int) -> None:
    """Exit at once, skipping the interpreter's teardown. After Ctrl-C in a campaign every kept
    run is already on disk (part files, renamed into place) and the cluster is closed; what is
    left is Dask's threads winding down, measured at ~3 s of nothing (#29)."""
    import os

    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


CAMPAIGN_FAIL_ON_HELP = (
    "exit with code 3 when some run had an alarm of one of these categories (comma-separated),"
    " as simulate --fail-on; e.g. overdischarge"
)


def _warn_identical(
    runs: int, bar: Callable[[int, int], None] | None
) -> Callable[[int, int], None]:
    """The campaign's progress callback, which first (once every option has been checked and
    the runs are about to start) warns that ``runs`` > 1 runs without spreads are identical."""
    warned = runs < 2

    def progress(done: int, total: int) -> None:
        nonlocal warned
        if not warned:
            warned = True
            typer.echo(
                f"warning: no --spread: the {runs} runs share every parameter and give the"
                " same result (add e.g. --spread capacity=5%,r0=10%)",
                err=True,
            )
        if bar is not None:
            bar(done, total)

    return progress


def check_campaign_out(out: Path) -> None:
    """A campaign writes Parquet (``--resume`` reads it back): refuse any other suffix before
    the runs, rather than Parquet bytes in a file called ``.csv``."""
    from packpilot.errors import InputError

    if out.suffix.lower() != ".parquet":
        raise InputError(
            f"--out {out}: a campaign writes Parquet; give a .parquet name (pyarrow or pandas"
            " read it; pyarrow.csv.write_csv converts it)"
        )


@app.command()
def dashboard(
    config: Annotated[
        Path | None,
        typer.Argument(
            help="scenario TOML file or an example's name to run, or a recorded SQLite run to"
            " open (none: pick on the page)"
        ),
    ] = None,
    host: Annotated[
        str, typer.Option(help="address to listen on (not loopback: needs --allow-remote)")
    ] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port (0: any free port)")] = 8765,
    speed: Annotated[
        float, typer.Option(help="simulated seconds per wall second (0: as fast as possible)")
    ] = 10.0,
    db: Annotated[Path | None, typer.Option(help="also record telemetry to this SQLite")] = None,
    duration: Annotated[float | None, typer.Option(help="override sim.duration_s")] = None,
    runs_dir: Annotated[
        Path | None,
        typer.Option(help="directory whose recorded runs (*.sqlite, *.db) the page may open"),
    ] = None,
    run_id: Annotated[
        int | None, typer.Option(help="run to open in a recording (default: latest)")
    ] = None,
    report: Annotated[
        Path | None,
        typer.Option(help="write the HTML report of a run that finishes here (page links it)"),
    ] = None,
    allow_remote: Annotated[
        bool,
        typer.Option(
            "--allow-remote",
            help="allow a non-loopback --host; every request then needs the token",
        ),
    ] = False,
    token: Annotated[
        str | None,
        typer.Option(
            envvar="PACKPILOT_DASHBOARD_TOKEN",
            help="access token (default: a fresh random one, printed with --allow-remote)",
        ),
    ] = None,
    allowed_host: Annotated[
        list[str] | None,
        typer.Option(help="another Host name the page is reached by (with --allow-remote)"),
    ] = None,
    max_websockets: Annotated[int, typer.Option(help="most live page connections at once")] = 32,
    max_connections: Annotated[int, typer.Option(help="most open HTTP connections at once")] = 64,
    fleet: Annotated[
        Path | None,
        typer.Option(help="a fleet SQLite (packpilot fleet add) shown on the page /fleet"),
    ] = None,
) -> None:
    """Run a scenario and watch it live in a browser, or open a recorded run (Ctrl-C stops)."""

    def go() -> None:
        import contextlib

        from packpilot.errors import ConfigError
        from packpilot.web.app import Dashboard
        from packpilot.web.recorded import is_sqlite
        from packpilot.web.session import RECORDING_SUFFIXES, Library

        check_option("--speed", speed, 0.0, MAX_SPEED, " (0 = as fast as possible)")
        check_option("--port", port, 0, 65535)
        check_option("--run-id", run_id, 1, MAX_RUN_ID)
        check_option("--max-websockets", max_websockets, 1, 10_000)
        check_option("--max-connections", max_connections, 1, 10_000)
        if runs_dir is not None and not runs_dir.is_dir():
            raise ConfigError(f"--runs-dir {runs_dir}: not a directory")
        if fleet is not None and not fleet.is_file():
            raise ConfigError(f"--fleet {fleet}: no such fleet database (packpilot fleet add)")
        if db is not None:
            _check_outputs(db=db)
        if report is not None:
            _check_outputs(report=report)
        recording = None
        if config is not None and (
            is_sqlite(config) or config.suffix.lower() in RECORDING_SUFFIXES
        ):
            recording = config
        runner, name, path = None, "no run yet", None
        if config is not None and recording is None:
            path = scenario_path(config)
            cfg = _load(path, duration)
            runner = _named(path, lambda: _runner(cfg))
            name = cfg.pack.name if "name" in cfg.pack.model_fields_set else path.stem
        library = Library.of_dirs(
            _example_dirs(), runs_dir, [recording] if recording is not None else []
        )
        dash = Dashboard(
            runner, scenario=name, source=str(path) if path else None, speed=speed, db=db,
            host=host, port=port,
            recording=recording, run_id=run_id, library=library,
            make_runner=lambda p: _named(p, lambda: _runner(_load(p, duration))),
            write_report=_dashboard_report(report), fleet=fleet, allow_remote=allow_remote,
            token=token,
            allowed_hosts=tuple(allowed_host or ()), max_websockets=max_websockets,
            max_connections=max_connections,
        )  # fmt: skip
        shown = dash.live.scenario
        typer.echo(f"dashboard for {shown} on {dash.open_url}  (Ctrl-C to stop)", err=True)
        if fleet is not None:
            typer.echo(f"fleet view: {dash.open_url.split('?')[0].rstrip('/')}/fleet", err=True)
        if dash.guard.remote:
            typer.echo(f"token: {dash.guard.token}  (every request needs it)", err=True)
        dash.start()
        with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C / SIGTERM: the normal way out
            dash.serve()
        st = dash.live.status()  # the run on show now: the page may have started another
        if st["kind"] == "live" and st["state"] != "idle":
            why = f": {st['error']}" if st["error"] and st["state"] == "error" else ""
            what = st["scenario"] + (f", {st['source']}" if st.get("source") else "")
            typer.echo(f"run {st['state']} at t = {st['t_s']:.1f} s{why} ({what})", err=True)

    _guard(go)


DRONECAN_HELP = (
    "batteries reporting by DroneCAN BatteryInfo + BatteryInfoAux: their battery_id in"
    " [[pack.batteries]] order, -1 for PackPilot frames (e.g. 21,22)"
)


def _ids(text: str | None) -> tuple[int, ...] | None:
    """``--dronecan-ids 21,22,-1`` as integers (a bad list is a one-line error)."""
    if text is None:
        return None
    from packpilot.errors import ConfigError

    try:
        return tuple(int(x) for x in text.split(","))
    except ValueError:
        raise ConfigError(f"--dronecan-ids {text!r}: comma-separated integers") from None


CanIface = Annotated[
    str, typer.Option(help="python-can interface (socketcan, socketcand, virtual, ...)")
]
CanChan = Annotated[str, typer.Option(help="CAN channel, e.g. can0")]
ChargerChan = Annotated[
    str | None, typer.Option(help="the charger's CAN channel, if not the batteries'")
]
CanArgs = Annotated[
    list[str] | None,
    typer.Option(
        "--can-arg",
        metavar="KEY=VALUE",
        help="a python-can interface option, repeatable (socketcand: --can-arg host=127.0.0.1"
        " --can-arg port=29536; hardware: bitrate=500000); numbers and true/false are typed",
    ),
]


def _can_args(items: list[str] | None) -> dict[str, Any]:
    from packpilot.io.can.bus import parse_bus_args

    return parse_bus_args(items or ())


@app.command()
def run(
    config: Annotated[Path, typer.Argument(help="scenario TOML file describing the pack")],
    can_interface: CanIface = "socketcan",
    can_channel: CanChan = "can0",
    charger_channel: ChargerChan = None,
    period: Annotated[float, typer.Option(help="BMS period, s (monotonic clock)")] = 0.1,
    duration: Annotated[float | None, typer.Option(help="stop after this many s")] = None,
    db: Annotated[Path | None, typer.Option(help="record telemetry to this SQLite file")] = None,
    can_log: Annotated[Path | None, typer.Option(help="log every frame to .blf or .asc")] = None,
    node_id: Annotated[int, typer.Option(help="DroneCAN node id of the BMS")] = 100,
    allow_unmonitored: Annotated[
        bool, typer.Option(help="run without [plausibility]: stale telemetry NOT detected")
    ] = False,
    replay_log: Annotated[
        Path | None,
        typer.Option(help="re-run the BMS over the frames received in this .blf/.asc log"),
    ] = None,
    dronecan_ids: Annotated[str | None, typer.Option(help=DRONECAN_HELP)] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the metrics as JSON")] = False,
    can_arg: CanArgs = None,
) -> None:
    """The BMS on a real pack over CAN, until Ctrl-C or --duration (docs/runtime.md)."""

    def go() -> dict[str, Any]:
        from packpilot.runtime.bms import BmsRuntime, RuntimeOptions

        check_option("--period", period, *PERIOD_RANGE_S, " s")
        _check_duration(duration)
        check_option("--node-id", node_id, *DRONECAN_NODE_IDS, " (a DroneCAN node id)")
        cfg = _load(scenario_path(config), None)
        _check_outputs(db=db, can_log=can_log)
        opts = RuntimeOptions(
            interface=can_interface, channel=can_channel, charger_channel=charger_channel,
            period_s=period, log_path=can_log, node_id=node_id,
            allow_unmonitored=allow_unmonitored, dronecan_ids=_ids(dronecan_ids),
            bus_kwargs=tuple(_can_args(can_arg).items()),
        )  # fmt: skip
        if replay_log is not None:
            return _replay_frames(cfg, replay_log, opts, db)
        recorder = _recorder(db)
        bms = BmsRuntime(cfg, opts, recorder)
        begin()
        _sigterm_interrupts()
        typer.echo(
            f"packpilot run: {len(cfg.pack.batteries)} batteries on {can_interface}:"
            f"{can_channel}, period {period * 1e3:g} ms (Ctrl-C stops)", err=True,
        )  # fmt: skip
        try:
            return bms.run(duration)
        except KeyboardInterrupt:
            return bms.metrics()
        finally:
            bms.close()
            if recorder is not None:
                recorder.close()

    _print_runtime(_guard(go), as_json)


def _replay_frames(cfg: ScenarioConfig, log: Path, opts: Any, db: Path | None) -> dict[str, Any]:
    """The BMS of ``cfg`` over the frames received in ``log`` (``replay can``, ``run
    --replay-log``); its metrics."""
    from packpilot.runtime.logreplay import replay_log

    recorder = _recorder(db)
    try:
        done = replay_log(cfg, log, opts, recorder)
    finally:
        if recorder is not None:
            recorder.close()
    metrics: dict[str, Any] = done.metrics()
    return metrics


@app.command()
def hil(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, or an example's name")],
    can_interface: CanIface = "socketcan",
    can_channel: CanChan = "vcan0",
    charger_channel: ChargerChan = None,
    speed: Annotated[
        float, typer.Option(help="simulated seconds per wall second (0: as fast as possible)")
    ] = 1.0,
    bms_period: Annotated[float, typer.Option(help="the BMS's period, s (switch timeout)")] = 0.1,
    timeout_periods: Annotated[
        int, typer.Option(help="a switch node opens after this many BMS periods unheard")
    ] = 5,
    duration: Annotated[float | None, typer.Option(help="override sim.duration_s")] = None,
    can_log: Annotated[Path | None, typer.Option(help="log every frame to .blf or .asc")] = None,
    dronecan_ids: Annotated[str | None, typer.Option(help=DRONECAN_HELP)] = None,
    can_arg: CanArgs = None,
) -> None:
    """The simulated pack as CAN nodes (batteries, switches, charger, inverter) for `run`."""

    def go() -> dict[str, Any]:
        from packpilot.io.can.bus import FrameLog, open_bus
        from packpilot.runtime.bms import filters
        from packpilot.runtime.hil import Hil, run_realtime
        from packpilot.runtime.lockstep import REQUEST_ONLY

        check_option("--speed", speed, 0.0, MAX_SPEED, " (0 = as fast as possible)")
        check_option("--bms-period", bms_period, *PERIOD_RANGE_S, " s")
        check_option("--timeout-periods", timeout_periods, 1, 1000)
        kw = _can_args(can_arg)
        cfg = _load(scenario_path(config), duration)
        _check_outputs(can_log=can_log)
        bus = open_bus(can_interface, can_channel, **kw)
        charger_bus = open_bus(can_interface, charger_channel or can_channel,
                               **filters(can_interface, REQUEST_ONLY), **kw)  # fmt: skip
        log = FrameLog(can_log) if can_log is not None else None
        ids = _ids(dronecan_ids) or ()
        twin = Hil(cfg, bus, charger_bus=charger_bus, bms_period_s=bms_period,
                   timeout_periods=timeout_periods, log=log,
                   dronecan_ids={i: b for i, b in enumerate(ids) if b >= 0})  # fmt: skip
        begin()
        _sigterm_interrupts()
        typer.echo(f"packpilot hil: {cfg.pack.name} on {can_interface}:{can_channel} "
                   f"at {speed:g}x (Ctrl-C stops)", err=True)  # fmt: skip
        try:
            steps = run_realtime(twin, cfg.sim.dt_s, cfg.sim.duration_s, speed)
        except KeyboardInterrupt:
            steps = -1
        finally:
            bus.shutdown()
            charger_bus.shutdown()
            if log is not None:
                log.close()
        inv = twin.inverter.last
        return {
            "steps": steps, "t_s": twin.t_s,
            "switch_timeouts": sum(n.timeouts for n in twin.switch),
            "frames_sent": twin.counters.sent, "frames_received": twin.counters.received,
            "inverter_limits": inv.get("Pylon_Limits"), "inverter_soc": inv.get("Pylon_SocSoh"),
            "state_of_power": twin.power or None,
        }  # fmt: skip

    _print_runtime(_guard(go), as_json=True)


@app.command("can-hub")
def can_hub(
    port: Annotated[int, typer.Option(help="TCP port (0: any free port)")] = 29536,
    host: Annotated[
        str, typer.Option(help="address to listen on (not loopback: needs --allow-remote)")
    ] = "127.0.0.1",
    allow_remote: Annotated[
        bool,
        typer.Option(
            "--allow-remote",
            help="allow a non-loopback --host: whoever reaches it can send frames (no auth)",
        ),
    ] = False,
    bitrate: Annotated[
        float,
        typer.Option(help="bit/s one client may send, as on a real bus (0: unlimited)"),
    ] = 500_000,
) -> None:
    """A CAN bus over TCP on 127.0.0.1 for `run` and `hil` as two processes without vcan
    (socketcand's raw mode: --can-interface socketcand --can-arg host=.. --can-arg port=..).
    Ctrl-C or SIGTERM stops it."""

    def go() -> dict[str, int]:
        from packpilot.io.can.hub import CanHub

        check_option("--port", port, 0, 65535)
        hub = CanHub(host, port, allow_remote=allow_remote, bitrate=bitrate)
        addr, bound = hub.start()
        _sigterm_interrupts()
        typer.echo(f"can-hub on {addr}:{bound}  (clients: --can-interface socketcand --can-arg"
                   f" host={addr} --can-arg port={bound}; Ctrl-C stops)")  # fmt: skip
        try:
            hub.wait()
        except KeyboardInterrupt:
            pass
        finally:
            hub.close()
        return hub.stats.as_dict()

    stats = _guard(go)
    typer.echo("can-hub: " + ", ".join(f"{k} {v}" for k, v in stats.items()), err=True)


def _sigterm_interrupts() -> None:
    """SIGTERM (systemd, docker stop) ends `run` as Ctrl-C does: the record is finished and
    stamped ``interrupted``, the buses shut down, exit 0 (`hil` and `can-hub` likewise)."""
    import signal

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)


def _recorder(db: Path | None) -> Any:
    if db is None:
        return None
    from packpilot.io.telemetry import SQLiteRecorder

    return SQLiteRecorder(db, flush_every=50)


@replay_app.command("can")
def replay_can_cmd(
    log: Annotated[
        Path, typer.Argument(help="CAN frame log (.blf/.asc) written by run or hil --can-log")
    ],
    config: Annotated[Path, typer.Argument(help="scenario TOML describing the pack, as for run")],
    period: Annotated[float, typer.Option(help="BMS period, s (as the recorded run's)")] = 0.1,
    db: Annotated[Path | None, typer.Option(help="record telemetry to this SQLite file")] = None,
    dronecan_ids: Annotated[str | None, typer.Option(help=DRONECAN_HELP)] = None,
    allow_unmonitored: Annotated[
        bool, typer.Option(help="run without [plausibility]: stale telemetry NOT detected")
    ] = False,
    as_json: JsonOpt = False,
) -> None:
    """Re-run the whole BMS over the frames a `packpilot run` received (its --can-log): the
    telemetry goes back onto a private bus at its recorded times and the BMS decides anew, so
    a changed CONFIG shows what it would have done with the same batteries (docs/runtime.md).
    Same as `packpilot run CONFIG --replay-log LOG`."""

    def go() -> dict[str, Any]:
        from packpilot.runtime.bms import RuntimeOptions

        cfg = _load(scenario_path(config), None)
        _check_outputs(db=db)
        check_option("--period", period, *PERIOD_RANGE_S, " s")
        opts = RuntimeOptions(period_s=period, dronecan_ids=_ids(dronecan_ids),
                              allow_unmonitored=allow_unmonitored)  # fmt: skip
        return _replay_frames(cfg, log, opts, db)

    _print_runtime(_guard(go), as_json)


def _print_runtime(metrics: dict[str, Any], as_json: bool) -> None:
    if as_json:
        typer.echo(json.dumps(metrics, default=_json_default, indent=2))
        return
    for k, v in metrics.items():
        typer.echo(f"{k:>24}  {_metric_text(v)}")


def _runner(cfg: ScenarioConfig) -> Any:
    from packpilot.sim.runner import Runner

    return Runner(cfg, progress=False)


def _dashboard_report(out: Path | None) -> Callable[[Result, Any], Path | None] | None:
    """The dashboard's report writer (the web layer may not import the report)."""
    if out is None:
        return None

    def write(result: Result, live: Any) -> Path | None:
        from packpilot.report.html import RunInfo, run_info_from_db, write_report

        if live.db is not None and result.run_id is not None:
            info = run_info_from_db(Path(live.db), result.run_id)
        else:
            now = datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")
            cfg = live.config or {}
            info = RunInfo.from_config(cfg, status="ok", finished_at=now, source=live.source)
        return write_report(result, out, info)

    return write


def main() -> None:
    app()


if __name__ == "__main__":
    main()
