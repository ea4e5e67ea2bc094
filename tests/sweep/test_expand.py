"""Expanding a sweep spec into points: products, explicit points, seeds, key and value errors."""

from __future__ import annotations

from pathlib import Path

import pytest
from sweep_configs import tiny_config
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.config.model import SweepSection
from cca_cli.errors import ConfigError
from cca_cli.stages.sweep import PAPER_STUDIES, expand_points, parse_set, point_cost, study_spec


def test_cartesian_product_of_parameters(tmp_path):
    spec = SweepSection(parameters={"array.overlap": [0.0, 0.41, 0.61], "noise.snr_db": [10, 30]})
    points = expand_points(tiny_config(), spec, tmp_path)
    assert len(points) == 6
    combos = {(p.overrides["array.overlap"], p.overrides["noise.snr_db"]) for p in points}
    assert combos == {(o, s) for o in (0.0, 0.41, 0.61) for s in (10, 30)}
    for p in points:
        assert p.config.array.overlap == p.overrides["array.overlap"]
        assert p.config.noise.snr_db == p.overrides["noise.snr_db"]
        assert p.config.noise.seed == 10 + p.index           # base seed + index
        assert p.config.reconstruct.options["threads"] == 1  # no oversubscription
        assert p.out_dir == tmp_path / "points" / p.point_id
        assert p.config.run.out_dir == p.out_dir
    assert len({p.point_id for p in points}) == 6
    # the same spec gives the same directories (so a re-run finds its points)
    again = expand_points(tiny_config(), spec, tmp_path)
    assert [p.point_id for p in again] == [p.point_id for p in points]


def test_explicit_points_crossed_with_parameters_and_explicit_seed(tmp_path):
    spec = SweepSection(points=[{"array.overlap": 0.0, "array.grid": 3}, {"array.overlap": 0.75, "array.grid": 5}],
                        parameters={"noise.seed": [7]})
    points = expand_points(tiny_config(), spec, tmp_path)
    assert [(p.config.array.overlap, p.config.array.grid, p.config.noise.seed) for p in points] == [
        (0.0, 3, 7), (0.75, 5, 7)]
    assert point_cost(points[1]).images == 25


