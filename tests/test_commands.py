"""The core's "off wins" merge of switch opinions (control/commands.py, #26 item 4: a generated
mutant that let a later "on" undo an earlier "off" survived every method's tests)."""

from __future__ import annotations

import itertools

import pytest

from packpilot.contract.arrays import NO_OPINION, cmd_arrays
from packpilot.contract.bms import Commands
from packpilot.contract.charger import ChargerCommand
from packpilot.control.core import put_commands


@pytest.mark.parametrize("path", ["chg_on", "dsg_on"])
@pytest.mark.parametrize("opinions", list(itertools.product([True, False, None], repeat=3)))
def test_off_wins_whatever_the_order_of_the_opinions(
    path: str, opinions: tuple[bool | None, ...]
) -> None:
    """A path is on only when someone asked for on and nobody asked for off, in any order and
    however many times (generated mutants 1192ca841c, b8f94ccb4e: ``old != 0`` -> ``old != 1``)."""
    cmd = cmd_arrays(1, 2, 1)
    for on in opinions:
        pair = (on, True)
        c = Commands(chg_on=pair) if path == "chg_on" else Commands(dsg_on=pair)
        put_commands(cmd, 0, c)
    said = [o for o in opinions if o is not None]
    want = NO_OPINION if not said else int(all(said))
    assert int(getattr(cmd, path)[0, 0]) == want
    assert int(getattr(cmd, path)[0, 1]) == 1  # three "on" in a row stay on


def test_a_balancer_opinion_replaces_the_earlier_one_and_leaves_out_groups_at_zero() -> None:
    """The latest controller's balancer rows win; groups (and batteries) it leaves out read
    0 A, not an earlier controller's current (generated mutant d474d81462: claim fills 1 A)."""
    cmd = cmd_arrays(1, 2, 3)
    put_commands(cmd, 0, Commands(balancer_a=((0.1, 0.2, 0.3), (0.4, 0.5, 0.6))))
    put_commands(cmd, 0, Commands(balancer_a=((0.05,),)))
    assert cmd.balancer_a[0].tolist() == [[0.05, 0.0, 0.0], [0.0, 0.0, 0.0]]
    assert bool(cmd.balancer_set[0])


@pytest.mark.parametrize("opinions", list(itertools.product([True, False], repeat=3)))
def test_the_charger_is_on_only_if_no_controller_said_off(opinions: tuple[bool, ...]) -> None:
    """Charger setpoints merge like the switches: the latest setpoint wins, but one "off" from
    any controller leaves the charger off at 0 V / 0 A whatever comes after it (generated
    mutant 575482da88: the merged "off" re-enabled the charger at 0 V / 0 A)."""
    cmd = cmd_arrays(1, 1, 1)
    for k, on in enumerate(opinions):
        put_commands(cmd, 0, Commands(charger=ChargerCommand(90.0 + k, 5.0 + k, enable=on)))
    assert bool(cmd.charger_set[0])
    got = (float(cmd.charger_v[0]), float(cmd.charger_a[0]), bool(cmd.charger_enable[0]))
    assert got == ((92.0, 7.0, True) if all(opinions) else (0.0, 0.0, False))


def test_a_full_event_buffer_keeps_every_event_it_has_room_for_and_counts_each_one_lost() -> None:
    """The core's event buffer (``commands.emit``): ``capacity`` events are kept in emission
    order, each one beyond is counted once in ``dropped`` and written to the scratch row only
    (generated mutants 32f861ca18, room for one less, and befa36d66e, a loss counted twice,
    survived every test: no test filled the buffer)."""
    from packpilot.contract.arrays import event_buf
    from packpilot.control.commands import emit

    ev = event_buf(4)
    rows = [emit(ev, 0, 1, 10 + i, i, float(i)) for i in range(7)]
    assert rows == [0, 1, 2, 3, 4, 4, 4]  # the last three land in the scratch row
    assert int(ev.n[0]) == 4 and int(ev.dropped[0]) == 3
    assert ev.code[:4].tolist() == [10, 11, 12, 13] and ev.t_s[:4].tolist() == [0, 1, 2, 3]
