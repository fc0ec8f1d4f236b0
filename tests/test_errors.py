"""One error base per layer, caught once at each edge: every exception class a module of ``protocol``,
``companion``, ``sitl`` or ``gcs`` defines derives from its layer's base (ProtocolError, CompanionError,
SitlError, GcsError), and the CLIs catch those bases, not a list of classes. Each module is imported and
its classes looked at, so a new error class without its layer's base fails here."""

from __future__ import annotations

import importlib
import inspect
import types
from pathlib import Path

import pytest
import typer

from triswarm.companion.errors import CompanionError
from triswarm.gcs.errors import GcsError, user_errors
from triswarm.protocol.errors import ProtocolError
from triswarm.sitl.errors import SitlError

ROOT = Path(__file__).resolve().parents[1]
BASES = {"protocol": ProtocolError, "companion": CompanionError, "sitl": SitlError, "gcs": GcsError}
GENERATED = ROOT / "protocol" / "dialect" / "triswarm_v20.py"
"""pymavlink's generator's output (tools/gen_dialect.py), with pymavlink's own MAVError: not triswarm's."""


def module_names(part: str) -> list[str]:
    """The importable name of every module of ``part`` (but the generated dialect)."""
    names = []
    for path in sorted((ROOT / part).rglob("*.py")):
        if path == GENERATED:
            continue
        bits = path.relative_to(ROOT).with_suffix("").parts
        names.append(".".join(["triswarm", *(bits[:-1] if bits[-1] == "__init__" else bits)]))
    return names


def error_classes(module: types.ModuleType) -> list[type[BaseException]]:
    """The exception classes ``module`` itself defines (not those it imports)."""
    return [c for c in vars(module).values()
            if inspect.isclass(c) and issubclass(c, BaseException) and c.__module__ == module.__name__]


def strays(modules: list[types.ModuleType], base: type[BaseException]) -> list[str]:
    """module.Class of each exception class defined in ``modules`` that does not derive from ``base``."""
    return [f"{c.__module__}.{c.__qualname__}" for m in modules for c in error_classes(m) if not issubclass(c, base)]


@pytest.mark.parametrize("part", BASES)
def test_every_error_class_of_a_layer_derives_from_its_base(part):
    modules = [importlib.import_module(name) for name in module_names(part)]
    assert BASES[part] in [c for m in modules for c in error_classes(m)]  # (the walk sees the layer's errors)
    wrong = strays(modules, BASES[part])
    assert not wrong, f"the errors of {part}/ derive from {BASES[part].__name__} (the edges catch it once): {wrong}"


def test_the_check_sees_a_class_without_its_base():
    class Fine(SitlError, OSError):
        pass

    class Stray(ValueError):
        pass

    probe = types.ModuleType("probe")
    for c in (Fine, Stray, ProtocolError):  # (ProtocolError: imported, another module's)
        setattr(probe, c.__name__, c)
    Fine.__module__ = Stray.__module__ = "probe"
    assert strays([probe], SitlError) == [f"probe.{Stray.__qualname__}"]


def test_the_cli_edges_catch_the_layers_bases():
    from triswarm.companion import cli as companion_cli
    from triswarm.gcs import errors

    assert set(errors.USER_ERRORS) == {GcsError, SitlError, CompanionError, ProtocolError}
    assert set(companion_cli.USER_ERRORS) == {CompanionError, ProtocolError}


@pytest.mark.parametrize("error", [c("what is wrong") for c in BASES.values()])
def test_a_layers_error_is_one_sentence_and_exit_status_2(error, capsys):
    with pytest.raises(typer.Exit) as got, user_errors():
        raise error
    assert got.value.exit_code == 2
    assert capsys.readouterr().err == "triswarm: error: what is wrong\n"


@pytest.mark.parametrize("error", [ValueError("a bug"), OSError(5, "a fault"), RuntimeError("a bug")])
def test_anything_else_passes_the_edge(error):
    with pytest.raises(type(error)), user_errors():
        raise error
