"""PX4's uORB messages as its Zenoh bridge carries them (``protocol/px4_msgs.py``), against what
the firmware says on the wire: the type hashes it announces, the byte layout of its samples, its
MAVLink custom modes; and the link's URL. (The firmware itself speaks in tests/test_px4.py.)"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from triswarm.companion.px4_link import parse_url
from triswarm.protocol import px4_msgs as px4

ANNOUNCED = {
    # What px4_sitl_zenoh (PX4 main 02e73e3b6f) publishes under, read off its keys (../shared/px4/README.md
    # gives the first; the others were read from a session of the firmware's).
    "VehicleOdometry": "RIHS01_4295b96ad312084aa35c84bdcec65ba2f57eb4f6a293d57d52d95acbe99ff817",
    "VehicleStatus": "RIHS01_b98c704379561e2bfa2a83902bea00bb14357240659617df3a8be1e209747e97",
    "VehicleLocalPosition": "RIHS01_690ad535169297241c696494adbd98bbdc45566645026fe7963513a29a1bf144",
    "VehicleLandDetected": "RIHS01_ced22fc1699e2a3746a1fa86aa4b5463b42f5b9c97e7913063365a04d8324901",
    "SensorGps": "RIHS01_0b0f92e680bbcad0c9d0e651868c0443b9d38fb8d50c21d4a8a532d3e90cf21a",
    "VehicleCommandAck": "RIHS01_36038d69f9db90980fb8fe154f27f22dffed0c35e530b32413cf0456aa8a29e2",
}


@pytest.mark.parametrize("name", sorted(ANNOUNCED))
def test_the_type_hashes_from_the_fields_are_the_firmwares(name):
    assert px4.type_hash(name) == ANNOUNCED[name]


def test_a_field_changed_changes_the_hash():
    """The hash is of the fields: one renamed is another type (what ``Px4ZenohLink`` refuses)."""
    assert "float32[3] position" in px4.FIELDS["VehicleOdometry"]
    renamed = px4.FIELDS["VehicleOdometry"].replace("float32[3] position;", "float32[3] position_ned;")
    try:
        px4.FIELDS["VehicleOdometry"] = renamed
        px4.type_hash.cache_clear()
        px4._store.cache_clear()
        assert px4.type_hash("VehicleOdometry") != ANNOUNCED["VehicleOdometry"]
    finally:
        px4.FIELDS["VehicleOdometry"] = renamed.replace("position_ned;", "position;")
        px4.type_hash.cache_clear()
        px4._store.cache_clear()
    assert px4.type_hash("VehicleOdometry") == ANNOUNCED["VehicleOdometry"]


def test_vehicle_command_bytes_are_xcdr1_in_the_msg_files_order():
    """Offsets by hand (XCDR1: each value aligned to its size from the start of the body, after the
    4-byte header): timestamp 0, param1-4 8..23, param5-6 (float64) 24, 32, param7 40, command 44,
    target_system 48, target_component 49, source_system 50, source_component (uint16) 52,
    confirmation 54, from_external 55."""
    raw = px4.encode("VehicleCommand", timestamp=7, param1=1.5, param2=6.0, param5=47.5, command=176,
                     target_system=3, target_component=1, source_system=3, source_component=191, from_external=True)
    assert raw[:4] == b"\x00\x01\x00\x00" and len(raw) == 4 + 56
    body = raw[4:]
    assert struct.unpack_from("<Q", body, 0)[0] == 7
    assert struct.unpack_from("<ff", body, 8) == (1.5, 6.0)
    assert struct.unpack_from("<d", body, 24)[0] == 47.5
    assert struct.unpack_from("<I", body, 44)[0] == 176
    assert tuple(body[48:51]) == (3, 1, 3)
    assert struct.unpack_from("<H", body, 52)[0] == 191
    assert body[55] == 1


def test_decode_reads_a_sample_with_the_firmwares_trailing_bytes_and_refuses_garbage():
    raw = px4.encode("VehicleOdometry", timestamp=5, pose_frame=1, position=[1.0, -2.0, -3.0], q=[1, 0, 0, 0])
    padded = raw + bytes(range(28))  # (PX4 sends its buffer whole: the struct's size + 28 bytes)
    m = px4.decode("VehicleOdometry", padded)
    assert m.timestamp == 5 and m.pose_frame == 1
    np.testing.assert_array_equal(m.position, [1.0, -2.0, -3.0])
    for bad in (b"", raw[:10], b"\x00\x00\x00\x00" + raw[4:], raw + bytes(px4.TRAILING_MAX + 1)):
        with pytest.raises(ValueError):
            px4.decode("VehicleOdometry", bad)


def test_custom_modes_are_px4s():
    """PX4's MAVLink custom mode: main mode in bits 16-23, sub mode in 24-31 (OFFBOARD is main mode
    6; AUTO_LAND main 4, sub 6; POSCTL main 3)."""
    assert px4.custom_mode(px4.NAV_STATE_OFFBOARD) == 6 << 16
    assert px4.custom_mode(18) == (4 << 16) | (6 << 24)
    assert px4.mode_name(3 << 16) == "POSCTL"
    assert px4.mode_name(px4.custom_mode(4)) == "AUTO_LOITER"


def test_liveliness_tokens_say_topic_type_and_hash():
    token = ("@ros2_lv/0/2e92d4d37a133a91d5b01e8f43314d7b/0/11/MS/%/%/px4_aabbcc00000000000000000000000000/"
             "%px4_3%fmu%in%actuator_motors/px4_msgs::msg::dds_::ActuatorMotors_/RIHS01_abc/::,7:,:,:,,")
    assert px4.announced(token) == ("/px4_3/fmu/in/actuator_motors", "px4_msgs::msg::dds_::ActuatorMotors_", "RIHS01_abc")
    assert px4.announced("@ros2_lv/0/2e92/0/0/NN/%/%/px4_aabb") is None


def test_key_expressions():
    assert px4.key(0, "px4_2", "in", "actuator_servos") == \
        f"0/px4_2/fmu/in/actuator_servos/px4_msgs::msg::dds_::ActuatorServos_/{px4.type_hash('ActuatorServos')}"
    assert px4.topic_path("", "out", "vehicle_status") == "/fmu/out/vehicle_status"


def test_the_links_url():
    assert parse_url("px4-zenoh://127.0.0.1:7447/px4_1") == ("tcp/127.0.0.1:7447", "px4_1", 0, False)
    assert parse_url("px4-zenoh://10.0.0.2:7448/?domain=3&simulator=1") == ("tcp/10.0.0.2:7448", "", 3, True)
    for bad in ("px4-zenoh://127.0.0.1/px4_1", "px4-zenoh://:7447/x", "px4-zenoh://h:1/x?domain=a",
                "px4-zenoh://h:1/x?simulator=yes", "tcp:127.0.0.1:5760"):
        with pytest.raises(ValueError):
            parse_url(bad)
