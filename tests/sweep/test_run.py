"""Running sweeps on a 2-worker LocalCluster: table, resume, failures, and the overlap watershed."""

from __future__ import annotations

import csv
import json
import logging
import os
import signal
import time

import h5py
import numpy as np
import pytest
from sweep_configs import tiny_config

from cca_cli.config.model import SweepSection
from cca_cli.errors import ctrl_c_pressed, noting_interrupts
from cca_cli.stages.sweep import expand_points, read_table, run_sweep, write_sweep_figures, write_table


def _run(client, spec, directory, **kwargs):
    base = tiny_config()
    points = expand_points(base, spec, directory)
    rows = run_sweep(points, client, **kwargs)
    write_table(rows, directory, spec=spec, base=base)
    return points, rows


def test_sweep_runs_on_two_workers_writes_table_and_resumes(client, tmp_path):
    spec = SweepSection(parameters={"array.overlap": [0.5, 0.61], "noise.snr_db": [20, 30]})
    seen = []
    points, rows = _run(client, spec, tmp_path, on_row=lambda row, done, total: seen.append((done, total)))
    assert [r["status"] for r in rows] == ["ok"] * 4
    assert seen[-1] == (4, 4)
    assert len(_workers(points)) == 2                                     # both workers took points
    for row, point in zip(rows, points):
        assert (point.out_dir / "report" / "report.json").exists()
        assert row["rmse_recovered"] > 0 and row["n_images"] == 9
        assert row["param:noise.seed"] == 10 + point.index

    with open(tmp_path / "sweep.csv") as handle:
        table = list(csv.DictReader(handle))
    assert [float(t["array.overlap"]) for t in table] == [0.5, 0.5, 0.61, 0.61]
    assert [float(t["noise.snr_db"]) for t in table] == [20, 30, 20, 30]
    h5rows = read_table(tmp_path / "sweep.h5")
    assert np.allclose([r["rmse_recovered"] for r in h5rows], [r["rmse_recovered"] for r in rows])
    with h5py.File(tmp_path / "sweep.h5") as handle:
        assert handle.attrs["stage"] == "sweep" and "array.overlap" in handle.attrs["config"]

    # an interruption: one point lost its reconstruction and left a temporary file behind
    lost = points[2]
    (lost.out_dir / "recon.h5").unlink()
    (lost.out_dir / "point.json").unlink()
    (lost.out_dir / ".recon.h5.tmp-123").write_bytes(b"partial")
    mtimes = {p.point_id: (p.out_dir / "captures.h5").stat().st_mtime_ns for p in points}
    recon_mtimes = {p.point_id: (p.out_dir / "recon.h5").stat().st_mtime_ns for p in points if p is not lost}
    points2, rows2 = _run(client, spec, tmp_path)
    assert [r["status"] for r in rows2] == ["cached", "cached", "ok", "cached"]
    stages = json.loads((lost.out_dir / "point.json").read_text())["result"]["stages"]
    assert stages == {"simulate": "skipped", "reconstruct": "ran", "report": "ran"}
    assert not (lost.out_dir / ".recon.h5.tmp-123").exists()
    assert {p.point_id: (p.out_dir / "captures.h5").stat().st_mtime_ns for p in points} == mtimes
    assert {p.point_id: (p.out_dir / "recon.h5").stat().st_mtime_ns for p in points if p is not lost} == recon_mtimes
    assert [r["rmse_recovered"] for r in rows2] == [r["rmse_recovered"] for r in rows]  # same seeds → same numbers

    # a third run recomputes nothing; --force recomputes everything
    _, rows3 = _run(client, spec, tmp_path)
    assert {r["status"] for r in rows3} == {"cached"}
    _, rows4 = _run(client, SweepSection(parameters={"array.overlap": [0.5]}, points=[{"noise.snr_db": 20}]),
                    tmp_path, force=True)
    assert rows4[0]["status"] == "ok"


def _workers(points):
    return {json.loads((p.out_dir / "point.json").read_text())["result"]["worker"] for p in points}


def test_failing_point_is_recorded_and_others_finish(client, tmp_path):
    # size_px 20 cannot hold the chart (fails on the worker); overlap 1.5 is invalid (fails at expansion)
    spec = SweepSection(points=[{"scene.size_px": 64}, {"scene.size_px": 20}, {"array.overlap": 1.5},
                                {"array.overlap": 0.5}])
    points, rows = _run(client, spec, tmp_path)
    assert [r["status"] for r in rows] == ["ok", "failed", "failed", "ok"]
    assert "does not fit" in rows[1]["error"] and "\n" not in rows[1]["error"]
    assert "array.overlap" in rows[2]["error"]
    with open(tmp_path / "sweep.csv") as handle:
        table = list(csv.DictReader(handle))
    assert [t["status"] for t in table] == ["ok", "failed", "failed", "ok"]
    assert table[0]["rmse_recovered"] and not table[1]["rmse_recovered"]


