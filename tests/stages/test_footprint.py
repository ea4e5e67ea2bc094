"""Memory and disk estimates made before a stage allocates anything."""

import logging
import math
import time

import numpy as np
import pytest

from cca_cli.config.load import apply_overrides
from cca_cli.errors import ConfigError, ResourceError
from cca_cli.io.h5 import Provenance
from cca_cli.sampling.design import plan_array
from cca_cli.sampling.grid import band_layout, band_sizes
from cca_cli.stages import simulate as simulate_stage
from cca_cli.stages.footprint import (Footprint, check_footprint, reconstruct_footprint, simulate_footprint,
                                      simulation_sizes)


def test_band_sizes_are_the_layouts_sizes():
    rng = np.random.default_rng(0)
    for _ in range(200):
        radius = float(rng.uniform(0.8, 40))
        centres = rng.uniform(-300, 300, size=(int(rng.integers(1, 30)), 2))
        sensor = int(rng.integers(8, 600))
        try:
            layout = band_layout(centres, radius, sensor_size=sensor)
        except ValueError:
            with pytest.raises(ValueError):
                band_sizes(float(np.max(np.abs(np.rint(centres)))), radius, sensor_size=sensor)
            continue
        sizes = band_sizes(float(np.max(np.abs(np.rint(centres)))), radius, sensor_size=sensor)
        assert (sizes.hires_size, sizes.lowres_size, sizes.box_size) == (layout.hires_size, layout.lowres_size,
                                                                         layout.box_size)


def test_estimated_sizes_and_disk_match_a_real_simulation(tiny_run_config, tmp_path):
    for overrides in ({}, {"simulate.store": "band"}, {"array.grid": None, "array.sar": 2.9}):
        config = apply_overrides(tiny_run_config, overrides)
        sizes = simulation_sizes(config)
        sim = simulate_stage.run(config, tmp_path / "c.h5", provenance=Provenance.make("simulate", "", "x"),
                                 force=True)
        assert sizes.images == sim.intensity.shape[0] and sizes.stored_px == sim.intensity.shape[-1]
        assert (sizes.lowres_px, sizes.hires_px) == (sim.layout.lowres_size, sim.layout.hires_size)
        written = (tmp_path / "c.h5").stat().st_size
        assert 0.8 * written < simulate_footprint(config).disk_bytes < 1.2 * written
        estimate = reconstruct_footprint(tmp_path / "c.h5")
        assert estimate.memory_bytes > sim.intensity.nbytes


def test_huge_configs_are_estimated_without_allocating(tiny_run_config):
    start = time.perf_counter()
    for overrides in ({"array.grid": None, "array.sar": 1e6}, {"scene.size_px": 10 ** 6},
                      {"optics.pixel_pitch_m": 1e-300}, {"scene.field_width_m": 1e5}):
        footprint = simulate_footprint(apply_overrides(tiny_run_config, overrides))
        assert footprint.memory_bytes > 1e12
    assert time.perf_counter() - start < 2
    with pytest.raises(ConfigError, match="sensor pixels"):
        simulate_footprint(apply_overrides(tiny_run_config, {"optics.pixel_pitch_m": 9e-4}))
    with pytest.raises(ConfigError, match="1 m is not a plausible pixel pitch"):   # a unit slip, named first
        simulate_footprint(apply_overrides(tiny_run_config, {"optics.pixel_pitch_m": 1.0}))


def test_a_run_that_does_not_fit_is_refused_and_a_large_write_is_announced(tmp_path, monkeypatch, caplog):
    big = Footprint("simulate", memory_bytes=5e9, disk_bytes=3e9, detail="many images", fix="lower array.grid")
    monkeypatch.setenv("CCA_MEMORY_LIMIT", "4G")
    with pytest.raises(ResourceError, match="about 5 GB of memory .*4 GB is available; lower array.grid"):
        check_footprint(big, tmp_path / "c.h5", source="cfg.yaml")
    monkeypatch.setenv("CCA_MEMORY_LIMIT", "64G")
    with caplog.at_level(logging.WARNING, logger="cca"):
        check_footprint(big, tmp_path / "c.h5")
    assert "will write about 3 GB" in caplog.text
    monkeypatch.setenv("CCA_MEMORY_LIMIT", "lots")
    with pytest.raises(ConfigError, match="CCA_MEMORY_LIMIT"):
        check_footprint(big, tmp_path / "c.h5")


