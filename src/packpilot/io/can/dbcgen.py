"""The PackPilot smart-battery DBC (``packpilot.dbc``), generated from one layout table.

Battery ``i`` (0..15, its position in ``[[pack.batteries]]``) owns its own identifiers
(``base + i``), as two CAN nodes must never send the same identifier. A DBC cannot say
"base + i", so the file spells every battery out; this module is the one source of the layout
and ``tests/test_runtime_frames.py`` checks that the shipped file is what it generates
(regenerate with ``python -m packpilot.io.can.dbcgen > src/packpilot/io/can/packpilot.dbc``).

A value that is not available travels as the field's all-ones count (unsigned) or its most
negative count (signed), in fields of 16 bits or more. Every field is little-endian (Intel,
``@1``): cantools' start bit is then the LSB's position,
``byte * 8 + bit``. Battery current is positive when **discharging** (PackPilot's convention).
"""

from __future__ import annotations

from dataclasses import dataclass

MAX_BATTERIES = 16
MAX_GROUPS = 33
"""Group voltages per battery the ``BatteryGroups`` frames can carry (11 blocks of 3)."""
GROUPS_PER_FRAME = 3
N_BLOCKS = MAX_GROUPS // GROUPS_PER_FRAME

BATTERY_MEAS = 0x300
BATTERY_STATE = 0x310
BATTERY_CAPACITY = 0x320
BATTERY_GROUPS = 0x330
BALANCER_CMD = 0x340
BATTERY_CELLS = 0x360
SWITCH_STATE = 0x370
SWITCH_CMD = 0x200
AUX_CMD = 0x210
PLATFORM_MEAS = 0x220
PROTECTION_STATE = 0x230
STATE_OF_POWER = 0x231
STATE_OF_CHARGE = 0x232


@dataclass(frozen=True)
class Sig:
    name: str
    start: int
    length: int
    signed: bool = False
    factor: float = 1.0
    unit: str = ""
    comment: str = ""
    mux: int | None = None
    """Multiplexed signal: present when the multiplexer equals this value."""
    is_mux: bool = False


@dataclass(frozen=True)
class Msg:
    name: str
    frame_id: int
    dlc: int
    sender: str
    receiver: str
    comment: str
    signals: tuple[Sig, ...]


def _group_signals() -> tuple[Sig, ...]:
    out = [Sig("Block", 0, 8, is_mux=True, comment="groups 3*Block .. 3*Block+2")]
    for b in range(N_BLOCKS):
        for j in range(GROUPS_PER_FRAME):
            g = b * GROUPS_PER_FRAME + j
            out.append(Sig(f"GroupV{g}", 8 + 16 * j, 16, factor=0.0001, unit="V", mux=b))
    out.append(Sig("NGroups", 56, 8, comment="series groups the battery reports"))
    return tuple(out)


def _balancer_signals() -> tuple[Sig, ...]:
    out = [Sig("Block", 0, 8, is_mux=True, comment="groups 3*Block .. 3*Block+2")]
    for b in range(N_BLOCKS):
        for j in range(GROUPS_PER_FRAME):
            g = b * GROUPS_PER_FRAME + j
            out.append(
                Sig(f"BalancerA{g}", 8 + 16 * j, 16, True, 0.001, "A", "+ = discharge", mux=b)
            )
    out.append(Sig("Seq", 56, 8, comment="sequence counter, +1 per period"))
    return tuple(out)


