"""Where outputs may go, atomic writes that keep the old version, stale temporaries, the run lock."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cca_cli.errors import OutputError, OutputExistsError, ResourceError, RunLockedError
from cca_cli.io.h5 import Provenance, atomic_h5, write_dataset
from cca_cli.io.lock import LOCK_NAME, folder_lock
from cca_cli.io.outputs import (MARKER, atomic_path, check_output, folder_complete, foreign_part,
                                remove_stale_temporaries, write_marker)


def _cca_file(path, value=1.0):
    with atomic_h5(path, Provenance.make("simulate", "", "x"), force=True) as handle:
        write_dataset(handle, "/measurements/intensity", np.full((1, 2, 2), value, np.float32))


def _report(folder):
    folder.mkdir()
    (folder / "report.json").write_text("{}")
    (folder / "a.png").write_bytes(b"png")
    write_marker(folder, "report")


def test_force_replaces_only_what_cca_wrote(tmp_path):
    mine, theirs = tmp_path / "mine.h5", tmp_path / "theirs.h5"
    _cca_file(mine)
    theirs.write_bytes(b"\x89HDF\r\n\x1a\nnot really")
    check_output(mine, force=True)
    with pytest.raises(OutputExistsError, match="--force"):
        check_output(mine, force=False)
    with pytest.raises(OutputError, match="cca did not write it"):
        check_output(theirs, force=True)
    report = tmp_path / "report"
    _report(report)
    assert foreign_part(report) is None and folder_complete(report)
    check_output(report, force=True, kind="folder")
    (report / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="notes.txt"):
        check_output(report, force=True, kind="folder")
    (report / "notes.txt").unlink()
    (report / "a.png").unlink()
    assert foreign_part(report) is None and not folder_complete(report)


def test_outputs_that_are_inputs_or_hold_them_or_hold_the_current_folder(tmp_path, monkeypatch):
    data = tmp_path / "exp" / "data.h5"
    data.parent.mkdir()
    _cca_file(data)
    os.link(data, tmp_path / "hard.h5")
    for output, kind in ((data, "file"), (tmp_path / "exp" / ".." / "exp" / "data.h5", "file"),
                         (tmp_path / "hard.h5", "file"), (tmp_path / "exp", "folder")):
        with pytest.raises(OutputError, match="input"):
            check_output(output, force=True, kind=kind, inputs=[data])
    monkeypatch.chdir(tmp_path / "exp")
    for output in (".", "..", str(tmp_path)):
        with pytest.raises(OutputError, match="current folder"):
            check_output(output, force=True, kind="folder")
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a file, not a folder"):
        check_output(tmp_path / "file" / "out.h5", force=False)
    with pytest.raises(OutputError, match="cannot write"):
        check_output("/proc/cca-out.h5", force=False)


def test_a_failed_folder_write_keeps_the_old_folder(tmp_path):
    report = tmp_path / "report"
    _report(report)
    before = sorted(p.name for p in report.iterdir())
    with pytest.raises(RuntimeError):
        with atomic_path(report, force=True, kind="folder") as tmp:
            tmp.mkdir()
            (tmp / "half.png").write_bytes(b"")
            raise RuntimeError("the figures failed")
    assert sorted(p.name for p in report.iterdir()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_a_full_disk_during_an_hdf5_write_is_one_error_and_the_old_file_stays(tmp_path, monkeypatch):
    import errno

    from cca_cli.io import h5

    path = tmp_path / "c.h5"
    _cca_file(path, 1.0)
    before = path.read_bytes()
    real_init = h5._DiskSink.__init__

    def full(self, target):
        real_init(self, target)

        class Full:
            def __getattr__(self, name):
                return getattr(self.raw, name)

            def write(self, data):
                raise OSError(errno.ENOSPC, "No space left on device")

        wrapper = Full()
        wrapper.raw = self._file
        self._file = wrapper

    monkeypatch.setattr(h5._DiskSink, "__init__", full)
    with pytest.raises(ResourceError, match="previous version is kept"):
        _cca_file(path, 2.0)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]


def test_only_cca_temporaries_of_dead_processes_are_removed(tmp_path):
    dead = 4_194_309
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        names = [f".captures.h5.tmp-{dead}", f".report.tmp-{dead}", f".recon.h5.tmp-{child.pid}",
                 f".notes.txt.tmp-{dead}", "captures.h5.tmp-1"]
        for name in names:
            (tmp_path / name).write_text("x")
        removed = remove_stale_temporaries(tmp_path)
        assert sorted(p.name for p in removed) == sorted(names[:2])
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names[2:])
    finally:
        child.kill()
        child.wait()


def test_one_run_per_folder_and_a_dead_runs_lock_is_taken_over(tmp_path):
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": 4_194_309}))  # left by a killed run
    with folder_lock(tmp_path) as lock:
        assert json.loads(lock.read_text())["pid"] == os.getpid()
        with pytest.raises(RunLockedError, match=f"pid {os.getpid()}"):
            with folder_lock(tmp_path):
                pass
    assert not (tmp_path / LOCK_NAME).exists()
    with folder_lock(tmp_path):
        pass
    assert MARKER not in os.listdir(tmp_path)
