"""The plan-file parser under fuzz (hypothesis): the text of a plan file through
``spec_from_toml`` and ``plan_from_dict``, as every reader of a plan file does. Only a plan or a
``PlanError`` (the user's error, one sentence) may come out, never another exception.

Three kinds of input, drawn at random:

- ``random_document``: a random TOML document, its keys mostly the plan format's own (taken from
  the example plans), its values any TOML value (integers beyond 64 bits' halves, NaN and the
  infinities, strings, booleans, dates and times, arrays, tables, nested);
- ``mutated_plan``: an example plan with one to five of its values replaced by random ones, keys
  deleted or added, arrays shortened or lengthened;
- ``mutated_text``: an example plan's text with bytes deleted, inserted, replaced or lines repeated
  (mostly not TOML any more: the error must still be a PlanError).
"""

from __future__ import annotations

import contextlib
import copy
import datetime as dt
import resource
import tomllib
from collections import Counter
from pathlib import Path

import tomli_w
from hypothesis import HealthCheck, given, seed as hypothesis_seed, settings, strategies as st

from triswarm.protocol.plan import PlanError, plan_from_dict, spec_from_toml

from .report import Clock, Report

EXAMPLES = sorted((Path(__file__).resolve().parents[2] / "examples").glob("*.toml"))
SOURCE = "fuzz.toml"


def _keys(value, out: set) -> set:
    if isinstance(value, dict):
        for k, v in value.items():
            out.add(k)
            _keys(v, out)
    elif isinstance(value, list):
        for v in value:
            _keys(v, out)
    return out


TEXTS = [p.read_text() for p in EXAMPLES]
SPECS = [tomllib.loads(t) for t in TEXTS]
KEYS = sorted(_keys(SPECS, set()))
keys = st.one_of(st.sampled_from(KEYS), st.text(min_size=0, max_size=8))
scalars = st.one_of(st.integers(min_value=-2**63, max_value=2**63 - 1), st.integers(-3, 20),
                    st.floats(allow_nan=True, allow_infinity=True), st.booleans(), st.text(max_size=12),
                    st.sampled_from(["rotating-polygon", "constant", "keyframes", "ring", "star", ""]),
                    st.datetimes(timezones=st.none() | st.just(dt.timezone.utc)), st.dates(), st.times())
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=6),
                                                        st.dictionaries(keys, inner, max_size=5)), max_leaves=10)
documents = st.dictionaries(keys, values, max_size=10)


def _paths(value, prefix=()) -> list[tuple]:
    """Every place in a plan dict: (key or index, ...)."""
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(value, list):
        for k, v in enumerate(value):
            out += _paths(v, prefix + (k,))
    return out


def _mutate(data, spec: dict) -> dict:
    """One to five random changes to a deep copy of ``spec``."""
    spec = copy.deepcopy(spec)
    for _ in range(data.draw(st.integers(1, 5))):
        paths = _paths(spec)
        if not paths:
            break
        path = data.draw(st.sampled_from(paths))
        parent = spec
        for step in path[:-1]:
            parent = parent[step]
        last = path[-1]
        op = data.draw(st.sampled_from(("replace", "replace", "delete", "add", "resize")))
        if op == "replace":
            parent[last] = data.draw(values)
        elif op == "delete":
            del parent[last]
        elif op == "add" and isinstance(parent, dict):
            parent[data.draw(keys)] = data.draw(values)
        elif op == "resize" and isinstance(parent[last], list):
            items = parent[last]
            parent[last] = items[:data.draw(st.integers(0, len(items)))] if data.draw(st.booleans()) \
                else items + [data.draw(values) if not items else items[-1]] * data.draw(st.integers(1, 3))
    return spec


def _mutate_text(data, text: str) -> str:
    for _ in range(data.draw(st.integers(1, 4))):
        k = data.draw(st.integers(0, len(text)))
        op = data.draw(st.sampled_from(("delete", "insert", "replace", "repeat_line")))
        if op == "delete":
            text = text[:k] + text[k + data.draw(st.integers(1, 20)):]
        elif op == "insert":
            text = text[:k] + data.draw(st.text(max_size=10) | st.sampled_from(("[", "]", "=", '"', "\n", "#", "[[x]]\n"))) + text[k:]
        elif op == "replace" and k < len(text):
            text = text[:k] + data.draw(st.characters()) + text[k + 1:]
        else:
            lines = text.splitlines(keepends=True)
            if lines:
                j = data.draw(st.integers(0, len(lines) - 1))
                lines.insert(j, lines[j])
                text = "".join(lines)
    return text


def parse(text: str) -> str:
    """What the parser made of ``text``: "accepted" or "refused" (a PlanError); anything else raises."""
    try:
        plan_from_dict(spec_from_toml(text, SOURCE), SOURCE)
    except PlanError as exc:
        if not str(exc).strip():
            raise AssertionError("a PlanError with no reason") from exc
        return "refused"
    return "accepted"


MEMORY_LIMIT_BYTES = 3 << 30
"""More address space than this for one plan file is a MemoryError, judged as a crash (the parser
must refuse a plan file that would take gigabytes, not take them)."""
CHUNK = 5000
"""Examples per hypothesis run: a run keeps what it explored, so 100,000 go in runs of this many
(each with a seed of its own), in bounded memory."""


@contextlib.contextmanager
def _memory_limit(extra_bytes: int):
    """The process's address space limited to what it has now plus ``extra_bytes`` (Linux)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        yield
        return
    before = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (pages * resource.getpagesize() + extra_bytes, before[1]))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, before)


def fuzz_plan_files(n: int, seed: int = 5) -> Report:
    """``n`` inputs through the parser; a problem for the (shrunk) input that raised anything but
    a PlanError."""
    report = Report("plan-files")
    outcomes: Counter[str] = Counter()
    last: list[str] = [""]

    def check(data) -> None:
        kind = data.draw(st.sampled_from(("random_document", "mutated_plan", "mutated_text")))
        k = data.draw(st.integers(0, len(EXAMPLES) - 1))
        if kind == "random_document":
            text = tomli_w.dumps(data.draw(documents))
        elif kind == "mutated_plan":
            text = tomli_w.dumps(_mutate(data, SPECS[k]))
        else:
            text = _mutate_text(data, TEXTS[k])
        last[0] = text
        outcome = parse(text)
        report.sent[kind] += 1
        outcomes[f"{kind}.{outcome}"] += 1

    with Clock() as clock, _memory_limit(MEMORY_LIMIT_BYTES):
        for start in range(0, n, CHUNK):
            run = given(data=st.data())(check)
            run = settings(max_examples=min(CHUNK, n - start), deadline=None, database=None,
                           suppress_health_check=list(HealthCheck))(run)
            try:
                hypothesis_seed(seed + start)(run)()
            except Exception as exc:  # (hypothesis raises the shrunk failure; anything but PlanError is one)
                report.problems.append(f"{exc.__class__.__name__}: {exc} for the plan file:\n{last[0][:2000]}")
                break
    report.seconds = clock.seconds
    report.inputs = sum(report.sent.values())
    report.counters = dict(outcomes)
    report.other = dict(outcomes)
    return report
