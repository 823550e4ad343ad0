"""A first run starts at once: interpreted while the kernels compile in the background.

Compiling the BMS core and the plant cold costs minutes of CPU (``docs/kernels.md``); the same
source run as plain Python gives the same bits (``docs/kernels.md``, "Exactness"; the golden
test runs both ways). So when the kernels a command needs are not compiled yet, the command
does not sit compiling: :func:`prepare` switches numba off for this process (interpreted from
the first step) and starts **one** background process (``packpilot.warmup``, ``nice`` 10)
that compiles them into numba's on-disk cache, with progress on stderr while the command runs
(:func:`reporting`). The next command finds them compiled and runs compiled.

Policy (decided here, before any kernel module is imported: numba reads ``DISABLE_JIT`` when
a kernel is decorated):

* kernels compiled for this scenario (a marker the background compile leaves, keyed by the
  kernels' source, numba, Python, the CPU and the scenario's methods) -> compiled;
* ``simulate``: interpreted when the run's estimated interpreted time is below the compile's
  estimated time (the compile still goes on in the background), else compiled in-process (as
  before: announced on stderr, compile time reported apart as ``build_time_s``);
* ``run`` / ``hil`` (real time): interpreted from the first period while compiling; the
  process stays interpreted for its life (no hand-over: the compiled kernels cannot be loaded
  into a process whose kernels were defined as plain Python).

``PACKPILOT_START=compiled`` keeps the old behaviour (compile in-process),
``PACKPILOT_START=interpreted`` runs interpreted without a background compile;
``NUMBA_DISABLE_JIT=1`` is honoured as always. The background compile keeps going when the
command ends (detached; its pid is in the progress line), so the next command finds the
kernels ready; at most one runs per cache directory (a lock file).

This module imports no kernel: it must run before them.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import platform
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

ENV_MODE = "PACKPILOT_START"
BACKGROUND = "compiling the BMS core for this machine in the background (first run only)"
COMMANDS = frozenset({"simulate", "run", "hil"})
"""Commands whose first run would compile the core (others compile nothing, or on demand)."""

PLANT_COMPILE_CPU_S = 45.0
"""Cold compile of the plant kernels, CPU s (docs/kernels.md: smart_battery, no method)."""
METHOD_COMPILE_CPU_S = {
    "charging": 56.5, "sequencing": 46.9, "plausibility": 29.2, "limits": 18.3,
    "protection": 12.6, "equalization": 7.1, "soc": 131.0, "supervisor": 24.5,
}  # fmt: skip
"""Cold compile per method's ``step_packs`` (exclusive CPU s, docs/kernels.md); the
supervisor's rules plus the fused step's own part for ``supervisor``. ``soc`` since #28's
observer: 71-76 CPU s (``tests/precompile.py``'s per-job figures, docs/kernels.md CI section;
the coulomb counter alone was 1.9 s); 131 CPU s since the CC/CV time to full (its three
kernels compiled once each; inlined into the rule they cost 517 CPU s)."""
INTERP_STEP_S = 0.4e-3
INTERP_CELL_STEP_S = 50e-6
INTERP_METHOD_STEP_S = 0.16e-3
"""Interpreted cost of a step: a base, per cell, per method (measured, benchmarks/RESULTS.md
2026-11-28 h25a)."""


@dataclass
class Start:
    """What :func:`prepare` decided for this process."""

    mode: str = "compiled"
    """``compiled``, ``interpreted`` (a background compile runs or ran) or ``interpreted``
    without one (``NUMBA_DISABLE_JIT=1`` / ``PACKPILOT_START=interpreted``)."""
    reason: str = ""
    status: Path | None = None
    """The background compile's status file (``k n label pid``), when one runs."""
    child: subprocess.Popen[bytes] | None = None
    estimates: dict[str, float] = field(default_factory=dict)
    decision: Decision | None = None
    begun: bool = False
    """:func:`begin` was called: the run started (the background compile with it)."""


START = Start()


