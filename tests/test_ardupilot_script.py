"""deploy/ardupilot/triswarm.lua's logic, run in Lua 5.3 (ArduPilot's) with its bindings faked
(tests/lua/ardupilot_fakes.lua records every call): which commands reach the outputs and how, what
is dropped, when the overrides are released, the failsafe and its LAND, and who may win it back.
The firmware test (test_ardupilot.py) runs the same script on ArduPilot itself."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest

from lupa import lua53 as lupa  # (Lua 5.3, as ArduPilot's scripting)

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "deploy" / "ardupilot" / "triswarm.lua"
FAKES = Path(__file__).parent / "lua" / "ardupilot_fakes.lua"
GUIDED, BRAKE, LAND = 4, 17, 9
MSG_ID = 139  # SET_ACTUATOR_CONTROL_TARGET


def frame(controls, time_usec: int, sysid: int = 1, compid: int = 191, target: int = 1, target_comp: int = 1,
          group: int = 0) -> bytes:
    """The raw mavlink_message_t a script receives: header (checksum, magic, len, flags, seq, sysid,
    compid, msgid), then the payload zero-filled to its longest."""
    payload = struct.pack("<q8fBBB", time_usec, *(list(controls) + [0.0] * (8 - len(controls))), group, target, target_comp)
    header = struct.pack("<HBBBBBBB", 0, 0xFD, len(payload), 0, 0, 0, sysid, compid) + MSG_ID.to_bytes(3, "little")
    return header + payload + bytes(280 - len(payload))


class Script:
    """The script loaded on a fake vehicle; ``run(ms)`` advances the clock and runs it once."""

    def __init__(self, **params) -> None:
        self.lua = lupa.LuaRuntime(unpack_returned_tuples=True)
        self.lua.execute(FAKES.read_text())
        self.H = self.lua.globals().H
        self.H.params.MAV_SYSID = 1
        self.H.params.MOT_PWM_MIN = 1000
        self.H.params.MOT_PWM_MAX = 1400
        for name, value in params.items():
            self.H.params[name] = value
        chunk = self.lua.eval("load")(SCRIPT.read_text(), "triswarm.lua")
        self.update, self.period_ms = chunk()

    def run(self, ms: float = 1.0) -> None:
        self.H.t_ms += ms
        self.update, _ = self.update()

    def command(self, controls, age_ms: float = 10.0, **fields) -> None:
        """A command received now, answering telemetry age_ms old."""
        stamp = int((self.H.t_ms - age_ms) * 1000)
        self.H.queue[len(self.H.queue) + 1] = self.lua.table(frame(controls, stamp, **fields), self.H.t_ms)

    def calls(self, name: str) -> list[tuple]:
        out = []
        for k in range(1, len(self.H.calls) + 1):
            call = self.H.calls[k]
            if call[1] == name:
                out.append(tuple(call[j] for j in range(2, len(call) + 1)))
        return out

    def clear(self) -> None:
        self.H.calls = self.lua.table()

    def texts(self) -> list[str]:
        return [self.H.texts[k] for k in range(1, len(self.H.texts) + 1)]

    def named(self, name: str) -> list[float]:
        return [self.H.named[k][2] for k in range(1, len(self.H.named) + 1) if self.H.named[k][1] == name]


@pytest.fixture
def flying():
    """Armed in GUIDED, the script running."""
    s = Script()
    s.H.armed, s.H.mode = True, GUIDED
    s.run()
    return s


CONTROLS = [0.5, 0.25, 1.0, 0.5, -0.5, -1.0]
PWM = {0: 1500, 1: 1250, 2: 2000, 3: 1750, 4: 1250, 5: 1000}
"""CONTROLS as the shipped mapping puts them on outputs 1..6 (channels 0..5)."""


def applied(s: Script) -> dict[int, int]:
    return {chan: pwm for chan, pwm, timeout in s.calls("pwm") if timeout > 0}


def test_a_fresh_command_drives_all_six_outputs_as_the_mapping_says(flying):
    s = flying
    s.clear()
    s.command(CONTROLS)
    s.run()
    assert applied(s) == PWM
    assert {t for _, _, t in s.calls("pwm")} == {200}  # (each override lapses TSW_CMD_TOUT after it is set)
    assert s.calls("aux") == [(159, 2)]  # force flying, while driving
    (p, q, r, thrust), = s.calls("track")  # ArduPilot's targets: its own throttle's share of the thrust
    expected = sum(min(max((pwm - 1000) / 400, 0), 1) ** 2 for pwm in (1500, 1250, 2000)) / 3
    assert thrust == pytest.approx(expected)


@pytest.mark.parametrize("state", ["disarmed", "estop", "safety", "other_mode", "disabled"])
def test_nothing_reaches_an_output_unless_armed_live_in_the_companions_mode_and_enabled(state):
    s = Script(TSW_ENABLE=0) if state == "disabled" else Script()
    s.H.armed, s.H.mode = state != "disarmed", LAND if state == "other_mode" else GUIDED
    s.H.estop, s.H.safety = state == "estop", state == "safety"
    for _ in range(20):
        s.command(CONTROLS)
        s.run(10)
    assert applied(s) == {}
    assert s.calls("set_mode") == []  # (and no failsafe: the commands did not stop)


@pytest.mark.parametrize("fields", [{"sysid": 255}, {"compid": 190}, {"target": 2}, {"target_comp": 5}, {"group": 1}])
def test_a_command_from_anyone_but_the_companion_or_for_another_is_dropped_and_counted(flying, fields):
    s = flying
    s.clear()
    s.command(CONTROLS, **fields)
    s.run()
    assert applied(s) == {}
    s.run(1000)
    assert s.named("TSW_DROP")[-1] == 1


def test_a_command_that_is_not_finite_is_dropped(flying):
    s = flying
    s.clear()
    s.command([math.nan] + CONTROLS[1:])
    s.run()
    assert applied(s) == {}


def test_a_command_answering_old_telemetry_is_not_applied(flying):
    s = flying
    s.clear()
    s.command(CONTROLS, age_ms=250.0)
    s.run()
    assert applied(s) == {}


def test_commands_stopped_the_overrides_go_the_script_brakes_then_lands(flying):
    s = flying
    s.command(CONTROLS)
    s.run()
    s.clear()
    s.run(150)  # still fresh: nothing released
    assert s.calls("set_mode") == [] and [c for c in s.calls("pwm") if c[2] == 0] == []
    s.run(60)  # 210 ms without a command: released at once, and the failsafe
    released = {chan: pwm for chan, pwm, timeout in s.calls("pwm") if timeout == 0}
    assert released == {0: 1000, 1: 1000, 2: 1000, 3: 1500, 4: 1500, 5: 1500}
    assert s.calls("set_mode") == [(BRAKE,)] and s.calls("aux") == [(159, 0)]
    assert s.named("TSW_STATE")[-1] == 2 and any("failsafe" in t for t in s.texts())
    s.clear()
    for _ in range(49):
        s.run(100)
    assert s.calls("set_mode") == []  # TSW_FS_LAND_S (5 s) not yet
    s.run(100)
    assert s.calls("set_mode") == [(LAND,)]


def test_fresh_commands_win_the_failsafe_back_but_never_an_operators_mode(flying):
    s = flying
    s.command(CONTROLS)
    s.run()
    s.run(250)
    assert s.H.mode == BRAKE
    s.clear()
    s.command(CONTROLS)  # the companion is back
    s.run()
    assert s.calls("set_mode") == [(GUIDED,)]
    s.run()
    assert applied(s) == PWM
    # the operator's LAND during a failsafe is the operator's: commands do not undo it
    s.run(250)
    assert s.H.mode == BRAKE
    s.H.mode = LAND
    s.run()
    s.clear()
    s.command(CONTROLS)
    s.run()
    assert s.calls("set_mode") == [] and applied(s) == {}


def test_it_reports_its_rate_the_commands_age_and_its_drops_once_a_second(flying):
    s = flying
    for _ in range(100):
        s.H.t_ms += 10
        s.command(CONTROLS, age_ms=12.0)  # (received now, answering telemetry 12 ms old)
        s.run(0)
    assert s.named("TSW_HZ")[-1] == pytest.approx(100, abs=1)
    assert 12.0 <= s.named("TSW_AGE")[-1] <= 13.0
    assert s.named("TSW_DROP")[-1] == 0 and s.named("TSW_STATE")[-1] == 1
