"""The companion's flight-controller link on a serial line: its URL forms; a link on a real
pseudo-terminal (frames across reads, both ways, a line that goes away and comes back under the same
name); and two companions flying the paper's plan (in still air) on simulated time over serial lines
bridged, byte for byte, to `triswarm sitl up --lockstep`, with the bytes each line carried per
simulated second held against a 921600-baud line's capacity."""

from __future__ import annotations

import asyncio
import os
import tty
from collections import Counter, defaultdict

import pytest
import tomli_w

from triswarm.companion.config import link_url, parse_link
from triswarm.companion.links import REOPEN_EVERY_S, MavLink
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.scenarios import load_plan
from triswarm.gcs.stack import Stack, stop_in_turn
from triswarm.protocol.mavlink import mavlink, new_codec

from .poll import poll_async
from .serial_bridge import PtyBridge, complete_frames
from .stack_helpers import judge, small_plan, wait_sim

LINE_BYTES_S = 921600 // 10
"""A 921600-baud line, 8N1 (10 bits a byte): bytes per second per direction."""
BUDGET_FRACTION = 0.5
"""docs/companion.md#serial-link-budget: each direction within half the line (PX4's own default
budget for a MAVLink port, MAV_x_RATE 0 = baud/20)."""
FRAME_BYTES = {"ATTITUDE": 40, "LOCAL_POSITION_NED": 40, "SET_ACTUATOR_CONTROL_TARGET": 55}
"""MAVLink 2 frames, unsigned: 10 header + payload (28, 28, 43 bytes; mavlink/c_library_v2's
*_LEN) + 2 CRC, none of these payloads ending in zeros in flight."""


@pytest.mark.parametrize("text", ["/dev/ttyACM0:921600", "/dev/ttyACM0,921600", "serial:///dev/ttyACM0:921600",
                                  " SERIAL:///dev/ttyACM0,921600 "])
def test_serial_url_forms(text):
    assert parse_link(text, "fc") == ("serial", "/dev/ttyACM0", 921600)
    assert link_url(text, "fc") == "/dev/ttyACM0,921600"  # pymavlink's form (its DEVICE:BAUD is a UDP address)


def test_serial_url_without_a_baud_rate_and_a_bad_one():
    assert link_url("/dev/serial/by-id/usb-Holybro_Pixhawk6C-if00", "fc") == "/dev/serial/by-id/usb-Holybro_Pixhawk6C-if00"
    with pytest.raises(ValueError, match="baud rate must be positive"):
        link_url("/dev/ttyACM0:0", "fc")


def _pty(tty_link) -> tuple[int, int]:
    master, slave = os.openpty()
    tty.setraw(slave)
    if tty_link.is_symlink():
        tty_link.unlink()
    tty_link.symlink_to(os.ttyname(slave))
    return master, slave


def test_a_serial_link_on_a_pty_carries_frames_and_outlives_an_unplugged_device(tmp_path):
    """A device name that a udev rule would give (a symlink): frames split across reads are whole; the
    companion's own go out; the device going away is said once, watched no more (no spin), retried
    quietly, and the link works again once a device is back under the name."""
    dev = tmp_path / "ttyFC"
    fc = new_codec(1, 1)
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3, 3)
    tm = mavlink.MAVLink_system_time_message(1_700_000_000_000_000, 1234)

    async def run() -> None:
        master, slave = _pty(dev)
        link = MavLink("fc", link_url(f"{dev}:921600", "fc"), 1, 191)
        events: list[str] = []
        link.on_event = events.append
        got: list = []
        link.open(asyncio.get_running_loop(), lambda lk, msgs, t_rx: got.extend(msgs))
        try:
            one, two = hb.pack(fc), tm.pack(fc)
            os.write(master, one[:7])
            await asyncio.sleep(0.05)
            os.write(master, one[7:] + two)
            assert await poll_async(lambda: len(got) == 2, 2.0), got
            assert [m.get_type() for m in got] == ["HEARTBEAT", "SYSTEM_TIME"] and got[1].time_boot_ms == 1234
            link.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MOT_MAX_RPM", -1))
            out = b""
            for _ in range(100):
                try:
                    out += os.read(master, 1024)
                except BlockingIOError:
                    pass
                if out:
                    break
                await asyncio.sleep(0.01)
            msgs = new_codec(255, 0).parse_buffer(out)
            assert [(m.get_type(), m.get_srcSystem(), m.get_srcComponent(), m.param_id) for m in msgs] == \
                [("PARAM_REQUEST_READ", 1, 191, "MOT_MAX_RPM")]

            os.close(master)  # unplugged: the port reads as ready, with nothing in it
            master = -1
            assert await poll_async(lambda: not link.up, 2.0)
            # its name still there, but dead: tried again, quietly (two tries failed, and said nothing)
            assert await poll_async(lambda: link.counters["reopen_failed"] >= 2, 10 * REOPEN_EVERY_S), link.counters
            assert len(events) == 1 and events[0].startswith(f"fc link {dev},921600 lost (disconnected"), events
            assert link.counters["read_errors"] == 1 and link.counters["lost"] == 1, link.counters
            assert link.counters["reopen_failed"] >= 2, link.counters
            link.send(hb)  # nowhere to go: counted, not raised
            assert link.counters["drop_link_down"] == 1

            os.close(slave)
            master, slave = _pty(dev)  # plugged in again, under the same name
            assert await poll_async(lambda: link.up, 3 * REOPEN_EVERY_S), link.counters
            os.write(master, hb.pack(fc))
            assert await poll_async(lambda: len(got) == 3, 2.0)
            assert len(events) == 2 and "open again" in events[1], events
        finally:
            link.close()
            for fd in (master, slave):
                if fd >= 0:
                    os.close(fd)

    asyncio.run(run())


