"""Lab tables, kinds, setup files, containers and refusals: ingest of directories laid out as labs record them.

Every refusal is checked through the real entry point: one line naming the file and the fix, exit != 0,
no output and no temporary file left.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import numpy as np
import OpenImageIO as oiio
import pytest
import yaml
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.io.images import write_image
from cca_cli.io.captures import read_captures

runner = CliRunner()
OPTICS = {"wavelength_m": 550e-9, "focal_length_m": 0.05, "aperture_diameter_m": 1.5e-3, "pixel_pitch_m": 2.5e-6,
          "distance_m": 5.0}
HEADER = ["file", "kind", "exposure_ms", "x_mm", "y_mm", "r", "c", "bits", "operator"]
MAPPING = {"path": "file", "kind": "kind", "exposure": "exposure_ms", "stage_x": "x_mm", "stage_y": "y_mm",
           "row": "r", "col": "c", "bit_depth": "bits"}
RNG = np.random.default_rng(0)


def _codes(level: float, shape=(16, 20)) -> np.ndarray:
    return np.clip(np.rint(level + RNG.normal(0, 2, shape)), 0, 4095).astype(np.uint16)


def _lab(tmp_path, *, shift=4, calibration=False, darks=False, flats=False, extra_rows=(), edit=None, sensor=None,
         manifest_extra=None):
    """A 2 x 2-position, 2-exposure lab directory: lab table, setup.json, a user's lab.yaml."""
    rows = []
    for r in range(2):
        for c in range(2):
            for t in (1.0, 4.0):
                name = f"p{r}{c}_{int(t)}.tif"
                write_image(tmp_path / name, _codes(64 + 50 * t * (1 + r + c)) << shift, bit_depth=16)
                rows.append([name, "coherent", t, 0.5 * c - 0.25, 0.5 * r - 0.25, r, c, 12, "ann"])
            if calibration:
                name = f"cal{r}{c}.tif"
                write_image(tmp_path / name, _codes(1500) << shift, bit_depth=16)
                rows.append([name, "calibration", 8.0, 0.5 * c - 0.25, 0.5 * r - 0.25, r, c, 12, "ann"])
    if darks:
        for t in (1.0, 4.0):
            for n in range(2):
                write_image(tmp_path / f"d{int(t)}_{n}.tif", _codes(64) << shift, bit_depth=16)
                rows.append([f"d{int(t)}_{n}.tif", "dark", t, "", "", "", "", 12, "ann"])
    if flats:
        for n in range(2):
            write_image(tmp_path / f"f{n}.tif", _codes(2000) << shift, bit_depth=16)
            rows.append([f"f{n}.tif", "flat", 4.0, "", "", "", "", 12, "ann"])
    rows += list(extra_rows)
    if edit is not None:
        rows = edit(rows)
    with open(tmp_path / "table.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(HEADER)
        writer.writerows(rows)
    (tmp_path / "setup.json").write_text(json.dumps({**OPTICS, "lens": "50 mm macro"}))
    manifest = {"images_csv": "table.csv", "setup": "setup.json", "columns": MAPPING,
                "units": {"exposure": "ms", "position": "mm"},
                "sensor": sensor if sensor is not None else {"bit_depth": 12, "container_bits": 16, "alignment": "msb",
                                                              "black_level": 64}}
    if calibration:
        manifest["checkerboard"] = {"pattern": [4, 3]}
    manifest.update(manifest_extra or {})
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return tmp_path / "lab.yaml"


def _ingest(manifest, out):
    return runner.invoke(app, ["ingest", str(manifest), "-o", str(out), "-q"])


def _refused(tmp_path, *needles):
    """Ingest of lab.yaml fails with one line containing every needle, and writes nothing."""
    out = tmp_path / "raw.h5"
    result = _ingest(tmp_path / "lab.yaml", out)
    assert result.exit_code != 0, result.output
    text = " ".join(result.output.split())
    assert text.startswith("error:") and text.count("error:") == 1, text
    for needle in needles:
        assert needle in text, (needle, text)
    assert not out.exists() and not list(tmp_path.glob(".raw.h5*"))
    return text


def test_lab_table_with_its_own_names_ingests(tmp_path):
    _lab(tmp_path, calibration=True, darks=True, flats=True)
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert text.count("ignored: operator") == 1 and text.count("ignored: lens") == 1  # listed once
    with h5py.File(tmp_path / "raw.h5") as f:
        frames = f["/raw/frames"][()]
        assert frames.shape == (4, 2, 16, 20)
        np.testing.assert_allclose(f["/raw/exposure_s"][0], [0.001, 0.004])
        np.testing.assert_allclose(f["/geometry/aperture_centres_yx_m"][()].min(axis=0), [-0.25e-3, -0.25e-3])
        assert f["/registration/board_views"].shape == (4, 16, 20)
        assert f["/sensor/black_level"].shape == (2, 16, 20)
        assert f["/sensor/gain_map"][()].mean() == pytest.approx(1.0, abs=1e-6)
        assert 1.0 < f["sensor"].attrs["read_noise"] < 3.5
        assert f["/geometry/grid_indices"][()].max() == 1
    # Codes shifted back (12-bit), black subtracted per pixel: position (0, 0) at 1 ms sits about 50 codes up.
    assert abs(np.median(frames[0, 0]) - 50) < 3


def test_values_below_the_black_level_are_kept(tmp_path):
    _lab(tmp_path, sensor={"bit_depth": 12, "alignment": "msb", "black_level": 120})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as f:
        dim = f["/raw/frames"][0, 0]
    assert abs(np.median(dim) + 6) < 1.5 and (dim < 0).mean() > 0.9  # not clipped at zero


def test_old_csv_with_fixed_name_sidecar_still_works(tmp_path):
    for i in range(2):
        write_image(tmp_path / f"v{i}.png", np.full((16, 16), 100 + i, np.float32), bit_depth=16)
    (tmp_path / "captures.csv").write_text("path,exposure_s,stage_x_mm,stage_y_mm\nv0.png,0.01,0,0\nv1.png,0.01,1,0\n")
    (tmp_path / "captures.yaml").write_text(yaml.safe_dump({"optics": OPTICS, "sensor": {"white_level": 4095}}))
    result = _ingest(tmp_path / "captures.csv", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "raw.h5") as f:
        np.testing.assert_allclose(f["/measurements/intensity"][1], 101 / 0.01, rtol=1e-6)


def test_known_defocus_and_pupil_reach_reconstruct(tmp_path):
    pupil = np.exp(1j * np.linspace(0, 1, 64)).reshape(8, 8).astype(np.complex64)
    np.save(tmp_path / "pupil.npy", pupil)
    (tmp_path / "setup.json").write_text("{}")
    _lab(tmp_path)
    manifest = yaml.safe_load((tmp_path / "lab.yaml").read_text())
    manifest.pop("setup")
    manifest["optics"] = {**OPTICS, "defocus_m": 1.5e-5, "pupil": "pupil.npy"}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    result = runner.invoke(app, ["hdr", str(tmp_path / "raw.h5"), "-o", str(tmp_path / "hdr.h5"), "-q"])
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "hdr.h5") as f:
        assert f["/calibration/initial_pupil"].attrs["units"] == "1"
        assert "description" in f["/calibration/initial_pupil"].attrs
    captures = read_captures(tmp_path / "hdr.h5")
    assert captures.geometry.defocus_m == pytest.approx(1.5e-5)
    np.testing.assert_array_equal(captures.initial_pupil, pupil)
    assert captures.boundary == "open"


def test_setup_section_given_twice(tmp_path):
    _lab(tmp_path, manifest_extra={"optics": OPTICS})
    _refused(tmp_path, "lab.yaml", "optics is given both here and in setup.json")


def test_unit_suffix_contradicting_units(tmp_path):
    _lab(tmp_path, manifest_extra={"units": {"exposure": "s", "position": "mm"}})
    _refused(tmp_path, "exposure_ms", "units: {exposure: ms}")


def test_mapped_column_missing(tmp_path):
    _lab(tmp_path, manifest_extra={"columns": {**MAPPING, "stage_x": "X"}})
    _refused(tmp_path, "columns.stage_x", "no column 'X'")


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_position(tmp_path, value):
    _lab(tmp_path, edit=lambda rows: [r if i != 2 else r[:3] + [value] + r[4:] for i, r in enumerate(rows)])
    _refused(tmp_path, "table.csv", "line 4", "p01_1.tif", "'x_mm'", "finite")


def test_unknown_kind_and_kind_values(tmp_path):
    _lab(tmp_path, edit=lambda rows: [r[:1] + ["obj"] + r[2:] for r in rows])
    _refused(tmp_path, "table.csv", "kind 'obj'", "kind_values")
    _lab(tmp_path, edit=lambda rows: [r[:1] + ["obj"] + r[2:] for r in rows],
         manifest_extra={"kind_values": {"obj": "coherent"}})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0


