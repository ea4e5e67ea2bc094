"""Tiled reconstruction on Dask: it matches the whole-frame recovery, resumes only unfinished tiles, reports its tiles."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from cca_cli.config.model import ReconstructSection
from cca_cli.errors import ConfigError
from cca_cli.io.h5 import Provenance
from cca_cli.io.tiles import remove_tile_folder, tile_folder, tile_path
from cca_cli.report.summary import band_limited_truth, on_grid
from cca_cli.metrics import rmse
from cca_cli.stages import reconstruct as stage
from cca_cli.workflows.tiled import plan_tiled, reconstruct_tiled


def _band_rmse(recon_path) -> float:
    from cca_cli.io.geometry import read_geometry

    with h5py.File(recon_path, "r") as f:
        truth = np.asarray(f["/truth/object"])
        recovered = np.asarray(f["/recon/intensity"])
        geometry = read_geometry(f)
    band = band_limited_truth(truth, geometry)
    return rmse(on_grid(recovered, band.shape[-1]), band)


@pytest.fixture(scope="module")
def tiled_run(tmp_path_factory, frame_captures, frame_config, client):
    out = tmp_path_factory.mktemp("tiled") / "recon.h5"
    provenance = Provenance.make("reconstruct", "", "", [frame_captures])
    tiled = stage.run_tiled(frame_captures, frame_config.reconstruct, out, provenance=provenance, client=client)
    return out, tiled


def test_tiles_join_without_loss_against_the_whole_frame(tiled_run, frame_captures, frame_config, tmp_path):
    out, tiled = tiled_run
    assert len(tiled.results) == 4 and tiled.ran == 4
    whole = tmp_path / "whole.h5"
    section = frame_config.reconstruct.model_copy(update={"tiles": None})
    stage.run(frame_captures, section, whole, provenance=Provenance.make("reconstruct", "", "", [frame_captures]))
    tiled_error, whole_error = _band_rmse(out), _band_rmse(whole)
    print(f"band-limited RMSE: tiles {tiled_error:.4f}, whole frame {whole_error:.4f}")
    assert tiled_error < 1.5 * whole_error + 0.005, (tiled_error, whole_error)
    assert not tile_folder(out).exists()         # the tile files go once recon.h5 is written


def _undescribed(path) -> list[str]:
    missing = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset) and not (obj.attrs.get("units") is not None
                                                  and str(obj.attrs.get("description", "")).strip()):
            missing.append(name)

    with h5py.File(path, "r") as handle:
        handle.visititems(visit)
    return missing


def test_tiled_recon_describes_every_tile(tiled_run):
    out, tiled = tiled_run
    assert _undescribed(out) == []
    with h5py.File(out, "r") as f:
        boxes = np.asarray(f["/tiles/box_px"])
        assert boxes.shape == (4, 4) and set(boxes[:, 2]) == {96}
        assert f["/tiles/zernike_waves"].shape[0] == 4 and f["/tiles/pupil"].shape[0] == 4
        for name in ("box_px", "residual", "iterations", "seconds", "zernike_waves", "pupil"):
            assert f[f"/tiles/{name}"].attrs["units"] is not None and f[f"/tiles/{name}"].attrs["description"]
        assert f["/recon/object"].shape == (160 * tiled.plan.upsampling,) * 2
        assert np.all(np.isfinite(f["/tiles/residual"][:, 0])) and 0 < f["recon"].attrs["residual_all_tile_median"] < 0.2


def test_report_maps_the_tiles(tiled_run, tmp_path):
    from cca_cli.config.model import ReportSection
    from cca_cli.stages import report

    out, _ = tiled_run
    summary = report.run(out, ReportSection(), tmp_path / "report", provenance=Provenance.make("report", "", ""))
    assert summary["tiles"]["count"] == 4 and summary["tiles"]["grid"] == [2, 2]
    assert "defocus" in summary["tiles"]["zernike_waves_min_median_max"]
    assert (tmp_path / "report" / "tiles.png").stat().st_size > 10_000
    assert "tiles.png" in json.loads((tmp_path / "report" / "report.json").read_text())["figures"]
    from cca_cli.commands.console import summary_table

    labels = [str(cell) for cell in summary_table(summary).columns[0].cells]
    assert "tiles: data residual, median / max" in labels and "tiles: defocus (waves), min / median / max" in labels


def test_a_stopped_run_recovers_only_its_unfinished_tiles(tmp_path, frame_captures, frame_config, client):
    out = tmp_path / "recon.h5"
    provenance = Provenance.make("reconstruct", "", "", [frame_captures])
    first = reconstruct_tiled(frame_captures, frame_config.reconstruct, out, run_fingerprint="abc",
                              provenance=provenance, client=client)
    assert first.ran == 4
    tile_path(out, 1, 1).unlink()                 # as if the run had been killed before this tile finished
    foreign = tile_folder(out) / "notes.txt"
    foreign.write_text("mine")
    again = reconstruct_tiled(frame_captures, frame_config.reconstruct, out, run_fingerprint="abc",
                              provenance=provenance, client=client)
    assert again.ran == 1
    assert _undescribed(tile_path(out, 1, 1)) == []
    np.testing.assert_allclose(again.object, first.object, atol=1e-3 * np.abs(first.object).max())
    other = reconstruct_tiled(frame_captures, frame_config.reconstruct, out, run_fingerprint="other options",
                              provenance=provenance, client=client)
    assert other.ran == 4                          # files of other inputs or options are not reused
    remove_tile_folder(out)
    assert foreign.read_text() == "mine" and not tile_path(out, 0, 0).exists()


def test_tile_options_are_checked_before_anything_runs(frame_captures):
    with pytest.raises(ConfigError, match="reconstruct.tiles: .*at most 160 px"):
        plan_tiled(frame_captures, ReconstructSection(tiles={"size_px": 200, "overlap_px": 32}))
    with pytest.raises(ConfigError, match="reconstruct.init"):
        plan_tiled(frame_captures, ReconstructSection(tiles={"size_px": 96, "overlap_px": 32}, init="x.h5"))


def test_python_api_recovers_tiles_from_arrays(frame_captures, client, tmp_path):
    from cca_cli import api

    captures = api.load(frame_captures)
    result = api.reconstruct_tiles(api.CaptureSet(captures.intensity, captures.geometry), size_px=96, overlap_px=32,
                                   engine="momentum", iterations=10, client=client, output=tmp_path / "recon.h5",
                                   pupil_recovery="shared", pupil_model="zernike", pupil_estimate=False)
    assert result.object.shape == (160 * result.upsampling,) * 2 and result.boxes_px.shape == (4, 4)
    assert result.zernike_waves.shape[:2] == (4, 1) and np.all(np.isfinite(result.residual[:, 0]))
    assert np.isclose(result.pixel_size_m * result.upsampling, captures.geometry.field_width_m / 160)
    assert isinstance(api.load(tmp_path / "recon.h5"), api.Reconstruction)
    with pytest.raises(ValueError, match="overlap_px"):
        api.reconstruct_tiles(frame_captures, size_px=96, overlap_px=60, client=client)


def test_local_workers_leave_ctrl_c_to_the_cca_process(client):
    """Ctrl-C reaches the whole process group: a local worker ignores it (no Dask tracebacks), cca stops them."""
    import signal

    from cca_cli.workflows.worker_setup import dask_setup

    handlers = client.run(lambda: signal.getsignal(signal.SIGINT))
    assert len(handlers) == 2 and all(h == signal.SIG_IGN for h in handlers.values())
    before = signal.getsignal(signal.SIGINT)
    try:
        dask_setup(None)
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def test_workers_resolve_the_engine_as_the_client_does():
    from cca_cli.workflows.tiled import task_section, tile_engine

    for data in ({"tiles": {"size_px": 96, "overlap_px": 32}},
                 {"engine": "momentum", "iterations": 40, "tiles": {"size_px": 96, "overlap_px": 32}}):
        section = ReconstructSection.model_validate(data)
        on_worker = ReconstructSection.model_validate(task_section(section))
        for kind in ("camera_scan", "led_array", "simulation"):
            assert tile_engine(on_worker, kind) == tile_engine(section, kind)
    name, options = tile_engine(ReconstructSection.model_validate(
        task_section(ReconstructSection(tiles={"size_px": 96, "overlap_px": 32}))), "camera_scan")
    assert options.max_iterations == 150 and options.threads == 1   # the preset's cap, one thread per tile


def test_tiles_of_a_defocused_lens_find_its_defocus(tmp_path, client):
    """Each tile is a window in a guard band: the first tile's starting estimate must see the shifts the defocus
    makes between neighbouring captures, not the band's edges (which held it at zero and the tiles at 0.07-0.1 of
    0.25 waves)."""
    import copy

    from cca_cli import api
    from cca_cli.config.load import parse_config
    from cca_cli.stages import simulate

    from .conftest import FRAME_CONFIG

    data = copy.deepcopy(FRAME_CONFIG)
    data["aberration"] = {"defocus_waves": 0.25}
    config = parse_config(data, source="defocused frame")
    path = tmp_path / "captures.h5"
    simulate.run(config, path, provenance=Provenance.make("simulate", "", ""))
    result = api.reconstruct_tiles(path, size_px=96, overlap_px=32, engine="momentum", iterations=40, tol=0.0,
                                   client=client, pupil_recovery="shared", pupil_model="zernike")
    defocus = result.zernike_waves[:, 0, 0]
    assert np.all(np.abs(defocus - 0.25) < 0.04), defocus


def test_dead_captures_are_judged_on_the_whole_frame_and_left_out_of_every_tile(tmp_path, frame_captures,
                                                                                 frame_config, monkeypatch, caplog):
    """A capture whose whole frame holds one value is left out of every tile; one dark in a tile only is kept."""
    import shutil

    from cca_cli.errors import InputError
    from cca_cli.workflows import tiled

    path = tmp_path / "captures.h5"
    shutil.copy(frame_captures, path)
    with h5py.File(path, "r+") as f:
        images = f["/measurements/intensity"]
        k = images.shape[0]
        dead, dark_in_a_tile = 0, 1                # corner LEDs of the 5 × 5 grid (the centre is 12)
        images[dead] = 0.0
        images[dark_in_a_tile, :96, :96] = 0.0
    section = frame_config.reconstruct
    with caplog.at_level("WARNING", logger="cca"):
        plan = tiled.without_dead_frames(plan_tiled(path, section))
    assert plan.dropped == (dead,)
    assert "left out 1 of 25 images" in caplog.text

    seen = []
    real_recover = tiled.recover
    monkeypatch.setattr(tiled, "recover", lambda captures, *a, **k: seen.append(captures.intensity.shape[0])
                        or real_recover(captures, *a, **k))
    corner = plan.tiles.tiles[0]
    task = tiled.TileTask(plan=plan, section=tiled.task_section(section), tile=corner, output=str(tmp_path / "r.h5"),
                          fingerprint="f", provenance={}, topic="t")
    result = tiled.run_tile(task)
    assert seen == [k - 1] and result.iterations == 40

    with h5py.File(path, "r+") as f:
        f["/measurements/intensity"][12] = 3.0     # the centre capture dead too: refused, in one line
    with pytest.raises(InputError, match="centre capture"):
        tiled.without_dead_frames(plan_tiled(path, section))


def test_a_tile_runs_on_the_device_the_section_names_and_says_so(tmp_path, frame_captures, frame_config, monkeypatch):
    """reconstruct.device reaches every tile's engine (numpy standing in for CuPy here); the tile file keeps it."""
    from cca_cli.io.tiles import read_tile_result
    from cca_cli.optics import backend
    from cca_cli.workflows import tiled

    monkeypatch.setattr(backend, "device_status", lambda: backend.DeviceStatus(True, "numpy standing in"))
    monkeypatch.setattr(backend, "array_module", lambda device: np)
    results = {}
    for device in ("cpu", "cuda"):
        section = frame_config.reconstruct.model_copy(update={"device": device})
        plan = tiled.without_dead_frames(plan_tiled(frame_captures, section))
        task = tiled.TileTask(plan=plan, section=tiled.task_section(section), tile=plan.tiles.tiles[0],
                              output=str(tmp_path / f"{device}.h5"), fingerprint="f",
                              provenance=dict(Provenance.make("reconstruct", "", "", [frame_captures])), topic="t")
        results[device] = tiled.run_tile(task)
        assert results[device].device == device
        assert read_tile_result(tile_path(tmp_path / f"{device}.h5", 0, 0)).device == device
    cpu, gpu = (results[d].residual["all"] for d in ("cpu", "cuda"))
    assert gpu < 1.2 * cpu + 0.01, (gpu, cpu)