def test_complete_frames_reads_only_the_header():
    codec = new_codec(1, 1)
    a = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3).pack(codec)
    b = mavlink.MAVLink_system_time_message(1, 2).pack(codec)
    assert complete_frames(a + b) == (len(a) + len(b), 0)
    assert complete_frames(a + b[:-1]) == (len(a), 0)
    assert complete_frames(b"\x00\x01" + a) == (2 + len(a), 2)


# -- two drones over serial lines --------------------------------------------------------------

END_S = 18.0  # plan time: the entry (3 s climb, 12 s blend) and 3 s of the formation itself
WINDOW_S = (4.0, 14.0)  # plan time over which the lines' bytes are counted (in flight)


def _frames(stream: bytes) -> list:
    msgs = new_codec(255, 0).parse_buffer(bytes(stream)) or []
    bad = [m for m in msgs if m.get_type() == "BAD_DATA"]
    assert not bad, bad[:3]
    return msgs


def _stamp_us(m) -> int | None:
    if hasattr(m, "time_boot_ms"):
        return m.time_boot_ms * 1000
    if m.get_type() in ("SET_ACTUATOR_CONTROL_TARGET", "HIGHRES_IMU", "ODOMETRY"):
        return int(m.time_usec)
    return None


def per_second(msgs: list, t0_us: int, t1_us: int) -> tuple[float, Counter, dict]:
    """Bytes per simulated second over [t0, t1) of the flight controller's boot time, from the first
    frame stamped at or after t0 to the first stamped at or after t1 (unstamped frames between
    count); and the samples per second (distinct stamps) and bytes of each message type there. (A
    state the lockstep offers again, after half a second of wall time unanswered on a busy machine,
    is the same sample sent twice: its bytes count, its sample once.)"""
    counts: Counter[str] = Counter()
    stamps: dict[str, set[int]] = defaultdict(set)
    sizes: dict[str, set[int]] = defaultdict(set)
    total = 0
    inside = False
    for m in msgs:
        t = _stamp_us(m)
        if t is not None and t >= t1_us:
            break
        if t is not None and t >= t0_us:
            inside = True
        if inside:
            n = len(m.get_msgbuf())
            total += n
            counts[m.get_type()] += 1
            if t is not None:
                stamps[m.get_type()].add(t)
            sizes[m.get_type()].add(n)
    span_s = (t1_us - t0_us) / 1e6
    samples = {k: (len(stamps[k]) if k in stamps else v) / span_s for k, v in counts.items()}
    return total / span_s, Counter(samples), sizes


