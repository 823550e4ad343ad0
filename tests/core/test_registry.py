"""The registry: every method and safety layer registered once, everything else derived."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from packpilot import config
from packpilot.cli import app
from packpilot.control.core_kernel import source
from packpilot.control.method import Method
from packpilot.control.registry import METHODS, REGISTRY, SAFETY

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_registry_matches_the_typed_sections_of_the_scenario() -> None:
    assert (METHODS, SAFETY) == (config.METHODS, config.SAFETY)
    for name, entry in REGISTRY.items():
        assert entry.name == name
        assert entry.config is config.SECTIONS[name]
        assert config.ScenarioConfig.model_fields[name].annotation == entry.config | None


def test_each_entry_resolves_to_a_method_of_its_config() -> None:
    for name, entry in REGISTRY.items():
        method = entry.resolve()
        assert isinstance(method, Method), name
        assert method.name == name and method.config is entry.config


def test_each_entry_runs_the_package_its_section_names() -> None:
    for name, entry in REGISTRY.items():
        assert entry.target == f"{config.PACKAGES[name]}:METHOD"
        assert config.PACKAGES[name] == f"packpilot.control.{name}"


def test_the_fused_step_of_every_registered_method_has_a_branch_for_each() -> None:
    """The whole registry under the supervisor, as uav_mission builds it: the generated step
    calls every method's rules, and the after-hook of the two that have one."""
    from packpilot.config import load_config
    from packpilot.sim.loop import build_core
    from packpilot.sim.plant_io import SimulatedPlant

    cfg = load_config(EXAMPLES / "uav_mission.toml")
    core = build_core(cfg, SimulatedPlant(cfg).infos)
    assert core.fusion is not None and core.fusion.supervised
    assert {x.method.name for x in core.compiled} == set(REGISTRY)
    text = source(core.fusion)
    for name in REGISTRY:
        assert f"packpilot.control.{name}.rules import step_packs as step" in text, name
    assert text.count("import close_out_packs as after") == 1
    assert text.count("import note_commands_packs as after") == 1


def test_replay_commands_follow_the_registry() -> None:
    with_replay = [n for n, e in REGISTRY.items() if e.replay is not None]
    assert with_replay == ["protection", "sequencing", "equalization"]
    for name in with_replay:
        replay = REGISTRY[name].replay
        assert replay is not None and callable(replay.function())
    out = CliRunner().invoke(app, ["replay", "--help"]).output
    for name in with_replay:
        assert name in out
    assert "charging" not in out
