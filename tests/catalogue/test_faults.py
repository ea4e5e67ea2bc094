"""Faults in real processes: kill -9 in every stage, two runs into one folder, a full disk, Ctrl-C.

Each test runs `cca` in a subprocess (cca_with_hooks.py pauses a write at a chosen output so the
process can be killed while its temporary file exists) and then checks that the next run resumes,
that no temporary file is left, and that nothing that existed was damaged.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from micro import micro_config

HOOKS = Path(__file__).with_name("cca_with_hooks.py")
REPO = Path(__file__).resolve().parents[2]


def _start(args, cwd: Path, **env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(HOOKS), *map(str, args)], cwd=cwd, env={**os.environ, **env},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _run(args, cwd: Path, timeout: float = 120, **env) -> subprocess.CompletedProcess:
    proc = _start(args, cwd, **env)
    out, err = proc.communicate(timeout=timeout)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _one_line(result) -> str:
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    return lines[0]


def _kill_when_written(proc: subprocess.Popen, folder: Path, name: str, timeout: float = 120) -> None:
    """SIGKILL ``proc`` once its temporary copy of ``name`` exists in ``folder``."""
    temporary = folder / f".{name}.tmp-{proc.pid}"
    deadline = time.monotonic() + timeout
    while not temporary.exists():
        assert proc.poll() is None, f"cca ended before writing {name}: {proc.communicate()}"
        assert time.monotonic() < deadline, f"no {temporary} after {timeout} s"
        time.sleep(0.01)
    proc.kill()
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    assert temporary.exists()  # what a killed run leaves behind


def _temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if ".tmp-" in p.name or ".old-" in p.name)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _statuses(stdout: str) -> dict[str, str]:
    out = {}
    for line in stdout.splitlines():
        parts = line.split()
        if len(parts) >= 3 and parts[1] in ("ran", "skipped"):
            out[parts[0]] = parts[1]
    return out


def _write_config(path: Path, **sections) -> Path:
    data = micro_config()
    for name, values in sections.items():
        data[name] = {**data.get(name, {}), **values}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.slow
def test_kill_in_each_stage_then_the_run_resumes(tmp_path):
    config = _write_config(tmp_path / "cfg.yaml")
    out = tmp_path / "out"
    done = []
    for stage, name in (("simulate", "captures.h5"), ("reconstruct", "recon.h5"), ("report", "report")):
        proc = _start(["run", config, "--out-dir", out, "-q"], tmp_path, CCA_TEST_PAUSE_BEFORE_RENAME=name)
        _kill_when_written(proc, out, name)
        assert not (out / name).exists()
        for earlier in done:  # what earlier runs completed is still there, untouched
            assert (out / earlier).exists()
        done.append(name)
    result = _run(["run", config, "--out-dir", out, "-q"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert _statuses(result.stdout) == {"simulate": "skipped", "reconstruct": "skipped", "report": "ran"}
    assert _temporaries(out) == []
    assert not (out / ".cca-run.lock").exists()
    report = json.loads((out / "report" / "report.json").read_text())
    assert json.loads(report["provenance"]["inputs"])[0]["sha256"] == _sha(out / "recon.h5")


@pytest.mark.slow
def test_kill_in_the_lab_stages_then_the_run_resumes(tmp_path):
    config = yaml.safe_load((REPO / "configs" / "sample_capture.yaml").read_text())
    config["ingest"]["manifest"] = str(REPO / "data_samples" / "sample_capture" / "manifest.yaml")
    config["reconstruct"]["iterations"] = 3
    config["report"]["figures"] = False
    config["run"].pop("out_dir")
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(config))
    out = tmp_path / "out"
    for name in ("raw.h5", "hdr.h5", "registered.h5"):
        proc = _start(["run", path, "--out-dir", out, "-q"], tmp_path, CCA_TEST_PAUSE_BEFORE_RENAME=name)
        _kill_when_written(proc, out, name)
    result = _run(["run", path, "--out-dir", out, "-q"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert _statuses(result.stdout) == {"ingest": "skipped", "hdr": "skipped", "register": "ran",
                                        "reconstruct": "ran", "report": "ran"}
    assert _temporaries(out) == []


@pytest.mark.slow
def test_a_second_run_into_a_busy_folder_is_refused_and_a_dead_runs_lock_is_taken_over(tmp_path):
    first = _write_config(tmp_path / "a.yaml")
    second = _write_config(tmp_path / "b.yaml", noise={"seed": 2})
    out = tmp_path / "out"
    proc = _start(["run", first, "--out-dir", out, "-q"], tmp_path, CCA_TEST_PAUSE_BEFORE_RENAME="captures.h5")
    try:
        deadline = time.monotonic() + 120
        while not (out / f".captures.h5.tmp-{proc.pid}").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.01)
        busy = _run(["run", second, "--out-dir", out, "-q"], tmp_path, timeout=60)
        line = _one_line(busy)
        assert busy.returncode == 6 and "out" in line and f"pid {proc.pid}" in line
        assert sorted(p.name for p in out.iterdir()) == sorted([".cca-run.lock", f".captures.h5.tmp-{proc.pid}"])
    finally:
        proc.kill()
        proc.communicate()
    result = _run(["run", second, "--out-dir", out, "-q"], tmp_path)  # the dead run's lock and temporary go
    assert result.returncode == 0, result.stderr
    assert _temporaries(out) == [] and not (out / ".cca-run.lock").exists()
    with open(out / "captures.h5", "rb") as handle:
        assert handle.read(8) == b"\x89HDF\r\n\x1a\n"
    recon = json.loads(__import__("h5py").File(out / "recon.h5", "r").attrs["inputs"])
    assert recon[0]["sha256"] == _sha(out / "captures.h5")


def _unshare_works() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                            "mount -t tmpfs -o size=64k tmpfs /tmp && echo ok"], capture_output=True, text=True)
    return probe.stdout.strip() == "ok"


@pytest.mark.skipif(not _unshare_works(), reason="needs user namespaces to mount a small tmpfs")
def test_a_full_disk_keeps_the_old_file_and_leaves_no_temporary(tmp_path, library):
    config = _write_config(tmp_path / "big.yaml", simulate={"store": "sensor"})  # about 200 kB: more than is free
    shutil.copy(library.captures, tmp_path / "old.h5")
    disk = tmp_path / "disk"
    disk.mkdir()
    script = (f"mount -t tmpfs -o size=120k tmpfs {disk} && cp old.h5 {disk}/c.h5 && "
              f"CCA_TEST_NO_DISK_CHECK=1 {sys.executable} {HOOKS} simulate big.yaml -o {disk}/c.h5 --force -q; "
              f"echo exit=$? >&2; ls -a {disk} >&2; sha256sum {disk}/c.h5 >&2")
    result = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120)
    lines = result.stderr.splitlines()
    error = [line for line in lines if line.startswith("error:")]
    assert len(error) == 1 and "c.h5" in error[0] and "no space left" in error[0], result.stderr
    assert "Traceback" not in result.stderr and "exit=5" in lines, result.stderr
    listing = lines[lines.index("exit=5") + 1:-1]
    assert sorted(listing) == [".", "..", "c.h5"], listing  # no temporary left
    assert lines[-1].split()[0] == _sha(tmp_path / "old.h5")  # the old file is intact


def test_an_output_folder_without_write_permission_is_refused_before_computing(tmp_path):
    config = _write_config(tmp_path / "cfg.yaml")
    locked = tmp_path / "locked"
    locked.mkdir()
    mark = tmp_path / "simulating"
    command = f"{sys.executable} {HOOKS} simulate cfg.yaml -o locked/sub/c.h5 -q"
    if os.geteuid() != 0:
        locked.chmod(0o555)
        args = ["sh", "-c", command]
    elif _unshare_works():  # root writes anywhere, except on a read-only mount
        args = ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                f"mount --bind {locked} {locked} && mount -o remount,ro,bind {locked} && {command}"]
    else:
        pytest.skip("root without user namespaces: no folder it cannot write")
    result = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=120,
                            env={**os.environ, "CCA_TEST_MARK_SIMULATING": str(mark)})
    line = _one_line(result)
    assert result.returncode == 4 and "locked" in line and "cannot write" in line, line
    assert not mark.exists()  # refused before the simulation started
    locked.chmod(0o755)
    assert list(locked.iterdir()) == []


@pytest.mark.slow
def test_a_write_past_the_file_size_limit_keeps_the_old_file(tmp_path, library):
    shutil.copy(library.captures, tmp_path / "c.h5")
    config = _write_config(tmp_path / "cfg.yaml")
    first = _run(["reconstruct", "c.h5", "-o", "r.h5", "-c", config, "-q"], tmp_path)
    assert first.returncode == 0, first.stderr
    before = _sha(tmp_path / "r.h5")

    def limit():  # writes beyond 20 kB fail with EFBIG, as on a full disk
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    proc = subprocess.run([sys.executable, str(HOOKS), "reconstruct", "c.h5", "-o", "r.h5", "-c", str(config),
                           "--force", "-q"], cwd=tmp_path, preexec_fn=limit, capture_output=True, text=True,
                          timeout=120)
    line = _one_line(proc)
    assert proc.returncode == 5 and "r.h5" in line and "previous version is kept" in line
    assert _sha(tmp_path / "r.h5") == before
    assert _temporaries(tmp_path) == []


def test_ctrl_c_during_a_reconstruction_stops_at_once_and_writes_nothing(tmp_path, library):
    shutil.copy(library.captures, tmp_path / "c.h5")
    shutil.copy(library.recon, tmp_path / "r.h5")
    before = _sha(tmp_path / "r.h5")
    mark = tmp_path / "iterating"
    proc = _start(["reconstruct", "c.h5", "-o", "r.h5", "--force", "--iterations", "100000000", "--tol", "0", "-q"],
                  tmp_path, CCA_TEST_MARK_ITERATING=str(mark))
    deadline = time.monotonic() + 120
    while not mark.exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.01)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    start = time.monotonic()
    out, err = proc.communicate(timeout=60)
    assert time.monotonic() - start < 3, "Ctrl-C took more than 3 s to stop the reconstruction"
    assert proc.returncode == 130, err
    assert _one_line(subprocess.CompletedProcess(proc.args, proc.returncode, out, err)).startswith("interrupted:")
    assert _sha(tmp_path / "r.h5") == before and _temporaries(tmp_path) == []


#: Moments of the report stage a Ctrl-C may land at (cca_with_hooks.py waits there for the signal).
REPORT_MOMENTS = ("report-start", "figure-in-gc", "report-complete", "report-renamed", "stage-done-in-gc")


@pytest.mark.slow
def test_ctrl_c_at_any_moment_of_the_report_stage_ends_with_exit_130_and_no_half_written_report(tmp_path, library):
    from cca_cli.io.outputs import folder_complete

    config = _write_config(tmp_path / "cfg.yaml", report={"figures": True})  # the library's run_dir config
    out = tmp_path / "out"
    shutil.copytree(library.run_dir, out)
    shutil.rmtree(out / "report")
    inputs = {name: _sha(out / name) for name in ("captures.h5", "recon.h5")}
    for moment in REPORT_MOMENTS:
        mark = tmp_path / f"{moment}.mark"
        proc = _start(["run", config, "--out-dir", out, "-q"], tmp_path, CCA_TEST_WAIT_AT=f"{moment}:{mark}")
        deadline = time.monotonic() + 120
        while not mark.exists():
            assert proc.poll() is None and time.monotonic() < deadline, (moment, proc.communicate())
            time.sleep(0.01)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 130, (moment, err)
        lines = [line for line in err.splitlines() if line.strip() and "is up to date, skipped" not in line]
        assert len(lines) == 1 and lines[0].startswith("interrupted:"), (moment, err)
        assert _temporaries(out) == [] and not (out / ".cca-run.lock").exists(), moment
        assert not (out / "report").exists() or folder_complete(out / "report"), moment
        assert {name: _sha(out / name) for name in inputs} == inputs, moment
        shutil.rmtree(out / "report", ignore_errors=True)


@pytest.fixture
def scheduler(tmp_path):
    """A Dask scheduler and one single-threaded worker, each in its own process (so the scheduler can be killed)."""
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "cwd": tmp_path}
    processes = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                   "--port", str(port), "--no-dashboard"], **quiet)]
    processes.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                                       "--no-dashboard"], **quiet))
    from distributed import Client

    with Client(address, timeout="60s") as client:
        client.wait_for_workers(1, timeout=60)
    yield processes[0], address
    for process in processes:
        process.kill()
        process.wait()


def _kill_when(proc: subprocess.Popen, victim: subprocess.Popen, pattern: str, folder: Path) -> str:
    """SIGKILL ``victim`` once a file matching ``pattern`` exists under ``folder``; return ``proc``'s one line."""
    deadline = time.monotonic() + 300
    while not list(folder.glob(pattern)):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)
    victim.kill()
    out, err = proc.communicate(timeout=120)
    notes = "\n".join(line for line in err.splitlines() if not line.startswith("note:"))
    result = subprocess.CompletedProcess(proc.args, proc.returncode, out, notes)
    line = _one_line(result)
    assert proc.returncode == 1, err
    return line