def test_local_workers_spread_over_the_gpus_and_others_keep_theirs(monkeypatch):
    """cca's local worker n takes GPU n mod count; a worker of an existing cluster keeps its launcher's GPU."""
    import contextlib
    import types

    import distributed

    from cca_cli.optics import backend
    from cca_cli.workflows import tiled
    from cca_cli.workflows.worker_setup import LOCAL_WORKER, dask_setup

    assert [backend.gpu_for_worker(n, 2) for n in range(4)] == [0, 1, 0, 1]
    with pytest.raises(ValueError):
        backend.gpu_for_worker(0, 0)
    chosen = []
    monkeypatch.setattr(backend, "gpu_count", lambda: 2)
    monkeypatch.setattr(backend, "using_gpu", lambda index: chosen.append(index) or contextlib.nullcontext())
    monkeypatch.setattr(distributed, "get_worker", lambda: types.SimpleNamespace(name=3))
    monkeypatch.delenv(LOCAL_WORKER, raising=False)
    with tiled._worker_gpu("cuda"):           # an existing cluster's worker: its launcher's GPU
        pass
    assert chosen == []
    with monkeypatch.context() as patch:
        patch.setattr("signal.signal", lambda *a: None)
        dask_setup(None)                         # what cca's local workers run as they start
    assert chosen == [] and __import__("os").environ[LOCAL_WORKER] == "1"
    for device in ("cpu", "cuda"):
        with tiled._worker_gpu(device):
            pass
    assert chosen == [1]                          # worker 3 of cca's local cluster, 2 GPUs, device cuda only
    monkeypatch.delenv(LOCAL_WORKER)


