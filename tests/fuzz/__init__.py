"""Fuzzers of the companion's faces (docs/testing.md#fuzzing): the ground-station link (signed and
unsigned), the flight-controller link, the Zenoh keys, the mission protocol and the plan parser.

Each face is a function of ``faces.py`` that drives a real companion process (or the parser) with
a given number of inputs and returns a ``Report``: what was sent by kind, what the companion
counted, and what it should have counted. ``tests/test_fuzz.py`` runs every face for a few
seconds inside ``make test``; ``make fuzz`` (``python -m tests.fuzz.run``) runs each with at least
100,000 inputs and prints the rates and the counters.
"""
