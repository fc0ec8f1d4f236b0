"""MAVLink 2 signing between the ground station and the companions: the key file, the codec's checks
(on the clock it is given), and against the real stack (sitl up and one companion with --signing-key), what the companion takes
from ground stations with the key, without it, with another key, and from a replay."""

from __future__ import annotations

import json
import secrets
import signal
import socket
import struct
import subprocess
import sys
import time
from collections import Counter

import pytest

from triswarm.companion.state import read_signing_key
from triswarm.gcs import missions
from triswarm.gcs.link import GroundLink
from triswarm.gcs.stack import Stack, free_ports, stop_in_turn
from triswarm.protocol.mavlink import (COMP_AUTOPILOT, COMP_ONBOARD, SIGNATURE_REFUSED, mavlink, new_codec,
                                       setup_signing, signing_key, signing_timestamp)
from triswarm.protocol.plan_transfer import decode_plan, encode_plan

from .stack_helpers import small_plan
from .poll import poll

KEY = bytes(range(1, 33))


# -- the key file ---------------------------------------------------------------------------------

BAD_KEYS = {"short": KEY[:31], "not-hex": b"g" * 64, "zero": bytes(32), "hex-short": b"ab" * 31}


def test_a_key_is_32_bytes_or_64_hex_digits():
    """The parser (pure: the bytes of the file, and the file's name for the message)."""
    assert signing_key(KEY, "raw.key") == KEY
    assert signing_key(KEY.hex().upper().encode() + b"\n", "text.key") == KEY
    assert signing_key(b"  " + KEY.hex().encode() + b"\r\n", "spaced.key") == KEY
    for name, content in BAD_KEYS.items():
        with pytest.raises(ValueError, match=f"^{name}: ") as exc:
            signing_key(content, name)
        assert "\n" not in str(exc.value) and str(exc.value).count(". ") == 0
    with pytest.raises(ValueError, match="not a signing key: expected 32 bytes, or 64 hexadecimal digits "
                                         r"\(the file has 31 bytes\)"):
        signing_key(KEY[:31], "short")
    with pytest.raises(ValueError, match="the all-zero signing key means no signing; make a random one"):
        signing_key(bytes(32), "zero")


def test_key_file_is_32_bytes_or_64_hex_digits(tmp_path):
    """The edges' reading of the file (companion.state.read_signing_key, which the ground station uses too)."""
    raw, text = tmp_path / "raw.key", tmp_path / "text.key"
    raw.write_bytes(KEY)
    text.write_text(KEY.hex().upper() + "\n")
    assert read_signing_key(raw) == KEY and read_signing_key(text) == KEY
    for name, content in BAD_KEYS.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ValueError, match=f"^{path}: "):
            read_signing_key(path)
    with pytest.raises(ValueError, match=f"^{tmp_path / 'missing.key'}: cannot read the signing key "
                                         r"\(No such file or directory\)$"):
        read_signing_key(tmp_path / "missing.key")


@pytest.mark.parametrize("cmd", [
    [sys.executable, "-m", "triswarm.companion.cli", "--id", "1", "--fc", "udpout:127.0.0.1:9", "--gcs", "udpin:127.0.0.1:0"],
    [sys.executable, "-m", "triswarm.gcs.cli", "arm", "--endpoint", "1=udpout:127.0.0.1:9"],
])
def test_a_wrong_key_file_is_one_error(tmp_path, cmd):
    bad = tmp_path / "bad.key"
    bad.write_text("not a key\n")
    r = subprocess.run(cmd + ["--signing-key", str(bad)], capture_output=True, text=True, timeout=60)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "not a signing key" in lines[0], r.stderr


# -- the codec ------------------------------------------------------------------------------------

def parsed(codec, frame: bytes) -> str:
    (msg,) = codec.parse_buffer(frame)
    assert msg.get_type() != "BAD_DATA" or msg.reason == SIGNATURE_REFUSED
    return msg.get_type()