def battery_messages(i: int) -> list[Msg]:
    """The frames of battery ``i``: telemetry it sends, commands its switch node obeys."""
    node, sw = f"Battery{i}", f"Switch{i}"
    return [
        Msg(f"BatteryMeas{i}", BATTERY_MEAS + i, 8, node, "BMS",
            "Fast telemetry, every BMS period.", (
                Sig("Voltage", 0, 24, factor=0.0001, unit="V", comment="terminal voltage"),
                Sig("Current", 24, 24, True, 0.001, "A", "positive = discharging"),
                Sig("Counter", 56, 8, comment="alive counter, +1 per frame"),
            )),
        Msg(f"BatteryCells{i}", BATTERY_CELLS + i, 8, node, "BMS",
            "Lowest and highest cell (group) voltage, every BMS period.", (
                Sig("MinCellV", 0, 16, factor=0.0001, unit="V"),
                Sig("MaxCellV", 16, 16, factor=0.0001, unit="V"),
            )),
        Msg(f"BatteryState{i}", BATTERY_STATE + i, 8, node, "BMS",
            "Temperatures, SOC, switch feedback, every BMS period.", (
                Sig("TempMax", 0, 16, True, 0.1, "degC", "hottest cell"),
                Sig("TempMin", 16, 16, True, 0.1, "degC", "coldest cell; -3276.8 = none"),
                Sig("SOC", 32, 16, factor=0.0001, comment="fraction 0..1 of the weakest cell"),
                Sig("ChgOn", 48, 1, comment="charge path conducts (feedback)"),
                Sig("DsgOn", 49, 1, comment="discharge path conducts (feedback)"),
                Sig("Present", 50, 1, comment="battery inserted"),
                Sig("Counter", 56, 8, comment="alive counter, +1 per frame"),
            )),
        Msg(f"BatteryCapacity{i}", BATTERY_CAPACITY + i, 8, node, "BMS",
            "Capacity and cycles, every BMS period.", (
                Sig("FullAh", 0, 16, factor=0.01, unit="Ah"),
                Sig("RemainingAh", 16, 16, factor=0.01, unit="Ah"),
                Sig("CycleCount", 32, 16, comment="65535 = not reported"),
                Sig("NGroups", 48, 8, comment="series groups"),
            )),
        Msg(f"BatteryGroups{i}", BATTERY_GROUPS + i, 8, node, "BMS",
            "Group (series cell) voltages, multiplexed by block, every BMS period.",
            _group_signals()),
        Msg(f"SwitchCmd{i}", SWITCH_CMD + i, 2, "BMS", sw,
            "Charge/discharge path command, every BMS period. The switch node opens both paths "
            "after N periods without a new command (a repeated Seq is not new).", (
                Sig("ChgOn", 0, 1, comment="1 = close the charge path"),
                Sig("DsgOn", 1, 1, comment="1 = close the discharge path"),
                Sig("Seq", 8, 8, comment="sequence counter, +1 per period"),
            )),
        Msg(f"SwitchState{i}", SWITCH_STATE + i, 2, sw, "BMS",
            "What the switch node does, every period: the switch feedback of a battery that "
            "does not report its own (a DroneCAN battery).", (
                Sig("ChgOn", 0, 1, comment="charge path conducts"),
                Sig("DsgOn", 1, 1, comment="discharge path conducts"),
                Sig("TimedOut", 2, 1, comment="opened by the command timeout"),
                Sig("Seq", 8, 8, comment="sequence number of the last command obeyed"),
            )),
        Msg(f"BalancerCmd{i}", BALANCER_CMD + i, 8, "BMS", sw,
            "Per-group balancer currents, multiplexed by block, every BMS period.",
            _balancer_signals()),
    ]


