"""The companion's log, written off the control loop.

A log line goes to stderr: a file, a pipe to journald or a terminal, any of which can hold a write
for a second or more (a busy disk throttling its writers, a journal that reads slowly). The loop
only puts each record on a queue (``logging.handlers.QueueHandler``); a thread of the standard
library's (``QueueListener``) writes them, in order, with the time each was made."""

from __future__ import annotations

import logging
import logging.handlers
import queue
from typing import TextIO

FORMAT = "%(asctime)s %(message)s"


def start_logging(stream: TextIO, verbose: bool = False) -> logging.handlers.QueueListener:
    """Log (the root logger, INFO or with ``verbose`` DEBUG) to ``stream`` from a thread of its own.
    Stop the returned listener at exit: it writes what is queued, then returns."""
    records: queue.SimpleQueue = queue.SimpleQueue()
    writer = logging.StreamHandler(stream)
    writer.setFormatter(logging.Formatter(FORMAT))
    queued = logging.handlers.QueueHandler(records)
    queued.setFormatter(logging.Formatter("%(message)s"))  # (the message and any traceback; the writer adds the time)
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[queued], force=True)
    logging.captureWarnings(True)  # (a warning, numpy's among them, is a log line too)
    listener = logging.handlers.QueueListener(records, writer)
    listener.start()
    return listener
