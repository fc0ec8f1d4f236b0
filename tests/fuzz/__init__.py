"""Fuzzers of the companion's faces (docs/testing.md#fuzzing): its ground-station link, unsigned
and signed (``mavlink_faces.py``), its flight-controller link (the same), the mission protocol
(``missions.py``), its Zenoh keys (``zenoh_face.py``) and the plan-file parser (``plan_files.py``).

Each face is a function that drives a real companion process (or, for the parser, the parser
itself) with a given number of inputs and returns a ``report.Report``: what was sent by kind, what
the companion counted, and what it should have counted. ``tests/test_fuzz.py`` runs every face for
a few seconds in the tests; ``make fuzz`` (``python -m tests.fuzz.run``) runs each with 100,000
inputs and prints the rates and the counters.
"""