def test_a_lost_scheduler_ends_a_tiled_reconstruction_in_one_line_and_keeps_the_finished_tiles(tmp_path, scheduler):
    from cca_cli.io.outputs import is_cca_hdf5

    process, address = scheduler
    config = _write_config(tmp_path / "cfg.yaml", simulate={"store": "sensor"},
                           reconstruct={"engine": "auto", "iterations": 3000, "tol": 0.0, "options": {"plateau": 0.0},
                                        "tiles": {"size_px": 40, "overlap_px": 16}})
    assert _run(["simulate", config, "-o", "c.h5", "-q"], tmp_path).returncode == 0
    proc = _start(["reconstruct", "c.h5", "-o", "r.h5", "-c", config, "-q", "--scheduler", address], tmp_path)
    line = _kill_when(proc, process, "r.h5.tiles/tile_*.h5", tmp_path)
    assert "lost the Dask scheduler" in line and "r.h5.tiles" in line, line
    kept = sorted((tmp_path / "r.h5.tiles").glob("tile_*.h5"))
    assert kept and all(is_cca_hdf5(path) for path in kept)
    assert not (tmp_path / "r.h5").exists() and _temporaries(tmp_path) == []


@pytest.mark.slow
def test_a_lost_scheduler_ends_a_sweep_in_one_line_and_keeps_the_finished_points(tmp_path, scheduler):
    process, address = scheduler
    config = _write_config(tmp_path / "cfg.yaml", reconstruct={"iterations": 3000})
    proc = _start(["sweep", "grid", config, "--set", "noise.snr_db=10,20,30", "--out-dir", "sw", "-q",
                   "--scheduler", address], tmp_path)
    line = _kill_when(proc, process, "sw/points/*/point.json", tmp_path)
    assert "lost the Dask scheduler" in line and "sw/points" in line, line
    done = [path.parent for path in (tmp_path / "sw" / "points").glob("*/point.json")]
    assert done and all(json.loads((d / "point.json").read_text())["result"]["status"] == "ok" for d in done)
    # the table of the finished points, the others pending, as after Ctrl-C
    with open(tmp_path / "sw" / "sweep.csv") as table:
        statuses = [row["status"] for row in csv.DictReader(table)]
    assert len(statuses) == 3 and statuses.count("ok") >= 1 and set(statuses) <= {"ok", "pending"}
    dry = _run(["sweep", "grid", config, "--set", "noise.snr_db=10,20,30", "--out-dir", "sw", "--dry-run"], tmp_path)
    assert dry.stdout.count("complete") == len(done), dry.stdout  # a re-run does only the others


@pytest.mark.slow
def test_ctrl_c_in_a_sweep_writes_the_table_of_the_points_finished_so_far(tmp_path):
    config = _write_config(tmp_path / "cfg.yaml", reconstruct={"iterations": 3000})
    args = ["sweep", "grid", config, "--set", "noise.snr_db=10,20,30,40,50,60", "--out-dir", "sw", "-q",
            "--workers", "2"]
    proc = _start(args, tmp_path)
    deadline = time.monotonic() + 300
    while not list((tmp_path / "sw" / "points").glob("*/point.json")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1].startswith("interrupted:") and "Traceback" not in err, err
    assert lines[-2].startswith("note: sw/sweep.csv holds the ") and "points finished so far" in lines[-2], err
    statuses = [line.split(",")[2] for line in (tmp_path / "sw" / "sweep.csv").read_text().splitlines()[1:]]
    assert len(statuses) == 6 and "ok" in statuses and "pending" in statuses, statuses
    assert set(statuses) <= {"ok", "pending"} and _temporaries(tmp_path / "sw") == []
