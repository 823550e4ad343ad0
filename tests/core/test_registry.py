"""The registry: every method and safety layer registered once, everything else derived."""

from __future__ import annotations

from typer.testing import CliRunner

from packpilot import config
from packpilot.cli import app
from packpilot.control.core_kernel import METHOD_IDS
from packpilot.control.method import Method
from packpilot.control.registry import METHODS, REGISTRY, SAFETY


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


def test_the_fused_step_has_a_branch_for_every_registered_method() -> None:
    assert set(METHOD_IDS) == set(REGISTRY)


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