def test_a_misspelt_kind_values_word_is_pointed_at(tmp_path):
    _lab(tmp_path, calibration=True, manifest_extra={"kind_values": {"calibraton": "calibration"}},
         edit=lambda rows: [r[:1] + ["calibraton" if r[1] == "calibration" else r[1]] + r[2:] for r in rows])
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    (tmp_path / "raw.h5").unlink()
    _lab(tmp_path, calibration=True, manifest_extra={"kind_values": {"calibraton": "calibration"}},
         edit=lambda rows: [r[:1] + ["calibratoin" if r[1] == "calibration" else r[1]] + r[2:] for r in rows])
    text = _refused(tmp_path, "kind 'calibratoin' is not one of cca's kinds (coherent, calibration, dark, flat)",
                    "kind_values in", "maps 'calibraton': did you mean 'calibratoin' there?")
    assert "{calibratoin: coherent}" not in text


def test_calibration_view_missing_at_a_position(tmp_path):
    _lab(tmp_path, calibration=True, edit=lambda rows: [r for r in rows if r[0] != "cal11.tif"])
    _refused(tmp_path, "lab.yaml", "grid position (row 1, col 1)", "no calibration image")


# --- containers -------------------------------------------------------------------------------------------


def test_msb_alignment_detected_from_the_values_with_a_note(tmp_path):
    _lab(tmp_path, sensor={"bit_depth": 12, "black_level": 64})
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert "MSB-aligned" in " ".join(result.output.split())
    with h5py.File(tmp_path / "raw.h5") as f:
        assert f["sensor"].attrs["white_level"] == 4095
        assert abs(np.median(f["/raw/frames"][0, 0]) - 50) < 3


def test_levels_in_stored_units_without_a_bit_depth(tmp_path):
    _lab(tmp_path, sensor={"black_level": 1024}, edit=lambda rows: [r[:7] + [""] + r[8:] for r in rows])
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert "multiple of 16" in " ".join(result.output.split())
    with h5py.File(tmp_path / "raw.h5") as f:
        assert f["sensor"].attrs["white_level"] == 65520  # the largest MSB-aligned 12-bit value, not 65535


def test_white_level_the_data_contradict(tmp_path):
    # The report's case: bit_depth 12 and white_level 4095 stated, 16-bit values, alignment lsb.
    _lab(tmp_path, sensor={"bit_depth": 12, "alignment": "lsb", "white_level": 4095})
    _refused(tmp_path, ".tif", "above the largest 12-bit code 4095", "alignment: msb")


def test_white_level_above_the_values(tmp_path):
    _lab(tmp_path, shift=0, sensor={"white_level": 3000}, edit=lambda rows: [r[:7] + [""] + r[8:] for r in rows])
    write_image(tmp_path / "p11_4.tif", np.full((16, 20), 3500, np.uint16), bit_depth=16)
    _refused(tmp_path, "p11_4.tif", "above sensor.white_level 3000")


def test_eight_bit_files_with_a_twelve_bit_white_level(tmp_path):
    _lab(tmp_path, sensor={"white_level": 4095}, edit=lambda rows: [
        [r[0].replace(".tif", ".png")] + r[1:7] + [""] + r[8:] for r in rows])
    for path in tmp_path.glob("p*.tif"):
        write_image(path.with_suffix(".png"), np.full((16, 20), 120, np.uint8), bit_depth=8)
    _refused(tmp_path, ".png", "white_level 4095 is above", "255")


def test_one_eight_bit_file_among_sixteen_bit_ones(tmp_path):
    _lab(tmp_path, edit=lambda rows: [r if r[0] != "p10_4.tif" else ["p10_4.png"] + r[1:] for r in rows])
    write_image(tmp_path / "p10_4.png", np.full((16, 20), 120, np.uint8), bit_depth=8)
    _refused(tmp_path, "p10_4.png", "8-bit", "16-bit", "same bit depth")


def test_rows_stating_different_bit_depths(tmp_path):
    _lab(tmp_path, edit=lambda rows: [r if r[0] != "p00_4.tif" else r[:7] + [14] + r[8:] for r in rows],
         sensor={})
    _refused(tmp_path, "lab.yaml", "bit depths 12", "14", "same bit depth")


def _eight_bit(tmp_path, prefix, *, bits=None):
    """Rows editor: the files of rows whose name starts with ``prefix`` become 8-bit PNGs, their rows stating ``bits``
    ("" for none)."""
    def edit(rows):
        out = []
        for row in rows:
            if row[0].startswith(prefix):
                name = row[0].replace(".tif", ".png")
                level = 90 if row[1] == "calibration" else 4
                write_image(tmp_path / name, np.clip(RNG.normal(level, 2, (16, 20)), 0, 255).astype(np.uint8),
                            bit_depth=8)
                row = [name] + row[1:7] + [row[7] if bits is None else bits] + row[8:]
            out.append(row)
        return out
    return edit


@pytest.mark.parametrize("bits", ["", 8])
def test_eight_bit_calibration_views_beside_sixteen_bit_captures(tmp_path, bits):
    # The board shot in another camera mode: accepted at its own depth whatever its row states (or without a column).
    _lab(tmp_path, calibration=True, darks=True, flats=True, edit=_eight_bit(tmp_path, "cal", bits=bits))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "calibration views at another bit depth than the captures" in text and "read at their own depth" in text
    with h5py.File(tmp_path / "raw.h5") as f:
        views = f["/registration/board_views"][()]
        frames = f["/raw/frames"][()]
        gain = f["/sensor/gain_map"][()]
    assert abs(np.median(frames[0, 0]) - 50) < 3  # the captures are decoded as before (12-bit codes, black removed)
    # the views keep their own 8-bit codes (no 12-bit black level taken off), per second of their 8 ms exposure
    assert views.shape == (4, 16, 20) and abs(np.median(views * gain) * 0.008 - 90) < 2


def test_calibration_row_stating_more_bits_than_its_file_holds(tmp_path):
    _lab(tmp_path, calibration=True, edit=_eight_bit(tmp_path, "cal", bits=12))
    _refused(tmp_path, "cal00.png", "8-bit file", "states bit depth 12", "lab.yaml")


def test_eight_bit_calibration_views_match_the_captures_when_every_file_is_eight_bit(tmp_path):
    # Every file 8-bit: the views are read like the captures (black level off), no note.
    _lab(tmp_path, calibration=True, sensor={"black_level": 2},
         edit=lambda rows: _eight_bit(tmp_path, "", bits="")(rows))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert "own depth" not in result.output
    with h5py.File(tmp_path / "raw.h5") as f:
        assert abs(np.median(f["/registration/board_views"][()]) * 0.008 - 88) < 2


@pytest.mark.parametrize("prefix", ["d1_0", "f0"])
def test_darks_and_flats_must_match_the_captures(tmp_path, prefix):
    _lab(tmp_path, darks=True, flats=True, edit=_eight_bit(tmp_path, prefix, bits=""))
    _refused(tmp_path, f"{prefix}.png", "8-bit", "16-bit", "same bit depth")


def test_dark_rows_stating_another_bit_depth(tmp_path):
    _lab(tmp_path, darks=True, sensor={}, edit=lambda rows: [r if r[0] != "d4_1.tif" else r[:7] + [14] + r[8:]
                                                            for r in rows])
    _refused(tmp_path, "lab.yaml", "bit depths 12", "14", "d4_1.tif", "same bit depth")


def _rgb(path, values):
    h, w, c = values.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, "uint16"))
    assert out.write_image(np.ascontiguousarray(values))
    out.close()


def test_colour_frames_need_a_channel_rule(tmp_path):
    _lab(tmp_path)
    for path in tmp_path.glob("p*.tif"):
        grey = np.asarray(oiio.ImageBuf(str(path)).get_pixels(oiio.UINT16))[..., 0]
        _rgb(path, np.stack([grey // 2, grey, grey // 4], axis=-1).astype(np.uint16) & 0xFFF0)
    _refused(tmp_path, ".tif", "colour image", "sensor.channel")
    manifest = yaml.safe_load((tmp_path / "lab.yaml").read_text())
    manifest["sensor"]["channel"] = "G"
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as f:
        assert abs(np.median(f["/raw/frames"][0, 0]) - 50) < 3  # the green channel, not the mean


def test_bayer_rule_keeps_one_colour_at_half_resolution(tmp_path):
    _lab(tmp_path, sensor={"bit_depth": 12, "alignment": "msb", "black_level": 64,
                           "bayer": {"pattern": "RGGB", "colour": "R"}})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as f:
        assert f["/raw/frames"].shape == (4, 2, 8, 10)
        assert f["geometry"].attrs["pixel_pitch_m"] == pytest.approx(5e-6)


def test_non_finite_position_in_a_yaml_manifest(tmp_path):
    write_image(tmp_path / "a.png", np.full((16, 16), 100, np.uint16), bit_depth=16)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"optics": OPTICS, "images": [
        {"path": "a.png", "exposure_s": 0.01, "stage_x_mm": float("nan"), "stage_y_mm": 0.0}]}))
    _refused(tmp_path, "lab.yaml", "images.0.stage_x_mm", "finite number")