@pytest.mark.slow
def test_two_drones_fly_the_paper_plan_over_serial_lines(tmp_path, paper_spec):
    """In still air (the plan's [wind] and the plant's): the companions' controllers take the
    accelerometer, so the line carries everything a companion asks for."""
    spec = small_plan(paper_spec, 2, "pair")
    spec["wind"] = {"speed_m_s": 0.0}
    plan_file = tmp_path / "pair.toml"
    plan_file.write_text(tomli_w.dumps(spec))
    plan = load_plan(str(plan_file))
    assert plan.controller_accelerometer(plan.wind)
    with Stack(plan_file, tmp_path / "run", 2, start_delay_s=4.0, lockstep=True, companions=False,
               sitl_args=["--wind-m-s", "0"]) as stack:
        ends = {v["sysid"]: (v["links"]["companion"]["host"], v["links"]["companion"]["port"])
                for v in stack.manifest["vehicles"]}
        with PtyBridge(ends) as bridge, Recorder(stack.manifest) as rec:
            for i, line in bridge.lines.items():
                stack.fc_links[i] = f"{line.path}:921600"
                stack.start_companion(i)
            wait_sim(rec.now, stack.start_at + END_S, stack)
            stop_in_turn([[p for name, p in stack.procs.items() if name != "sitl"]])  # (before their lines go)
        sitl_stats_path = stack.workdir / "stats" / "sitl.json"
        lines = bridge.lines
    boot_unix_s = stack.manifest["clock"]["boot_unix_s"]
    start = stack.start_at

    # the formation, from the flight controllers' own telemetry (their ground-station links)
    ok, worst = judge(plan, rec, start, 15.0, END_S)
    assert ok, f"worst (position m, attitude rad) per drone over [15, {END_S:g}] s: {worst}"

    t0_us, t1_us = (round((start + w - boot_unix_s) * 1e6) for w in WINDOW_S)
    for i, line in lines.items():
        assert line.counters["skipped"] == 0 and line.counters["overrun_bytes"] == 0, line.counters
        up, down = _frames(line.to_fc), _frames(line.to_companion)
        # set-up over the line: parameters read, rates asked for, the clock
        asked = {(m.get_type(), getattr(m, "param_id", None) or getattr(m, "command", None)) for m in up}
        assert {("PARAM_REQUEST_READ", "MOT_MAX_RPM"), ("PARAM_REQUEST_READ", "SIM_LOCKSTEP"),
                ("COMMAND_LONG", mavlink.MAV_CMD_SET_MESSAGE_INTERVAL)} <= asked, asked
        said = {m.get_type() for m in down}
        assert {"PARAM_VALUE", "COMMAND_ACK", "SYSTEM_TIME", "HEARTBEAT"} <= said, said

        # the budget, per simulated second
        rate_up, n_up, size_up = per_second(up, t0_us, t1_us)
        rate_down, n_down, size_down = per_second(down, t0_us, t1_us)
        print(f"drone {i}: FC->companion {rate_down:.0f} B/s {dict(n_down)} {dict(size_down)}; "
              f"companion->FC {rate_up:.0f} B/s {dict(n_up)} {dict(size_up)}")
        for name in ("ATTITUDE", "LOCAL_POSITION_NED"):
            assert n_down[name] == pytest.approx(200.0, abs=0.2) and size_down[name] == {FRAME_BYTES[name]}, name
        assert n_up["SET_ACTUATOR_CONTROL_TARGET"] == pytest.approx(200.0, abs=0.2)
        assert size_up["SET_ACTUATOR_CONTROL_TARGET"] == {FRAME_BYTES["SET_ACTUATOR_CONTROL_TARGET"]}
        assert n_down["HIGHRES_IMU"] == pytest.approx(200.0, abs=0.2)  # (its accelerometer: the plan in air takes it)
        assert not {"ATTITUDE_QUATERNION", "ODOMETRY"} & set(n_down), n_down  # (turned off: unused)
        assert 200 * (FRAME_BYTES["ATTITUDE"] + FRAME_BYTES["LOCAL_POSITION_NED"]) <= rate_down <= BUDGET_FRACTION * LINE_BYTES_S
        assert 200 * FRAME_BYTES["SET_ACTUATOR_CONTROL_TARGET"] <= rate_up <= BUDGET_FRACTION * LINE_BYTES_S

    # the commands reached the flight controllers, and the companions' links never failed
    import json

    sitl = json.loads(sitl_stats_path.read_text())
    for v in sitl["vehicles"]:
        assert v["counters"].get("actuator_commands", 0) >= 200 * (END_S - 1.0), v["counters"]
    for i in lines:
        s = stack.stats(str(i))
        fc = s["links"]["fc"]
        assert not {"lost", "read_errors", "write_errors", "drop_tx_full", "tx_short"} & set(fc), fc
        assert s["tick_errors"] == 0
