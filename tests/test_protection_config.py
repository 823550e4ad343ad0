"""ProtectionConfig: defaults, the edge convention, and load-time rejection of bad tables."""

from __future__ import annotations

import tomllib

import pytest
from pydantic import ValidationError

from packpilot.control.protection import (
    DEFAULT_PARAMETERS,
    DEFAULT_TABLE,
    AxisRange,
    CompiledTable,
    ProtectionConfig,
    ProtectionParameter,
    TableRow,
)


def _param(table: CompiledTable, current_a: float, temp_c: float) -> str:
    row = table.lookup([current_a, temp_c])
    return table.params[table.rows[row][0]].name


def _rows(*rows: tuple[str, dict[str, str]]) -> tuple[TableRow, ...]:
    return tuple(TableRow.model_validate({"param": p, "ranges": r}) for p, r in rows)


def test_defaults_reproduce_spec_weights() -> None:
    table = CompiledTable.from_config(ProtectionConfig())
    assert table.axes == ("current_a", "temp_c")
    assert table.m_ms == 30_000
    assert {p.name: n for p, n in zip(table.params, table.weights, strict=True)} == {
        "P1": 2,
        "P2": 3,
        "P3": 6,
    }
    assert [(p.cutoff_v, p.t_max_s) for p in table.params] == [(2.8, 15.0), (3.0, 10.0), (3.2, 5.0)]


@pytest.mark.parametrize(
    ("current_a", "temp_c", "expected"),
    [
        # spec §4 grid away from the edges
        (10.0, 0.0, "P1"),
        (10.0, 10.0, "P2"),
        (10.0, 25.0, "P3"),
        (20.0, 0.0, "P1"),
        (20.0, 10.0, "P2"),
        (20.0, 25.0, "P2"),
        (30.0, 0.0, "P1"),
        (30.0, 10.0, "P1"),
        (30.0, 25.0, "P1"),
        # §10.1 edges: I = 15 is low, I = 25 is mid; T = 5 is cool, T = 15 is warm
        (15.0, 25.0, "P3"),
        (15.000001, 25.0, "P2"),
        (25.0, 25.0, "P2"),
        (25.000001, 25.0, "P1"),
        (10.0, 5.0, "P2"),
        (10.0, 4.999999, "P1"),
        (10.0, 15.0, "P3"),
        (10.0, 14.999999, "P2"),
        (25.0, 5.0, "P2"),
        (15.0, 15.0, "P3"),
        (25.0, 4.999999, "P1"),
        (0.0, 25.0, "P3"),
        (-20.0, 25.0, "P3"),  # charging current falls in the low row
    ],
)
def test_default_lookup_follows_edge_convention(
    current_a: float, temp_c: float, expected: str
) -> None:
    table = CompiledTable.from_config(ProtectionConfig())
    assert _param(table, current_a, temp_c) == expected


def test_edge_convention_is_configurable() -> None:
    """Move I = 15 A into the mid row by flipping the brackets."""
    rows = _rows(
        ("P3", {"current_a": "(-inf, 15)"}),
        ("P2", {"current_a": "[15, 25]"}),
        ("P1", {"current_a": "(25, inf)"}),
    )
    table = CompiledTable.from_config(ProtectionConfig(table=rows))
    assert _param_1d(table, 15.0) == "P2"
    assert _param_1d(table, 14.999) == "P3"
    assert _param_1d(table, 25.0) == "P2"


def _param_1d(table: CompiledTable, x: float) -> str:
    return table.params[table.rows[table.lookup([x])][0]].name


def test_interval_notation_and_dict_form_agree() -> None:
    a = AxisRange.model_validate("(15, 25]")
    b = AxisRange.model_validate({"lo": 15, "hi": 25, "lo_closed": False, "hi_closed": True})
    assert a == b
    assert str(a) == "(15, 25]"
    assert not a.contains(15.0) and a.contains(25.0) and a.contains(20.0)
    assert a.contains(14.8, band=0.5) and not a.contains(14.4, band=0.5)
    assert AxisRange.model_validate("[5, inf)").contains(1e300)


