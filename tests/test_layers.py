"""The layers, from their imports (every module's, parsed, not run): ``protocol`` (pure math, the
formats) imports no other part of triswarm; ``companion`` and ``sitl`` import ``protocol`` only, and
not each other (a companion flies real autopilots; a simulator needs no companion); ``gcs``, the
operator's tool that starts, configures and deploys the others, may import them all."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("protocol", "companion", "sitl", "gcs")
MAY_IMPORT = {"protocol": set(), "companion": {"protocol"}, "sitl": {"protocol"},
              "gcs": {"protocol", "companion", "sitl"}}


def triswarm_imports(path: Path, part: str, root: Path = ROOT) -> set[str]:
    """The parts of triswarm a module of ``root/part`` imports (relative imports resolved; its own
    part left out)."""
    package = [part, *path.relative_to(root / part).parent.parts]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                names = [".".join(["triswarm", *base, *([node.module] if node.module else [])])]
            else:
                names = [node.module or ""]
        else:
            continue
        for name in names:
            bits = name.split(".")
            if bits[0] == "triswarm" and len(bits) > 1 and bits[1] in PARTS and bits[1] != part:
                found.add(bits[1])
    return found


@pytest.mark.parametrize("part", PARTS)
def test_each_part_imports_only_the_layers_below_it(part):
    modules = sorted((ROOT / part).rglob("*.py"))
    assert modules
    wrong = {str(m.relative_to(ROOT)): sorted(got - MAY_IMPORT[part])
             for m in modules if (got := triswarm_imports(m, part)) - MAY_IMPORT[part]}
    assert not wrong, f"{part}/ may import only {sorted(MAY_IMPORT[part]) or 'nothing of triswarm'}: {wrong}"


def test_the_rule_sees_an_import_that_breaks_it(tmp_path):
    """(The parser, on a module written to break each kind of import.)"""
    probe = tmp_path / "sitl" / "deep" / "probe.py"
    probe.parent.mkdir(parents=True)
    probe.write_text("from triswarm.companion import bus\nfrom ...gcs import stack\nimport triswarm.protocol.frames\n"
                     "from . import sibling\nfrom .. import physics\n")
    assert triswarm_imports(probe, "sitl", tmp_path) == {"companion", "gcs", "protocol"}


def rooms_handed_the_agent(source: str) -> list[str]:
    """The classes that ``source`` (``companion/agent.py``) builds with ``self``, the whole agent,
    among their arguments."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id[:1].isupper():
            if any(isinstance(arg, ast.Name) and arg.id == "self" for arg in [*node.args, *(k.value for k in node.keywords)]):
                found.append(node.func.id)
    return sorted(found)


def test_no_companion_room_is_handed_the_whole_agent():
    """The agent builds each of its rooms (flight, ground station, plans...) from the collaborators it
    uses, never from the agent itself: a room changes another only through that room's methods."""
    assert rooms_handed_the_agent((ROOT / "companion" / "agent.py").read_text(encoding="utf-8")) == []
    broken = "def __init__(self, url):\n    self.flight = Flight(self)\n    self.gcs = GroundStation(url, agent=self)\n"
    assert rooms_handed_the_agent(broken) == ["Flight", "GroundStation"]
