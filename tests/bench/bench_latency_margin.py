"""How much real-time slack the formation has: the paper's plan flown in-process, every command
reaching the plant ``L`` ms after the telemetry it answers (beyond the servos' own 10 ms, which the
controller compensates), and every neighbour estimate ``D`` ms old with a share ``p`` of them lost
(the receiver keeps the last one it got). Prints the worst position and attitude errors over
[20, 40] s of plan time ("diverged" if the plant left the sky first; kilometres: diverging).

    python tests/bench/bench_latency_margin.py --rate-hz 100 --latency-ms 0,10,15,20 --age-ms 30 --loss 0.2

Measured on the development machine (worst over [20, 40] s; 100 Hz, estimates 30 ms old, 20 % lost):
latency 0 ms: 1e-4 m; 5 ms: 0.008 m; 10 ms: 0.015 m; 15 ms: 0.023 m, 0.010 rad; 20 ms: 4800 m, the
formation lost (200 Hz: 15 ms 0.023 m; 18 ms lost). Estimates 0 or 30 ms old, none or 20 % lost: the
same within 0.1 mm. So a real-time run fails when its loop answers 15-20 ms late, which a loaded
machine does (tests/test_stack_lossy.py), whatever the network.

With ``--compensated-ms C`` the controllers compensate C ms ([controller] latency_s; ``same``: each
latency). Measured (100 Hz): a latency compensated flies as none, 7.2e-5 m at 0, 10, 20 and 30 ms;
10 ms off either way 0.013 m; 20 ms too much (0 ms late, 20 compensated) 1.9 m, and 30 ms late with
10 compensated 0.027 m, 0.24 rad.
"""

from __future__ import annotations

import argparse

import numpy as np
import scipy.sparse

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import metrics
from triswarm.protocol.agent import protocol_input, reference_at
from triswarm.protocol.controller import FormationController
from triswarm.protocol.plan import plan_from_dict
from triswarm.sitl.physics import Plant
from triswarm.sitl.simulation import default_start_positions

PHYSICS_HZ = 1000


def fly(rate_hz: float, latency_ms: int, age_ms: float, loss: float, until_s: float = 40.0, judged_from_s: float = 20.0,
        seed: int = 1, adaptation_rate_1_s: float | None = None,
        compensated_ms: float = 0.0) -> tuple[float, float] | None:
    """Worst (position m, attitude rad) over [judged_from_s, until_s], None if it diverged."""
    spec = dict(load_plan("paper-hexagon").spec)
    spec["controller"] = dict(spec["controller"], rate_hz=rate_hz)
    plan = plan_from_dict(spec)
    design, n = plan.design, plan.n_agents
    dt, sub = 1.0 / rate_hz, int(round(PHYSICS_HZ / rate_hz))
    start = default_start_positions(n, 0)
    plant = Plant(plan.airframe, n, dt_s=1.0 / PHYSICS_HZ)
    rate = plan.controller.thrust_adaptation_rate_1_s if adaptation_rate_1_s is None else adaptation_rate_1_s
    ctrl = FormationController(design, n, rate_hz, thrust_adaptation_rate_1_s=rate, latency_s=compensated_ms / 1000.0)
    plant.reset(start)
    ctrl.reset(plant.observe().paper_state())
    plant.reset(start, servo_rad=ctrl.initial_actuation.alpha_rad)
    offsets = plan.entry_formation(start, 0.0)
    adjacency = {t.name: scipy.sparse.csr_matrix(t.adjacency) for t in plan.schedule.topologies}
    rng = np.random.default_rng(seed)
    age = int(round(age_ms / 1000.0 / dt))
    history, heard, pending = [], None, []  # estimates by tick; what the receivers hold; (due ms, command)
    t_log, pos_log, eta_log = [], [], []
    for k in range(int(round(until_s * rate_hz)) + 1):
        t = k * dt
        obs = plant.observe()
        if not np.all(np.isfinite(plant.state)) or np.abs(obs.position_m).max() > 1e4:
            return None
        t_log.append(t)
        pos_log.append(obs.position_m.copy())
        eta_log.append(obs.euler_rad.copy())
        xhat = ctrl.observe(np.concatenate([obs.euler_rad, obs.position_m], axis=1))
        ref = reference_at(design, offsets.offsets, plan.leader_state, t, ctrl.lead_s, dt)
        xi = xhat - ref.h
        history.append(xi.copy())
        sent = history[max(0, len(history) - 1 - age)]
        lost = rng.random(n) < loss
        heard = sent if heard is None else np.where(lost[:, None], heard, sent)
        topo = plan.schedule.at(ref.t_p)
        v = protocol_input(design, xi, adjacency[topo.name] @ heard, topo.in_degree, topo.pinning, ref.x0, ref.gamma)
        act = ctrl.actuate(v)
        pending.append((k * sub + latency_ms, act.omega_rad_s.copy(), act.alpha_rad.copy()))
        for ms in range(k * sub, (k + 1) * sub):  # the plant, a millisecond at a time: commands land when due
            due = [p for p in pending if p[0] <= ms]
            if due:
                _, omega, alpha = max(due, key=lambda p: p[0])
                plant.command(omega, alpha)
                pending = [p for p in pending if p[0] > ms]
            plant.advance(1)
    t = np.asarray(t_log)
    keep = t >= judged_from_s
    pe, ae = metrics.formation_errors(plan, t[keep], np.asarray(pos_log)[keep], np.asarray(eta_log)[keep])
    return float(pe.max()), float(ae.max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--latency-ms", default="0,5,10,15,20", help="comma-separated")
    ap.add_argument("--age-ms", type=float, default=30.0)
    ap.add_argument("--loss", type=float, default=0.2)
    ap.add_argument("--adaptation-rate", type=float, default=None,
                    help="the thrust adaptation's rate [1/s] (default: the plan's; 0: off)")
    ap.add_argument("--compensated-ms", default="0",
                    help="the latency the controllers compensate ([controller] latency_s) [ms], or 'same': each latency")
    a = ap.parse_args()
    for latency in (int(x) for x in a.latency_ms.split(",")):
        compensated = latency if a.compensated_ms == "same" else float(a.compensated_ms)
        worst = fly(a.rate_hz, latency, a.age_ms, a.loss, adaptation_rate_1_s=a.adaptation_rate, compensated_ms=compensated)
        text = "diverged" if worst is None else f"{worst[0]:.4f} m, {worst[1]:.4f} rad"
        print(f"{a.rate_hz:g} Hz, commands {latency} ms late ({compensated:g} ms compensated), estimates {a.age_ms:g} ms "
              f"old, {a.loss:.0%} lost: {text}", flush=True)


if __name__ == "__main__":
    main()