@pytest.mark.parametrize("gpus, cores, gib, expected", [(1, 16, 139, 16), (1, 16, 8, 4), (1, 2, 80, 2),
                                                          (2, 16, 80, 16), (4, 2, 80, 4), (1, 16, 1, 1)])
def test_a_tiled_run_on_gpus_starts_a_worker_per_core_that_their_memory_holds(monkeypatch, gpus, cores, gib,
                                                                              expected):
    from cca_cli.optics import backend, fft
    from cca_cli.workflows import tiled

    monkeypatch.setattr(backend, "gpu_count", lambda: gpus)
    monkeypatch.setattr(backend, "gpu_memory_bytes", lambda: gib << 30)
    monkeypatch.setattr(fft, "cpu_count", lambda: cores)
    assert tiled.local_tile_workers(None, None, "cuda") == expected
    assert tiled.local_tile_workers(None, None, "cpu") is None          # one per core, the cluster's default
    assert tiled.local_tile_workers(3, None, "cuda") == 3               # --workers as asked
    assert tiled.local_tile_workers(None, "tcp://host:8786", "cuda") is None


@pytest.mark.gpu
def test_tiles_on_the_gpu_match_the_cpu_tiles(tmp_path, frame_captures, frame_config, client):
    """The same tiled run on the GPU and on the CPU: the same tiles, the blended objects alike."""
    from cca_cli.optics import backend

    if not backend.device_status().cuda:
        pytest.skip(f"needs CuPy and a CUDA GPU ({backend.device_status().summary})")
    provenance = Provenance.make("reconstruct", "", "", [frame_captures])
    objects = {}
    for device in ("cpu", "cuda"):
        section = frame_config.reconstruct.model_copy(update={"device": device})
        run = reconstruct_tiled(frame_captures, section, tmp_path / f"{device}.h5", run_fingerprint=device,
                                provenance=provenance, client=client)
        assert {r.device for r in run.results} == {device}
        objects[device] = run.object
    peak = np.abs(objects["cpu"]).max()
    assert np.abs(np.abs(objects["cuda"]) - np.abs(objects["cpu"])).max() < 0.05 * peak