def cache_root() -> Path:
    """Where numba caches this package's kernels: ``NUMBA_CACHE_DIR``, else the package's own
    ``__pycache__`` when writable, else numba's user-wide cache directory."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve().parent / "__pycache__"
    with contextlib.suppress(OSError):
        here.mkdir(exist_ok=True)
    if os.access(here, os.W_OK):
        return here
    from numba.misc.appdirs import AppDirs

    return Path(AppDirs(appname="numba", appauthor=False).user_cache_dir)  # type: ignore[no-untyped-call]


_IMPORT = re.compile(
    r"^[ \t]*(?:from[ \t]+(packpilot[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)"
    r"|import[ \t]+(packpilot[\w.]*))",
    re.M,
)


def _imports(text: str, root: Path) -> set[Path]:
    """Files of this package that a module's source ``text`` imports, found by path
    (``importlib`` would import the parent packages, and with them kernels, before the
    decision; a regular expression: ``ast`` took seconds for the kernel files here)."""
    names: set[str] = set()
    for module, what, plain in _IMPORT.findall(text):
        if plain:
            names.add(plain)
            continue
        names.add(module)
        for item in what.strip("()").split(","):
            word = item.split("#")[0].split(" as ")[0].strip()
            if word.isidentifier():
                names.add(f"{module}.{word}")
    out: set[Path] = set()
    for name in names:
        base = root.joinpath(*name.split(".")[1:])
        for f in (base.with_suffix(".py"), base / "__init__.py"):
            if f.is_file():
                out.add(f)
    return out


def _source_digest() -> str:
    """Digest of every kernel file of the package and of what they import, transitively (the
    files whose edit recompiles a kernel, as :func:`packpilot.jit.dependency_files` says)."""
    root = Path(__file__).resolve().parent
    todo = [f for f in root.rglob("*.py") if b"@kernel" in (t := f.read_bytes()) or b"@_jit" in t]
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f not in seen:
            seen.add(f)
            todo.extend(_imports(f.read_text(), root))
    h = hashlib.sha256()
    for f in sorted(seen):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def _machine() -> str:
    import llvmlite  # type: ignore[import-untyped]
    import numba
    from llvmlite import binding

    features = binding.get_host_cpu_features().flatten()
    return "|".join(
        [numba.__version__, llvmlite.__version__, sys.version, platform.machine(),
         binding.get_host_cpu_name(), features]
    )  # fmt: skip


def profile(cfg: Any) -> list[Any]:
    """What decides which kernels a scenario compiles: its methods, the safety layers under
    the supervisor, and the plant's optional parts."""
    safety = [n for n in ("limits", "plausibility", "soc") if getattr(cfg, n, None) is not None]
    return [
        list(cfg.controller),
        bool(cfg.supervised),
        safety if cfg.supervised else [],
        bool(cfg.charger.present),
        sorted({b.role for b in cfg.pack.batteries}),
    ]


def marker(cfg: Any) -> Path:
    """The file the background compile leaves when this scenario's kernels are compiled."""
    key = json.dumps([profile(cfg), _source_digest(), _machine()])
    name = hashlib.sha256(key.encode()).hexdigest()[:20]
    return cache_root() / "packpilot-compiled" / name


def methods_of(cfg: Any) -> list[str]:
    names = list(cfg.controller)
    if cfg.supervised:
        names += [n for n in ("limits", "plausibility", "soc") if getattr(cfg, n, None)]
        names.append("supervisor")
    return names


def estimates(cfg: Any, steps: int) -> dict[str, float]:
    """Estimated seconds: the run interpreted, and the compile (cold, one free core)."""
    cells = sum(b.series_groups * b.cells_per_group for b in cfg.pack.batteries)
    names = methods_of(cfg)
    per_step = INTERP_STEP_S + INTERP_CELL_STEP_S * cells + INTERP_METHOD_STEP_S * len(names)
    compile_s = PLANT_COMPILE_CPU_S + sum(METHOD_COMPILE_CPU_S.get(n, 20.0) for n in names)
    return {"interpreted_s": steps * per_step, "compile_s": compile_s, "steps": float(steps)}


_VALUE_OPTIONS_FREE = {"--json", "--progress", "--no-progress", "--allow-unmonitored"}


