"""A Zenoh router for the multi-host test, until SIGINT/SIGTERM: what ``zenohd -c CONFIG`` does,
without installing zenohd.

    python tests/zenoh_router.py CONFIG.json5
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path


def command(config: Path) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), str(config)]


def main() -> None:
    if len(sys.argv) != 2:
        sys.exit("usage: zenoh_router.py CONFIG.json5")
    # Zenoh's default runtime, not the companion's single worker that a test's environment passes on
    # (triswarm.companion.bus sets it on import): a router with one worker stops whenever it blocks
    os.environ.pop("ZENOH_RUNTIME", None)
    import zenoh

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    zenoh.init_log_from_env_or("warn")
    session = zenoh.open(zenoh.Config.from_file(sys.argv[1]))
    print(f"router {session.zid()} up", flush=True)
    while not stop.wait(0.5):
        pass
    session.close()


if __name__ == "__main__":
    main()
