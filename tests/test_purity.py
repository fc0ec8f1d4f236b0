"""protocol/ does no I/O: no file reads or writes, clocks, environment or sockets. The companion, the
SITL and the ground station (the edges) read files and clocks and pass what they read in.

Two checks: the source of protocol/ holds none of those calls (a grep over its code, strings and
comments left out), and importing every module of it in a fresh interpreter whose home and temporary
folders are read-only creates no file, anywhere."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROTOCOL = ROOT / "protocol"
GENERATED = PROTOCOL / "dialect" / "triswarm_v20.py"

# -- the source -----------------------------------------------------------------------------------

FORBIDDEN = {
    r"\bopen\s*\(": "opens a file",
    r"\.\s*(read_text|read_bytes|write_text|write_bytes)\s*\(": "reads or writes a file",
    r"\btime\s*\.": "reads a clock (time.*)",
    r"^\s*(import\s+time\b|from\s+time\s+import\b)": "imports the clock (time)",
    r"\bdatetime\s*\.\s*(now|today|utcnow)\b": "reads a clock (datetime)",
    r"\bos\s*\.\s*environ\b|\benviron\b|\bgetenv\b": "reads the environment",
    r"\bsocket\b": "uses a socket",
}


def code_lines(text: str) -> list[str]:
    """The lines of a Python source with its strings (docstrings too) and comments blanked out."""
    lines = [list(line) for line in text.splitlines()]
    blanked = {tokenize.STRING, tokenize.COMMENT, getattr(tokenize, "FSTRING_MIDDLE", tokenize.STRING)}
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type not in blanked:
            continue
        (r0, c0), (r1, c1) = tok.start, tok.end
        for r in range(r0, r1 + 1):
            row = lines[r - 1]
            for c in range(c0 if r == r0 else 0, c1 if r == r1 else len(row)):
                row[c] = " "
    return ["".join(row) for row in lines]


def io_uses(path: Path) -> list[str]:
    """Each use of a file, a clock, the environment or a socket in a source file: "file:line: what (the line)"."""
    found = []
    for number, line in enumerate(code_lines(path.read_text(encoding="utf-8")), 1):
        for pattern, what in FORBIDDEN.items():
            if re.search(pattern, line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {what} ({line.strip()})")
    return found


def protocol_sources() -> list[Path]:
    """protocol/'s Python files but the generated dialect, which is pymavlink's generator's output as it
    comes (tools/gen_dialect.py takes out its one environment read; its MAVLink class still notes
    time.time() as its start-up time, which triswarm never reads) and is checked by tests/test_dialect.py."""
    return sorted(p for p in PROTOCOL.rglob("*.py") if p != GENERATED)


def test_the_grep_sees_code_and_not_words():
    source = '''"""A docstring may say time.time() or open(x)."""
import time  # a comment may say os.environ
label = "socket"
stamp = time.time()
key = open(path).read()
home = os.environ["HOME"]
'''
    hits = [number for number, line in enumerate(code_lines(source), 1) if any(re.search(p, line) for p in FORBIDDEN)]
    assert hits == [2, 4, 5, 6]


def test_protocol_does_no_io():
    sources = protocol_sources()
    assert len(sources) > 15 and PROTOCOL / "mavlink.py" in sources
    found = [use for path in sources for use in io_uses(path)]
    assert not found, ("protocol/ does no I/O: pass files' contents, clocks and keys in from the companion, "
                       "the SITL or the ground station instead:\n  " + "\n  ".join(found))


# -- importing it ---------------------------------------------------------------------------------

def protocol_modules() -> list[str]:
    """triswarm.protocol and every module in it, the dialect too."""
    names = []
    for path in sorted(PROTOCOL.rglob("*.py")):
        parts = path.relative_to(PROTOCOL).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names.append(".".join(("triswarm", "protocol", *parts)))
    return names


# Runs in the fresh interpreter: records every file opened for writing and every other change to
# the file system (and any socket or process started) while the modules are imported.
IMPORTER = r"""
import importlib, json, os, sys