def test_non_square_led_array_frames_are_recovered_whole(tmp_path):
    # A 3 x 3 LED grid, 24 x 40 px frames: ingest writes /measurements; reconstruct pads and crops back.
    images = []
    for i, (ky, kx) in enumerate([(a, b) for a in (-0.04, 0, 0.04) for b in (-0.04, 0, 0.04)]):
        frame = 200 + 50 * np.cos(np.arange(40)[None, :] / 3.0 + i) * np.ones((24, 1))
        write_image(tmp_path / f"led{i}.png", frame, bit_depth=16)
        images.append({"path": f"led{i}.png", "kx_norm": kx, "ky_norm": ky})
    illumination = {"wavelength_m": 532e-9, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1.0e-6}
    (tmp_path / "led.yaml").write_text(yaml.safe_dump({"illumination": illumination, "images": images}))
    assert _ingest(tmp_path / "led.yaml", tmp_path / "raw.h5").exit_code == 0
    result = runner.invoke(app, ["reconstruct", str(tmp_path / "raw.h5"), "-o", str(tmp_path / "recon.h5"),
                                 "--iterations", "5", "-q"])
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "recon.h5") as f:
        region = f["/recon/region_px"][()]
        assert tuple(region[1, 2:]) == (24, 40)
        assert f["/recon/intensity"].shape == tuple(region[0, 2:])
        assert f["/recon/intensity"].shape[1] / f["/recon/intensity"].shape[0] == pytest.approx(40 / 24, rel=0.05)
        assert f["/observed/centre"].shape == (24, 40)


@pytest.mark.parametrize("slip", [1.0, 20.0])
def test_a_position_far_from_every_other_is_reported(tmp_path, slip):
    """A slipped decimal point (one stage reading 20× too far out) is ingested with a note naming its row."""
    rows = []
    for r in range(3):
        for c in range(3):
            name = f"p{r}{c}.png"
            write_image(tmp_path / name, _codes(800), bit_depth=16)
            x, y = 0.5 * (c - 1), 0.5 * (r - 1)
            if (r, c) == (2, 2):
                x *= slip
            rows.append({"path": name, "exposure_s": 0.01, "stage_x_mm": x, "stage_y_mm": y})
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"optics": OPTICS, "images": rows}))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    if slip == 1.0:
        assert "usual spacing" not in text
    else:
        assert text.count("usual spacing") == 1
        assert "p22.png" in text and "a mistyped position? check that row's stage position" in text


def _scan_table(tmp_path, edit=None, exposures=(10,)) -> None:
    """A 4 x 4 stage scan whose table gives both the grid indices and the positions."""
    lines = ["file,kind,exposure_ms,x_mm,y_mm,r,c"]
    for r in range(4):
        for c in range(4):
            for t in exposures:
                write_image(tmp_path / f"p{r}{c}_{t}.png", _codes(80 * t), bit_depth=16)
                lines.append(f"p{r}{c}_{t}.png,coherent,{t},{0.4 * c - 0.6:.3f},{0.4 * r - 0.6:.3f},{r},{c}")
    lines = edit(lines) if edit is not None else lines
    (tmp_path / "table.csv").write_text("\n".join(lines) + "\n")
    mapping = {"path": "file", "kind": "kind", "exposure": "exposure_ms", "stage_x": "x_mm", "stage_y": "y_mm",
               "row": "r", "col": "c"}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"images_csv": "table.csv", "optics": OPTICS, "columns": mapping,
                                                       "units": {"exposure": "ms", "position": "mm"}}))


def test_a_position_off_its_grid_row_and_col_is_refused_by_its_table_line(tmp_path):
    """A slipped digit (x 2.000 for 0.200) in a table that also gives row and col: refused, naming the line."""
    _scan_table(tmp_path)
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0   # the clean table
    (tmp_path / "raw.h5").unlink()
    _scan_table(tmp_path, edit=lambda lines: [line.replace(",0.200,", ",2.000,") if line.startswith("p12_10.png") else line
                                              for line in lines])
    text = _refused(tmp_path, "lab.yaml", "grid position (row 1, col 2) (line 8 of table.csv)", "x 2, y -0.2 mm",
                    "(x 0.2, y -0.2 mm)", "fix that position")
    assert "4.5 grid steps" in text


def test_rows_of_one_grid_position_that_disagree_name_the_odd_line(tmp_path):
    """Two exposures at each position; the second row of position (1, 2) has a slipped digit."""
    _scan_table(tmp_path, exposures=(10, 20), edit=lambda lines: [
        line.replace(",0.200,", ",2.000,") if line.startswith("p12_20.png") else line for line in lines])
    _refused(tmp_path, "rows at grid position (row 1, col 2)", "lines 14 and 15 of table.csv disagree")


def test_a_negative_wavelength_is_named_with_its_unit(tmp_path):
    """YAML reads ``-550e-9`` (no decimal point) as text: the message shows the number and the unit the key is in."""
    write_image(tmp_path / "a.png", np.full((16, 16), 100, np.uint16), bit_depth=16)
    (tmp_path / "lab.yaml").write_text("optics: {wavelength_m: -550e-9, focal_length_m: 0.05, aperture_diameter_m: "
                                       "1.5e-3, pixel_pitch_m: 2.5e-6, distance_m: 5.0}\n"
                                       "images: [{path: a.png, exposure_s: 0.01, stage_x_mm: 0, stage_y_mm: 0}]\n")
    _refused(tmp_path, "lab.yaml", "optics.wavelength_m: must be greater than 0 (in metres) (got -550e-9)")


def test_designed_layouts_are_not_reported_as_stray():
    """A centre LED inside a ring, sparse outer LEDs around a dense grid, repeated positions: no note; a slipped
    LED row is named with the columns to check."""
    from types import SimpleNamespace

    from cca_cli.stages.ingest import stray_positions

    def notes(centres, kind="led_array"):
        plan = SimpleNamespace(kind=kind, labels=[f"row {i}" for i in range(len(centres))],
                               manifest=SimpleNamespace(images=[]))
        return stray_positions(plan, SimpleNamespace(spectrum_centres_yx_px=np.asarray(centres, float)))

    angles = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    ring = 100 * np.stack([np.sin(angles), np.cos(angles)], axis=1)
    assert notes(np.vstack([[0, 0], ring])) == []
    yy, xx = np.mgrid[-7:8, -7:8]
    dense = 5.0 * np.stack([yy.ravel(), xx.ravel()], axis=1)
    assert notes(np.vstack([dense, [[0, 120], [0, -120], [120, 0], [-120, 0]]])) == []
    assert notes(np.vstack([dense, dense])) == []
    slipped = dense.copy()
    slipped[3] *= 30
    found = notes(slipped)
    assert len(found) == 1 and found[0].startswith("row 3 lies") and found[0].endswith("check that row's kx_norm/ky_norm (or LED position)")


def test_images_scaled_each_on_its_own_reach_reconstruct_with_brightness_fitted(tmp_path):
    from cca_cli.config.model import ReconstructSection
    from cca_cli.workflows.recovery import engine_options

    per_frame = {"bit_depth": 12, "container_bits": 16, "alignment": "msb", "black_level": 64,
                 "frame_scale": "per_frame"}
    one_exposure = lambda rows: [row for row in rows if row[2] == 1.0]   # noqa: E731
    _lab(tmp_path, sensor=per_frame, edit=one_exposure)
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    captures = read_captures(tmp_path / "raw.h5")
    assert captures.frame_scale == "per_frame"
    _, options = engine_options(ReconstructSection(), captures.kind, frame_scale=captures.frame_scale)
    assert options.brightness is True
    _, told = engine_options(ReconstructSection(options={"brightness": False}), captures.kind,
                             frame_scale=captures.frame_scale)
    assert told.brightness is False
    (tmp_path / "raw.h5").unlink()
    _lab(tmp_path, sensor=per_frame)   # two exposures a position: their times mean nothing then
    _refused(tmp_path, "sensor.frame_scale is per_frame", "2 exposures", "frame_scale: shared")
    _lab(tmp_path, sensor={"frame_scale": "each"})
    _refused(tmp_path, "sensor.frame_scale", "per_frame")