def _config_arg(args: list[str]) -> tuple[str | None, dict[str, str]]:
    """The command's first positional argument and its ``--option value`` pairs."""
    config, opts, k = None, {}, 0
    while k < len(args):
        a = args[k]
        if a.startswith("--"):
            if "=" in a:
                name, value = a.split("=", 1)
                opts[name] = value
            elif a not in _VALUE_OPTIONS_FREE and k + 1 < len(args):
                opts[a] = args[k + 1]
                k += 1
        elif config is None:
            config = a
        k += 1
    return config, opts


def _scenario(config: str) -> Path | None:
    path = Path(config)
    if path.exists():
        return path
    if path.suffix or len(path.parts) > 1:
        return None
    import packpilot

    for folder in (Path("examples"), Path(packpilot.__file__).resolve().parents[2] / "examples",
                   Path(sys.prefix) / "share" / "packpilot" / "examples"):  # fmt: skip
        if (folder / f"{config}.toml").is_file():
            return folder / f"{config}.toml"
    return None


def _interpreted(reason: str) -> None:
    """Kernels defined from now on are plain Python. The environment variable too: numba
    re-reads its configuration from the environment whenever it compiles anything."""
    from numba.core import config

    os.environ["NUMBA_DISABLE_JIT"] = "1"
    config.reload_config()  # type: ignore[no-untyped-call]
    config.DISABLE_JIT = True  # type: ignore[attr-defined]
    START.mode, START.reason = "interpreted", reason


@dataclass(frozen=True)
class Decision:
    """How a command runs its kernels: ``compiled``, ``interpreted`` (nothing compiles), or
    ``background`` (interpreted while a background process compiles ``scenario``)."""

    mode: str
    reason: str = ""
    scenario: Path | None = None
    marker: Path | None = None
    estimates: dict[str, float] = field(default_factory=dict)


def decide(argv: list[str], disable_jit: bool, want: str = "auto") -> Decision:
    """The policy of the module's docstring for the command line ``argv`` (no side effect).
    Any doubt (an unknown command, a config that does not load: the command will say why)
    gives the default: compiled."""
    if disable_jit:
        return Decision("interpreted", "NUMBA_DISABLE_JIT=1")
    if want == "compiled" or not argv or argv[0] not in COMMANDS:
        return Decision("compiled")
    if want == "interpreted":
        return Decision("interpreted", f"{ENV_MODE}=interpreted")
    config, opts = _config_arg(argv[1:])
    path = _scenario(config) if config else None
    if path is None:
        return Decision("compiled")
    try:
        from packpilot.config import load_config

        cfg = load_config(path)
        duration = float(opts.get("--duration", cfg.sim.duration_s))
        mark = marker(cfg)
    except Exception:
        return Decision("compiled")
    if mark.exists():
        return Decision("compiled", "kernels compiled for this scenario")
    if argv[0] != "simulate":
        why = "kernels not compiled yet; a real-time run does not wait for a compile"
        return Decision("background", why, path, mark)
    est = estimates(cfg, max(1, int(duration / cfg.sim.dt_s)))
    run_s, build_s = est["interpreted_s"], est["compile_s"]
    if run_s >= build_s:
        why = (f"compiling first: the run interpreted (~{run_s:.1f} s) would take longer than"
               f" the compile (~{build_s:.0f} s)")  # fmt: skip
        return Decision("compiled", why, path, mark, est)
    why = (f"kernels not compiled yet; the run interpreted (~{run_s:.1f} s) is shorter than"
           f" the compile (~{build_s:.0f} s)")  # fmt: skip
    return Decision("background", why, path, mark, est)


def prepare(argv: list[str]) -> Start:
    """Apply :func:`decide` to this process: call it before any kernel module is imported."""
    import numba

    off = bool(numba.config.DISABLE_JIT)  # type: ignore[attr-defined]
    d = decide(argv, off, os.environ.get(ENV_MODE, "auto"))
    START.reason, START.estimates, START.decision = d.reason, d.estimates, d
    if d.mode == "compiled":
        START.mode = "compiled"
        return START
    if d.reason != "NUMBA_DISABLE_JIT=1":
        _interpreted(d.reason)
    START.mode = "interpreted"  # the background compile starts with the run (:func:`begin`)
    return START


