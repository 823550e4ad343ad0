"""What the report says about a run beyond its ``Result``: where it came from, its config.

Read from a scenario config (``simulate --report``) or from the ``runs`` row of a telemetry
database (``packpilot report``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from packpilot.config import SUPERVISED, ScenarioConfig
from packpilot.contract.topology import Topology
from packpilot.errors import InputError, PackPilotError


@dataclass(frozen=True)
class RunInfo:
    """What the report says about a run beyond its ``Result``: where it came from, its config."""

    config_name: str | None = None
    status: str | None = None
    started_at: str | None = None
    finished_at: str | None = None
    source: str | None = None
    config: Mapping[str, Any] | None = None
    versions: Mapping[str, str] = field(default_factory=dict)
    can_log: str | None = None
    """A CAN log (.blf / .asc) of the run; None: the one the config names (``can.log``), if any."""
    db: str | None = None
    """The telemetry file the run is recorded in (the page names it, with the run id, in its
    ``packpilot-run`` meta, so the dashboard finds the report of a recording it opens)."""

    @classmethod
    def from_config(cls, config: Mapping[str, Any], **kw: Any) -> RunInfo:
        """From a scenario config as a JSON-able dict (``cfg.model_dump(mode="json")``)."""
        pack = config.get("pack")
        name = pack.get("name") if isinstance(pack, Mapping) else None
        return cls(config_name=kw.pop("config_name", name), config=config, **kw)

    def _batteries(self) -> list[Mapping[str, Any]]:
        pack = (self.config or {}).get("pack")
        bats = pack.get("batteries") if isinstance(pack, Mapping) else None
        return [b for b in bats if isinstance(b, Mapping)] if isinstance(bats, list) else []

    def roles(self, names: Sequence[str]) -> list[str | None]:
        by_name = {b.get("name"): b.get("role", "traction") for b in self._batteries()}
        return [by_name.get(n) for n in names]

    def switch_kinds(self, names: Sequence[str]) -> list[str | None]:
        """Each battery's switch kind (its own ``switch`` or the pack default), None if unknown."""
        pack = (self.config or {}).get("pack")
        default = None
        if isinstance(pack, Mapping):
            sw = pack.get("switch")
            default = sw.get("kind", "mosfet_pair") if isinstance(sw, Mapping) else "mosfet_pair"
        kinds: dict[Any, str | None] = {}
        for b in self._batteries():
            sw = b.get("switch")
            kinds[b.get("name")] = sw.get("kind") if isinstance(sw, Mapping) else default
        return [kinds.get(n) for n in names]

    def event_batteries(self, names: Sequence[str]) -> list[int]:
        """Trace index of each ``Event.battery`` value: events count traction batteries only."""
        return list(Topology.of_config(self.config, names).traction)

    def event_names(self, names: Sequence[str]) -> list[str]:
        """Names for ``Event.battery`` values (the aux battery has no index of its own)."""
        return [names[i] for i in self.event_batteries(names)]

    def can_log_path(self) -> Path | None:
        """The CAN log to report: the one given, else the config's ``can.log``."""
        if self.can_log:
            return Path(self.can_log)
        can = (self.config or {}).get("can")
        log = can.get("log") if isinstance(can, Mapping) else None
        return Path(log) if isinstance(log, str) and log else None

    def scenario(self) -> ScenarioConfig | None:
        """The scenario as validated config (for the methods' figures); None when the run's
        config is missing or no longer validates (a database written by another version)."""
        if not isinstance(self.config, Mapping):
            return None
        from packpilot.config import parse_config

        try:
            return parse_config(dict(self.config))
        except (PackPilotError, ValueError, TypeError, OSError):
            return None

    def enabled(self, method: str) -> bool:
        """Whether the scenario runs a method (``controller`` list or its own section)."""
        return method in self.controllers()

    def controllers(self) -> list[str]:
        cfg = self.config or {}
        out = [str(c) for c in cfg.get("controller") or []]
        out += [s for s in SUPERVISED if cfg.get(s) is not None]
        return out


def run_info_from_db(db_path: Path | str, run_id: int | None = None) -> RunInfo:
    """The ``runs`` row of a telemetry file (latest run when ``run_id`` is None)."""
    from packpilot.io.telemetry import list_runs

    runs = list_runs(db_path)
    if not runs:
        raise InputError(f"{db_path}: telemetry database holds no runs")
    row = runs[-1] if run_id is None else next((r for r in runs if r["id"] == run_id), None)
    if row is None:
        raise InputError(f"{db_path}: no run with id {run_id}")
    config = row["config"] if isinstance(row["config"], Mapping) else {}
    return RunInfo.from_config(
        config,
        status=row["status"],
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        source=str(db_path),
        versions=row["versions"] if isinstance(row["versions"], Mapping) else {},
        db=str(db_path),
    )


__all__ = ["RunInfo", "run_info_from_db"]