@pytest.mark.parametrize("factor", [1000.0, 20000.0])
def test_positions_in_the_wrong_unit_are_noted_or_refused(tmp_path, factor):
    """Micrometres read as millimetres: no two captures overlap (refused: phase retrieval cannot join them); far
    enough out, the recovery grid with its guard band could not hold them (although the pupils alone would fit in
    65536 px)."""
    rows = []
    for r in range(3):
        for c in range(3):
            write_image(tmp_path / f"p{r}{c}.png", _codes(800), bit_depth=16)
            rows.append({"path": f"p{r}{c}.png", "exposure_s": 0.01, "stage_x_mm": 0.5 * (c - 1) * factor,
                         "stage_y_mm": 0.5 * (r - 1) * factor})
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"optics": OPTICS, "images": rows}))
    if factor == 1000.0:
        _refused(tmp_path, "lab.yaml", "no two overlap", "units.position")
    else:
        _refused(tmp_path, "lab.yaml", "the recovery grid would be", "at most 65536")


def test_reconstructing_unmerged_brackets_says_to_merge_them(tmp_path):
    _lab(tmp_path)
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    result = runner.invoke(app, ["reconstruct", str(tmp_path / "raw.h5"), "-o", str(tmp_path / "r.h5"), "-q"])
    assert result.exit_code == 3
    assert "merge them first with cca hdr" in " ".join(result.output.split())


def test_a_setup_file_of_sections_may_carry_the_lab_s_other_facts(tmp_path):
    _lab(tmp_path)
    (tmp_path / "setup.json").write_text(json.dumps({"optics": OPTICS, "operator": "jdoe", "room": "B2"}))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert "setup.json: keys not used by cca, ignored: operator, room" in " ".join(result.output.split())
    # but cca's own keys out of their section, or a misspelled section, are not dropped quietly
    (tmp_path / "raw.h5").unlink()
    (tmp_path / "setup.json").write_text(json.dumps({"optics": OPTICS, "black_level": 800}))
    _refused(tmp_path, "setup.json: black_level belongs in the sensor section")
    (tmp_path / "setup.json").write_text(json.dumps({"optics": OPTICS, "sensors": {"black_level": 800}}))
    _refused(tmp_path, "setup.json: sensors is not a section; did you mean sensor?")


def _ingested_led_lab(tmp_path, images, sines, *, dead=None, kx_shift=0.0) -> str:
    """Write simulated LED-array images as 16-bit PNGs (capture ``dead`` as dark noise, the listed kx shifted by
    ``kx_shift``) with their manifest, ingest them and return what ingest printed, on one line."""
    scale = 30000 / float(images.max())
    rows = []
    for k, (ky, kx) in enumerate(np.asarray(sines)):
        codes = RNG.normal(100, 3, images[k].shape) if k == dead else images[k] * scale + 100
        write_image(tmp_path / f"led{k}.png", np.clip(np.rint(codes), 0, 65535).astype(np.uint16), bit_depth=16)
        rows.append({"path": f"led{k}.png", "exposure_s": 0.01, "kx_norm": float(kx + kx_shift), "ky_norm": float(ky)})
    manifest = {"illumination": {"wavelength_m": 532e-9, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1.845e-6},
                "sensor": {"black_level": 100}, "images": rows}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    return " ".join(result.output.split())


def test_a_bright_field_led_that_did_not_fire_is_named(tmp_path):
    import cca_cli as cca

    sines = cca.led_grid_sines(5, pitch_m=4e-3, height_m=60e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=32)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, geometry, snr_db=None)
    bright = np.flatnonzero(np.hypot(*geometry.spectrum_centres_yx_px.T) < 0.9 * geometry.pupil_radius_px)
    dead = int(bright[-1])
    assert dead != geometry.centre_index and bright.size == 5
    text = _ingested_led_lab(tmp_path, images, sines, dead=dead)
    assert text.count("did its LED fire?") == 1 and f"led{dead}.png" in text and "reconstruct leaves it out" in text
    result = runner.invoke(app, ["reconstruct", str(tmp_path / "raw.h5"), "-o", str(tmp_path / "recon.h5"),
                                 "--iterations", "3"])
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert f"left out 1 of 25 images of /measurements/intensity in the bright field" in said
    assert f"image {dead} (its pupil at" in said and "the recovery uses the other 24" in said
    with h5py.File(tmp_path / "recon.h5") as f:
        assert list(f["/recon"].attrs["dropped_captures"]) == [dead]


def test_an_unlit_centre_capture_or_many_unlit_ones_are_refused_and_a_wrong_geometry_leaves_out_none():
    import cca_cli as cca

    sines = cca.led_grid_sines(9, pitch_m=2e-3, height_m=60e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=32)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, geometry, snr_db=None)
    unlit = np.abs(RNG.normal(0, 1e-3 * images.mean(), images.shape[1:])).astype(np.float32)
    bright = np.flatnonzero(np.hypot(*geometry.spectrum_centres_yx_px.T) < 0.9 * geometry.pupil_radius_px)
    centre = geometry.centre_index
    others = [int(i) for i in bright if i != centre]
    assert len(others) >= 12

    def with_unlit(indices, dead=()):
        out = images.copy()
        out[list(indices)] = unlit
        out[list(dead)] = 7.0
        return out

    with pytest.raises(ValueError, match=rf"^image {centre} of intensities, the centre capture .* recorded "
                                         r"[\d.e+]+ times less light than the median bright-field capture"):
        cca.reconstruct(with_unlit([centre]), geometry, iterations=1)
    # 4 of 81 may be left out (5%): three unlit and two dead are too many
    with pytest.raises(ValueError, match=r"^3 bright-field images of intensities recorded 10 times less light .* and "
                                         r"2 hold one value; at most 5% of the captures \(4 here\)"):
        cca.reconstruct(with_unlit(others[:3], dead=(0, 80)), geometry, iterations=1)
    assert cca.reconstruct(with_unlit(others[:3], dead=(0,)), geometry, iterations=1).dropped == (0, *others[:3])
    # most bright-field captures dark: the LEDs are not where the geometry says, and nothing is left out
    assert cca.reconstruct(with_unlit(others[:len(others) // 2 + 1]), geometry, iterations=1).dropped == ()


@pytest.mark.parametrize("sensor, noted", [({"bit_depth": 12, "container_bits": 16, "alignment": "msb"}, False),
                                           ({"bit_depth": 14, "alignment": "msb"}, True),
                                           ({"bit_depth": 16}, True)])
def test_a_stated_bit_depth_the_empty_low_bits_contradict_is_noted(tmp_path, sensor, noted):
    unstated = lambda rows: [row[:7] + [""] + row[8:] for row in rows]   # noqa: E731  (no bits column)
    _lab(tmp_path, sensor={**sensor, "black_level": 64}, edit=unstated)   # 12-bit codes, MSB-aligned in 16 bits
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert ("every value is a multiple of 16, as 12-bit data" in text and "check sensor.bit_depth" in text) is noted


def test_degrees_in_a_sine_column_are_named_with_the_table_s_column_and_value(tmp_path):
    for i in range(2):
        write_image(tmp_path / f"a{i}.png", np.full((16, 16), 100 + i, np.uint16), bit_depth=16)
    (tmp_path / "t.csv").write_text("img,NAx,NAy,t\na0.png,30,0,0.01\na1.png,0,0,0.01\n")
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(
        {"images_csv": "t.csv", "columns": {"path": "img", "kx_norm": "NAx", "ky_norm": "NAy", "exposure": "t"},
         "illumination": {"wavelength_m": 5e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1e-6}}))
    _refused(tmp_path, "t.csv: line 2 (a0.png): column 'NAx' (kx_norm)", "(got 30)", "sin θ", "not an angle")


def test_a_csv_manifest_s_inputs_are_each_recorded_once(tmp_path):
    for i in range(2):
        write_image(tmp_path / f"a{i}.png", np.full((16, 16), 100 + i, np.uint16), bit_depth=16)
    (tmp_path / "c.csv").write_text("img,kx_norm,ky_norm,t\na0.png,0,0,0.01\na1.png,0.05,0,0.01\n")
    (tmp_path / "c.yaml").write_text("illumination: {wavelength_m: 5.0e-7, numerical_aperture: 0.1, "
                                     "pixel_pitch_object_m: 1.0e-6}\ncolumns: {path: img, exposure: t}\n")
    assert _ingest(tmp_path / "c.csv", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as handle:
        paths = [Path(entry["path"]).resolve() for entry in json.loads(handle.attrs["inputs"])]
    assert len(paths) == len(set(paths)) == 4
    # and a run of it is up to date the second time (its inputs compared each once)
    from cca_cli.config.model import RunConfig
    from cca_cli.stages.runner import run_pipeline

    config = RunConfig.model_validate({"run": {"stages": ["ingest"]}, "ingest": {"manifest": str(tmp_path / "c.csv")}})
    first = run_pipeline(config, tmp_path / "run")
    again = run_pipeline(config, tmp_path / "run")
    assert [o.status for o in first] == ["ran"] and [o.status for o in again] == ["skipped"]


def _led_table(tmp_path, rows: str, illumination_extra: dict | None = None) -> Path:
    """A 3 x 3 LED array listed by physical position: the lab's table and its manifest."""
    for i in range(9):
        write_image(tmp_path / f"led{i}.png", np.full((32, 32), 2000 if i == 4 else 200, np.uint16), bit_depth=16)
    (tmp_path / "leds.csv").write_text(rows)
    illumination = {"wavelength_m": 5e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1e-6,
                    **(illumination_extra or {})}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"images_csv": "leds.csv", "illumination": illumination}))
    return tmp_path / "lab.yaml"