def test_small_overlap_study_fails_at_zero_and_recovers_above_sixty(client, tmp_path):
    base = tiny_config(reconstruct={"iterations": 150, "tol": 1e-5})
    spec = SweepSection(study="overlap", x="array.overlap",
                        points=[{"array.overlap": 0.0, "array.grid": 5}, {"array.overlap": 0.61, "array.grid": 11},
                                {"array.overlap": 0.75, "array.grid": 17}])
    points = expand_points(base, spec, tmp_path)
    rows = run_sweep(points, client)
    rmse = {r["param:array.overlap"]: r["rmse_recovered"] for r in rows}
    observed = rows[0]["rmse_observed"]
    assert rmse[0.0] > observed                   # no overlap: worse than the single centre image
    assert rmse[0.61] < 0.75 * observed and rmse[0.75] < 0.75 * observed
    assert rmse[0.0] > 1.5 * max(rmse[0.61], rmse[0.75])
    figures = write_sweep_figures(rows, tmp_path, spec=spec, points=points)
    names = {f.name for f in figures}
    assert {"rmse_vs_array_overlap.png", "contrast_vs_width.png", "montage.png"} <= names
    assert all(f.stat().st_size > 5000 for f in figures)


def test_a_second_sweep_into_the_folder_adds_its_points_to_the_table(client, tmp_path):
    import pytest

    from cca_cli.errors import OutputExistsError
    from cca_cli.stages.sweep import earlier_points, earlier_rows

    base = tiny_config()
    first = SweepSection(parameters={"noise.snr_db": [10, 20]})
    _run(client, first, tmp_path)
    second = SweepSection(parameters={"noise.snr_db": [30, 40]})
    points = expand_points(base, second, tmp_path)
    earlier = earlier_points(base, second, points, tmp_path)
    assert [p.overrides["noise.snr_db"] for p in earlier] == [10, 20]
    rows = earlier_rows(earlier) + run_sweep(points, client)
    write_table(rows, tmp_path, spec=second, base=base)
    figures = write_sweep_figures(rows, tmp_path, spec=second, points=earlier + points)
    table = read_table(tmp_path / "sweep.h5")
    assert [r["noise.snr_db"] for r in table] == [10, 20, 30, 40]
    assert [r["status"] for r in table] == ["cached", "cached", "ok", "ok"]
    assert {f.name for f in figures} >= {"rmse_vs_noise_snr_db.png", "montage.png"}
    # every row its own index and noise draw: the new points follow the folder's last
    assert [r["index"] for r in table] == [0, 1, 2, 3]
    assert [r["noise.seed"] for r in table] == [base.noise.seed + i for i in range(4)]
    # run again, a sweep's points are found where they are (the same indices, seeds and results)
    again = expand_points(base, first, tmp_path)
    assert [(p.index, p.point_id) for p in again] == [(0, earlier[0].point_id), (1, earlier[1].point_id)]
    assert [p.index for p in expand_points(base, SweepSection(parameters={"noise.snr_db": [40, 25]}), tmp_path)] \
        == [3, 4]

    # points of an older cca (no overrides in point.json) are found through the table
    for point in earlier:
        record = json.loads((point.out_dir / "point.json").read_text())
        del record["overrides"], record["index"]
        (point.out_dir / "point.json").write_text(json.dumps(record, indent=2))
    third = SweepSection(parameters={"noise.snr_db": [50]})
    found = earlier_points(base, third, expand_points(base, third, tmp_path), tmp_path)
    assert [p.overrides["noise.snr_db"] for p in found] == [10, 20, 30, 40]

    # another base config or another study: refused, unless --force (which keeps only this config's points)
    other = tiny_config(reconstruct={"iterations": 7})
    with pytest.raises(OutputExistsError, match="another base config"):
        earlier_points(other, third, expand_points(other, third, tmp_path), tmp_path)
    assert earlier_points(other, third, expand_points(other, third, tmp_path), tmp_path, force=True) == []
    noise = SweepSection(study="noise", parameters={"noise.snr_db": [50]})
    with pytest.raises(OutputExistsError, match="noise"):
        earlier_points(base, noise, expand_points(base, noise, tmp_path), tmp_path)


def test_what_the_clients_event_loop_logs_after_ctrl_c_is_not_shown(client, caplog):
    # distributed's sync() answers a Ctrl-C that comes before its call started with a NameError in the loop's
    # thread, which tornado logs as "Exception in callback"; the user already has the one "interrupted:" line
    loop_log = logging.getLogger("tornado.application")
    with caplog.at_level(logging.ERROR, logger="tornado.application"):
        with noting_interrupts():
            loop_log.error("a failure before Ctrl-C")
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(5)
            assert ctrl_c_pressed()
            loop_log.error("Exception in callback functools.partial(<function sync.<locals>.cancel>)")
        assert not ctrl_c_pressed()
        loop_log.error("a failure in the next command")
    assert [r.getMessage() for r in caplog.records] == ["a failure before Ctrl-C", "a failure in the next command"]