def test_toml_section_loads() -> None:
    doc = tomllib.loads(
        """
        [protection]
        reset_on_recovery = false
        hysteresis = { current_a = 0.5, temp_c = 0.5 }
        parameters = [
          { name = "hot", cutoff_v = 3.3, t_max_s = 4 },
          { name = "cold", cutoff_v = 2.9, t_max_s = 6 },
        ]
        table = [
          { param = "cold", ranges = { temp_c = "(-inf, 10)" } },
          { param = "hot", ranges = { temp_c = "[10, inf)" } },
        ]
        """
    )
    cfg = ProtectionConfig.model_validate(doc["protection"])
    table = CompiledTable.from_config(cfg)
    assert table.m_ms == 12_000
    assert dict(zip([p.name for p in table.params], table.weights, strict=True)) == {
        "cold": 2,
        "hot": 3,
    }


def test_one_row_table_is_the_conventional_fixed_criterion() -> None:
    cfg = ProtectionConfig(
        parameters=(ProtectionParameter(name="fixed", cutoff_v=3.2, t_max_s=5.0),),
        table=(TableRow(param="fixed"),),
    )
    table = CompiledTable.from_config(cfg)
    assert table.axes == ()
    assert table.m_ms == 5_000 and table.weights == (1,)


def test_lcm_is_exact_for_millisecond_durations() -> None:
    cfg = ProtectionConfig(
        parameters=(
            ProtectionParameter(name="a", cutoff_v=3.0, t_max_s=1.5),
            ProtectionParameter(name="b", cutoff_v=3.1, t_max_s=2.0),
            ProtectionParameter(name="c", cutoff_v=3.2, t_max_s=0.7),
        ),
        table=_rows(
            ("a", {"temp_c": "(-inf, 0)"}),
            ("b", {"temp_c": "[0, 20)"}),
            ("c", {"temp_c": "[20, inf)"}),
        ),
    )
    table = CompiledTable.from_config(cfg)
    assert table.m_ms == 42_000
    assert table.weights == (28, 21, 60)


def test_unused_parameters_do_not_enter_m() -> None:
    cfg = ProtectionConfig(table=(TableRow(param="P2"),))
    table = CompiledTable.from_config(cfg)
    assert table.m_ms == 10_000 and [p.name for p in table.params] == ["P2"]


def test_three_axis_table_with_soh() -> None:
    rows = []
    for name, soh in (("P1", "(-inf, 0.8)"), ("P2", "[0.8, inf)")):
        for t in ("(-inf, 5)", "[5, inf)"):
            rows.append((name, {"soh": soh, "temp_c": t, "current_a": "(-inf, inf)"}))
    cfg = ProtectionConfig(table=_rows(*rows))
    assert cfg.axes == ("current_a", "temp_c", "soh")
    bad = list(rows)
    bad[3] = ("P2", {"soh": "(0.8, inf)", "temp_c": "[5, inf)"})
    with pytest.raises(ValidationError, match=r"gap.*soh = 0\.8"):
        ProtectionConfig(table=_rows(*bad))


# ---- rejection: each message must name the culprit ---------------------------------------


def test_overlap_is_rejected_naming_both_rows() -> None:
    rows = list(DEFAULT_TABLE)
    rows[0] = TableRow.model_validate(
        {"param": "P1", "ranges": {"current_a": "(-inf, 16]", "temp_c": "(-inf, 5)"}}
    )
    with pytest.raises(ValidationError, match=r"overlap.*table\[0\] \(P1\) and table\[3\] \(P1\)"):
        ProtectionConfig(table=tuple(rows))


def test_overlap_on_a_shared_edge_is_rejected() -> None:
    rows = _rows(("P1", {"temp_c": "(-inf, 5]"}), ("P2", {"temp_c": "[5, inf)"}))
    with pytest.raises(
        ValidationError, match=r"table\[0\] \(P1\) and table\[1\] \(P2\).*temp_c = 5"
    ):
        ProtectionConfig(table=rows)


def test_gap_is_rejected_naming_the_uncovered_region() -> None:
    with pytest.raises(ValidationError, match=r"gap: no row covers current_a in \(25, inf\)"):
        ProtectionConfig(table=DEFAULT_TABLE[:-1])