def test_signed_frames_pass_once_and_only_with_the_key():
    receiver, refused = new_codec(1, COMP_ONBOARD), Counter()
    setup_signing(receiver, KEY, 1, lambda msg_id: msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT, refused, clock=time.time)
    signer, other, plain = new_codec(255, 190), new_codec(255, 190), new_codec(255, 190)
    setup_signing(signer, KEY, 3, clock=time.time)
    setup_signing(other, bytes(reversed(KEY)), 3, clock=time.time)
    command = mavlink.MAVLink_command_long_message(1, COMP_ONBOARD, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0)
    heartbeat = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)

    frame = command.pack(signer)
    assert parsed(receiver, frame) == "COMMAND_LONG"
    assert parsed(receiver, frame) == "BAD_DATA"  # the same frame again
    assert parsed(receiver, command.pack(plain)) == "BAD_DATA"
    assert parsed(receiver, heartbeat.pack(plain)) == "HEARTBEAT"  # allowed unsigned
    assert parsed(receiver, heartbeat.pack(other)) == "BAD_DATA"  # a wrong signature never passes
    # a forged frame from far in the future does not shut the real sender out (pymavlink's own
    # check would keep its timestamp as the stream's last)
    forged = bytearray(command.pack(signer))
    forged[-12:-6] = (2**48 - 1).to_bytes(6, "little")
    assert parsed(receiver, bytes(forged)) == "BAD_DATA"
    assert parsed(receiver, command.pack(signer)) == "COMMAND_LONG"
    assert refused == {"refused_replay": 1, "refused_unsigned": 1, "refused_bad_signature": 2}


def test_signing_streams_survive_a_round_trip_and_garbage_is_skipped(tmp_path):
    from triswarm.companion.state import StateStore

    sender, receiver = new_codec(254, 190), new_codec(1, COMP_ONBOARD)
    setup_signing(sender, KEY, 7, clock=time.time)
    setup_signing(receiver, KEY, 1, clock=time.time)
    frame = mavlink.MAVLink_command_long_message(1, COMP_ONBOARD, mavlink.MAV_CMD_USER_1, 0,
                                                 0, 0, 0, 0, 0, 0, 0).pack(sender)
    assert parsed(receiver, frame) == "COMMAND_LONG"
    store = StateStore(tmp_path)
    store.save_signing_streams(receiver.signing.streams())

    forgetful = new_codec(1, COMP_ONBOARD)  # restarted without the streams: the stream looks new,
    setup_signing(forgetful, KEY, 1, clock=time.time)  # and a new stream may be up to a minute old
    assert parsed(forgetful, frame) == "COMMAND_LONG"
    restarted = new_codec(1, COMP_ONBOARD)
    setup_signing(restarted, KEY, 1, clock=time.time)
    saved = store.load_signing_streams()
    assert list(saved) == ["7,254,190"]
    garbage = {"7,254": 1, "7,254,999": 1, "a,b,c": 1, "1,2,3": "late", "4,5,6": -1, "8,9,10": 2**48}
    assert restarted.signing.restore({**saved, **garbage}) == 1
    assert parsed(restarted, frame) == "BAD_DATA"  # a replay, after the "restart" too
    assert parsed(restarted, mavlink.MAVLink_command_long_message(1, COMP_ONBOARD, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0,
                                                                  0, 0, 0, 0).pack(sender)) == "COMMAND_LONG"

    store.signing_path.write_text("[1, 2")
    assert store.load_signing_streams() == {} and "unusable signing streams" in store.problem


