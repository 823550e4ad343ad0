"""What the dashboard shows now, and what the page may switch it to.

A :class:`Session` holds the current run (a live run in its ``SimThread``, or a recording) and
a generation number that bumps on every switch, so each WebSocket loop notices a new run and
greets its browser again. The page may only start a *shipped example* by name and open a
*recording* from the directory the user named (``--runs-dir``) or a file named on the command
line: :class:`Library` resolves names and refuses anything else (absolute paths, ``..``,
symlinks that lead out of the directory, files that are not SQLite).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from packpilot.contract.record import Result
from packpilot.errors import InputError
from packpilot.web.live import LiveRun, SimThread
from packpilot.web.recorded import Follower, Recording, is_sqlite

RECORDING_SUFFIXES = (".sqlite", ".sqlite3", ".db")
MAX_LISTED = 500
"""At most this many recordings are listed (a runs directory of thousands stays responsive)."""

ReportWriter = Callable[[Result, LiveRun], Path | None]
"""Writes a finished live run's report (supplied by the CLI, which may import the report)."""


class NotAllowed(InputError):
    """A name the page asked for that resolves outside what the user allowed."""


@dataclass
class Library:
    """The examples the page may start and the recordings it may open."""

    examples: Mapping[str, Path] = field(default_factory=dict)
    runs_dir: Path | None = None
    files: tuple[Path, ...] = ()
    """Recordings named on the command line (listed by file name)."""

    @classmethod
    def of_dirs(
        cls, example_dirs: Iterable[Path], runs_dir: Path | None, files: Iterable[Path] = ()
    ) -> Library:
        examples: dict[str, Path] = {}
        for d in example_dirs:
            for p in sorted(d.glob("*.toml")):
                examples.setdefault(p.stem, p)
        root = runs_dir.resolve(strict=True) if runs_dir is not None else None
        return cls(examples, root, tuple(f.resolve() for f in files))

    def recordings(self) -> list[str]:
        """Names the page may pass to :meth:`resolve`: command-line files, then the runs
        directory's SQLite files (two levels deep, sorted)."""
        out = [f.name for f in self.files]
        if self.runs_dir is None:
            return out
        found: list[str] = []
        for p in sorted(self.runs_dir.glob("*")) + sorted(self.runs_dir.glob("*/*")):
            if len(found) >= MAX_LISTED:
                break
            if p.suffix.lower() in RECORDING_SUFFIXES and self._inside(p) and is_sqlite(p):
                found.append(p.relative_to(self.runs_dir).as_posix())
        return out + [n for n in found if n not in out]

    def _inside(self, p: Path) -> bool:
        """``p``, with every symlink followed, is a file inside the runs directory."""
        assert self.runs_dir is not None
        try:
            real = p.resolve(strict=True)
        except (OSError, RuntimeError):
            return False
        return real.is_file() and real.is_relative_to(self.runs_dir)

    def resolve(self, name: str) -> Path:
        """The recording ``name`` names; :class:`NotAllowed` for anything outside."""
        if not name or "\x00" in name or len(name) > 1000:
            raise NotAllowed("no such recording")
        for f in self.files:
            if name == f.name:
                return f
        if self.runs_dir is None:
            raise NotAllowed("no runs directory: start the dashboard with --runs-dir DIR")
        # One rule for "..", absolute names and symlinks alike: the name, with every link
        # followed, must land on a file inside the runs directory.
        candidate = self.runs_dir / name
        if not self._inside(candidate):
            raise NotAllowed(f"{name!r}: not a file inside the runs directory")
        if not is_sqlite(candidate):
            raise NotAllowed(f"{name!r}: not a SQLite telemetry file")
        return candidate.resolve()


REPORT_META = "packpilot-run"
"""``<meta name="packpilot-run" content="FILE#RUN">``: which recorded run a report shows (the
report writes it when it knows its telemetry file)."""
MAX_SCANNED = 200
"""At most this many ``*.html`` files beside a recording are looked into for its report."""


def _report_run(path: Path) -> str | None:
    """The ``packpilot-run`` meta of an HTML file's head, if any (only the first 4 kB read)."""
    import re

    try:
        with path.open("r", encoding="utf-8", errors="replace") as f:
            head = f.read(4096)
    except OSError:
        return None
    m = re.search(r'<meta name="packpilot-run" content="([^"]*)"', head)
    return m.group(1) if m else None


def existing_report(db: Path, run_id: int | None) -> Path | None:
    """The report of a recorded run beside its file: first under ``packpilot report``'s
    default names (``run.html``, ``run_3.html``), then any ``*.html`` there whose
    ``packpilot-run`` meta names this file and run, whatever it is called (``make demo``
    writes ``report.html`` beside ``demo.sqlite``)."""
    names = [db.stem + ".html"] if run_id is None else [f"{db.stem}_{run_id}.html"]
    names += [db.stem + ".html"]
    for n in names:
        p = db.with_name(n)
        if p.is_file():
            return p
    if run_id is None:
        return None
    want = f"{db.name}#{run_id}"
    for k, p in enumerate(sorted(db.parent.glob("*.html"))):
        if k >= MAX_SCANNED:
            break
        if p.is_file() and _report_run(p) == want:
            return p
    return None


RunnerFactory = Callable[[Path], Any]
"""Builds a prepared ``Runner`` for a scenario file (the CLI's loading rules)."""