def test_gap_at_an_open_edge_is_rejected() -> None:
    rows = _rows(("P1", {"temp_c": "(-inf, 5)"}), ("P2", {"temp_c": "(5, inf)"}))
    with pytest.raises(ValidationError, match=r"gap: no row covers temp_c = 5"):
        ProtectionConfig(table=rows)


@pytest.mark.parametrize("t_max_s", [0.0, -1.0, float("nan"), float("inf")])
def test_non_positive_duration_is_rejected(t_max_s: float) -> None:
    with pytest.raises(ValidationError, match=r"parameter 'P2': t_max_s must be a positive"):
        ProtectionConfig(
            parameters=(
                DEFAULT_PARAMETERS[0],
                {"name": "P2", "cutoff_v": 3.0, "t_max_s": t_max_s},
                DEFAULT_PARAMETERS[2],
            )
        )


def test_duration_must_be_whole_milliseconds() -> None:
    with pytest.raises(ValidationError, match=r"parameter 'P3': t_max_s must be a whole number"):
        ProtectionParameter(name="P3", cutoff_v=3.2, t_max_s=5.0004)


@pytest.mark.parametrize("cutoff_v", [1.99, 4.51, 0.0, float("nan")])
def test_cutoff_out_of_range_is_rejected(cutoff_v: float) -> None:
    with pytest.raises(
        ValidationError, match=r"parameter 'P1': cutoff_v must be between 2.0 and 4.5"
    ):
        ProtectionParameter(name="P1", cutoff_v=cutoff_v, t_max_s=15.0)


def test_cutoff_edges_are_allowed() -> None:
    ProtectionParameter(name="lo", cutoff_v=2.0, t_max_s=1.0)
    ProtectionParameter(name="hi", cutoff_v=4.5, t_max_s=1.0)


def test_unknown_parameter_in_row_is_rejected() -> None:
    rows = list(DEFAULT_TABLE)
    rows[4] = TableRow(param="P9", ranges=rows[4].ranges)
    with pytest.raises(ValidationError, match=r"table\[4\]\.param: unknown parameter 'P9'"):
        ProtectionConfig(table=tuple(rows))


def test_unknown_axis_is_rejected() -> None:
    rows = _rows(("P1", {"temperature": "(-inf, inf)"}))
    with pytest.raises(ValidationError, match=r"table\[0\]\.ranges\.temperature: unknown axis"):
        ProtectionConfig(table=rows)


def test_duplicate_parameter_names_are_rejected() -> None:
    dup = (*DEFAULT_PARAMETERS, ProtectionParameter(name="P2", cutoff_v=3.1, t_max_s=7.0))
    with pytest.raises(ValidationError, match=r"duplicate name\(s\) P2"):
        ProtectionConfig(parameters=dup)


@pytest.mark.parametrize(
    ("text", "msg"),
    [
        ("15..25", "expected interval notation"),
        ("(a, 25]", "edges must be numbers"),
        ("[-inf, 5)", "infinite edge must be open"),
        ("(25, 15]", "is empty"),
        ("(5, 5]", "is empty"),
    ],
)
def test_bad_interval_is_rejected(text: str, msg: str) -> None:
    with pytest.raises(ValidationError, match=msg):
        AxisRange.model_validate(text)


def test_point_interval_is_allowed() -> None:
    assert AxisRange.model_validate("[5, 5]").contains(5.0)


@pytest.mark.parametrize(
    ("field", "value", "msg"),
    [
        ("hysteresis", {"current": 0.5}, r"hysteresis\.current: unknown axis"),
        ("hysteresis", {"temp_c": -0.5}, r"hysteresis\.temp_c must be"),
        ("filter_tau_s", {"current_a": 0.0}, r"filter_tau_s\.current_a must be"),
        ("charge_detect_s", -1.0, r"charge_detect_s must be"),
        ("discharge_threshold_a", float("nan"), r"discharge_threshold_a must be"),
    ],
)
def test_bad_options_are_rejected(field: str, value: object, msg: str) -> None:
    with pytest.raises(ValidationError, match=msg):
        ProtectionConfig.model_validate({field: value})


def test_unknown_option_is_rejected() -> None:
    with pytest.raises(ValidationError, match="reset_on_recover"):
        ProtectionConfig.model_validate({"reset_on_recover": True})
