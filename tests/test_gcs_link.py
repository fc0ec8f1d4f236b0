"""The ground station's link to a drone whose flight controller has a link of its own beside its
companion's (PX4, flown by its companion over Zenoh): what is for component 1 goes to the flight
controller's port, the rest to the companion's, and both are heard. Real UDP sockets on loopback
stand for the two ends."""

from __future__ import annotations

import socket

from triswarm.gcs.link import GroundLink, parse_endpoints, write_manifest
from triswarm.protocol.mavlink import COMP_AUTOPILOT, COMP_ONBOARD, mavlink, new_codec

from .poll import poll


class End:
    """One end of the ground station's link (a companion's or a flight controller's port) that
    keeps what it received and answers from (1, compid)."""

    def __init__(self, compid: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.url = f"udpout:127.0.0.1:{self.sock.getsockname()[1]}"
        self.codec = new_codec(1, compid)
        self.parser = new_codec(1, compid)
        self.got: list = []
        self.peer = None

    def read(self) -> None:
        while True:
            try:
                data, self.peer = self.sock.recvfrom(65536)
            except BlockingIOError:
                return
            self.got.extend(self.parser.parse_buffer(data) or [])

    def send(self, msg) -> None:
        self.sock.sendto(msg.pack(self.codec), self.peer)

    def types(self) -> list[str]:
        return [m.get_type() for m in self.got]


def test_commands_for_the_flight_controller_go_to_its_own_link(tmp_path):
    companion, fc = End(COMP_ONBOARD), End(COMP_AUTOPILOT)
    try:
        with GroundLink({1: companion.url}, fc_endpoints={1: fc.url}) as link:
            poll(lambda: companion.read() or fc.read() or ("HEARTBEAT" in companion.types() and "HEARTBEAT" in fc.types()),
                 10.0, "the ground station's heartbeat on both links")
            fc.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_TRICOPTER, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3, 3))
            companion.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                                             mavlink.MAV_AUTOPILOT_INVALID, 0, 2, 4, 3))
            poll(lambda: link.autopilot(1).heartbeat is not None and link.companion(1).heartbeat is not None, 10.0,
                 "both heartbeats heard")
            assert link.autopilot(1).heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
            assert link.companion(1).heartbeat.custom_mode == 2

            link.send(1, mavlink.MAVLink_command_long_message(1, COMP_AUTOPILOT, mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
                                                              0, 1, 0, 0, 0, 0, 0, 0))
            link.send(1, mavlink.MAVLink_command_long_message(1, COMP_ONBOARD, mavlink.MAV_CMD_NAV_LAND,
                                                              0, 0, 0, 0, 0, 0, 0, 0))
            commands = lambda end: [m.command for m in end.got if m.get_type() == "COMMAND_LONG"]  # noqa: E731
            poll(lambda: companion.read() or fc.read() or (commands(companion) and commands(fc)), 10.0, "both commands")
            assert commands(fc) == [mavlink.MAV_CMD_COMPONENT_ARM_DISARM], fc.types()
            assert commands(companion) == [mavlink.MAV_CMD_NAV_LAND], companion.types()

            # the flight controller's answer is heard as its own
            with link.subscribe(1, COMP_AUTOPILOT, "COMMAND_ACK") as acks:
                fc.send(mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_ACCEPTED))
                ack = acks.get(10.0)
            assert ack is not None and ack.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    finally:
        companion.sock.close()
        fc.sock.close()


def test_a_swarm_manifest_names_each_flight_controllers_own_link(tmp_path):
    path = tmp_path / "swarm.json"
    write_manifest(path, "pair", {1: "udpout:127.0.0.1:14601", 2: "udpout:127.0.0.1:14602"}, {2: "udpout:127.0.0.1:18572"})
    assert parse_endpoints(path, None) == ({1: "udpout:127.0.0.1:14601", 2: "udpout:127.0.0.1:14602"},
                                           {2: "udpout:127.0.0.1:18572"})
    write_manifest(path, "pair", {1: "udpout:127.0.0.1:14601"})
    assert parse_endpoints(path, None)[1] == {}
