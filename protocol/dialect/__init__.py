"""triswarm's MAVLink dialect (``triswarm.xml``), built with pymavlink's own generator.

The Python module is generated on first use from the XML and pymavlink's ``common.xml``, and kept
in a cache folder keyed by both (``$TRISWARM_CACHE_DIR``, else ``~/.cache/triswarm``, else the
temporary folder), so a change to either rebuilds it and nothing generated is checked in.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import importlib.util
import os
import shutil
import sys
import tempfile
from pathlib import Path
from types import ModuleType

XML = Path(__file__).with_name("triswarm.xml")
MODULE_NAME = "triswarm_mavlink_dialect"


def _pymavlink_xml_dir() -> Path:
    import pymavlink.dialects.v20 as v20

    return Path(v20.__file__).parent


def _cache_dirs() -> list[Path]:
    dirs = []
    if os.environ.get("TRISWARM_CACHE_DIR"):
        dirs.append(Path(os.environ["TRISWARM_CACHE_DIR"]))
    dirs.append(Path.home() / ".cache" / "triswarm")
    dirs.append(Path(tempfile.gettempdir()) / f"triswarm-{os.getuid() if hasattr(os, 'getuid') else 'user'}")
    return dirs


def _fingerprint() -> str:
    import pymavlink

    h = hashlib.sha256(XML.read_bytes())
    h.update(getattr(pymavlink, "__version__", "").encode())
    for name in ("common.xml", "standard.xml", "minimal.xml"):
        h.update((_pymavlink_xml_dir() / name).read_bytes())
    return h.hexdigest()[:16]


def generate(output: Path) -> None:
    """Run pymavlink's mavgen (Python 3, MAVLink 2) on the dialect; written atomically."""
    from pymavlink.generator import mavgen

    with tempfile.TemporaryDirectory() as tmp:
        for name in ("common.xml", "standard.xml", "minimal.xml"):
            shutil.copy(_pymavlink_xml_dir() / name, tmp)
        shutil.copy(XML, tmp)
        out = Path(tmp) / "generated.py"
        opts = mavgen.Opts(str(out), wire_protocol="2.0", language="Python3", validate=False)
        chatter = io.StringIO()
        with contextlib.redirect_stdout(chatter):
            ok = mavgen.mavgen(opts, [str(Path(tmp) / XML.name)])
        if not ok:
            raise RuntimeError(f"pymavlink's generator refused {XML}: {chatter.getvalue()[-500:]}")
        output.parent.mkdir(parents=True, exist_ok=True)
        staged = output.with_name(f".{output.name}.{os.getpid()}.tmp")
        shutil.copy(out, staged)
        os.replace(staged, output)


def load() -> ModuleType:
    """The generated module (a MAVLink 2 module like pymavlink's ``common``, with our commands)."""
    if MODULE_NAME in sys.modules:
        return sys.modules[MODULE_NAME]
    name = f"triswarm_{_fingerprint()}.py"
    problems = []
    for folder in _cache_dirs():
        path = folder / "mavlink" / name
        try:
            if not path.exists():
                generate(path)
            break
        except OSError as exc:
            problems.append(f"{folder}: {exc.strerror or exc}")
    else:
        raise RuntimeError("cannot build the triswarm MAVLink dialect: " + "; ".join(problems))
    spec = importlib.util.spec_from_file_location(MODULE_NAME, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[MODULE_NAME] = module
    spec.loader.exec_module(module)
    return module