def _grid_rows(origin_mm=(0.0, 0.0), pitch_mm=4.0, z_column=None) -> str:
    lines = ["path,led_x_mm,led_y_mm" + (",led_z_mm" if z_column is not None else "")]
    for i in range(9):
        x, y = origin_mm[0] + pitch_mm * (i % 3 - 1), origin_mm[1] + pitch_mm * (i // 3 - 1)
        lines.append(f"led{i}.png,{x},{y}" + (f",{z_column}" if z_column is not None else ""))
    return "\n".join(lines) + "\n"


def _sines(raw: Path) -> np.ndarray:
    """Where each capture's pupil sits, in sines (the illumination's sines times the sign)."""
    with h5py.File(raw) as handle:
        return handle["/geometry/aperture_centres_yx_m"][()]


def test_led_positions_in_mm_become_the_sines_of_their_light(tmp_path):
    """x, y in the LED plane, its height from the sample and where the axis meets it: sin θ = (x − x₀) / r."""
    _led_table(tmp_path, _grid_rows(origin_mm=(27.0, 18.0)), {"led_distance_m": 0.06, "led_axis_m": [0.025, 0.018]})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    offsets = np.array([[4.0 * (i // 3 - 1), 2.0 + 4.0 * (i % 3 - 1)] for i in range(9)])   # [y, x] mm from the axis
    expected = offsets / np.sqrt(np.sum(offsets ** 2, axis=1, keepdims=True) + 60.0 ** 2)
    sines = _sines(tmp_path / "raw.h5")
    assert np.allclose(sines, -expected, atol=1e-12)    # the rows' order; each pupil at sign · sin θ, sign −1
    # the same from a height column, in metres, with no axis stated (the table's origin on the axis)
    (tmp_path / "raw.h5").unlink()
    _led_table(tmp_path, _grid_rows(origin_mm=(0.002, 0.0), pitch_mm=0.004, z_column=0.06).replace("_mm", "_m"))
    text = (tmp_path / "lab.yaml").read_text()
    (tmp_path / "lab.yaml").write_text(text + "columns: {led_x: led_x_m, led_y: led_y_m, led_z: led_z_m}\n"
                                              "units: {position: m}\n")
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0, "metres"
    assert np.allclose(_sines(tmp_path / "raw.h5"), sines, atol=1e-12)


def test_led_positions_need_their_height_and_not_sines_beside_them(tmp_path):
    _led_table(tmp_path, _grid_rows())
    _refused(tmp_path, "leds.csv: led0.png gives its LED's position but not its height above the sample",
             "illumination.led_distance_m")
    _led_table(tmp_path, _grid_rows(z_column=-60), {"led_distance_m": 0.06})
    _refused(tmp_path, "leds.csv: line 2 (led0.png): led_z_mm", "greater than 0")
    # a table with sines uses them; the LED positions beside them are the lab's notes
    text = _ingested_sines_table(tmp_path, "led_x_mm,led_y_mm", "999,999")
    assert "columns not used by cca, ignored: led_x_mm, led_y_mm" in text
    assert np.isclose(np.abs(_sines(tmp_path / "raw.h5")).max(), 0.05)


def test_float_frames_without_a_white_level_count_no_pixel_as_clipped(tmp_path):
    values = np.linspace(0.1, 0.75, 16 * 16, dtype=np.float32).reshape(16, 16)
    images = []
    for i in range(2):
        write_image(tmp_path / f"f{i}.tif", values * (1 + i))
        images.append({"path": f"f{i}.tif", "kx_norm": 0.05 * i, "ky_norm": 0.0})
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"illumination": {
        "wavelength_m": 5e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1e-6}, "images": images}))
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as handle:
        assert handle["/measurements/weight"][()].min() == 1.0
        assert handle["/raw/frames"].attrs["saturation_level"] > 1.5


def test_exposures_without_dark_frames_are_named_in_one_note(tmp_path):
    """Each exposure of a per-frame-exposure scan between two dark exposures: one note, not one per exposure."""
    def edit(rows):
        times = iter(np.linspace(1.5, 3.5, 8))
        return [[r[0], r[1], round(float(next(times)), 3), *r[3:]] if r[1] == "coherent" else r for r in rows]

    _lab(tmp_path, darks=True, edit=edit)
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert text.count("no dark frames at") == 1, text
    assert "no dark frames at 8 of the exposures (1.5 … 3.5 ms); their black level is the per-pixel line through " \
           "the dark frames at 1, 4 ms" in text


def test_an_led_matrix_by_row_and_column_needs_its_pitch(tmp_path):
    rows = "path,row,col\n" + "\n".join(f"led{i}.png,{10 + i // 3},{4 + i % 3}" for i in range(9)) + "\n"
    _led_table(tmp_path, rows, {"led_distance_m": 0.06})
    _refused(tmp_path, "leds.csv: led0.png gives only grid indices [row, col]", "illumination.led_pitch_m")
    _led_table(tmp_path, rows, {"led_distance_m": 0.06, "led_pitch_m": 0.004})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    offsets = np.array([[4.0 * (i // 3 - 1), 4.0 * (i % 3 - 1)] for i in range(9)])      # the grid's middle on axis
    expected = offsets / np.sqrt(np.sum(offsets ** 2, axis=1, keepdims=True) + 60.0 ** 2)
    assert np.allclose(_sines(tmp_path / "raw.h5"), -expected, atol=1e-12)
    with h5py.File(tmp_path / "raw.h5") as handle:
        assert handle["/geometry/grid_indices"][()].tolist() == [[i // 3, i % 3] for i in range(9)]


def test_a_column_merely_called_camera_is_the_lab_s_note(tmp_path):
    """A camera model in a column named camera (or cameras beside an LED array) is ignored with the other notes."""
    assert "columns not used by cca, ignored: camera" in _ingested_sines_table(tmp_path, "camera", "Basler acA1920")


def _ingested_sines_table(tmp_path, columns: str, values: str) -> str:
    """Ingest a 3 x 3 LED table of sines with more columns (the same values in every row); its output, one line."""
    rows = f"path,kx_norm,ky_norm,{columns}\n" + "\n".join(
        f"led{i}.png,{0.05 * (i % 3 - 1)},{0.05 * (i // 3 - 1)},{values}" for i in range(9)) + "\n"
    _led_table(tmp_path, rows)
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    return " ".join(result.output.split())


def test_an_exposure_column_named_in_its_unit_is_read_without_a_mapping(tmp_path):
    """A table with exposure_ms needs no columns: entry, and its name says its unit where units: does not; a
    stated unit that the name contradicts is refused, never a silent reading in the other unit."""
    for units in ({"exposure": "ms", "position": "mm"}, {"position": "mm"}):
        _lab(tmp_path, manifest_extra={"columns": {k: v for k, v in MAPPING.items() if k != "exposure"},
                                       "units": units})
        assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
        with h5py.File(tmp_path / "raw.h5") as handle:
            assert np.allclose(np.unique(handle["/raw/exposure_s"][()]), [1e-3, 4e-3])
        (tmp_path / "raw.h5").unlink()
    _lab(tmp_path, manifest_extra={"columns": {k: v for k, v in MAPPING.items() if k != "exposure"},
                                   "units": {"exposure": "s", "position": "mm"}})
    _refused(tmp_path, "column 'exposure_ms' of table.csv looks like ms but units.exposure is s",
             "set units: {exposure: ms}")


def test_an_empty_exposure_cell_among_stated_ones_is_refused(tmp_path):
    def blank_one(rows):
        rows[1][2] = ""
        return rows

    _lab(tmp_path, edit=blank_one)
    _refused(tmp_path, "table.csv: line 3 (p00_4.tif): column 'exposure_ms' is empty",
             "give this image's exposure as the other rows do")


@pytest.mark.parametrize("key, value, fix", [("wavelength_m", 550, "(550e-9 for 550 nm)"),
                                             ("pixel_pitch_m", 2.5, "(2.5e-6 for 2.5 µm)"),
                                             ("focal_length_m", 50, "(50e-3 for 50 mm)")])
def test_lengths_typed_in_another_unit_are_refused_naming_the_setup_file(tmp_path, key, value, fix):
    _lab(tmp_path)
    (tmp_path / "setup.json").write_text(json.dumps({**OPTICS, key: value}))
    _refused(tmp_path, f"setup.json: optics.{key}: {value} m is not a plausible", fix)


def test_a_setup_file_s_own_name_for_a_key_is_pointed_at(tmp_path):
    _lab(tmp_path)
    setup = {k: v for k, v in OPTICS.items() if k != "wavelength_m"}
    (tmp_path / "setup.json").write_text(json.dumps({**setup, "wavelength_nm": 550}))
    _refused(tmp_path, "setup.json: optics.wavelength_m: Field required",
             "setup.json has wavelength_nm (not read): give wavelength_m instead")


@pytest.mark.parametrize("extra, fix", [({"led_pitch_m": 4, "led_distance_m": 0.06}, "(4e-3 for 4 mm)"),
                                        ({"led_pitch_m": 4e-3, "led_distance_m": 60}, "(60e-3 for 60 mm)")])
def test_an_led_matrix_in_millimetres_is_refused(tmp_path, extra, fix):
    rows = "path,row,col\n" + "".join(f"led{i}.png,{i // 3},{i % 3}\n" for i in range(9))
    _led_table(tmp_path, rows, extra)
    _refused(tmp_path, "lab.yaml: illumination.led_", "m is not a plausible LED", fix)


def test_positions_a_thousand_times_too_close_are_refused_and_crowded_ones_noted(tmp_path):
    """Stage positions in metres in a _mm column: every capture on one spot (SAR 1), refused naming the unit to
    check; positions merely crowded (a few % of the pupil apart) get a note."""
    rows = []
    for r in range(3):
        for c in range(3):
            write_image(tmp_path / f"p{r}{c}.png", _codes(800), bit_depth=16)
            rows.append({"path": f"p{r}{c}.png", "exposure_s": 0.01, "stage_x_mm": 0.5 * (c - 1),
                         "stage_y_mm": 0.5 * (r - 1)})

    def ingest_at(scale: float):
        scaled = [{**row, "stage_x_mm": row["stage_x_mm"] * scale, "stage_y_mm": row["stage_y_mm"] * scale}
                  for row in rows]
        (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"optics": OPTICS, "images": scaled}))
        (tmp_path / "raw.h5").unlink(missing_ok=True)
        return _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")

    result = ingest_at(1e-3)
    assert result.exit_code == 2 and not (tmp_path / "raw.h5").exists()
    line = " ".join(result.output.split())
    assert "no LED board or scan is that dense" in line and "units.position" in line
    result = ingest_at(1 / 15)
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "overlap almost wholly" in text and "units.position" in text
    result = ingest_at(1.0)   # at the intended spacing no such note
    assert result.exit_code == 0 and "overlap almost wholly" not in " ".join(result.output.split())


def test_many_dark_bright_field_captures_are_one_note_on_the_geometry(tmp_path):
    """An LED table whose axis is off by one and a half LEDs puts half the bright field on dark-field captures:
    one note says the geometry does not match the light, instead of one "did its LED fire?" per LED."""
    import cca_cli as cca

    sines = cca.led_grid_sines(7, pitch_m=4e-3, height_m=60e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=32)
    y, x = np.mgrid[-32:32, -32:32]
    smooth = (0.2 + np.exp(-(x * x + y * y) / (2 * 12.0 ** 2))).astype(np.complex64)   # no light in the dark field
    images = cca.simulate(smooth, geometry, snr_db=None)
    text = _ingested_led_lab(tmp_path, images, sines, kx_shift=6 / np.hypot(4, 60))
    assert "did its LED fire?" not in text
    assert text.count("the LEDs' geometry does not match the light recorded") == 1


def test_led_positions_crowded_into_the_bright_field_are_one_note_on_the_geometry(tmp_path):
    """LED sines four times too small (a distance or pitch slip): the geometry puts most captures in the bright
    field, where most recorded dark-field light; their median is dark too, so the brightest tell."""
    import cca_cli as cca

    sines = cca.led_grid_sines(7, pitch_m=4e-3, height_m=60e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=32)
    y, x = np.mgrid[-32:32, -32:32]
    smooth = (0.2 + np.exp(-(x * x + y * y) / (2 * 12.0 ** 2))).astype(np.complex64)
    images = cca.simulate(smooth, geometry, snr_db=None)
    text = _ingested_led_lab(tmp_path, images, np.asarray(sines) / 4)
    assert text.count("the LEDs' geometry does not match the light recorded") == 1


def test_unit_columns_with_spaces_two_candidates_and_beside_sines(tmp_path):
    # "exposure [ ms]" announces ms like "exposure_ms": read so unless units say otherwise
    _lab(tmp_path, manifest_extra={"columns": {k: v for k, v in MAPPING.items() if k != "exposure"},
                                   "units": {"position": "mm"}})
    text = (tmp_path / "table.csv").read_text()
    (tmp_path / "table.csv").write_text(text.replace("exposure_ms", "exposure [ ms]", 1))
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as handle:
        assert np.allclose(np.unique(handle["/raw/exposure_s"][()]), [1e-3, 4e-3])
    (tmp_path / "raw.h5").unlink()
    manifest = yaml.safe_load((tmp_path / "lab.yaml").read_text())
    manifest["units"]["exposure"] = "s"
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    _refused(tmp_path, "'exposure [ ms]' of table.csv looks like ms but units.exposure is s")

    def led_table(header: str, rows: list[str]) -> None:
        for i in range(2):
            write_image(tmp_path / f"a{i}.png", np.full((16, 16), 100 + i, np.uint16), bit_depth=16)
        (tmp_path / "t.csv").write_text("\n".join([header, *rows]) + "\n")
        (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"images_csv": "t.csv", "illumination": {
            "wavelength_m": 5e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1e-6}}))

    # two columns that could be the exposure: say which
    led_table("path,kx_norm,ky_norm,Exposure_s,exposure_ms", ["a0.png,0.0,0,0.01,10", "a1.png,0.05,0,0.01,10"])
    _refused(tmp_path, "t.csv has 'Exposure_s' and 'exposure_ms'", "columns: {exposure: <column>}")
    # an LED table's stage columns in another unit are the lab's notes, as before
    led_table("path,kx_norm,ky_norm,exposure_s,stage_x_um,stage_y_um", ["a0.png,0.0,0,0.01,5,5", "a1.png,0.05,0,0.01,6,6"])
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert "ignored: stage_x_um, stage_y_um" in " ".join(result.output.split())


def test_a_spreadsheet_s_table_is_read_as_it_is_saved(tmp_path):
    """A byte-order mark ("CSV UTF-8") is dropped; semicolon- or tab-separated tables are read so, with a note, and
    so are their decimal commas."""
    rows = _grid_rows()
    _led_table(tmp_path, rows, {"led_distance_m": 0.06})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    expected = _sines(tmp_path / "raw.h5")
    import re

    german = re.sub(r"(\d)\.(\d)", r"\1,\2", rows.replace(",", ";"))   # Excel in a decimal-comma locale
    assert "4,0" in german
    for text, note in (("\ufeff" + rows, None), (rows.replace(",", ";"), "separated by semicolons"),
                       ("\ufeff" + rows.replace(",", "\t"), "separated by tabs"),
                       (german, "decimal commas in led_x_mm, led_y_mm read as decimal points")):
        (tmp_path / "raw.h5").unlink()
        (tmp_path / "leds.csv").write_text(text, encoding="utf-8")
        result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
        assert result.exit_code == 0, result.output
        assert np.array_equal(_sines(tmp_path / "raw.h5"), expected)
        assert note is None or note in " ".join(result.output.split())


def test_a_table_whose_position_columns_are_not_found_names_its_columns_and_the_fix(tmp_path):
    rows = _grid_rows().replace("led_x_mm,led_y_mm", "x (mm),y (mm)")
    _led_table(tmp_path, rows, {"led_distance_m": 0.06})
    _refused(tmp_path, "leds.csv: line 2 (led0.png): no position column found",
             "leds.csv has path, x (mm), y (mm)", "columns: {led_x: <column>, led_y: <column>}")


def test_a_missing_image_is_named_with_its_table_line_and_unlisted_ones_noted(tmp_path):
    _led_table(tmp_path, _grid_rows(), {"led_distance_m": 0.06})
    (tmp_path / "led7.png").rename(tmp_path / "elsewhere.png")
    _refused(tmp_path, "led7.png: named by line 9 of", "leds.csv but not found; check that row")
    (tmp_path / "elsewhere.png").rename(tmp_path / "led7.png")
    write_image(tmp_path / "led9.png", np.full((32, 32), 200, np.uint16), bit_depth=16)   # not in the table
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "holds 1 more .png file(s) than leds.csv lists (led9.png); they are not read" in text
    assert "no image gives its exposure: each is taken as 1 s" in text


def test_a_matlab_file_s_table_without_sines_is_one_line_naming_its_columns(tmp_path):
    import scipy.io

    scipy.io.savemat(tmp_path / "stack.mat", {"imlow_HDR": np.ones((16, 16, 4), np.float32)})
    (tmp_path / "leds.csv").write_text("\ufeffled_x_mm,led_y_mm\n" + "".join(f"{i},{i}\n" for i in range(4)))
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({
        "illumination": {"wavelength_m": 5e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1e-6},
        "source": {"mat": "stack.mat", "illumination_csv": "leds.csv"}}))
    _refused(tmp_path, "leds.csv gives LED positions (led_x_mm, led_y_mm) but not their height above the sample",
             "illumination.led_distance_m")
    (tmp_path / "leds.csv").write_text("\ufeffx,y\n" + "".join(f"{i},{i}\n" for i in range(4)))
    text = _refused(tmp_path, "leds.csv: needs the columns kx_norm and ky_norm", "its columns: x, y",
                    "kx_norm = x / √(x² + y² + z²)")
    assert "('kx_norm')" not in text


def test_a_matlab_file_s_table_of_led_positions_gives_the_sines_an_image_table_would(tmp_path):
    import scipy.io

    stack = np.full((16, 16, 9), 100, np.uint16)
    stack[4:12, 4:12, :] += 50
    stack[..., 4] += 900
    scipy.io.savemat(tmp_path / "stack.mat", {"imlow_HDR": stack})
    (tmp_path / "leds.csv").write_text("led_x_mm,led_y_mm\n" + "".join(f"{4.0 * (i % 3 - 1)},{4.0 * (i // 3 - 1)}\n"
                                                                       for i in range(9)))
    illumination = {"wavelength_m": 5e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1e-6,
                    "led_distance_m": 0.06, "led_axis_m": [0.001, 0.0]}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"illumination": illumination,
                                                       "source": {"mat": "stack.mat", "illumination_csv": "leds.csv"}}))
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    offsets = np.array([[4.0 * (i // 3 - 1), 4.0 * (i % 3 - 1) - 1.0] for i in range(9)])   # [y, x] mm from the axis
    expected = offsets / np.sqrt(np.sum(offsets ** 2, axis=1, keepdims=True) + 60.0 ** 2)
    assert np.allclose(_sines(tmp_path / "raw.h5"), -expected, atol=1e-12)


def test_a_table_without_a_file_column_names_its_files_by_a_pattern(tmp_path):
    """The lab's table as it is (index, x, y): image_files makes each row's file name from its cells."""
    rows = _grid_rows()
    _led_table(tmp_path, rows, {"led_distance_m": 0.06})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    expected = _sines(tmp_path / "raw.h5")
    for i in range(9):
        (tmp_path / f"led{i}.png").rename(tmp_path / f"img_{i:03d}.png")
    lines = rows.splitlines()
    (tmp_path / "leds.csv").write_text("index,x_mm,y_mm\n" + "".join(
        f"{i}," + ",".join(line.split(",")[1:]) + "\n" for i, line in enumerate(lines[1:])))
    text = (tmp_path / "lab.yaml").read_text()
    (tmp_path / "lab.yaml").write_text(text + "image_files: img_{index:03d}.png\ncolumns: {led_x: x_mm, led_y: y_mm}\n")
    (tmp_path / "raw.h5").unlink()
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert np.array_equal(_sines(tmp_path / "raw.h5"), expected)
    assert "ignored" not in " ".join(result.output.split())      # the index column is used
    (tmp_path / "raw.h5").unlink()
    (tmp_path / "lab.yaml").write_text(text + "image_files: img_{number:03d}.png\ncolumns: {led_x: x_mm, led_y: y_mm}\n")
    _refused(tmp_path, "image_files 'img_{number:03d}.png' names 'number', which leds.csv lacks",
             "its columns: index, x_mm, y_mm")
    (tmp_path / "lab.yaml").write_text(text + "columns: {led_x: x_mm, led_y: y_mm}\n")
    _refused(tmp_path, "leds.csv: no file column", "image_files: img_{index:03d}.tif")


def test_image_files_keeps_a_cell_s_text_unless_its_field_asks_for_a_number(tmp_path):
    from cca_cli.errors import ConfigError
    from cca_cli.io.manifest import _file_of_row

    row = {"index": "001", "x": "2.50", "name": "a"}
    assert _file_of_row("img_{index}.tif", row, tmp_path / "t.csv", 2) == "img_001.tif"
    assert _file_of_row("img_{index:04d}_{x:.1f}_{name}.tif", row, tmp_path / "t.csv", 2) == "img_0001_2.5_a.tif"
    with pytest.raises(ConfigError, match="line 2: image_files"):
        _file_of_row("img_{name:03d}.tif", row, tmp_path / "t.csv", 2)


def test_a_row_with_empty_position_cells_is_not_told_its_table_lacks_position_columns(tmp_path):
    rows = _grid_rows().replace("led0.png,-4.0,-4.0", "led0.png,,")
    _led_table(tmp_path, rows, {"led_distance_m": 0.06})
    text = _refused(tmp_path, "leds.csv: line 2 (led0.png)")
    assert "no position column found" not in text


def test_a_calibration_view_without_the_board_is_named_by_its_own_file(tmp_path):
    """The board is looked for in the calibration images: the error names that image, not the position's capture."""
    _lab(tmp_path, calibration=True)   # the calibration images hold noise, no board
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    assert runner.invoke(app, ["hdr", str(tmp_path / "raw.h5"), "-o", str(tmp_path / "hdr.h5"), "-q"]).exit_code == 0
    with h5py.File(tmp_path / "hdr.h5") as f:
        assert list(f["/registration/board_views"].attrs["files"]) == ["cal00.tif", "cal01.tif", "cal10.tif",
                                                                       "cal11.tif"]
    result = runner.invoke(app, ["register", str(tmp_path / "hdr.h5"), "-o", str(tmp_path / "reg.h5"), "-q"])
    text = " ".join(result.output.split())
    assert result.exit_code == 3 and text.startswith("error: cal"), text
    assert "tif (the board's view at grid position (row" in text and "p0" not in text and "no 4x3 checkerboard" in text


def _mat_lab(tmp_path, sensor: dict) -> None:
    """A 3 x 3 LED stack in a MATLAB file (H, W, K), 16-bit counts over a black level of 100."""
    import scipy.io

    k = 9
    stack = np.full((32, 32, k), 100, np.uint16)
    stack[..., 4] += 3000                              # the centre LED: bright field
    stack[8:24, 8:24, :] += 400                        # something to see in every image
    scipy.io.savemat(tmp_path / "stack.mat", {"frames": stack})
    sines = [(0.06 * (i % 3 - 1), 0.06 * (i // 3 - 1)) for i in range(k)]
    (tmp_path / "sines.csv").write_text("kx_norm,ky_norm\n" + "".join(f"{x},{y}\n" for x, y in sines))
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({
        "illumination": {"wavelength_m": 5.3e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1.6e-6},
        "source": {"mat": "stack.mat", "variable": "frames", "illumination_csv": "sines.csv"}, "sensor": sensor}))


def test_a_matlab_stack_takes_the_sensor_s_black_and_white_levels(tmp_path):
    _mat_lab(tmp_path, {"black_level": 100, "bit_depth": 12})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as f:
        intensity = f["/measurements/intensity"][()]
        assert f["/raw/frames"].attrs["saturation_level"] == 4095 - 100
    assert intensity.min() == 0 and intensity[4].max() == 3400   # the black level is subtracted
    (tmp_path / "raw.h5").unlink()
    _mat_lab(tmp_path, {"black_level": 100, "channel": "G"})
    _refused(tmp_path, "sensor.channel does not apply to a MATLAB variable (source.mat)", "remove it")
    _mat_lab(tmp_path, {"black_level": 5000, "white_level": 7})
    _refused(tmp_path, "sensor.black_level (5000) is not below the white level (7)")


@pytest.mark.parametrize("clipped, noted", [(40, True), (3, False)])
def test_twelve_bit_frames_clipping_in_sixteen_bit_files_without_a_bit_depth_are_noted(tmp_path, clipped, noted):
    """LSB-aligned 12-bit codes (nothing in the low bits to tell) with a bright spot clipped at 4095."""
    rows = []
    for i in range(4):
        frame = _codes(900 + 300 * i)
        if i == 3:
            frame.flat[:clipped] = 4095
        write_image(tmp_path / f"p{i}.png", frame, bit_depth=16)
        rows.append({"path": f"p{i}.png", "exposure_s": 0.01, "stage_x_mm": 0.5 * (i % 2), "stage_y_mm": 0.5 * (i // 2)})
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"optics": OPTICS, "images": rows}))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert (f"{clipped} pixels of p3.png sit at exactly 4095 = 2^12 − 1" in text
            and "state sensor.bit_depth: 12 (or sensor.white_level: 4095)" in text) is noted


def test_an_led_table_with_its_sines_swapped_is_warned_of_at_ingest(tmp_path):
    import cca_cli as cca

    sines = cca.led_grid_sines(7, pitch_m=3e-3, height_m=60e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=48)
    images = cca.simulate(cca.resolution_chart(96, widths=(6, 4, 3, 2)).image, geometry, snr_db=40)
    assert "far better" not in _ingested_led_lab(tmp_path, images, sines)
    (tmp_path / "raw.h5").unlink()
    text = _ingested_led_lab(tmp_path, images, np.asarray(sines)[:, ::-1])
    assert text.count("warning:") == 1
    assert "lab.yaml: the captures fit far better with their positions' x and y swapped" in text
    assert "exchange the x and y position columns" in text


def test_an_exposure_column_without_a_unit_says_how_to_give_it(tmp_path):
    _scan_table(tmp_path, exposures=(10, 20))
    table = (tmp_path / "table.csv").read_text().replace("exposure_ms", "Exposure")
    (tmp_path / "table.csv").write_text(table)
    manifest = yaml.safe_load((tmp_path / "lab.yaml").read_text())
    del manifest["columns"]["exposure"]
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    _refused(tmp_path, "table.csv's column 'Exposure' gives no unit", "columns: {exposure: Exposure}",
             "units: {exposure: ms}")
    manifest["columns"]["exposure"] = "Exposure"
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0


def test_a_table_without_a_header_line_says_so(tmp_path):
    _scan_table(tmp_path)
    lines = (tmp_path / "table.csv").read_text().splitlines()
    (tmp_path / "table.csv").write_text("\n".join(lines[1:]) + "\n")
    _refused(tmp_path, "table.csv: its first line holds values (p00_10.png, coherent, 10, -0.600)",
             "add a header line naming the columns")


def test_an_led_array_s_object_pixel_may_be_the_camera_s_over_the_magnification(tmp_path):
    _led_table(tmp_path, _grid_rows(), {"led_distance_m": 0.06})
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as f:
        given = dict(f["geometry"].attrs)
    manifest = yaml.safe_load((tmp_path / "lab.yaml").read_text())
    del manifest["illumination"]["pixel_pitch_object_m"]          # 1 µm at the sample
    manifest["illumination"].update(pixel_pitch_m=6.5e-6, magnification=6.5)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    (tmp_path / "raw.h5").unlink()
    assert _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5").exit_code == 0
    with h5py.File(tmp_path / "raw.h5") as f:
        assert dict(f["geometry"].attrs)["pixel_pitch_m"] == pytest.approx(given["pixel_pitch_m"], rel=1e-12)
    manifest["illumination"]["pixel_pitch_object_m"] = 1e-6
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    (tmp_path / "raw.h5").unlink()
    _refused(tmp_path, "illumination: give either pixel_pitch_object_m or pixel_pitch_m with magnification, not both")


def test_a_wide_led_board_given_by_its_indices_is_not_taken_for_slipped_digits(tmp_path):
    """A flat 17 x 17 board reaching sin θ 0.45: its sines bend away from a lattice, and nothing is wrong."""
    lines = ["path,row,col"]
    for i in range(17 * 17):
        write_image(tmp_path / f"led{i}.png", np.full((16, 16), 2000 if i == 144 else 200, np.uint16) + (
            np.arange(256, dtype=np.uint16).reshape(16, 16) % 7), bit_depth=16)
        lines.append(f"led{i}.png,{i // 17},{i % 17}")
    (tmp_path / "leds.csv").write_text("\n".join(lines) + "\n")
    illumination = {"wavelength_m": 5e-7, "numerical_aperture": 0.1, "pixel_pitch_object_m": 1e-6,
                    "led_pitch_m": 5e-3, "led_distance_m": 0.08}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"images_csv": "leds.csv", "illumination": illumination}))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert np.abs(_sines(tmp_path / "raw.h5")).max() > 0.4


def test_a_cell_that_is_not_a_number_is_named_with_its_line_and_image(tmp_path):
    _scan_table(tmp_path, edit=lambda lines: [line.replace(",10,", ",ten,") if line.startswith("p12_10.png") else line
                                              for line in lines])
    _refused(tmp_path, "table.csv: line 8 (p12_10.png): column 'exposure_ms' is 'ten', not a number; fix the row")


def test_positions_in_centimetres_are_read_by_their_column_s_name_or_units(tmp_path):
    _scan_table(tmp_path)
    expected = None
    for header, units in (("x_mm,y_mm", {"exposure": "ms", "position": "mm"}),
                          ("x_cm,y_cm", {"exposure": "ms"}), ("x,y", {"exposure": "ms", "position": "cm"})):
        table = (tmp_path / "table.csv").read_text().splitlines()
        cells = [line.split(",") for line in table[1:]]
        scale = 1.0 if header == "x_mm,y_mm" else 0.1
        rows = [",".join([c[0], c[1], c[2], f"{float(c[3]) * scale:g}", f"{float(c[4]) * scale:g}", c[5], c[6]])
                for c in cells]
        (tmp_path / f"t_{units.get('position', 'name')}.csv").write_text(
            "\n".join([f"file,kind,exposure_ms,{header},r,c", *rows]) + "\n")
        x, y = header.split(",")
        manifest = {"images_csv": f"t_{units.get('position', 'name')}.csv", "optics": OPTICS, "units": units,
                    "columns": {"path": "file", "kind": "kind", "exposure": "exposure_ms", "stage_x": x,
                                "stage_y": y, "row": "r", "col": "c"}}
        (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
        out = tmp_path / f"raw_{units.get('position', 'name')}.h5"
        result = _ingest(tmp_path / "lab.yaml", out)
        assert result.exit_code == 0, (header, result.output)
        with h5py.File(out) as f:
            centres = f["/geometry/aperture_centres_yx_m"][()]
        expected = centres if expected is None else expected
        np.testing.assert_allclose(centres, expected, rtol=1e-12)


def _camera_table(tmp_path, camera_of, board_camera=None) -> None:
    """The 4 x 4 scan as a camera array: a camera column (``camera_of(r, c)``), and board rows when asked."""
    _scan_table(tmp_path)
    lines = (tmp_path / "table.csv").read_text().splitlines()
    rows = [lines[0] + ",cam"] + [f"{line},{camera_of(int(line.split(',')[5]), int(line.split(',')[6]))}"
                                  for line in lines[1:]]
    if board_camera is not None:   # a board photo at every position, the one at (0, 0) naming board_camera
        for r in range(4):
            for c in range(4):
                write_image(tmp_path / f"board{r}{c}.png", _codes(900), bit_depth=16)
                camera = board_camera if (r, c) == (0, 0) else camera_of(r, c)
                rows.append(f"board{r}{c}.png,calibration,10,{0.4 * c - 0.6:.3f},{0.4 * r - 0.6:.3f},{r},{c},{camera}")
    (tmp_path / "table.csv").write_text("\n".join(rows) + "\n")
    manifest = yaml.safe_load((tmp_path / "lab.yaml").read_text())
    manifest["columns"]["camera"] = "cam"
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))


def test_a_camera_named_at_two_positions_is_noted_and_a_board_of_another_camera_refused(tmp_path):
    _camera_table(tmp_path, lambda r, c: 4 * r + c if (r, c) != (0, 1) else 0)
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "camera 0 took the images at 2 positions" in text and "fix the camera column" in text
    (tmp_path / "raw.h5").unlink()
    _camera_table(tmp_path, lambda r, c: 4 * r + c, board_camera=5)
    _refused(tmp_path, "calibration image board00.png names camera 5 but the images at grid position (row 0, col 0) "
                       "name camera 0")


def test_a_crop_the_frames_cannot_hold_is_refused_right_after_ingest(tmp_path):
    _lab(tmp_path, calibration=True)
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({
        "run": {"stages": ["ingest", "hdr", "register", "reconstruct", "report"]},
        "ingest": {"manifest": "lab.yaml"}, "registration": {"crop_xywh": [10, 4, 16, 16]}}))
    result = runner.invoke(app, ["run", str(tmp_path / "run.yaml"), "--out-dir", str(tmp_path / "out"), "-q"])
    text = " ".join(result.output.split())
    assert result.exit_code == 2, text
    assert "run.yaml: registration.crop_xywh: (10, 4, 16, 16) does not fit in the 20x16 px frames" in text
    assert sorted(p.name for p in (tmp_path / "out").iterdir() if not p.name.startswith(".")) == ["raw.h5"]
