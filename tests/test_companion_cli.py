"""`triswarm-companion` refuses to start as asked in one sentence with exit status 2 (a link it cannot
open, a port taken, a Zenoh endpoint it cannot listen on), and never calls a bug a user error."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from .conftest import PAPER_PLAN_FILE
from .poll import poll

COMPANION = [sys.executable, "-m", "triswarm.companion.cli", "--id", "1"]


def one_error(args: list[str]) -> str:
    r = subprocess.run(COMPANION + args, capture_output=True, text=True, timeout=120)
    lines = [line for line in r.stderr.splitlines() if line.strip() and "triswarm-companion: error:" in line]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


def test_a_link_url_it_cannot_open():
    line = one_error(["--fc", "udpin:999.1.1.1:5", "--gcs", "udpin:127.0.0.1:0"])
    assert "cannot open MAVLink link fc at udpin:999.1.1.1:5" in line, line


def test_a_ground_station_port_that_is_taken():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        line = one_error(["--fc", "udpout:127.0.0.1:9", "--gcs", f"udpin:127.0.0.1:{port}"])
    assert f"cannot open MAVLink link gcs at udpin:127.0.0.1:{port}" in line, line


def test_a_zenoh_endpoint_that_is_taken():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = one_error(["--fc", "udpout:127.0.0.1:9", "--gcs", "udpin:127.0.0.1:0", str(PAPER_PLAN_FILE),
                          "--zenoh-listen", f"tcp/127.0.0.1:{port}"])
    assert "cannot open the Zenoh session" in line and str(port) in line, line


@pytest.mark.parametrize("plan_text, message", [("drones = 0\n", "drones"), ("[formation\n", "")])
def test_a_bad_plan_file(tmp_path, plan_text, message):
    plan = tmp_path / "bad.toml"
    plan.write_text(plan_text)
    line = one_error(["--fc", "udpout:127.0.0.1:9", "--gcs", "udpin:127.0.0.1:0", str(plan)])
    assert str(plan) in line and message in line, line


def test_the_old_plan_option_still_works_for_one_release_and_says_so(tmp_path):
    plan = tmp_path / "bad.toml"
    plan.write_text("drones = 0\n")
    r = subprocess.run(COMPANION + ["--fc", "udpout:127.0.0.1:9", "--gcs", "udpin:127.0.0.1:0", "--plan", str(plan)],
                       capture_output=True, text=True, timeout=120)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith("triswarm-companion: warning: --plan FILE is deprecated"), lines
    assert lines[-1].startswith("triswarm-companion: error: ") and str(plan) in lines[-1], lines


def test_a_bad_option_is_one_sentence(tmp_path):
    assert "--rate-hz must be between 1 and 2000" in one_error(["--fc", "udpout:127.0.0.1:9", "--gcs",
                                                                "udpin:127.0.0.1:0", "--rate-hz", "0"])
    assert "--fc 'udpout:nowhere': expected udpout:HOST:PORT" in one_error(["--fc", "udpout:nowhere", "--gcs",
                                                                           "udpin:127.0.0.1:0"])


@pytest.mark.parametrize("option,value,sentence", [
    ("--fc-profile", "betaflight", "--fc-profile must be one of auto, triswarm, ardupilot, px4, got 'betaflight'"),
    ("--home", "53.4,-2.2", "--home must be LAT,LON,ALT_M (three numbers), got '53.4,-2.2'"),
    ("--home", "95,0,0", "--home 95,0,0: home latitude must be"),
])
def test_the_flight_controllers_kind_and_the_swarms_home_are_checked(option, value, sentence):
    assert sentence in one_error(["--fc", "udpout:127.0.0.1:9", "--gcs", "udpin:127.0.0.1:0", option, value])


def test_every_option_is_one_description_the_command_line_the_file_and_the_agents_options_share(tmp_path):
    """The command line, the configuration file and CompanionOptions are made from OPTIONS: each
    option's flag is in --help, its key is taken by the file, its field is the agent's."""
    import dataclasses

    from triswarm.companion.config import load_config
    from triswarm.companion.options import OPTIONS, CompanionOptions

    help_text = subprocess.run(COMPANION[:3] + ["--help"], capture_output=True, text=True, timeout=120).stdout
    assert [f.name for f in dataclasses.fields(CompanionOptions)] == [o.name for o in OPTIONS]
    for o in OPTIONS:
        assert (o.metavar if o.name == "plan" else o.flag) in help_text, o.flag  # (the plan: the positional PLAN)
    conf = tmp_path / "drone.toml"
    conf.write_text('fc_profile = "ardupilot"\nhome = "53.4668,-2.2339,60"\n[zenoh]\nbase_port = 20000\n')
    assert load_config(conf) == {"fc_profile": "ardupilot", "home": "53.4668,-2.2339,60", "zenoh_base_port": 20000}


def test_a_bug_is_not_called_a_user_error(monkeypatch):
    """A ValueError from inside (not from reading what the operator wrote) ends as itself, not in exit status 2."""
    from typer.testing import CliRunner

    from triswarm.companion import cli, config

    def broken(*args, **kwargs):
        raise ValueError("a bug inside")

    monkeypatch.setattr(config, "resolve_options", broken)
    r = CliRunner().invoke(cli.app, ["--id", "1", "--fc", "udpout:127.0.0.1:9", "--gcs", "udpin:127.0.0.1:0"])
    assert r.exit_code != 2 and isinstance(r.exception, ValueError) and "a bug inside" in str(r.exception)


def test_a_silent_flight_controller_is_said_within_seconds(tmp_path):
    """Against a flight-controller URL where nothing answers (a socket of the test's that only
    listens), the companion says in one line what it waits for, and where, every few seconds, and
    keeps asking (its heartbeats reach the socket). Bounded: at most 60 s of wall time for the first
    line, which comes after 5 s on any machine."""
    import threading
    import time

    from triswarm.gcs.stack import free_ports

    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))
    silent.settimeout(0.5)
    port = silent.getsockname()[1]
    zenoh = free_ports(1)[0]
    proc = subprocess.Popen(COMPANION + ["--fc", f"udpout:127.0.0.1:{port}", "--gcs", "udpin:127.0.0.1:0",
                                         "--zenoh-listen", f"tcp/127.0.0.1:{zenoh}", "--state-dir", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and not any("waiting" in line for line in lines) and proc.poll() is None:
            time.sleep(0.2)
        heard = []  # (it keeps asking: three datagrams, however slowly they come)

        def listen() -> None:
            try:
                heard.append(silent.recv(4096))
            except TimeoutError:
                pass

        poll(lambda: len(heard) >= 3, 30.0, every_s=0.0, step=listen)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        silent.close()
        reader.join(timeout=5)
        proc.stdout.close()
    said = [line for line in lines if "waiting" in line]
    assert said, "".join(lines[-30:])
    assert f"for a HEARTBEAT from the flight controller (system 1) on udpout:127.0.0.1:{port}" in said[0], said[0]
    assert len(heard) >= 3  # (it kept asking)