WRITE = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC
CHANGES = {"os.mkdir", "os.rename", "os.replace", "os.remove", "os.rmdir", "os.symlink", "os.link", "os.truncate",
           "os.chmod", "os.chown", "os.utime", "shutil.copyfile", "shutil.rmtree", "socket.__new__", "socket.bind",
           "socket.connect", "subprocess.Popen", "os.system", "os.exec", "os.posix_spawn", "os.fork"}
seen = []

def hook(event, args):
    if event == "open":
        path, mode, flags = args
        if (isinstance(mode, str) and any(c in mode for c in "wax+")) or (flags or 0) & WRITE:
            seen.append(f"open {path!r} {mode or flags}")
    elif event in CHANGES:
        seen.append(f"{event} {args!r}"[:300])

sys.addaudithook(hook)
for name in json.loads(sys.argv[1]):
    importlib.import_module(name)
print(json.dumps(seen))
"""


def test_importing_protocol_writes_no_file(tmp_path):
    home, tmp, cwd, watched = (tmp_path / name for name in ("home", "tmp", "cwd", "writable"))
    for folder in (home, tmp, cwd, watched):
        folder.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "XDG_", "NUMBA_", "TRISWARM_", "MPL"))}
    env.update(HOME=str(home), TMPDIR=str(tmp), PYTHONDONTWRITEBYTECODE="1",
               # every cache a library might write to, in a folder it could write in (it must not)
               XDG_CACHE_HOME=str(watched / "cache"), XDG_CONFIG_HOME=str(watched / "config"),
               XDG_DATA_HOME=str(watched / "data"), TRISWARM_CACHE_DIR=str(watched / "triswarm"),
               NUMBA_CACHE_DIR=str(watched / "numba"), MPLCONFIGDIR=str(watched / "matplotlib"))
    modules = protocol_modules()
    assert "triswarm.protocol" in modules and "triswarm.protocol.mavlink" in modules
    assert "triswarm.protocol.dialect.triswarm_v20" in modules and len(modules) > 15
    for folder in (home, tmp, cwd):
        folder.chmod(0o555)  # (root writes anyway: what is checked is that nothing is written, below)
    try:
        r = subprocess.run([sys.executable, "-c", IMPORTER, json.dumps(modules)], cwd=cwd, env=env,
                           capture_output=True, text=True, timeout=240)
    finally:
        for folder in (home, tmp, cwd):
            folder.chmod(0o755)
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == [], "importing triswarm.protocol wrote to the file system"
    created = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p not in (home, tmp, cwd, watched))
    assert created == [], f"importing triswarm.protocol created files: {created}"
    assert r.stderr == "", r.stderr[-3000:]


def test_the_edges_keep_the_compiled_code_on_disk():
    """protocol/'s numba functions are decorated without numba's cache (which writes files on import);
    the edges (here the tests' conftest, elsewhere the companion, sitl and gcs packages) switch it on."""
    from triswarm.protocol import dynamics, jit, kernels, wind  # noqa: F401 (their functions, compiled)

    assert jit.caching() and len(jit._compiled) >= 15
    assert all(type(d._cache).__name__ == "FunctionCache" for d in jit._compiled)
    code = ("import triswarm.protocol.kernels as k, triswarm.protocol.jit as j; a = j.caching(); "
            "import triswarm.sitl; print(a, j.caching(), type(k.actuate._cache).__name__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240)
    assert r.stdout.split() == ["False", "True", "FunctionCache"], r.stderr[-3000:]


def test_the_import_check_sees_a_write(tmp_path):
    """The audit hook above does see a file written (here by the importer itself, after the imports)."""
    probe = tmp_path / "probe.txt"
    code = IMPORTER.replace("print(json.dumps(seen))", f"open({str(probe)!r}, 'w').close()\nprint(json.dumps(seen))")
    r = subprocess.run([sys.executable, "-c", code, json.dumps(["triswarm.protocol.mavlink"])], capture_output=True, text=True, timeout=240,
                       env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert r.returncode == 0, r.stderr[-3000:]
    assert any(str(probe) in s for s in json.loads(r.stdout.strip().splitlines()[-1])), r.stdout
