"""How serious each event kind is: one declarative table, next to the reason tables.

The reason tables (:mod:`packpilot.contract.events`) say what an event code *means*; this table
says how much it *matters* to the person reading the run: its severity (info, warning, alarm,
fault), the category ``simulate --fail-on`` names it by, and the kind of event that clears it.
Every kind a controller or the loop can emit has a row (a test enumerates the registry's reason
tables and the loop's own kinds), so a new event kind cannot silently read as "ok".

Severities and categories are presentation: they never feed back into a run, so the traces,
events and metrics of a run do not depend on this table.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType


class Severity(enum.IntEnum):
    """Ordered: a run's verdict is the highest severity it saw."""

    INFO = 0
    WARNING = 1
    ALARM = 2
    FAULT = 3

    @property
    def label(self) -> str:
        """Lower-case name (``"warning"``), as JSON and the pages show it."""
        return self.name.lower()


VERDICTS: Mapping[Severity, str] = MappingProxyType(
    {Severity.INFO: "OK", Severity.WARNING: "WARNING", Severity.ALARM: "ALARM",
     Severity.FAULT: "FAULT"}
)  # fmt: skip
"""The word a run's verdict shows for its highest severity."""


@dataclass(frozen=True, slots=True)
class KindRow:
    """One row: how an event kind counts for a run's verdict and its alarms table."""

    severity: Severity
    category: str = ""
    """What ``--fail-on`` calls it (``trip``, ``fault``, ...); empty for routine events."""
    cleared_by: str | None = None
    """The event kind that ends this condition for the same battery (None: never cleared,
    a one-off such as a refused command)."""


_I = KindRow(Severity.INFO)

EVENT_SEVERITY: Mapping[str, KindRow] = MappingProxyType(
    {
        # faults: a sensor, the charger or a link cannot be trusted
        "Fault": KindRow(Severity.FAULT, "fault", "FaultCleared"),
        # alarms: the pack protected itself, or the load lost power
        "ProtectionTripped": KindRow(Severity.ALARM, "trip", "ProtectionReset"),
        "LimitTripped": KindRow(Severity.ALARM, "trip", "LimitReset"),
        "LoadUnsupplied": KindRow(Severity.ALARM, "unsupplied", "LoadResupplied"),
        "BmuBrownOut": KindRow(Severity.ALARM, "brownout", "BmuRestarted"),
        # warnings: close to a limit, or a command the supervisor would not carry out
        "LimitWarning": KindRow(Severity.WARNING, "limit", "LimitReset"),
        "ProtectionWarning": KindRow(Severity.WARNING, "limit", "ProtectionReset"),
        "LimitDerate": KindRow(Severity.WARNING, "limit", "LimitReset"),
        "CommandRefused": KindRow(Severity.WARNING, "refused"),
        "CrossCurrentRisk": KindRow(Severity.WARNING, "crosscurrent"),
        # a battery with a failed sensor now supplies the load (degraded mode, #15 §5)
        "ReserveEngaged": KindRow(Severity.WARNING, "reserve"),
        # the SOC observer failed its innovation test: the coulomb counter is shown (#28)
        "SocObserverDiverged": KindRow(Severity.WARNING, "estimator", "SocObserverResumed"),
        # ... or its SOC left what the coulomb counter can be wrong by (its model is wrong)
        "SocObserverInconsistent": KindRow(
            Severity.WARNING, "estimator", "SocObserverResumed"
        ),
        # the battery's step resistance is far from its cell set's: fit it (packpilot fit)
        "SocCellSetMismatch": KindRow(Severity.WARNING, "estimator"),
        # the CAN runtime's own detections (issue #26): telemetry not trusted, a dock contact
        # contradicted by the measurements, a switch node that opened on its command timeout
        "TelemetrySuspect": KindRow(Severity.WARNING, "telemetry", "TelemetryTrusted"),
        "DockRejected": KindRow(Severity.WARNING, "dock"),
        "SwitchTimeoutSeen": KindRow(Severity.WARNING, "switchtimeout"),
        "TelemetryTrusted": _I,
        "TelemetryResync": _I,
        "PresenceConfirmed": _I,
        "DockConfirmed": _I,
        # routine: the controllers doing their job
        "BalancingUpdated": _I,
        "BatteryFull": _I,
        "BatteryJoined": _I,
        "ChargeComplete": _I,
        "DiodeBypassed": _I,
        "FaultCleared": _I,
        "LimitReset": _I,
        "LoadResupplied": _I,
        "BmuRestarted": _I,
        "ModeChanged": _I,
        "ProtectionReset": _I,
        # sequencing saw a battery take charge from a sibling and stood it by: the controller
        # handling it (the physics check flags a cross-charge that is too large)
        "ReverseCurrent": _I,
        "SocCorrected": _I,
        "SocObserverResumed": _I,
        "StageChanged": _I,
        "StateChanged": _I,
    }
)
"""Event kind -> its row. A kind missing here is a bug (see ``row_of``)."""

UNKNOWN_KIND = KindRow(Severity.WARNING, "unknown")
"""What an event kind without a row counts as (a run read from an older or newer file):
visible, never silently "ok"."""

MATCH_FIELDS: tuple[str, ...] = ("limit", "tier", "kind", "source", "field")
"""Data fields that must agree between a condition and the event that clears it (a limit's
reset clears that tier of that limit, a plausibility kind's clearing that kind)."""


def row_of(kind: str) -> KindRow:
    """The row of ``kind``; an unknown kind is a warning."""
    return EVENT_SEVERITY.get(kind, UNKNOWN_KIND)


__all__ = [
    "EVENT_SEVERITY",
    "MATCH_FIELDS",
    "UNKNOWN_KIND",
    "VERDICTS",
    "KindRow",
    "Severity",
    "row_of",
]
