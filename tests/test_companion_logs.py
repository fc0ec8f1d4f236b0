"""The companion's log does not hold its loop: a log call returns while the writer is stuck (a full
pipe here, as a slow journal or a throttled disk would hold it), and every line comes out, in order,
once the pipe is read. Judged on the order of events; the joins' bounds only guard against a hang."""

from __future__ import annotations

import fcntl
import logging
import os
import threading

from triswarm.companion.logs import start_logging

HANG_GUARD_S = 30.0


def test_a_log_call_returns_while_the_stream_is_stuck_and_every_line_comes_out_after():
    r, w = os.pipe()
    fcntl.fcntl(w, fcntl.F_SETFL, fcntl.fcntl(w, fcntl.F_GETFL) | os.O_NONBLOCK)
    filled = 0
    try:
        while True:
            filled += os.write(w, b"x" * 4096)
    except BlockingIOError:
        pass
    fcntl.fcntl(w, fcntl.F_SETFL, fcntl.fcntl(w, fcntl.F_GETFL) & ~os.O_NONBLOCK)
    stream = os.fdopen(w, "w", buffering=1)
    listener = start_logging(stream)
    try:
        done = threading.Event()

        def loop():  # (the control loop: it logs and goes on)
            for k in range(3):
                logging.getLogger("triswarm.companion").info("line %d", k)
            done.set()

        threading.Thread(target=loop, daemon=True).start()
        assert done.wait(HANG_GUARD_S), "a log call waited for the stuck stream"
        out = b""
        stopper = threading.Thread(target=listener.stop, daemon=True)  # (it writes what is queued, then returns)
        stopper.start()
        while b"line 2" not in out:
            chunk = os.read(r, 65536)
            assert chunk, out[-200:]
            out += chunk
        stopper.join(HANG_GUARD_S)
        assert not stopper.is_alive()
    finally:  # (the reading end first: a writer still stuck on the pipe then fails instead of hanging)
        logging.getLogger().handlers.clear()
        os.close(r)
        try:
            stream.close()
        except BrokenPipeError:
            pass
    text = out[filled:].decode()
    assert [line.split(" ", 2)[-1] for line in text.splitlines()] == ["line 0", "line 1", "line 2"], text
