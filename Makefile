# triswarm: `make demo` runs the paper's case study, `make test` the tests (`make test-slow` the long
# flights), `make bench` the benchmarks,
# `make fuzz` fuzzes every face of the companion (100,000 inputs each),
# `make docs` regenerates the CLI reference docs/cli.md, `make dialect` the MAVLink dialect's module.
# Every target creates (once) and uses the project's own virtual environment in .venv.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# Python keeps the bytecode of what it imports (its default), even where the environment says not to
# (PYTHONDONTWRITEBYTECODE): every process would otherwise compile triswarm's modules anew, the
# 25,000-line MAVLink dialect among them, 0.35 s of each of the tests' hundreds of processes.
# So the packages are installed without their bytecode (--no-compile): what is imported is compiled
# then, once, and the set-up takes half the time.
unexport PYTHONDONTWRITEBYTECODE
ONE_CORE := OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1

.PHONY: demo test test-slow bench fuzz docs dialect venv clean lint netns-tools

# The packages go in with uv, installed in the venv first (the whole set-up takes 5 s on two cores,
# against 12-17 s with pip); where uv cannot reach an index (pip's own configuration, a mirror, is
# what it reads, not uv), pip does it all.
$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "triswarm needs Python >= 3.11, found " + sys.version.split()[0]'
	$(PYTHON) -m venv $(VENV)
	@if $(PY) -m pip install --quiet uv && $(VENV)/bin/uv pip install --quiet --python $(PY) -e '.[test]' && \
	     $(VENV)/bin/uv pip install --quiet --python $(PY) --no-deps 'MAVProxy==1.8.75'; then :; else \
	  echo "uv could not install the packages: pip installs them"; \
	  $(PY) -m pip install --quiet --upgrade pip && \
	  $(PY) -m pip install --quiet --no-compile -e '.[test]' && \
	  $(PY) -m pip install --quiet --no-compile --no-deps 'MAVProxy==1.8.75'; fi
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/triswarm demo examples/paper-hexagon.toml --lockstep --max-rtf 1

# Two workers for everything on simulated time or with no clock at all; beside them, ahead of them
# (niceness -10, as root), the few tests that judge something on the wall clock (tests/run_suite.py).
# `make test`: every test but the slow ones (a whole scenario flown for tens of seconds), which
# `make test-slow` runs; CI runs both (.ci/run).
test: $(STAMP) netns-tools lint
	$(PY) tests/run_suite.py --quick

test-slow: $(STAMP) netns-tools
	$(PY) tests/run_suite.py --slow

lint: $(STAMP)
	$(PY) -m ruff check --quiet .

# The lossy-network test impairs Zenoh inside a network namespace with iptables (Debian package), and
# the deploy test runs its own OpenSSH server (openssh-server, which brings ssh and scp) and checks the
# systemd unit with systemd-analyze (systemd).
# As root, install them when missing; otherwise those tests say what they need.
netns-tools:
	@{ command -v iptables && command -v ip; } >/dev/null 2>&1 || [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1 || \
		{ echo "installing iptables and iproute2 (apt-get) for the network tests"; \
		  apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iptables iproute2 >/dev/null; }
	@{ [ -x /usr/sbin/sshd ] && command -v ssh && command -v scp; } >/dev/null 2>&1 || [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1 || \
		{ echo "installing openssh-server (apt-get) for the deploy tests"; \
		  apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq openssh-server >/dev/null; }
	@command -v systemd-analyze >/dev/null 2>&1 || [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1 || \
		{ echo "installing systemd (apt-get) for systemd-analyze in the deploy tests"; \
		  apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq systemd >/dev/null; }

bench: $(STAMP)
	$(ONE_CORE) $(PY) tests/bench/bench_sim.py
	$(ONE_CORE) $(PY) tests/bench/bench_formations.py
	$(ONE_CORE) $(PY) tests/bench/bench_sitl.py
	$(ONE_CORE) $(PY) tests/bench/bench_lockstep.py --sizes 6 --duration-s 50
	$(ONE_CORE) $(PY) tests/bench/bench_lockstep.py --sizes 24 --duration-s 30
	$(ONE_CORE) $(PY) tests/bench/bench_lockstep.py --sizes 100 --duration-s 42 --judge-from 38
	$(ONE_CORE) $(PY) tests/bench/bench_soak.py --minutes 30
	$(ONE_CORE) $(PY) tests/bench/bench_stack.py --agents-per-process 0
	$(ONE_CORE) $(PY) tests/bench/bench_stack.py --agents-per-process 1 --sizes 2,4,6,8
	$(ONE_CORE) $(PY) tests/bench/bench_floor.py
	$(ONE_CORE) $(PY) tests/bench/bench_wind.py
	$(ONE_CORE) $(PY) tests/bench/bench_goal.py
	$(ONE_CORE) $(PY) tests/bench/bench_rates.py
	$(ONE_CORE) $(PY) tests/bench/bench_estimators.py
	$(ONE_CORE) $(PY) tests/bench/bench_zenoh_loss.py
	$(ONE_CORE) $(PY) tests/bench/bench_ardupilot.py
	$(ONE_CORE) $(PY) tests/bench/bench_px4.py

# Every face of the companion under 100,000 inputs each (docs/testing.md#fuzzing): the inputs/s
# and the counters per face; exits 1 on a crash, a counter off, or a companion that stopped answering
fuzz: $(STAMP)
	$(ONE_CORE) $(PY) -m tests.fuzz.run --count 100000

# docs/cli.md: the --help of every command, from the CLI itself
docs: $(STAMP)
	$(PY) tools/gen_cli_docs.py

# protocol/dialect/triswarm_v20.py: the MAVLink dialect, from the XML files beside it, by pymavlink's generator
# (after a change to them; tests/test_dialect.py says when it is due)
dialect: $(STAMP)
	$(PY) tools/gen_dialect.py

clean:
	rm -rf $(VENV) runs .pytest_cache