def _background(path: Path, mark: Path) -> None:
    """Start the background compile (one per cache directory: if one runs, follow it)."""
    work = cache_root() / "packpilot-compiled"
    work.mkdir(parents=True, exist_ok=True)
    START.status = work / "status"
    lock = work / "lock"
    if _locked(lock):
        return  # one is running: report its progress, start none
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    env[ENV_MODE] = "compiled"
    log = open(work / "log", "wb")  # noqa: SIM115 - handed to the child
    START.child = subprocess.Popen(
        [sys.executable, "-m", "packpilot.warmup", str(path), str(START.status), str(mark),
         str(lock)],
        stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env,
        start_new_session=True,  # Ctrl-C of the command does not stop the compile
        preexec_fn=_nice if os.name == "posix" else None,
    )  # fmt: skip
    log.close()
    START.status.write_text(f"0 0 starting {START.child.pid}\n")


def _nice() -> None:
    """Lowest priority that does not starve: ``nice`` 10, and the same for the child's
    scheduling *group*: with Linux's autogroups (the default on desktops and this VM) a new
    session is a group of its own that competes with the command as an equal, whatever the
    process's nice value, so the group's nice is what keeps the compile behind the run."""
    with contextlib.suppress(OSError):
        os.nice(10)
    with contextlib.suppress(OSError), open("/proc/self/autogroup", "w") as fh:
        fh.write("10")


def _locked(lock: Path) -> bool:
    """A background compile holds ``lock`` (``fcntl`` lock, released when it exits)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        return False
    if not lock.exists():
        return False
    with open(lock, "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return True
        fcntl.flock(fh, fcntl.LOCK_UN)
    return False


def _status() -> tuple[int, int, str, str] | None:
    if START.status is None:
        return None
    try:
        k, n, label, pid = START.status.read_text().split()[:4]
        return int(k), int(n), label, pid
    except (OSError, ValueError):
        return None


def begin(stream: IO[str] | None = None) -> None:
    """The run is about to start (its input checked): start the background compile, if this
    process was set to run interpreted while one compiles, and say so. Not earlier: a command
    refused for bad input prints its one ``error:`` line and nothing else."""
    d = START.decision
    if START.begun or d is None or d.mode != "background":
        return
    START.begun = True
    if d.scenario is not None and d.marker is not None:
        _background(d.scenario, d.marker)
    print(
        f"running interpreted from the first step ({d.reason}); same results as compiled",
        file=stream or sys.stderr, flush=True,
    )  # fmt: skip


@contextlib.contextmanager
def reporting(stream: IO[str], every_s: float = 1.5) -> Iterator[None]:
    """While the block runs, once :func:`begin` was called: the background compile's progress
    at least every ``every_s`` (``k/n`` stages: each method's rules, the fused step, the
    plant), and when it is done."""
    if START.decision is None or START.decision.mode != "background":
        yield
        return
    stop = threading.Event()
    t0 = time.perf_counter()
    said = False

    def say() -> None:
        nonlocal said
        st = _status() if START.begun else None
        if st is None:
            return
        said = True
        k, n, label, pid = st
        el = time.perf_counter() - t0
        if label == "done":
            print(f"{BACKGROUND}: done ({el:.0f} s); the next runs start compiled",
                  file=stream, flush=True)  # fmt: skip
            stop.set()
            return
        total = f"{k}/{n}" if n else "starting"
        print(f"{BACKGROUND}: {total} ({label}; pid {pid}; {el:.0f} s)", file=stream, flush=True)

    def beat() -> None:
        was = False
        while True:
            if START.begun and not was:
                was = True
                say()
            elif was:
                say()
            if stop.wait(every_s if was else 0.1):
                return

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done = stop.is_set()
        stop.set()
        thread.join()
        if START.begun and not said and not done:
            say()  # a run shorter than the first beat still says what goes on behind it


def main() -> None:
    """The ``packpilot`` command: the start decision, then the command line itself."""
    prepare(sys.argv[1:])
    from packpilot.cli import main as cli_main

    cli_main()


__all__ = ["BACKGROUND", "START", "Start", "estimates", "marker", "prepare", "reporting"]
