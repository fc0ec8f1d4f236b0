"""The whole stack with a bad network between the companions: inside a network namespace this test
creates, all Zenoh traffic between the companions goes through a relay that delivers it 20 ms late
(UDP and TCP), and iptables drops 20 % of the Zenoh data plane at random (UDP, where the estimates
ride). Every drone must stay within 0.5 m of its place in the formation, judged from the flight
controllers' telemetry.

TCP (declarations, liveliness, status) is delayed but not dropped here: at 20 % segment loss TCP's
retransmission back-off outlasts Zenoh's 1 s lease now and then, a session closes and reconnects, and
the agents that lose their path to the leader hold for a moment. That case is not handled yet (see
docs/companion.md, "Absent neighbours, hold, rejoin")."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from .lossy_flight import N, RELAY_BASE, ZENOH_BASE
from .netem import NetNamespace

pytestmark = pytest.mark.slow
DROP = 0.2
DELAY_MS = 20.0


def test_drop_20_percent_and_delay_20_ms(tmp_path):
    problem = NetNamespace.problem()
    if problem:
        pytest.fail(f"cannot impair the network here: {problem} (make test installs iptables when run as root)")
    zenoh_ports = f"{ZENOH_BASE + 1}:{ZENOH_BASE + N}"
    relay_ports = f"{RELAY_BASE + 1}:{RELAY_BASE + N}"
    out = tmp_path / "result.json"
    with NetNamespace(f"triswarm-test-{os.getpid()}") as ns:
        # Every relayed datagram leaves the relay exactly once: towards an agent's port (forward) or
        # from a relay port (back). Count them, then drop a random 20 % of each.
        for match in (["--dports", zenoh_ports], ["--sports", relay_ports]):
            rule = ["OUTPUT", "-p", "udp", "-m", "multiport", *match]
            ns.iptables("-A", *rule)
            ns.iptables("-A", *rule, "-m", "statistic", "--mode", "random", "--probability", str(DROP), "-j", "DROP")
        run = subprocess.run(ns.exec_prefix() + [sys.executable, str(Path(__file__).with_name("lossy_flight.py")),
                                                 str(out), str(tmp_path / "run"), "--delay-ms", str(DELAY_MS)],
                             capture_output=True, text=True, timeout=240)
        counts = ns.rule_packets("OUTPUT")
    assert run.returncode == 0, run.stderr[-4000:]
    result = json.loads(out.read_text())
    print(json.dumps({"iptables_packets": counts, "relay": result["relay"], "worst": result["worst"],
                      "neighbour_age_p50_ms": {i: c["loop"]["neighbour_age_p50_ms"] for i, c in result["companions"].items()}}))

    # the impairment happened: about 20 % of the relayed datagrams dropped, both ways ...
    assert len(counts) == 4, counts
    for sent, dropped in zip(counts[0::2], counts[1::2]):
        assert sent > 20_000 and dropped / sent == pytest.approx(DROP, abs=0.02), counts
    # ... and the estimates the companions used came through the relay (20 ms late at least)
    for i, s in result["companions"].items():
        assert s["loop"]["neighbour_age_p50_ms"] > DELAY_MS, (i, s["loop"])
        assert s["tick_errors"] == 0
    assert result["relay"]["udp_forward"] > 20_000 and result["relay"]["tcp_forward"] > 100, result["relay"]
    assert all(result["alive"].values()), result["alive"]

    # and the formation held
    assert result["ok"], f"worst (position m, attitude rad) per drone over [25, 50] s: {result['worst']}"