def pack_messages() -> list[Msg]:
    return [
        Msg("AuxCmd", AUX_CMD, 4, "BMS", "AuxNode",
            "Aux battery relay and DC/DC charge current, every BMS period.", (
                Sig("AuxRelay", 0, 1, comment="1 = close the aux relay"),
                Sig("AuxChargeA", 8, 16, factor=0.01, unit="A"),
                Sig("Seq", 24, 8),
            )),
        Msg("PlatformMeas", PLATFORM_MEAS, 4, "Platform", "BMS",
            "Bus voltage and dock contact, every BMS period.", (
                Sig("BusV", 0, 16, factor=0.01, unit="V"),
                Sig("Docked", 16, 1, comment="1 = on the charging dock"),
                Sig("Counter", 24, 8),
            )),
        Msg("ProtectionState", PROTECTION_STATE, 8, "BMS", "Platform",
            "The protection's platform interface, every 1 s.", (
                Sig("Mode", 0, 8, comment="supervisor mode index (255 = none)"),
                Sig("ActiveParam", 8, 8, comment="active protection parameter (255 = none)"),
                Sig("AllowanceUsed", 16, 16, factor=0.001, comment="used share, 0..1 (>1 trip)"),
                Sig("TimeToTrip", 32, 16, unit="s", comment="65535 = none / beyond"),
                Sig("TimeToEmpty", 48, 16, unit="s", comment="65535 = none / beyond"),
            )),
        Msg("StateOfPower", STATE_OF_POWER, 8, "BMS", "Platform",
            "The pack's state of power, every 1 s: the largest current it can hold for the "
            "horizon without any battery crossing its cut-off, current or temperature limit "
            "(docs/power.md).", (
                Sig("Dcl2s", 0, 16, factor=0.1, unit="A", comment="discharge, 2 s"),
                Sig("Dcl10s", 16, 16, factor=0.1, unit="A", comment="discharge, 10 s"),
                Sig("Dcl30s", 32, 16, factor=0.1, unit="A", comment="discharge, 30 s"),
                Sig("Ccl10s", 48, 16, factor=0.1, unit="A", comment="charge, 10 s"),
            )),
        Msg("StateOfCharge", STATE_OF_CHARGE, 8, "BMS", "Platform",
            "The pack's SOC as the core estimates it, every 1 s, and where it comes from "
            "(contract/soc_source.py).", (
                Sig("Soc", 0, 16, factor=0.01, unit="%", comment="capacity-weighted pack SOC"),
                Sig("SocStdev", 16, 16, factor=0.01, unit="%",
                    comment="its standard deviation (65535 = not the observer's)"),
                Sig("Source", 32, 8, comment="0 battery's own, 1 coulomb counter, 2 observer, "
                    "3 fallback (observer not trusted)"),
                Sig("Observed", 40, 8, comment="batteries on the observer"),
                Sig("Fallback", 48, 8, comment="batteries on the fallback"),
                Sig("Reserved", 56, 8),
            )),
    ]


def all_messages() -> list[Msg]:
    out: list[Msg] = []
    for i in range(MAX_BATTERIES):
        out += battery_messages(i)
    return out + pack_messages()


def _fmt(x: float) -> str:
    return f"{x:.10g}"


def _range(s: Sig) -> tuple[float, float]:
    if s.signed:
        return (-(1 << (s.length - 1)) * s.factor, ((1 << (s.length - 1)) - 1) * s.factor)
    return (0.0, ((1 << s.length) - 1) * s.factor)


def _sig_line(s: Sig, receiver: str) -> str:
    mux = " M" if s.is_mux else (f" m{s.mux}" if s.mux is not None else "")
    lo, hi = _range(s)
    sign = "-" if s.signed else "+"
    return (
        f' SG_ {s.name}{mux} : {s.start}|{s.length}@1{sign} ({_fmt(s.factor)},0) '
        f'[{_fmt(lo)}|{_fmt(hi)}] "{s.unit}" {receiver}'
    )


def dbc_text() -> str:
    msgs = all_messages()
    nodes = ["BMS", "Platform", "AuxNode"]
    for i in range(MAX_BATTERIES):
        nodes += [f"Battery{i}", f"Switch{i}"]
    lines = ['VERSION "packpilot-battery-1"', "", "", "NS_ :", "\tCM_", "\tBA_DEF_", "\tBA_",
             "\tVAL_", "", "BS_:", "", "BU_: " + " ".join(nodes), "", ""]  # fmt: skip
    for m in msgs:
        lines.append(f"BO_ {m.frame_id} {m.name}: {m.dlc} {m.sender}")
        lines += [_sig_line(s, m.receiver) for s in m.signals]
        lines.append("")
    lines.append("")
    for m in msgs:
        lines.append(f'CM_ BO_ {m.frame_id} "{m.comment}";')
        lines += [
            f'CM_ SG_ {m.frame_id} {s.name} "{s.comment}";' for s in m.signals if s.comment
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    print(dbc_text(), end="")


if __name__ == "__main__":
    main()