def test_timestamps_follow_the_clock_given_and_never_fall_behind_it():
    """The signing state reads no clock of its own: the caller's (here a fake one) sets the floor
    of its timestamps, and a new stream more than a minute behind it is refused as a replay."""
    now = [1.7e9]
    sender, receiver, refused = new_codec(254, 190), new_codec(1, COMP_ONBOARD), Counter()
    setup_signing(sender, KEY, 7, clock=lambda: now[0])
    setup_signing(receiver, KEY, 1, counters=refused, clock=lambda: now[0] + 55.0)

    def stamp(frame: bytes) -> int:
        low, high = struct.unpack_from("<IH", frame, len(frame) - 12)
        return low | high << 32

    def command() -> bytes:
        return mavlink.MAVLink_command_long_message(1, COMP_ONBOARD, mavlink.MAV_CMD_USER_1, 0,
                                                    0, 0, 0, 0, 0, 0, 0).pack(sender)

    first = command()
    assert stamp(first) == signing_timestamp(now[0])
    assert stamp(command()) == signing_timestamp(now[0]) + 1  # (one more per frame, as pymavlink does)
    now[0] += 10.0
    assert stamp(command()) == signing_timestamp(now[0])  # a quiet link's stamps catch up with the clock
    assert parsed(receiver, first) == "BAD_DATA" and refused == {"refused_replay": 1}  # 65 s behind: too old
    assert parsed(receiver, command()) == "COMMAND_LONG"  # 55 s behind: a new stream may be a minute old
    with pytest.raises(TypeError, match="clock"):
        setup_signing(new_codec(1, COMP_ONBOARD), KEY, 1)  # no default clock


# -- the stack ------------------------------------------------------------------------------------

def heard_companion(link: GroundLink) -> None:
    poll(lambda: link.companion(1).heartbeat is not None, 60, "the companion's heartbeat")  # (its start)


@pytest.mark.slow
def test_the_companion_takes_only_signed_frames_from_the_ground(tmp_path, paper_spec):
    keyfile = tmp_path / "swarm.key"
    keyfile.write_text(KEY.hex() + "\n")
    items = encode_plan(small_plan(paper_spec, 1, "solo"))
    with Stack(None, tmp_path / "stack", 1, companion_args={1: ["--signing-key", str(keyfile)]}, lockstep=True) as stack:
        endpoints = stack.endpoints()

        # without the key: heard (heartbeats pass unsigned), but no plan, command or arm gets through
        with GroundLink(endpoints) as link:
            heard_companion(link)
            out = missions.upload(link, 1, items, timeout_s=0.3, retries=2)
            assert not out.ok and out.code is None, out
            pid = decode_plan(items)[1]
            result, _ = link.command(1, COMP_ONBOARD, mavlink.MAV_CMD_TRISWARM_PLAN_START, [pid >> 16, pid & 0xFFFF],
                                     use_int=True, x=int(time.time() + 30), timeout_s=0.3, retries=1)
            assert result is None
            result, _ = link.command(1, COMP_AUTOPILOT, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [1.0], timeout_s=0.3, retries=1)
            assert result is None
            poll(lambda: any("refused frames from the ground station" in text and "unsigned" in text
                                 for _, _, text in link.companion(1).texts), 3, "the companion's report")

        # another key: each side refuses the other's frames
        with GroundLink(endpoints, signing_key=secrets.token_bytes(32)) as link:
            poll(lambda: link.counters["refused_bad_signature"] > 0 and link.autopilot(1).heartbeat is not None, 5,
                     "the companion's frames refused, the flight controller's (not signed) taken")
            assert link.companion(1).heartbeat is None
            out = missions.upload(link, 1, items, timeout_s=0.3, retries=1)
            assert not out.ok and out.code is None, out

        # the key: the plan goes up and comes back
        with GroundLink(endpoints, signing_key=KEY) as link:
            heard_companion(link)
            out = missions.upload(link, 1, items)
            assert out.ok, out
            assert decode_plan(missions.download(link, 1)) == decode_plan(items)
            assert not any(k.startswith("refused_") for k in link.counters)

        # a signed command to the flight controller, through the companion, twice: it gets there once
        codec = new_codec(254, 190)
        setup_signing(codec, KEY, 7, clock=time.time)
        frame = mavlink.MAVLink_command_long_message(1, COMP_AUTOPILOT, mavlink.MAV_CMD_USER_1, 0,
                                                     0, 0, 0, 0, 0, 0, 0).pack(codec)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.connect(("127.0.0.1", stack.gcs_ports[0]))
            sock.settimeout(0.1)
            acks = []
            reader = new_codec(254, 190)
            for _ in range(2):
                sock.send(frame)
                deadline = time.monotonic() + 1.5
                while time.monotonic() < deadline:
                    try:
                        data = sock.recv(65536)
                    except socket.timeout:
                        continue
                    acks += [m for m in reader.parse_buffer(data) or []
                             if m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_USER_1]
            assert [m.result for m in acks] == [mavlink.MAV_RESULT_UNSUPPORTED]

    gcs = stack.stats("1")["links"]["gcs"]
    assert gcs["refused_unsigned"] >= 5 and gcs["refused_bad_signature"] >= 1 and gcs["refused_replay"] == 1, gcs
    fc = stack.stats("sitl")["vehicles"][0]
    assert fc["counters"].get("commands_unsupported") == 1 and not fc["armed"], fc


