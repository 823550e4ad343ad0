"""Fuzzed configs and logs never produce a traceback: exit code 2 and a message naming the
field or row (or a normal run when the mutation happens to be valid)."""

from __future__ import annotations

import copy
import time
import tomllib
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, given
from hypothesis import strategies as st
from typer.testing import CliRunner

from packpilot.cli import app
from tests.budget import budget
from tests.conftest import EXAMPLES

RUNNER = CliRunner()
FIXTURE_OK = [HealthCheck.function_scoped_fixture]
BASE = tomllib.loads((EXAMPLES / "uav_dual_parallel.toml").read_text())

BAD_VALUES = st.one_of(
    st.text(max_size=8),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.lists(st.integers(), max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out: list[tuple[Any, ...]] = []
    if isinstance(node, dict):
        for k, v in node.items():
            out.append((*prefix, k))
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


PATHS = [*_paths(BASE), ("pack", "bogus"), ("sim", "dt_s"), ("protection", "table")]


def _set(cfg: dict[str, Any], path: tuple[Any, ...], value: Any) -> None:
    node: Any = cfg
    for key in path[:-1]:
        node = node.setdefault(key, {}) if isinstance(node, dict) else node[key]
    if isinstance(node, dict):
        node[path[-1]] = value
    else:
        node[path[-1]] = value


def _check(result: Any, *names: str) -> None:
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert result.exit_code in (0, 2), (result.exit_code, result.output)
    if result.exit_code == 2:
        lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1, result.stderr
        assert "Traceback" not in result.stderr
        assert lines[0].startswith("error: ")
        if names:
            assert any(n in lines[0] for n in names), (lines[0], names)


@budget(200, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(path=st.sampled_from(PATHS), value=BAD_VALUES)
def test_fuzzed_config_values(tmp_path: Path, path: tuple[Any, ...], value: Any) -> None:
    cfg = copy.deepcopy(BASE)
    _set(cfg, path, value)
    p = tmp_path / "fuzz.toml"
    try:
        p.write_text(tomli_w.dumps(cfg))
    except (TypeError, ValueError):
        return  # not representable in TOML (e.g. a NaN key): nothing to feed the CLI
    res = RUNNER.invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    leaf = str(path[-1]) if not isinstance(path[-1], int) else str(path[-2])
    _check(res, leaf, "fuzz.toml")


@pytest.mark.parametrize("key", ["\x1e", "\x1c", "a\u2028b", "\x85", "tab\there"])
def test_control_characters_in_a_key_stay_on_one_line(tmp_path: Path, key: str) -> None:
    """Found by the fuzz test above: ``str.splitlines`` breaks on \\x1c-\\x1e, \\x85 and
    U+2028, so an unknown key made of them split the one-line error; keys are escaped now."""
    cfg = copy.deepcopy(BASE)
    cfg["load"][key] = 0
    p = tmp_path / "keys.toml"
    p.write_text(tomli_w.dumps(cfg))
    res = RUNNER.invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    assert res.exit_code == 2
    _check(res, "load", "unknown key")


@budget(200, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(max_size=200))
def test_fuzzed_toml_text(tmp_path: Path, text: str) -> None:
    p = tmp_path / "raw.toml"
    p.write_bytes(text.encode("utf-8", "replace"))
    res = RUNNER.invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    _check(res, "raw.toml")


CELL = st.one_of(
    st.floats(-1e3, 1e3, allow_nan=False).map(lambda x: f"{x:.6g}"),
    st.sampled_from(["", "nan", "inf", "abc", "1,2", " ", "--1", "1e999"]),
)


@budget(200, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    method=st.sampled_from(["protection", "sequencing", "equalization"]),
    rows=st.lists(st.lists(CELL, min_size=1, max_size=6), min_size=0, max_size=6),
    drop=st.booleans(),
)
def test_fuzzed_replay_logs(tmp_path: Path, method: str, rows: list[list[str]], drop: bool) -> None:
    header = {
        "protection": ["t_s", "current_a", "temp_c", "min_cell_v"],
        "sequencing": ["t_s", "v_0", "v_1", "i_0", "i_1"],
        "equalization": ["t_s", "current_a", "v_0", "v_1", "v_2"],
    }[method]
    if drop:
        header = header[:-1]
    lines = [",".join(header)] + [",".join(r) for r in rows]
    p = tmp_path / "log.csv"
    p.write_text("\n".join(lines) + "\n")
    res = RUNNER.invoke(app, ["replay", method, str(p), "--json"])
    _check(res, "log.csv")


# The safety and method sections (issue 7, equalization): the same mutation over the mission
# config with each section's keys spelled out, plus a scheduled fault.
MISSION = tomllib.loads((EXAMPLES / "uav_mission.toml").read_text())
MISSION.pop("can", None)  # no CAN bus in a 0.2 s fuzz run
MISSION["equalization"].update(sample_period_s=1.0, time_mode="string_current", min_current_a=0.5)
MISSION["supervisor"].update(init_time_s=0.5, idle_after_s=5.0, fault_hold_s=10.0)
MISSION["limits"].update(derate_fraction=0.5, context_current_c=0.05)
MISSION["plausibility"].update(
    cell_v_range=[0.5, 5.0], stuck_time_s=60.0, max_sample_age_s=2.0, clear_after_s=5.0
)
MISSION["soc"].update(rest_current_a=0.1, rest_time_s=600.0, blend=1.0, voltage="min")
MISSION["faults"] = [{"kind": "sensor_nan", "at_s": 0.1, "battery": "A", "quantity": "temp_c"}]
SECTIONS = ("equalization", "supervisor", "limits", "plausibility", "soc", "faults")
MISSION_PATHS = [p for p in _paths(MISSION) if p[0] in SECTIONS]


@budget(200, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(path=st.sampled_from(MISSION_PATHS), value=BAD_VALUES)
def test_fuzzed_safety_section_values(tmp_path: Path, path: tuple[Any, ...], value: Any) -> None:
    cfg = copy.deepcopy(MISSION)
    _set(cfg, path, value)
    p = tmp_path / "fuzz.toml"
    try:
        p.write_text(tomli_w.dumps(cfg))
    except (TypeError, ValueError):
        return
    res = RUNNER.invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    leaf = next(str(k) for k in reversed(path) if not isinstance(k, int))
    _check(res, leaf, "fuzz.toml")


PROFILE_ROW = st.lists(CELL, min_size=0, max_size=3)


@budget(200, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(PROFILE_ROW, min_size=0, max_size=6), raw=st.binary(max_size=16))
def test_fuzzed_load_profile_rows(tmp_path: Path, rows: list[list[str]], raw: bytes) -> None:
    """A load profile CSV with malformed rows (gaps, text, extra cells, stray bytes)."""
    prof = tmp_path / "prof.csv"
    body = "\n".join(["t_s,current_a", *(",".join(r) for r in rows)]) + "\n"
    prof.write_bytes(body.encode() + raw)
    cfg = copy.deepcopy(BASE)
    cfg["load"] = {"kind": "current", "value": 1.0, "profile": str(prof)}
    p = tmp_path / "scenario.toml"
    p.write_text(tomli_w.dumps(cfg))
    res = RUNNER.invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    _check(res, "prof.csv")
    if res.exit_code == 2:
        assert "row" in res.stderr or "header" in res.stderr or "UTF-8" in res.stderr


@budget(200, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=st.binary(max_size=64))
def test_fuzzed_replay_bytes(tmp_path: Path, raw: bytes) -> None:
    """Arbitrary bytes after a valid header (not UTF-8, NUL, stray separators)."""
    p = tmp_path / "log.csv"
    p.write_bytes(b"t_s,current_a,v_0,v_1\n0,1,3.3,3.31\n" + raw)
    res = RUNNER.invoke(app, ["replay", "equalization", str(p), "--json"])
    _check(res, "log.csv")


def test_not_a_file_and_unwritable_output(tmp_path: Path) -> None:
    res = RUNNER.invoke(app, ["simulate", str(tmp_path), "--json"])
    _check(res, str(tmp_path))
    assert res.exit_code == 2
    res = RUNNER.invoke(app, ["replay", "equalization", str(tmp_path)])
    assert res.exit_code == 2
    log = tmp_path / "log.csv"
    log.write_text("t_s,current_a,v_0,v_1\n0,1,3.3,3.31\n")
    out = tmp_path / "missing" / "out.csv"
    res = RUNNER.invoke(app, ["replay", "equalization", str(log), "--out", str(out)])
    _check(res, "out.csv")
    assert res.exit_code == 2


# ---------------------------------------------------------------- cheap, many (issue #18 §3)
# The tests above feed the CLI and run 0.2 s of simulation per example; these validate and
# parse only (a few ms each), so CI affords hundreds of cases: every drawn config must either
# be one clean ConfigError naming the file, or a valid config whose run is bounded.

ABSURD = st.sampled_from(
    [0, -0.0, 1e-300, -1e-300, 1e308, -1e308, 1e24, -1, 2**70, True, False, "", [], {}, 1e9, 4.5]
)
SCHEMA_VALUES = st.one_of(ABSURD, BAD_VALUES, st.floats(-1e12, 1e12))
SCHEMA_PATHS = [*PATHS, *((*p,) for p in MISSION_PATHS)]
MAX_CASE_S = 5.0
"""Bound on one case: validating never takes long; a hang (10^30 steps) would show here."""


def _validated_or_one_line(p: Path) -> Any:
    """``load_config(p)``: a config, or None after checking the error is one clean line."""
    from packpilot.config import load_config
    from packpilot.errors import ConfigError

    try:
        return load_config(p)
    except ConfigError as err:
        text = str(err)
        assert "\n" not in text and len(text) < 1000, text
        assert text.startswith(str(p)), text
        return None


@budget(300, suppress_health_check=FIXTURE_OK)
@given(
    mutations=st.lists(
        st.tuples(st.sampled_from(SCHEMA_PATHS), SCHEMA_VALUES), min_size=1, max_size=3
    ),
    mission=st.booleans(),
)
def test_fuzzed_schema_is_refused_cleanly_or_bounded(
    tmp_path: Path, mutations: list[tuple[tuple[Any, ...], Any]], mission: bool
) -> None:
    from packpilot.config.scenario import MAX_STEPS
    from packpilot.sim.loop import n_steps

    cfg = copy.deepcopy(MISSION if mission else BASE)
    for path, value in mutations:
        try:
            _set(cfg, path, value)
        except (TypeError, IndexError, KeyError):
            continue  # the path runs through a mutated scalar
    p = tmp_path / "fuzz.toml"
    try:
        p.write_text(tomli_w.dumps(cfg))
    except (TypeError, ValueError):
        return
    t0 = time.perf_counter()
    scenario = _validated_or_one_line(p)
    if scenario is not None:
        assert 1 <= n_steps(scenario) <= MAX_STEPS
    assert time.perf_counter() - t0 < MAX_CASE_S


CSV_CELL = st.one_of(
    CELL,
    st.sampled_from(["1e306", "-1e306", "1e308", "1e-300", "-0", "1e24", "0x10", "1_0"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
)


@budget(200, suppress_health_check=FIXTURE_OK)
@given(
    column=st.sampled_from(["current_a", "power_w", "resistance_ohm"]),
    rows=st.lists(st.lists(CSV_CELL, min_size=0, max_size=3), min_size=0, max_size=8),
)
def test_fuzzed_profile_csv_is_parsed_or_refused(
    tmp_path: Path, column: str, rows: list[list[str]]
) -> None:
    from packpilot.errors import InputError
    from packpilot.model import loads
    from packpilot.model.loads import _BOUNDS

    p = tmp_path / "prof.csv"
    p.write_text("\n".join([f"t_s,{column}", *(",".join(r) for r in rows)]) + "\n")
    try:
        prof = loads.from_csv(p)
    except InputError as err:
        assert "\n" not in str(err) and str(err).startswith(str(p))
        return
    lo, hi = _BOUNDS[column]
    assert np.all(np.isfinite(prof.t_s)) and np.all((lo <= prof.value) & (prof.value <= hi))


@budget(200, suppress_health_check=FIXTURE_OK)
@given(
    method=st.sampled_from(["protection", "sequencing", "equalization"]),
    rows=st.lists(st.lists(CSV_CELL, min_size=4, max_size=5), min_size=1, max_size=5),
)
def test_fuzzed_replay_csv_is_replayed_or_refused(
    tmp_path: Path, method: str, rows: list[list[str]]
) -> None:
    """The replay functions in-process (no CLI): a clean InputError or a bounded replay."""
    from packpilot.config import load_section
    from packpilot.control.registry import REGISTRY
    from packpilot.errors import InputError

    header = {
        "protection": ["t_s", "current_a", "temp_c", "min_cell_v"],
        "sequencing": ["t_s", "v_0", "v_1", "i_0", "i_1"],
        "equalization": ["t_s", "current_a", "v_0", "v_1", "v_2"],
    }[method]
    p = tmp_path / "log.csv"
    body = [",".join(header), *(",".join(r[: len(header)]) for r in rows)]
    p.write_text("\n".join(body) + "\n")
    replay = REGISTRY[method].replay
    assert replay is not None
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a NumPy overflow is a finding
        try:
            replay.function()(p, load_section(None, method))
        except InputError as err:
            assert "\n" not in str(err) and str(err).startswith(str(p))
    assert time.perf_counter() - t0 < MAX_CASE_S
