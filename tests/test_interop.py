"""Third-party MAVLink clients against the SITL, through the manifest: the `mavsdk` package
(Telemetry, Action, Param plugins) and MAVProxy run non-interactively. On the wall clock, as these
clients expect a flight controller to be (make test runs them alone, after the others)."""

from __future__ import annotations

import asyncio
import contextlib
import time

import pytest
from pymavlink import mavutil

from triswarm.protocol.frames import LocalProjection

from .mavproxy_run import mavproxy_until_saved
from .poll import poll
from .sitl_helpers import command, connect, read_param, sitl_process

M = mavutil.mavlink
pytestmark = pytest.mark.realtime


async def _wait_for_autopilot(mavsdk, sysid: int, timeout: float):
    async def wait():
        async with contextlib.aclosing(mavsdk.on_new_system()) as events:
            while True:
                for system in await mavsdk.get_systems():
                    if (await system.get_system_id() == sysid and await system.is_connected()
                            and await system.has_autopilot()):
                        return system
                await events.__anext__()
    return await asyncio.wait_for(wait(), timeout)


async def _first(agen, pred, timeout: float = 5.0):
    async def get():
        async with contextlib.aclosing(agen) as gen:
            async for item in gen:
                if pred(item):
                    return item
    return await asyncio.wait_for(get(), timeout)


async def _until(getter, pred, timeout: float = 3.0):
    deadline = time.monotonic() + timeout
    while True:
        value = await getter()
        if pred(value):
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"last value {value!r}")
        await asyncio.sleep(0.05)


async def _check_vehicle(vehicle: dict, home: LocalProjection, expect_alt_m: float, expect_armed: bool) -> dict:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.param import ParamAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as mavsdk:
        await mavsdk.add_any_connection(vehicle["links"]["gcs"]["mavsdk"])
        system = await _wait_for_autopilot(mavsdk, vehicle["sysid"], 15.0)
        telemetry, action, param = TelemetryAsync(system), ActionAsync(system), ParamAsync(system)
        pos = await _first(telemetry.subscribe_position(), lambda p: p.latitude_deg == p.latitude_deg)
        att = await _first(telemetry.subscribe_attitude_euler(), lambda e: e.roll_deg == e.roll_deg)
        out = {"lat": pos.latitude_deg, "lon": pos.longitude_deg, "rel_alt": pos.relative_altitude_m,
               "abs_alt": pos.absolute_altitude_m, "roll": att.roll_deg, "pitch": att.pitch_deg,
               "armed": await _until(telemetry.armed, lambda a: a is expect_armed)}
        north, east, _ = vehicle["start_ned_m"]
        lat, lon = home.to_geodetic(north, east)
        assert out["lat"] == pytest.approx(lat, abs=2e-7) and out["lon"] == pytest.approx(lon, abs=2e-7)
        assert out["rel_alt"] == pytest.approx(expect_alt_m, abs=0.05)
        assert out["abs_alt"] == pytest.approx(home.alt_m + expect_alt_m, abs=0.05)
        assert abs(out["roll"]) < 1.0 and abs(out["pitch"]) < 1.0
        if not expect_armed:  # Action: arm and disarm a vehicle on the ground
            await action.arm()
            await _until(telemetry.armed, lambda a: a is True)
            await action.disarm()
            await _until(telemetry.armed, lambda a: a is False)
        # Param: read and set
        assert await param.get_param_float("MASS_KG") == pytest.approx(0.5)
        await param.set_param_float("NOISE_POS_M", 0.01 * vehicle["sysid"])
        out["noise"] = await param.get_param_float("NOISE_POS_M")
    return out


def test_mavsdk_sees_every_vehicle_in_the_manifest(tmp_path):
    with sitl_process(tmp_path, 3) as (manifest, _):
        home = LocalProjection(manifest["home"]["lat_deg"], manifest["home"]["lon_deg"], manifest["home"]["alt_m"])
        # vehicle 2 flies: armed, taken off to 2.5 m by its own controller
        pilot = connect(manifest["vehicles"][1]["links"]["companion"]["pymavlink"])
        assert command(pilot, 2, M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_ACCEPTED
        assert command(pilot, 2, M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, float("nan"), 0, 0, home.alt_m + 2.5).result == M.MAV_RESULT_ACCEPTED
        # until it hovers there, as its ground-station link reports (what mavsdk reads below)
        gcs = connect(manifest["vehicles"][1]["links"]["gcs"]["pymavlink"])
        last = []

        def read_position() -> None:
            m = gcs.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=0.2)
            if m is not None:
                last[:] = [m]

        poll(lambda: last and abs(last[0].relative_alt / 1000 - 2.5) < 0.02 and abs(last[0].vz) <= 2, 30.0,
             "vehicle 2 hovering at 2.5 m", every_s=0.0, step=read_position)

        async def all_vehicles():
            return await asyncio.gather(*(
                _check_vehicle(v, home, 2.5 if v["sysid"] == 2 else 0.0, v["sysid"] == 2) for v in manifest["vehicles"]))

        results = asyncio.run(all_vehicles())
        for v, r in zip(manifest["vehicles"], results):
            assert r["noise"] == pytest.approx(0.01 * v["sysid"])
            # the set went to that vehicle only, as pymavlink sees it
            conn = connect(v["links"]["companion"]["pymavlink"])
            assert read_param(conn, v["sysid"], "NOISE_POS_M") == pytest.approx(0.01 * v["sysid"])


def test_mavproxy_fetches_the_parameter_list(tmp_path):
    with sitl_process(tmp_path, 1) as (manifest, _):
        # MAVProxy fetches the parameters on its own, and saves them once it has them all
        master = f"--master={manifest['vehicles'][0]['links']['gcs']['pymavlink']}"
        saved_count, saved = mavproxy_until_saved([master], "param fetch", tmp_path)
        params = dict(line.split() for line in saved.read_text().splitlines() if line.strip())
        conn = connect(manifest["vehicles"][0]["links"]["companion"]["pymavlink"])
        conn.mav.param_request_read_send(1, 1, b"", 0)
        count = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=3).param_count
        assert len(params) == saved_count == count
        # MAVProxy saves six decimals
        assert float(params["MASS_KG"]) == pytest.approx(0.5) and float(params["MOT_MAX_RPM"]) == pytest.approx(12000)
        assert float(params["SERVO_DELAY_S"]) == pytest.approx(0.01) and float(params["KF"]) == pytest.approx(2e-5, abs=1e-6)