# -- a restart ------------------------------------------------------------------------------------

class SignedStation:
    """A ground station on a raw UDP socket (system 254, component 190), signing as link 7."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", port))
        self.sock.settimeout(0.05)
        self.codec, self.reader = new_codec(254, 190), new_codec(254, 190)
        setup_signing(self.codec, KEY, 7, clock=time.time)

    def command(self) -> bytes:
        """A new signed COMMAND_LONG for the companion (it answers UNSUPPORTED)."""
        return mavlink.MAVLink_command_long_message(1, COMP_ONBOARD, mavlink.MAV_CMD_USER_1, 0,
                                                    0, 0, 0, 0, 0, 0, 0).pack(self.codec)

    def answered(self, frame: bytes, wait_s: float) -> bool:
        """Send the frame; whether a COMMAND_ACK for it comes back within wait_s."""
        self.sock.send(frame)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            try:
                data = self.sock.recv(65536)
            except (socket.timeout, ConnectionRefusedError):
                continue
            if any(m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_USER_1
                   for m in self.reader.parse_buffer(data) or []):
                return True
        return False

    def close(self) -> None:
        self.sock.close()


def test_a_frame_captured_before_a_restart_is_still_a_replay_after_it(tmp_path):
    """With a state folder, the companion keeps the signing streams (once a second) and a frame it
    took before a crash (SIGKILL) is refused after the restart. (Without them the restarted
    companion would take it: a new stream may be up to a minute old, as the specification allows;
    see the test above.)"""
    keyfile = tmp_path / "swarm.key"
    keyfile.write_text(KEY.hex() + "\n")
    port, fc_port = free_ports(2)
    cmd = [sys.executable, "-m", "triswarm.companion.cli", "--id", "1", "--fc", f"udpout:127.0.0.1:{fc_port}",
           "--gcs", f"udpin:127.0.0.1:{port}", "--signing-key", str(keyfile), "--stats", str(tmp_path / "stats.json"),
           "--state-dir", str(tmp_path / "state")]
    log = (tmp_path / "companion.log").open("w")
    station = SignedStation(port)
    procs: list[subprocess.Popen] = []
    try:
        procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT))
        for _ in range(60):  # until it is up (at most 30 s)
            captured = station.command()
            if station.answered(captured, 0.5):
                break
        else:
            pytest.fail("the companion never answered")
        saved = tmp_path / "state" / "signing.json"
        # (saved once a second; 30 s for a process starved by a busy machine)
        poll(lambda: saved.exists() and "7,254,190" in json.loads(saved.read_text()), 30.0, "the streams saved")
        procs[0].kill()
        procs[0].wait(timeout=10)

        procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT))
        unsigned_heartbeat = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                               0, 0, 0, 3).pack(new_codec(254, 190))
        reader = new_codec(254, 190)

        def companion_heard() -> bool:
            station.sock.send(unsigned_heartbeat)  # (taken unsigned: the companion answers)
            try:
                return any(m.get_type() == "HEARTBEAT" for m in reader.parse_buffer(station.sock.recv(65536)) or [])
            except (socket.timeout, ConnectionRefusedError):
                return False

        poll(companion_heard, 30.0, "the restarted companion")
        assert not station.answered(captured, 1.0)  # the replay
        assert station.answered(station.command(), 2.0)  # the station's next frame
        stop_in_turn([procs[1:]], sig=signal.SIGTERM)
    finally:
        stop_in_turn([procs], sig=signal.SIGKILL)
        station.close()
        log.close()
    gcs = json.loads((tmp_path / "stats.json").read_text())["links"]["gcs"]
    assert gcs.get("refused_replay", 0) == 1, gcs
