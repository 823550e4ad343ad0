"""Scenario configuration: TOML files validated by pydantic.

One file describes a pack (batteries, switches, cells), what loads and charges it, how long to
simulate, and which control methods run. Each method and safety layer owns its config model
(``config/<name>.py``); this file places them as typed TOML sections of :class:`ScenarioConfig`
(marked :class:`Section`, which says the role), so a whole file is validated in one pass and
every error, in any section, becomes one line naming the file, the field path and what is
allowed (:func:`~packpilot.config.base.fmt_error`, :class:`packpilot.errors.ConfigError`).
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType, NoneType
from typing import Annotated, Any, Literal, get_args

from pydantic import (
    AfterValidator,
    BaseModel,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from packpilot.config.base import (
    CELL_V_MAX_V,
    DETECT_DELAY_MAX_S,
    DETECT_MAX_A,
    MAX_CURRENT_A,
    MAX_LIST_ITEMS,
    MAX_TIME_S,
    MAX_VOLTAGE_V,
    OHM_MAX,
    Finite,
    Fraction,
    NonNegFloat,
    PosFloat,
    Seconds,
    Strict,
    fmt_error,
    load_section_model,
    oversized,
    plus_zero,
)
from packpilot.config.charging import ChargingConfig
from packpilot.config.equalization import EqualizationConfig
from packpilot.config.limits import LimitsConfig
from packpilot.config.plausibility import PlausibilityConfig
from packpilot.config.protection import ProtectionConfig
from packpilot.config.sequencing import SequencingConfig
from packpilot.config.soc import SocConfig
from packpilot.config.supervisor import SupervisorConfig
from packpilot.errors import ConfigError

_Strict = Strict

CELL_V_MIN_V = 1.0
"""Lowest rest voltage per cell an initial ``ocv0_v`` may imply (below any chemistry's empty
cell); with :data:`~packpilot.config.base.CELL_V_MAX_V` the window a battery's
``ocv0_v / n_cells`` must fall in (every cell of a battery is in series)."""
CELL_R_OHM = (1e-5, 10.0)
"""Sane DC resistance of one cell (10 uOhm for a large prismatic cell to 10 Ohm for a coin cell);
``resistance_ohm`` is checked as the per-cell value it implies."""
MAX_POWER_W = 1e8
"""Largest power a load may name (100 MW)."""
LOAD_R_OHM = (1e-6, 1e9)
"""Sane resistance of a resistive load."""


class SwitchConfig(_Strict):
    """Switch between a battery and the bus."""

    kind: Literal["relay", "mosfet_pair"] = "mosfet_pair"
    on_ohm: NonNegFloat = Field(
        0.0005, le=10.0, description="relay contact resistance, or channel resistance of one FET"
    )
    diode_drop_v: NonNegFloat = Field(
        0.6, le=5.0, description="body-diode forward drop (spec: 0.5-0.7 V; at most 5 V)"
    )
    diode_ohm: PosFloat = Field(0.002, le=OHM_MAX, description="body-diode slope resistance")
    chg_on: bool = Field(True, description="initial charge-path state (relay: closed iff both)")
    dsg_on: bool = Field(True, description="initial discharge-path state")
    welded: bool = Field(False, description="relay contact welded closed (fault)")
    reverse_comparator: bool = Field(
        False,
        description=(
            "MOSFET pair only: a reverse-current comparator / ideal-diode controller drives the "
            "charge FET. While no charger output is on, current into the battery above "
            "reverse_trip_a opens the charge FET within the plant step (its body diode then "
            "blocks charging; the battery can still discharge through it). Off by default: "
            "optional hardware; the controller's reverse cut acts one control period later."
        ),
    )
    reverse_trip_a: PosFloat = Field(
        1.0,
        le=DETECT_MAX_A,
        description="reverse-current comparator trip current (A into the battery; a detection "
        "threshold, at most DETECT_MAX_A)",
    )


class BatteryConfig(_Strict):
    """One battery: ``series_groups`` groups in series, each of ``cells_per_group`` cells."""

    name: str = Field(min_length=1, max_length=32)
    role: Literal["traction", "aux"] = "traction"
    cell: str | None = Field(None, description="cell parameter set; default: pack.cell")
    series_groups: int = Field(1, ge=1, le=64)
    cells_per_group: int = Field(1, ge=1, le=64)
    soc0: Fraction | None = Field(None, description="initial SOC (0..1)")
    ocv0_v: PosFloat | None = Field(
        None, description="initial rest voltage of the whole battery (alternative to soc0)"
    )
    group_soc0: list[Fraction] | None = Field(None, description="per-group initial SOC")
    capacity_ah: PosFloat | None = Field(
        None, ge=1e-3, le=1e4, description="cell capacity (1 mAh..10 kAh); default from cell set"
    )
    group_capacity_scale: list[Annotated[float, Field(gt=0, le=10)]] | None = None
    resistance_ohm: PosFloat | None = Field(
        None,
        description="battery DC resistance (sum of cell R0 at resistance_temp_c and the initial "
        "SOC, no current); scales the cells, whose set keeps its own temperature dependence",
    )
    resistance_temp_c: Annotated[float, Field(ge=-40, le=80, allow_inf_nan=False)] = Field(
        25.0,
        description="temperature at which resistance_ohm holds (a datasheet's or an "
        "ohmmeter's: 25 degC); at another ambient the cells' resistance follows their set's "
        "temperature law from this value",
    )
    series_ohm: Annotated[float, Field(ge=0, le=10.0, allow_inf_nan=False)] | None = Field(
        None,
        description="resistance between the battery's cells and its load terminal (leads, "
        "connectors, a current shunt): drops the voltage at the bus, heats no cell, constant in "
        "temperature; default: the cell set's series_ohm x series_groups / cells_per_group "
        "(0 for the shipped sets)",
    )
    cooling_scale: Annotated[float, Field(gt=0, le=20.0, allow_inf_nan=False)] = Field(
        1.0,
        description="multiplier on the cells' heat transfer from their surface to ambient (the "
        "cell set's jig_air_w_per_k): above 1 for airflow over the battery (prop wash, forward "
        "flight, a fan: forced convection 25-40 W/(m2 K) against still air's ~12), below 1 "
        "for an enclosed bay",
    )
    cell_soc_spread: Annotated[float, Field(ge=0, le=0.2), AfterValidator(plus_zero)] = Field(
        0.0, description="uniform +- spread of cell SOC inside each group"
    )
    cell_capacity_spread: Annotated[float, Field(ge=0, le=0.3), AfterValidator(plus_zero)] = Field(
        0.0, description="uniform +- relative spread of cell capacity"
    )
    switch: SwitchConfig | None = Field(None, description="default: pack.switch")
    present_from_s: Seconds = Field(0.0, description="hot insertion time")
    ambient_offset_c: Annotated[float, Field(ge=-100, le=100, allow_inf_nan=False)] = 0.0

    @model_validator(mode="after")
    def _check(self) -> BatteryConfig:
        if self.soc0 is not None and self.ocv0_v is not None:
            raise ValueError("give soc0 or ocv0_v, not both")
        for name in ("group_soc0", "group_capacity_scale"):
            val = getattr(self, name)
            if val is not None and len(val) != self.series_groups:
                raise ValueError(
                    f"{name} has {len(val)} entries but series_groups is {self.series_groups}"
                )
        self._check_physics()
        return self

    def _check_physics(self) -> None:
        """Values that pass their own bounds but are absurd for this battery's cell count
        (``ocv0_v = 1e9`` on a 6S battery, ``resistance_ohm = 1e6``)."""
        if self.ocv0_v is not None:
            per_cell = self.ocv0_v / self.n_cells
            if not CELL_V_MIN_V <= per_cell <= CELL_V_MAX_V:
                raise ValueError(
                    f"ocv0_v: {self.ocv0_v:g} V is {per_cell:.4g} V per cell ({self.n_cells} in "
                    f"series); a cell rests within {CELL_V_MIN_V:g}..{CELL_V_MAX_V:g} V"
                )
        if self.resistance_ohm is not None:
            per_cell = self.resistance_ohm / self.n_cells
            lo, hi = CELL_R_OHM
            if not lo <= per_cell <= hi:
                raise ValueError(
                    f"resistance_ohm: {self.resistance_ohm:g} Ohm is {per_cell:.3g} Ohm per cell "
                    f"({self.n_cells} in series); a cell has {lo:g}..{hi:g} Ohm"
                )

    @property
    def n_cells(self) -> int:
        return self.series_groups * self.cells_per_group


class PackConfig(_Strict):
    name: str = Field("pack", max_length=64)
    cell: str = Field("uav_5ah", description="cell parameter set name or path to a set file")
    ambient_c: Annotated[float, Field(ge=-60, le=80, allow_inf_nan=False)] = 25.0
    thermal_nodes: Literal[1, 2] = 2
    switch: SwitchConfig = SwitchConfig()
    seed: int = Field(0, ge=0, lt=2**63)
    batteries: list[BatteryConfig] = Field(min_length=1, max_length=32)

    @field_validator("batteries")
    @classmethod
    def _unique(cls, v: list[BatteryConfig]) -> list[BatteryConfig]:
        names = [b.name for b in v]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"battery names must be unique; repeated: {', '.join(sorted(dup))}")
        if sum(b.role == "aux" for b in v) > 1:
            raise ValueError("at most one battery may have role 'aux'")
        if not any(b.role == "traction" for b in v):
            raise ValueError("at least one battery must have role 'traction'")
        return v


class LoadConfig(_Strict):
    kind: Literal["current", "power", "resistance", "none"] = "none"
    value: Finite = Field(
        0.0,
        description="constant demand, or the base the profile scales (at most 100 kA, 100 MW; "
        "a resistance 1 uOhm..1 GOhm)",
    )
    profile: str | None = Field(
        None,
        description="built-in profile (uav_flight, uav_hover, step), a CSV path, or a flight "
        "log (.ulg, .bin, .log, .tlog) whose batteries' total current or power is replayed",
    )
    repeat: bool = False
    v_min_v: NonNegFloat = Field(
        0.0, le=MAX_VOLTAGE_V, description="under-voltage lock-out of the load"
    )
    start_s: Seconds = 0.0

    @model_validator(mode="after")
    def _check(self) -> LoadConfig:
        if self.kind == "resistance" and self.profile is None and self.value <= 0:
            raise ValueError("value must be > 0 for a resistance load")
        if self.kind in ("current", "power") and self.value < 0:
            raise ValueError("value must be >= 0 (a load draws; use the charger to charge)")
        self._check_magnitude()
        return self

    def _check_magnitude(self) -> None:
        """A 1e24 A load ran and reported 0 Wh delivered: refuse what no pack can supply."""
        if self.kind == "current" and self.value > MAX_CURRENT_A:
            raise ValueError(f"value: {self.value:g} A is more than {MAX_CURRENT_A:g} A")
        if self.kind == "power" and self.value > MAX_POWER_W:
            raise ValueError(f"value: {self.value:g} W is more than {MAX_POWER_W:g} W")
        lo, hi = LOAD_R_OHM
        if self.kind == "resistance" and self.value > 0 and not lo <= self.value <= hi:
            raise ValueError(f"value: {self.value:g} Ohm is outside {lo:g}..{hi:g} Ohm")


class ChargerConfig(_Strict):
    present: bool = False
    connect_s: Seconds = 0.0
    disconnect_s: Seconds | None = None
    rated_v: PosFloat = Field(500.0, le=MAX_VOLTAGE_V)
    rated_a: PosFloat = Field(100.0, le=MAX_CURRENT_A)
    r_out_ohm: PosFloat = Field(0.01, le=OHM_MAX)
    heartbeat_timeout_s: Annotated[
        float, Field(gt=0, le=DETECT_DELAY_MAX_S, allow_inf_nan=False)
    ] = Field(
        5.0,
        description="the charger stops this long after the last setpoint (a BMS that died must "
        "not leave it charging for longer than a detection delay)",
    )
    voltage_v: NonNegFloat = Field(
        0.0, le=MAX_VOLTAGE_V, description="setpoint used when no controller commands it"
    )
    current_a: NonNegFloat = Field(0.0, le=MAX_CURRENT_A, description="setpoint (A), <= rated_a")
    enable: bool = False

    @model_validator(mode="after")
    def _within_rating(self) -> ChargerConfig:
        """A setpoint above the charger's rating cannot be delivered (``current_a = 1e308``
        was accepted): the rating is the physical range of the setpoint."""
        if self.current_a > self.rated_a:
            raise ValueError(
                f"current_a ({self.current_a:g} A) must be <= rated_a ({self.rated_a:g} A)"
            )
        if self.voltage_v > self.rated_v:
            raise ValueError(
                f"voltage_v ({self.voltage_v:g} V) must be <= rated_v ({self.rated_v:g} V)"
            )
        return self


class BalancerConfig(_Strict):
    present: bool = False
    max_current_a: PosFloat = Field(2.0, le=MAX_CURRENT_A)
    bidirectional: bool = False
    efficiency: Annotated[float, Field(gt=0, le=1)] = 0.9


class AuxConfig(_Strict):
    """DC/DC from the bus into the auxiliary battery, and the BMS load it powers."""

    dcdc_max_a: PosFloat = Field(5.0, le=MAX_CURRENT_A)
    dcdc_efficiency: Annotated[float, Field(gt=0, le=1)] = 0.9
    dcdc_min_input_v: NonNegFloat = Field(20.0, le=MAX_VOLTAGE_V)
    bms_load_w: NonNegFloat = Field(
        15.0,
        le=MAX_POWER_W,
        description="Power the battery-pack management unit (BMU) draws from the aux battery "
        "while it is powered (W)",
    )
    bmu_cutoff_v: PosFloat | None = Field(
        None,
        le=MAX_VOLTAGE_V,
        description="Aux battery terminal voltage below which the BMU browns out: every relay "
        "and FET drops to its unpowered (open) state and the BMU draws nothing; default the "
        "aux battery's series groups x its cell's v_min_v",
    )
    bmu_recover_hysteresis_v: NonNegFloat = Field(
        0.5,
        le=MAX_VOLTAGE_V,
        description="A browned-out BMU restarts when the aux battery is back above "
        "bmu_cutoff_v + this (V); the switches stay open until commanded again",
    )
    dock_powers_bmu: bool = Field(
        True,
        description="While the charging dock is connected it supplies the BMU itself (its "
        "low-voltage output, no relay or command of the BMU in the path) and charges the aux "
        "battery at dock_aux_charge_a: a browned-out BMU restarts as soon as the dock "
        "connects (issue #24). False: the BMU lives on the aux battery alone",
    )
    dock_aux_charge_a: NonNegFloat = Field(
        1.0,
        le=MAX_CURRENT_A,
        description="Current the dock's own path pushes into the aux battery while connected "
        "(A), tapering to 0 over the last 0.2 V below dock_aux_cv_v; 0: none",
    )
    dock_aux_cv_v: PosFloat | None = Field(
        None,
        le=MAX_VOLTAGE_V,
        description="Voltage limit of the dock's aux path (V); default the aux battery's "
        "series groups x its cell's v_max_v",
    )


class CanConfig(_Strict):
    """Charger setpoints over a python-can bus (``virtual`` in one process for simulation)."""

    interface: str = Field(
        "virtual",
        description="python-can interface; 'virtual' runs an emulated charger node in-process, "
        "anything else (e.g. socketcan) talks to the real charger on that bus",
    )
    channel: str | None = Field(
        None, description="bus channel (e.g. can0); default: a fresh in-process virtual bus"
    )
    log: str | None = Field(None, description="log every frame to this .blf or .asc file")


MAX_STEPS = 100_000_000
"""Most periods one run may take: about a day of simulated time at 1 ms, ~2 h of CPU. A bound,
so that a typo such as ``dt_s = 1e-30`` is a clear error, not a run that never ends."""


class SimConfig(_Strict):
    dt_s: Annotated[float, Field(ge=1e-4, le=10)] = 0.1
    """The control period: 0.1 ms (faster than any BMS loop) to 10 s."""
    duration_s: Annotated[float, Field(ge=1e-4, le=MAX_TIME_S, allow_inf_nan=False)] = 600.0
    """At least 0.1 ms (one period of any dt_s: a run has a first sample)."""
    stop_when_unsupplied_s: Seconds | None = Field(
        None, description="stop after the load has been unsupplied this long"
    )
    progress: bool = True

    @model_validator(mode="after")
    def _bounded(self) -> SimConfig:
        steps = self.duration_s / self.dt_s
        if steps > MAX_STEPS:
            raise ValueError(
                f"duration_s / dt_s = {steps:.3g} periods, more than {MAX_STEPS:,} per run"
            )
        return self


class SensorError(_Strict):
    """The error of one measured quantity, in that quantity's unit (V, A or degC): what a real
    BMS's front end reads is ``gain * truth + offset + noise``, rounded to ``quantum``, from the
    sample ``delay_s`` old. The defaults are a perfect sensor."""

    noise_sigma: NonNegFloat = Field(
        0.0, le=1000.0, description="standard deviation of white Gaussian noise (its unit)"
    )
    gain: Annotated[float, Field(gt=0.5, lt=2.0, allow_inf_nan=False)] = Field(
        1.0, description="scale error: 1.01 reads 1 % high"
    )
    offset: Annotated[float, Field(ge=-1000.0, le=1000.0, allow_inf_nan=False)] = Field(
        0.0, description="additive error (unit of the quantity)"
    )
    quantum: NonNegFloat = Field(
        0.0, le=100.0, description="resolution: readings are rounded to a multiple (0: none)"
    )
    delay_s: Annotated[float, Field(ge=0.0, le=60.0, allow_inf_nan=False)] = Field(
        0.0, description="the reading is the truth this long ago (latest sample at or before)"
    )

    @property
    def perfect(self) -> bool:
        return (
            self.noise_sigma == 0.0 and self.gain == 1.0 and self.offset == 0.0
            and self.quantum == 0.0 and self.delay_s == 0.0
        )  # fmt: skip


class SensorsConfig(_Strict):
    """``[sensors]``: realistic sensing in the plant (issue #28 item 0), off when absent.

    Errors apply per quantity where the BMS's front end measures it: every cell voltage (so
    group, battery, min and max cell voltages are sums and extremes of erroneous cells), every
    battery's current, every cell temperature and the bus (pack) voltage. The noise is drawn
    from ``seed`` (one stream per quantity), so a run is reproducible."""

    seed: int = Field(0, ge=0, lt=2**63, description="seed of the noise streams")
    cell_v: SensorError = Field(SensorError(), description="each cell (group) voltage, V")
    pack_v: SensorError = Field(SensorError(), description="the bus (pack) voltage, V")
    current: SensorError = Field(SensorError(), description="each battery's current, A")
    temp: SensorError = Field(SensorError(), description="each cell temperature, degC")
    soc0_error: Annotated[float, Field(ge=0.0, le=0.5, allow_inf_nan=False)] = Field(
        0.0,
        description="the SOC the BMS starts from is this far from the truth (SOC fraction, "
        "toward 50 %), as if restored from a stale memory at power-up; 0: it reads the OCV of "
        "its first sample as before. Applies to the [soc] estimator (both the observer and "
        "the coulomb counter start from it)",
    )


FaultKind = Literal[
    "sensor_nan",
    "sensor_stuck",
    "sensor_dropout",
    "welded_relay",
    "shorted_fet",
    "charger_fault",
    "can_silence",
    "cooling_failure",
]
FAULT_KINDS: tuple[str, ...] = get_args(FaultKind)


class FaultConfig(_Strict):
    """A fault injected into the run at ``at_s`` (until ``until_s``, if given)."""

    kind: FaultKind
    at_s: Seconds
    until_s: Seconds | None = None
    battery: str | None = Field(None, description="battery name (sensor/switch/thermal faults)")
    quantity: Literal["voltage_v", "current_a", "temp_c", "min_cell_v", "max_cell_v", "soc"] = (
        "voltage_v"
    )
    fet: Literal["chg", "dsg"] = "chg"
    flag: Literal[
        "hardware_failure",
        "over_temperature",
        "input_voltage_fault",
        "battery_not_detected",
    ] = "hardware_failure"
    cooling_factor: Annotated[float, Field(gt=0, lt=1)] = Field(
        0.02, description="heat-transfer-to-ambient multiplier during a cooling failure"
    )

    @model_validator(mode="after")
    def _check(self) -> FaultConfig:
        if self.until_s is not None and self.until_s <= self.at_s:
            raise ValueError("until_s must be after at_s")
        needs_battery = self.kind not in ("charger_fault", "can_silence")
        if needs_battery and self.battery is None:
            raise ValueError(f"fault kind {self.kind!r} needs a battery name")
        return self


@dataclass(frozen=True)
class Section:
    """Registers a field of :class:`ScenarioConfig` as the section of a control method
    (``role="method"``: runs when ``controller`` lists it, in that order) or of a safety layer
    (``role="safety"``: runs, under the supervisor, when its section is present), run by the
    compiled method of ``package`` (its ``METHOD``, or ``method_for(config, infos)``;
    default ``packpilot.control.<field name>``).

    This field is the **one registry line** of a method: :data:`METHODS` / :data:`SAFETY` /
    :data:`PACKAGES` are derived from these fields, and so is
    :mod:`packpilot.control.registry` (``config`` sits below ``control``: it names the package
    as a string and never imports it). The core's fused step is generated from the parts a
    scenario builds (:mod:`packpilot.control.core_kernel`), so nothing else lists methods."""

    role: Literal["method", "safety"]
    package: str | None = None


_METHOD = Section("method")
_SAFETY = Section("safety")


def _known_method(name: str) -> str:
    if name not in METHODS:
        allowed = ", ".join(repr(m) for m in METHODS[:-1]) + f" or {METHODS[-1]!r}"
        raise ValueError(f"Input should be {allowed}")
    return name


class ScenarioConfig(_Strict):
    """A whole scenario file."""

    pack: PackConfig
    load: LoadConfig = LoadConfig()
    charger: ChargerConfig = ChargerConfig()
    balancer: BalancerConfig = BalancerConfig()
    aux: AuxConfig = AuxConfig()
    sim: SimConfig = SimConfig()
    controller: list[Annotated[str, AfterValidator(_known_method)]] = Field(
        default_factory=list,
        description="control methods to run, in order; each at most once",
    )
    protection: Annotated[ProtectionConfig | None, _METHOD] = None
    sequencing: Annotated[SequencingConfig | None, _METHOD] = None
    charging: Annotated[ChargingConfig | None, _METHOD] = None
    equalization: Annotated[EqualizationConfig | None, _METHOD] = None
    supervisor: SupervisorConfig | None = Field(
        None, description="present: run the methods under the supervisor's mode machine"
    )
    limits: Annotated[LimitsConfig | None, _SAFETY] = Field(
        None, description="present: enable safety limits"
    )
    plausibility: Annotated[PlausibilityConfig | None, _SAFETY] = Field(
        None, description="present: enable sensor/switch plausibility checks"
    )
    soc: Annotated[SocConfig | None, _SAFETY] = Field(
        None, description="present: BMS SOC estimation (coulomb counting + OCV after rest)"
    )
    can: CanConfig | None = Field(None, description="charger over CAN (python-can)")
    sensors: SensorsConfig | None = Field(
        None, description="present: the plant's sensors read with these errors (issue #28)"
    )
    faults: list[FaultConfig] = Field(default_factory=list)

    @field_validator("controller", mode="before")
    @classmethod
    def _few_controllers(cls, value: Any) -> Any:
        """Each method runs at most once (a repeated one made the core's part lookup raise), so
        the list is at most as long as :data:`METHODS`; checked before the elements are."""
        if isinstance(value, list | tuple) and len(value) > len(METHODS):
            raise ValueError(f"at most {len(METHODS)} methods (each once), got {len(value)}")
        return value

    @field_validator("controller")
    @classmethod
    def _unique_controllers(cls, value: list[str]) -> list[str]:
        dup = sorted({m for m in value if value.count(m) > 1})
        if dup:
            raise ValueError(f"each method runs once; repeated: {', '.join(dup)}")
        return value

    @model_validator(mode="after")
    def _check_faults(self) -> ScenarioConfig:
        names = {b.name for b in self.pack.batteries}
        for k, f in enumerate(self.faults):
            if f.battery is not None and f.battery not in names:
                raise ValueError(
                    f"faults.{k}.battery: unknown battery {f.battery!r}; "
                    f"known: {', '.join(sorted(names))}"
                )
        return self

    @property
    def supervised(self) -> bool:
        """Any of ``[supervisor]`` and the safety sections is present (:data:`SUPERVISED`)."""
        return any(getattr(self, name) is not None for name in SUPERVISED)

    def section(self, name: str) -> BaseModel:
        """The typed ``[name]`` section, or its defaults when the file has none (a method
        listed in ``controller`` without its table runs with its defaults)."""
        value = getattr(self, name)
        if value is None:
            return SECTIONS[name]()
        assert isinstance(value, SECTIONS[name])
        return value


def _sections(role: str) -> dict[str, type[BaseModel]]:
    """The fields of :class:`ScenarioConfig` marked with ``role``, in declaration order, and
    the model each one holds."""
    out: dict[str, type[BaseModel]] = {}
    for name, info in ScenarioConfig.model_fields.items():
        if any(isinstance(m, Section) and m.role == role for m in info.metadata):
            (model,) = (a for a in get_args(info.annotation) if a is not NoneType)
            out[name] = model
    return out


def _packages() -> dict[str, str]:
    out: dict[str, str] = {}
    for name, info in ScenarioConfig.model_fields.items():
        for m in info.metadata:
            if isinstance(m, Section):
                out[name] = m.package or f"packpilot.control.{name}"
    return out


_METHOD_MODELS = _sections("method")
_SAFETY_MODELS = _sections("safety")
METHODS: tuple[str, ...] = tuple(_METHOD_MODELS)
"""The control methods; a scenario's ``controller`` lists the ones it runs, in its order."""
SAFETY: tuple[str, ...] = tuple(_SAFETY_MODELS)
"""The safety layers, in the order they run (after the methods)."""
SUPERVISED: tuple[str, ...] = ("supervisor", *SAFETY)
"""Sections whose presence puts the run under the supervisor."""
SECTIONS: Mapping[str, type[BaseModel]] = MappingProxyType(
    {**_METHOD_MODELS, "supervisor": SupervisorConfig, **_SAFETY_MODELS}
)
"""Every section a method, the supervisor or a safety layer reads -> its config model."""
PACKAGES: Mapping[str, str] = MappingProxyType(_packages())
"""Each method and safety layer -> the control package whose ``METHOD`` runs it."""


MAX_FILE_BYTES = 1 << 20
"""Largest scenario file read (1 MiB): the largest example is 2 kB; a file of megabytes is not
a scenario, and parsing it would cost seconds before any field is checked."""


def read_toml(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise ConfigError(f"{path}: file not found")
    if not path.is_file():
        raise ConfigError(f"{path}: not a file")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ConfigError(f"{path}: {size:,} bytes; a scenario file has at most {MAX_FILE_BYTES:,}")
    try:
        raw = path.read_bytes().removeprefix(b"\xef\xbb\xbf")  # a UTF-8 BOM is dropped
        data = tomllib.loads(raw.decode("utf-8"))
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML: {err}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file") from None
    except RecursionError:  # tomllib parses nested arrays / inline tables recursively
        raise ConfigError(f"{path}: nested more than {MAX_DEPTH} levels deep") from None
    if _depth(data) > MAX_DEPTH:
        raise ConfigError(f"{path}: nested more than {MAX_DEPTH} levels deep")
    return data


MAX_DEPTH = 16
"""Deepest nesting of tables and arrays a scenario may use (the schema needs 5: a protection
table row's ranges). A file nested 500 deep made tomllib raise RecursionError."""


def _depth(node: object, level: int = 0) -> int:
    """Nesting depth of parsed TOML, stopping once it is past :data:`MAX_DEPTH`."""
    if level > MAX_DEPTH:
        return level
    children = node.values() if isinstance(node, dict) else node if isinstance(node, list) else ()
    return max((_depth(c, level + 1) for c in children), default=level)


def parse_config(data: dict[str, Any], source: str = "<config>") -> ScenarioConfig:
    """Validate a whole scenario, every section typed; the first error becomes one line
    naming ``source`` and the field path (``protection.parameters.0.cutoff_v``)."""
    big = oversized(data)
    if big is not None:
        where, n = big
        raise ConfigError(
            f"{source}: {where or '(top level)'}: at most {MAX_LIST_ITEMS:,} entries, got {n:,}"
        )
    try:
        return ScenarioConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(fmt_error(source, err, model=ScenarioConfig)) from None


def load_config(path: str | Path) -> ScenarioConfig:
    """Read and validate a scenario TOML file (relative profile paths resolve next to it)."""
    p = Path(path)
    data = read_toml(p)
    load = data.get("load")
    if isinstance(load, dict):
        prof = load.get("profile")
        suffixes = (".csv", ".ulg", ".bin", ".log", ".tlog")  # a CSV profile or a flight log (#27)
        if isinstance(prof, str) and prof.endswith(suffixes) and not Path(prof).is_absolute():
            load["profile"] = str((p.parent / prof).resolve())
    return parse_config(data, str(p))


def load_section(path: str | Path | None, section: str) -> BaseModel:
    """A single section from a file (or its defaults) — used by ``replay``."""
    model = SECTIONS[section]
    if path is None:
        return model()
    p = Path(path)
    data = read_toml(p)
    raw = data.get(section)
    if raw is not None and not isinstance(raw, dict):
        raise ConfigError(f"{p}: [{section}] must be a table")
    return load_section_model(model, raw, section, str(p))