@pytest.mark.parametrize("key", ["array.bogus", "nosuch.key", "sweep.study", "overlap"])
def test_bad_key_names_the_key(tmp_path, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        expand_points(tiny_config(), SweepSection(parameters={key: [1, 2]}), tmp_path)


def test_invalid_value_marks_only_that_point(tmp_path):
    points = expand_points(tiny_config(), SweepSection(parameters={"array.overlap": [0.5, 1.5]}), tmp_path)
    assert points[0].error is None and points[0].config is not None
    assert points[1].config is None and "array.overlap" in points[1].error


def test_parse_set_and_study_spec():
    assert parse_set("array.overlap=0,0.2,0.41") == ("array.overlap", [0, 0.2, 0.41])
    assert parse_set("noise.model=none,gaussian") == ("noise.model", ["none", "gaussian"])
    with pytest.raises(ConfigError, match="key=value"):
        parse_set("array.overlap")
    spec = study_spec(tiny_config(), "grid", sets=["array.grid=3,5"])
    assert spec.parameters == {"array.grid": [3, 5]}
    assert study_spec(tiny_config(), "overlap") == PAPER_STUDIES["overlap"]
    with pytest.raises(ConfigError, match="nothing to sweep"):
        study_spec(tiny_config(), "grid")
    with pytest.raises(ConfigError, match="sweep.study is 'sar'"):
        study_spec(tiny_config(sweep={"study": "sar", "parameters": {"array.grid": [1, 3]}}), "overlap")


def test_paper_overlap_study_holds_sar_near_ten():
    from cca_cli.sampling.overlap import synthetic_aperture_ratio

    for point in PAPER_STUDIES["overlap"].points:
        assert point["array.grid"] % 2 == 1
        assert 9.0 <= synthetic_aperture_ratio(point["array.grid"], point["array.overlap"]) <= 10.7


def test_shipped_study_configs_expand(tmp_path):
    from cca_cli.config.load import load_config

    root = Path(__file__).resolve().parents[2] / "configs"
    sizes = {"study_overlap.yaml": 7, "study_sar.yaml": 6, "study_noise.yaml": 18}
    for name, n in sizes.items():
        cfg = load_config(root / name)
        spec = study_spec(cfg, cfg.sweep.study, source=name)
        points = expand_points(cfg, spec, tmp_path)
        assert len(points) == n and all(p.error is None for p in points)


def test_dry_run_lists_points_and_runs_nothing(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(tiny_config().model_dump_json())
    result = CliRunner().invoke(app, ["sweep", "grid", str(config), "--set", "array.overlap=0,0.61",
                                      "--set", "noise.snr_db=10,20", "--dry-run", "--out-dir", str(tmp_path / "s")])
    assert result.exit_code == 0, result.output
    assert "4 points" in result.output and "36 images" in result.output
    assert not (tmp_path / "s").exists()
    bad = CliRunner().invoke(app, ["sweep", "grid", str(config), "--set", "array.nope=1", "--dry-run"])
    assert bad.exit_code == 2 and "array.nope" in bad.output


def test_a_chart_that_does_not_fit_is_an_invalid_point_before_anything_runs(tmp_path):
    base = tiny_config()
    size = base.scene.size_px
    spec = SweepSection(parameters={"scene.widths_px": [[2], [size]]})
    fits, too_wide = expand_points(base, spec, tmp_path)
    assert fits.error is None
    assert "does not fit" in too_wide.error and "scene.widths_px" in too_wide.error
    config = tmp_path / "c.yaml"
    config.write_text(base.model_dump_json())
    every = CliRunner().invoke(app, ["sweep", "grid", str(config), "--set", f"scene.widths_px=[{size}]", "--dry-run",
                                     "--out-dir", str(tmp_path / "s")])
    assert every.exit_code == 2 and "1 of 1 points of the sweep are invalid, so none ran" in every.output
    some = CliRunner().invoke(app, ["sweep", "grid", str(config), "--set", "array.grid=3,nine",
                                    "--out-dir", str(tmp_path / "s2")])
    text = " ".join(some.output.split())
    assert some.exit_code == 2 and "1 of 2 points of the sweep are invalid, so none ran" in text, some.output
    assert "(array.grid=nine" in text and "must be a whole number" in text and not (tmp_path / "s2").exists()


def test_a_dask_scheduler_is_recognised_and_other_servers_are_refused_in_bounded_time(client):
    import http.server
    import threading
    import time

    from cca_cli.errors import ConfigError
    from cca_cli.stages.sweep import check_scheduler

    check_scheduler(client.scheduler.address, 10)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        start = time.perf_counter()
        with pytest.raises(ConfigError, match="--scheduler"):
            check_scheduler(f"tcp://127.0.0.1:{server.server_address[1]}", 1)
        assert time.perf_counter() - start < 5
    finally:
        server.shutdown()


def test_a_number_column_missing_in_every_row_is_stored_as_numbers(tmp_path):
    import h5py
    import numpy as np

    from cca_cli.stages.sweep import read_table, write_table

    rows = [{"point_id": f"p{i}", "index": i, "status": "ok", "param:noise.snr_db": 10 * (i + 1),
             "mtf20_observed_px": None, "resolution_gain": None, "mtf20_recovered_px": 2} for i in range(2)]
    write_table(rows, tmp_path, spec=SweepSection(parameters={"noise.snr_db": [10, 20]}), base=tiny_config())
    with h5py.File(tmp_path / "sweep.h5") as handle:
        for name in ("mtf20_observed_px", "resolution_gain"):
            data = handle[f"table/{name}"]
            assert data.dtype == np.float64 and np.isnan(data[()]).all(), name
            assert data.attrs["units"] != "text"
    assert [r["mtf20_observed_px"] for r in read_table(tmp_path / "sweep.h5")] == [None, None]