class Session:
    """The run on show; switched by the page's example picker and recording chooser."""

    def __init__(
        self,
        live: LiveRun,
        sim: SimThread | None = None,
        *,
        library: Library | None = None,
        make_runner: RunnerFactory | None = None,
        db: Path | None = None,
        write_report: ReportWriter | None = None,
        max_points: int = 2000,
    ) -> None:
        self.library = library or Library()
        self.make_runner = make_runner
        self.db = db
        self.write_report = write_report
        self.max_points = max_points
        self.recording: Recording | None = None
        self.follower: Follower | None = None
        self.report_path: Path | None = None
        self.generation = 0
        self._lock = threading.Lock()
        self.live = live
        self.sim = sim
        if sim is not None:
            sim.on_result = self._on_result

    # ---------------------------------------------------------------- switching
    def _switch(
        self,
        live: LiveRun,
        sim: SimThread | None,
        rec: Recording | None,
        follower: Follower | None = None,
    ) -> None:
        with self._lock:
            old, old_follower = self.sim, self.follower
            self.live, self.sim, self.recording = live, sim, rec
            self.follower = follower
            self.report_path = None
            self.generation += 1
        if old is not None:
            old.stop(timeout_s=5.0)
        if old_follower is not None:
            old_follower.stop()
        if follower is not None:
            follower.start()

    def start(self) -> None:
        if self.sim is not None and not self.sim.is_alive() and self.sim.ident is None:
            self.sim.start()

    def stop(self) -> None:
        if self.sim is not None:
            self.sim.stop()
        if self.follower is not None:
            self.follower.stop()

    def start_example(self, name: str, speed: float) -> LiveRun:
        """Start the shipped example ``name`` (blocking: the runner is built here)."""
        path = self.library.examples.get(name)
        if path is None:
            raise NotAllowed(f"{name!r}: not one of the shipped examples")
        if self.make_runner is None:
            raise NotAllowed("this dashboard cannot start runs")
        runner = self.make_runner(path)
        cfg = runner.cfg
        live = LiveRun(
            scenario=cfg.pack.name if "name" in cfg.pack.model_fields_set else path.stem,
            duration_s=float(cfg.sim.duration_s),
            dt_s=float(cfg.sim.dt_s),
            speed=float(speed),
            max_points=self.max_points,
            battery_names=list(runner.pack.names),
            db=str(self.db) if self.db is not None else None,
            source=f"example {name}",
        )
        sim = SimThread(runner, live, self.db)
        sim.on_result = self._on_result
        self._switch(live, sim, None)
        sim.start()
        return live

    def open_recording(self, name: str, run_id: int | None = None) -> LiveRun:
        """Show the recording ``name`` (a name from :meth:`Library.recordings`)."""
        path = self.library.resolve(name)
        return self.open_path(path, run_id)

    def open_path(self, path: Path, run_id: int | None = None) -> LiveRun:
        """Show a recording the user named (the command line, or resolved by the library). A
        run still being written is followed, read-only, until its writer finishes."""
        rec = Recording(path, run_id, self.max_points)
        follower = Follower(rec, self._followed_end) if rec.following else None
        self._switch(rec.live, None, rec, follower)
        report = existing_report(path, rec.run_id)
        if report is not None:
            self._set_report(rec.live, report)
        return rec.live

    def _followed_end(self, rec: Recording) -> None:
        """A followed run has ended (in the follower's thread): if it is still on show, reopen
        it as a plain recording, so the page gets the scrubber and the report link."""
        with self._lock:
            if rec is not self.recording:
                return
        try:
            self.open_path(rec.path, rec.run_id)
        except InputError as err:  # keep showing what was followed, and say why
            rec.live.note(f"the finished run could not be reopened: {err}")

    # ---------------------------------------------------------------- reports
    def _on_result(self, live: LiveRun, result: Result) -> None:
        """A live run finished (in its thread): write its report if the CLI asked for one."""
        if self.write_report is None:
            return
        try:
            path = self.write_report(result, live)
        except Exception as err:  # shown on the page; the run itself is fine
            live.note(f"report not written: {err}")
            return
        if path is not None:
            self._set_report(live, path)

    def _set_report(self, live: LiveRun, path: Path) -> None:
        with self._lock:
            if live is not self.live:
                return  # the page moved on to another run
            self.report_path = path
        live.set_report("/report")

    def current_example(self) -> str | None:
        """The shipped example on show (started by name, or its file named on the command
        line), so the page's picker shows it rather than the first name in the list."""
        if self.recording is not None:
            return None
        source = self.live.source or ""
        if source.startswith("example "):
            name = source.removeprefix("example ")
            return name if name in self.library.examples else None
        if not source:
            return None
        try:
            here = Path(source).resolve()
        except (OSError, RuntimeError):
            return None
        for name, path in self.library.examples.items():
            if path.resolve() == here:
                return name
        return None

    def catalog(self) -> dict[str, Any]:
        """What the page's pickers offer, and the example on show (``current``, or None)."""
        can_start = self.make_runner is not None
        return {
            "examples": sorted(self.library.examples) if can_start else [],
            "current": self.current_example() if can_start else None,
            "recordings": self.library.recordings(),
            "runs_dir": str(self.library.runs_dir) if self.library.runs_dir else None,
        }