def test_design_plans_any_target_instantly():
    start = time.perf_counter()
    plan = plan_array(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=0.018, pixel_pitch_m=2e-6,
                      distance_m=50, sar=1e9)
    assert time.perf_counter() - start < 1
    assert plan.grid > 10 ** 9 and plan.n_images == plan.grid ** 2 and plan.memory_bytes > 1e24
    with pytest.raises(ValueError, match="positive number"):
        plan_array(wavelength_m=math.inf, focal_length_m=0.8, aperture_diameter_m=0.018, pixel_pitch_m=2e-6,
                   distance_m=50, sar=3)


def test_each_engine_thread_counts_its_own_work_arrays(tiny_run_config, tmp_path):
    from cca_cli.config.model import ReconstructSection
    from cca_cli.engines.momentum import MAX_THREADS

    sim = simulate_stage.run(tiny_run_config, tmp_path / "c.h5", provenance=Provenance.make("simulate", "", "x"),
                             force=True)
    k, box = sim.layout.n_images, sim.layout.box_size
    estimates = {t: reconstruct_footprint(tmp_path / "c.h5", ReconstructSection(options={"threads": t}))
                 for t in (1, 4, 1000)}
    # every thread beyond the first holds at least a whole batch of update boxes (k of them at the largest)
    assert estimates[4].memory_bytes - estimates[1].memory_bytes >= 3 * k * box * box * 8
    capped = reconstruct_footprint(tmp_path / "c.h5", ReconstructSection(options={"threads": MAX_THREADS}))
    # beyond momentum's cap only the spectrum-sized arrays grow (altmin uses every thread asked for)
    assert 0 < estimates[1000].memory_bytes - capped.memory_bytes < (1000 - MAX_THREADS) * k * box * box * 8
    assert estimates[1].detail.endswith("1 thread") and estimates[4].detail.endswith("4 threads")


def test_recorded_frames_are_estimated_on_the_guard_banded_grid_with_the_checkpoint(tmp_path):
    """Recorded frames are recovered on a wider grid (their guard band): the estimate is the recovery's own
    grid, and the disk counts the checkpoint that lies beside the output (and beside its successor)."""
    import cca_cli as cca
    from cca_cli.config.model import ReconstructSection
    from cca_cli.library.recovery import build_model, embed_region

    geometry = cca.led_array(cca.led_grid_sines(7, pitch_m=4e-3, height_m=60e-3), wavelength_m=532e-9,
                             numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6, image_pixels=48)
    images = cca.simulate(cca.resolution_chart(48 * 4, widths=(6, 4, 3, 2)).image, geometry, snr_db=35)
    path = tmp_path / "raw.h5"
    cca.save(cca.CaptureSet(images, geometry, units="counts/s", boundary="open"), path)
    padded, region = embed_region(cca.load(path), padding="auto")
    assert region is not None and region.size > 48
    hires = build_model(padded.geometry, region.size).layout.hires_size

    estimate = reconstruct_footprint(path, ReconstructSection())
    assert f"object {hires}² px" in estimate.detail and f"recovered on a {region.size}² grid" in estimate.detail
    output = hires * hires * 20 + 48 * 48 * 4
    checkpoint = 3 * hires * hires * 8
    assert estimate.disk_bytes == max(output + checkpoint, 2 * checkpoint)
    without = reconstruct_footprint(path, ReconstructSection(checkpoint_every=0))
    assert without.disk_bytes == output
    # padding off: the frames' own grid
    unpadded = reconstruct_footprint(path, ReconstructSection(padding={"mode": "off"}))
    assert "grid" not in unpadded.detail and unpadded.memory_bytes < estimate.memory_bytes
    # pupils that may move: the object grid gets the run's margin
    moving = ReconstructSection(options={"position_refinement": "per_image"})
    margin = int(np.ceil(padded.geometry.pupil_radius_px / 8)) + 2
    wider = build_model(padded.geometry, region.size, margin_px=margin).layout.hires_size
    assert wider > hires and f"object {wider}² px" in reconstruct_footprint(path, moving).detail