def test_the_api_refuses_tiles_on_a_gpu_it_lacks_before_any_tile_runs(frame_captures, monkeypatch, tmp_path):
    from cca_cli import api
    from cca_cli.optics import backend

    monkeypatch.setattr(backend, "device_status", lambda: backend.DeviceStatus(False, "cpu only: CuPy not installed"))
    with pytest.raises(ValueError, match=r"^device: device cuda needs CuPy .*device cpu"):
        api.reconstruct_tiles(frame_captures, size_px=96, overlap_px=32, device="cuda", output=tmp_path / "r.h5")
    assert not (tmp_path / "r.h5").exists() and not tile_folder(tmp_path / "r.h5").exists()


def test_a_simulation_s_aberration_is_read_at_each_tile_and_compared(tmp_path):
    """The lens's Zernike modes at the tiles' centres (bilinear between the field points), their error in
    report.json and a second row of maps in tiles.png."""
    from cca_cli.report.figures import write_tile_figure
    from cca_cli.stages.report import tiles_summary, truth_at_tiles

    nodes = np.array([0.0, 99.0])
    waves = np.zeros((2, 2, 5))
    waves[..., 0] = [[0.0, 0.2], [0.2, 0.4]]          # defocus grows towards the far corner
    boxes = np.array([[0, 0, 50, 50], [0, 50, 50, 50], [50, 0, 50, 50], [50, 50, 50, 50]])
    names = ["defocus", "astigmatism_0", "astigmatism_45"]
    tiles = {"box_px": boxes, "residual": np.full(4, 0.05), "iterations": np.full(4, 10), "seconds": np.ones(4),
             "attrs": {"rows": 2, "cols": 2}, "zernike_names": names,
             "zernike_waves": np.array([[0.05, 0, 0], [0.1, 0, 0], [0.1, 0, 0], [0.2, 0, 0]])}
    truth = truth_at_tiles({"aberration_waves": waves, "aberration_nodes_px": nodes}, tiles)
    centres = boxes[:, :2] + 24.5                      # bilinear: 0.2 (y + x) / 99 on this field
    np.testing.assert_allclose(truth["defocus"], 0.2 * centres.sum(axis=1) / 99.0, rtol=1e-12)
    assert set(truth) == set(names)
    assert truth_at_tiles({}, tiles) is None
    summary = tiles_summary(dict(tiles, truth_waves=truth))
    error = summary["zernike_waves_vs_truth"]["defocus"]
    assert error["rms_error"] > 0 and error["truth_min_max"][1] == round(float(truth["defocus"].max()), 4)
    path = write_tile_figure(tmp_path / "tiles.png", dict(tiles, truth_waves=truth), field_width_m=1e-3,
                             frame_shape=(100, 100))
    assert path.stat().st_size > 10_000
