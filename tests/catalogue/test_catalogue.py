"""Run every case of the catalogue (cases.py) through the real `cca` entry point, in process.

Each case runs in a fresh folder. A failing case must exit with its code and
print one line on stderr naming the file or key; a working case must exit 0.
Every file the case found must be unchanged afterwards (compared by hash), apart
from the paths a working case is allowed to write.
"""

from __future__ import annotations

import hashlib
import http.server
import os
import socket
import stat
import threading
import time
from pathlib import Path

import pytest
from cases import CASES, Case
from makers import make
from typer.testing import CliRunner

from cca_cli.commands.app import app


def snapshot(root: Path) -> dict[str, str]:
    """Every path under ``root`` (hidden ones included) → a digest of what it is."""
    out = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        mode = path.lstat().st_mode
        if stat.S_ISLNK(mode):
            out[rel] = "link:" + os.readlink(path)
        elif stat.S_ISDIR(mode):
            out[rel] = "dir"
        elif stat.S_ISREG(mode):
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[rel] = "special"
    return out


def _allowed(rel: str, writes: tuple[str, ...]) -> bool:
    return any(rel == w or rel.startswith(w.rstrip("/") + "/") for w in writes)


@pytest.fixture(scope="module")
def ports():
    """A port that speaks HTTP (not Dask) and a port where nothing listens."""
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        dead = probe.getsockname()[1]
    yield {"http_port": server.server_address[1], "dead_port": dead}
    server.shutdown()


def _argv(case: Case, folder: Path, ports: dict) -> list[str]:
    values = {"cwd": str(folder), **ports}
    out = []
    for arg in case.argv:
        for key, value in values.items():
            arg = arg.replace("{" + key + "}", str(value))
        out.append(arg)
    return out


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_case(case: Case, library, ports, tmp_path, monkeypatch):
    folder = tmp_path / "case"
    folder.mkdir()
    make(case.files, folder, library)
    cwd = folder / case.cwd
    cwd.mkdir(parents=True, exist_ok=True)
    before = snapshot(tmp_path)
    monkeypatch.chdir(cwd)
    for key, value in case.env.items():
        monkeypatch.setenv(key, value)
    cleanup = case.patch(monkeypatch, folder) if case.patch is not None else None
    start = time.perf_counter()
    try:
        result = CliRunner().invoke(app, _argv(case, folder, ports))
    finally:
        seconds = time.perf_counter() - start
        monkeypatch.undo()
        if callable(cleanup):
            cleanup()

    if os.environ.get("CCA_CATALOGUE_LOG"):  # a table of every case's exit code and message, for reading them
        with open(os.environ["CCA_CATALOGUE_LOG"], "a") as log:
            log.write(f"{case.id}\t{result.exit_code}\t{' | '.join(result.stderr.splitlines())}\n")
    output = result.output + (result.stderr if result.stderr not in result.output else "")
    assert result.exception is None or isinstance(result.exception, SystemExit), (
        f"{type(result.exception).__name__}: {result.exception}\n{output}")
    assert "Traceback" not in output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    if case.exit == 0:
        assert result.exit_code == 0, output
    else:
        assert result.exit_code != 0, output
        if case.exit is not None:
            assert result.exit_code == case.exit, output
        assert len(lines) == 1, result.stderr
        for text in case.says:
            assert text in lines[0], lines[0]
    for text in case.not_says:
        assert text not in result.stderr, result.stderr
    after = snapshot(tmp_path)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k)
                     and not _allowed(k.removeprefix("case/"), case.writes))
    assert not changed, f"changed: {changed}"
    assert seconds < case.seconds, f"took {seconds:.1f} s"
    if case.check is not None:
        case.check(folder, result)
