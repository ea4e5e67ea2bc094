"""The catalogue: bad input, careless use and faults, one row each.

A case is a command line run in a fresh folder holding ``files``. A failing
case must exit with ``exit``, print exactly one line on stderr that contains
every string of ``says`` (the file or key, and often the fix) and none of
``not_says``, and leave every file it found unchanged. A case with
``exit=0`` must work; it may change only the paths in ``writes`` and passes
``check(folder, result)`` when given.

Categories: data-loss, silent (wrong result without a word), resources,
traceback, hang, faults, messages, validation (bad values), usage (careless
command lines), works (odd but valid input that must simply work).

Exit codes: 2 config or usage, 3 input file, 4 output, 5 memory or disk, 6 run
folder in use, 130 interrupted.
"""

from __future__ import annotations

import errno
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from makers import (DROP, Bytes, Checkpoint, Config, Copy, Fifo, Folder, H5, Simulated, SweepFolder, Symlink, Text,
                    Truncated, drop, set_attr, set_data)

__all__ = ["Case", "CASES"]


@dataclass(frozen=True)
class Case:
    id: str
    category: str
    argv: list[str]
    files: dict = field(default_factory=dict)
    exit: int = 2
    says: tuple[str, ...] = ()
    not_says: tuple[str, ...] = ("Traceback", "internal error")
    writes: tuple[str, ...] = ()
    env: dict = field(default_factory=dict)
    patch: Callable[[Any, Path], Any] | None = None  # (monkeypatch, folder); may return a cleanup callable
    check: Callable[[Path, Any], None] | None = None
    cwd: str = "."
    seconds: float = 20.0


CASES: list[Case] = []


def case(*args, **kwargs) -> None:
    CASES.append(Case(*args, **kwargs))


SIM = ["simulate", "cfg.yaml", "-o", "c.h5", "-q"]
REC = ["reconstruct", "in.h5", "-o", "r.h5", "-q"]
REP = ["report", "in.h5", "-o", "rep"]
RUN = ["run", "cfg.yaml", "--out-dir", "out", "-q"]
HEADLINE_SIZES = {"scene.size_px": 512, "scene.field_width_m": 64e-3, "simulate.store": "sensor",
                  "scene.widths_px": DROP}


def config_case(id, category, overrides, says, *, exit=2, argv=SIM, **kwargs):
    """A config value that must be refused when the config is loaded (before anything runs)."""
    case(id, category, argv, {"cfg.yaml": Config(overrides)}, exit=exit, says=("cfg.yaml",) + tuple(says), **kwargs)


# --- tracebacks named by the issue --------------------------------------------------------------------------------
config_case("wavelength-inf", "traceback", {"optics.wavelength_m": float("inf")}, ["optics.wavelength_m"])
config_case("field-width-inf", "traceback", {"scene.field_width_m": float("inf")}, ["scene.field_width_m"])
config_case("seed-negative", "traceback", {"noise.seed": -5}, ["noise.seed"])
config_case("poisson-photons-1e25", "traceback",
            {"noise.model": "poisson", "noise.photons_per_unit": 1e25}, ["noise.photons_per_unit"])
config_case("momentum-batch-1.5", "traceback",
            {"reconstruct.engine": "momentum", "reconstruct.options": {"batch": 1.5}}, ["batch"])
for value in (0, 1.5, "nan"):
    case(f"report-threshold-{value}", "traceback", ["report", "in.h5", "-o", "rep", "--threshold", str(value)],
         {"in.h5": Copy("recon")}, exit=2, says=("--threshold",))
config_case("surface-seed-negative", "traceback",
            {"scene.surface_phase": "random", "scene.surface_seed": -1}, ["scene.surface_seed"])

# --- silent wrong results named by the issue -----------------------------------------------------------------------
config_case("position-refinement-string-no", "silent",
            {"reconstruct.engine": "momentum", "reconstruct.options": {"position_refinement": "no"}},
            ["position_refinement", "none, global, per_image, both"])
config_case("tau-inf", "silent", {"reconstruct.tau": float("inf")}, ["reconstruct.tau"])
config_case("seed-true", "silent", {"noise.seed": True}, ["noise.seed"])
config_case("stages-empty", "silent", {"run.stages": []}, ["run.stages"], argv=RUN)
case("config-empty", "silent", SIM, {"cfg.yaml": Text("")}, exit=2, says=("cfg.yaml", "empty"))
case("config-only-comments", "silent", SIM, {"cfg.yaml": Text("# nothing here yet\n\n")}, exit=2,
     says=("cfg.yaml", "empty"))
case("config-dev-null", "silent", ["simulate", "/dev/null", "-o", "c.h5", "-q"], exit=2, says=("/dev/null",))
config_case("momentum-batch-12.7", "silent",
            {"reconstruct.engine": "momentum", "reconstruct.options": {"batch": 12.7}}, ["batch"])
config_case("options-string-true", "silent",
            {"reconstruct.engine": "momentum", "reconstruct.options": {"pupil_estimate": "yes please"}},
            ["pupil_estimate"])
config_case("report-figures-string", "silent", {"report.figures": "no"}, ["report.figures"])
config_case("altmin-chunk-true", "silent", {"reconstruct.options": {"chunk": True}}, ["chunk"])
config_case("grid-true", "silent", {"array.grid": True}, ["array.grid"])
config_case("size-px-true", "silent", {"scene.size_px": True}, ["scene.size_px"])
config_case("wavelength-true", "silent", {"optics.wavelength_m": True}, ["optics.wavelength_m"])
case("duplicate-section", "silent", SIM,
     {"cfg.yaml": Text("array: {grid: 3, overlap: 0.61}\nscene: {size_px: 64, field_width_m: 8e-3}\n"
                       "reconstruct: {iterations: 3}\nreconstruct: {tau: 1}\n")},
     exit=2, says=("cfg.yaml", "reconstruct", "twice"))
case("duplicate-key", "silent", SIM,
     {"cfg.yaml": Text("array: {grid: 3, grid: 5}\nscene: {size_px: 64, field_width_m: 8e-3}\n")},
     exit=2, says=("cfg.yaml", "grid", "twice"))
case("workers-0", "silent", ["sweep", "grid", "cfg.yaml", "--set", "noise.snr_db=20,30", "--workers", "0",
                             "--out-dir", "sw"], {"cfg.yaml": Config()}, exit=2, says=("--workers",))
case("workers-negative", "usage", ["sweep", "grid", "cfg.yaml", "--set", "noise.snr_db=20,30", "--workers", "-2",
                                   "--out-dir", "sw"], {"cfg.yaml": Config()}, exit=2, says=("--workers",))


def _png_back(folder: Path, result) -> None:
    assert (folder / "out" / "report" / "observed.png").is_file() or any((folder / "out" / "report").glob("*.png"))
    document = json.loads((folder / "out" / "report" / "report.json").read_text())
    for name in document["figures"]:
        assert (folder / "out" / "report" / name).is_file(), name


def _delete_pngs(path: Path) -> None:
    for png in sorted((path / "report").glob("*.png"))[::2]:
        png.unlink()


case("report-pngs-deleted", "silent", RUN,
     {"cfg.yaml": Config({"report.figures": True}), "out": Copy("run_dir", _delete_pngs)},
     exit=0, writes=("out/report", "out/.cca-run.lock"), check=_png_back)


def _zero(a):
    return np.zeros_like(a)


def _add_weight(path: Path, value, shape=None) -> None:
    import h5py

    with h5py.File(path, "r+") as handle:
        intensity = handle["/measurements/intensity"]
        weight = np.full(shape or intensity.shape, value, np.float32)
        handle.create_dataset("/measurements/weight", data=weight)


case("weights-all-zero", "silent", REC, {"in.h5": Copy("captures", lambda p: _add_weight(p, 0.0))},
     exit=3, says=("in.h5", "/measurements/weight"))
case("weights-nan", "silent", REC, {"in.h5": Copy("captures", lambda p: _add_weight(p, np.nan))},
     exit=3, says=("in.h5", "/measurements/weight"))
case("weights-above-one", "silent", REC, {"in.h5": Copy("captures", lambda p: _add_weight(p, 7.0))},
     exit=3, says=("in.h5", "/measurements/weight"))
case("weights-negative", "silent", REC, {"in.h5": Copy("captures", lambda p: _add_weight(p, -1.0))},
     exit=3, says=("in.h5", "/measurements/weight"))
case("intensity-all-zero", "silent", REC, {"in.h5": Copy("captures", set_data("/measurements/intensity", _zero))},
     exit=3, says=("in.h5", "/measurements/intensity"))
case("intensity-negative", "silent", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: -a))},
     exit=3, says=("in.h5", "/measurements/intensity"))


def _negate_one(a):
    a = a.copy()
    a[4] = -a[4]
    return a


case("intensity-one-image-negative", "silent", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", _negate_one))},
     exit=3, says=("in.h5", "image 4"))
case("intensity-constant", "silent", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: np.ones_like(a)))},
     exit=3, says=("in.h5", "/measurements/intensity"))
case("recon-intensity-nan", "silent", REP,
     {"in.h5": Copy("recon", set_data("/recon/intensity", lambda a: np.full_like(a, np.nan)))},
     exit=3, says=("in.h5", "/recon/intensity"))
case("recon-object-nan", "silent", REP,
     {"in.h5": Copy("recon", set_data("/recon/object", lambda a: np.full_like(a, np.nan)))},
     exit=3, says=("in.h5", "/recon/object"))

# --- data loss -----------------------------------------------------------------------------------------------------
EXPERIMENT = Folder({"recon.h5": Copy("recon"), "captures.h5": Copy("captures"), "notes.txt": Text("my notes\n"),
                     "raw": Folder({"img0.tif": Bytes(b"II*\x00raw")})})
case("report-over-its-experiment", "data-loss", ["report", "myexp/recon.h5", "-o", "myexp", "--force"],
     {"myexp": EXPERIMENT}, exit=4, says=("myexp",))
case("report-over-cwd-absolute", "data-loss", ["report", "recon.h5", "-o", "{cwd}", "--force"],
     {"recon.h5": Copy("recon"), "notes.txt": Text("keep me\n")}, exit=4, says=())
case("report-over-dot", "data-loss", ["report", "recon.h5", "-o", ".", "--force"],
     {"recon.h5": Copy("recon"), "notes.txt": Text("keep me\n")}, exit=4, says=())
case("report-over-parent", "data-loss", ["report", "recon.h5", "-o", "..", "--force"],
     {"work/sub/recon.h5": Copy("recon"), "work/notes.txt": Text("keep me\n")}, exit=4, says=("..",), cwd="work/sub")
case("report-over-foreign-folder", "data-loss", ["report", "recon.h5", "-o", "thesis", "--force"],
     {"recon.h5": Copy("recon"), "thesis": Folder({"chapter1.tex": Text("\\chapter{One}\n")})},
     exit=4, says=("thesis",))
case("report-over-foreign-folder-no-force", "data-loss", ["report", "recon.h5", "-o", "thesis"],
     {"recon.h5": Copy("recon"), "thesis": Folder({"chapter1.tex": Text("\\chapter{One}\n")})},
     exit=4, says=("thesis",))
case("report-over-empty-folder", "data-loss", ["report", "recon.h5", "-o", "empty", "--force"],
     {"recon.h5": Copy("recon"), "empty": Folder()}, exit=4, says=("empty",))
case("report-over-report-with-notes", "data-loss", ["report", "recon.h5", "-o", "rep", "--force"],
     {"recon.h5": Copy("recon"), "rep": Copy("report", lambda p: (p / "my_notes.txt").write_text("mine\n"))},
     exit=4, says=("my_notes.txt",))
case("report-over-own-report", "works", ["report", "recon.h5", "-o", "rep", "--force", "--no-figures"],
     {"recon.h5": Copy("recon"), "rep": Copy("report")}, exit=0, writes=("rep",))
case("report-to-existing-file", "data-loss", ["report", "recon.h5", "-o", "notes.txt"],
     {"recon.h5": Copy("recon"), "notes.txt": Text("keep me\n")}, exit=4, says=("notes.txt",))
case("report-to-existing-file-force", "data-loss", ["report", "recon.h5", "-o", "notes.txt", "--force"],
     {"recon.h5": Copy("recon"), "notes.txt": Text("keep me\n")}, exit=4, says=("notes.txt",))
case("report-over-its-input-file", "data-loss", ["report", "recon.h5", "-o", "recon.h5", "--force"],
     {"recon.h5": Copy("recon")}, exit=4, says=("recon.h5",))
case("report-parent-is-file", "traceback", ["report", "recon.h5", "-o", "notes.txt/rep"],
     {"recon.h5": Copy("recon"), "notes.txt": Text("keep me\n")}, exit=4, says=("notes.txt",))
case("report-unwritable", "traceback", ["report", "recon.h5", "-o", "/proc/cca-report"],
     {"recon.h5": Copy("recon")}, exit=4, says=("/proc",))
case("reconstruct-over-input", "data-loss", ["reconstruct", "o.h5", "-o", "o.h5", "--force", "-q"],
     {"o.h5": Copy("captures")}, exit=4, says=("o.h5",))
case("reconstruct-over-input-dotted", "data-loss", ["reconstruct", "o.h5", "-o", "./sub/../o.h5", "--force", "-q"],
     {"o.h5": Copy("captures"), "sub": Folder()}, exit=4, says=("o.h5",))
case("reconstruct-over-input-symlink", "data-loss", ["reconstruct", "link.h5", "-o", "o.h5", "--force", "-q"],
     {"o.h5": Copy("captures"), "link.h5": Symlink("o.h5")}, exit=4, says=("o.h5",))
case("reconstruct-over-input-via-symlinked-output", "data-loss",
     ["reconstruct", "o.h5", "-o", "link.h5", "--force", "-q"],
     {"o.h5": Copy("captures"), "link.h5": Symlink("o.h5")}, exit=4, says=("link.h5",))
case("reconstruct-to-existing-dir", "traceback", ["reconstruct", "c.h5", "-o", "results", "-q"],
     {"c.h5": Copy("captures"), "results": Folder({"a.txt": Text("a")})}, exit=4, says=("results",))
case("reconstruct-to-existing-dir-force", "traceback", ["reconstruct", "c.h5", "-o", "results", "--force", "-q"],
     {"c.h5": Copy("captures"), "results": Folder({"a.txt": Text("a")})}, exit=4, says=("results",))
case("reconstruct-over-foreign-text", "data-loss", ["reconstruct", "c.h5", "-o", "notes.txt", "--force", "-q"],
     {"c.h5": Copy("captures"), "notes.txt": Text("keep me\n")}, exit=4, says=("notes.txt",))
case("reconstruct-over-foreign-h5", "data-loss", ["reconstruct", "c.h5", "-o", "data.h5", "--force", "-q"],
     {"c.h5": Copy("captures"), "data.h5": H5(lambda h: h.create_dataset("x", data=np.arange(3)))},
     exit=4, says=("data.h5",))
case("reconstruct-over-truncated", "data-loss", ["reconstruct", "c.h5", "-o", "r.h5", "--force", "-q"],
     {"c.h5": Copy("captures"), "r.h5": Truncated("recon", 0.5)}, exit=4, says=("r.h5",))
case("reconstruct-over-own-recon", "works", ["reconstruct", "c.h5", "-o", "r.h5", "--force", "-q", "--iterations", "3"],
     {"c.h5": Copy("captures"), "r.h5": Copy("recon")}, exit=0, writes=("r.h5",))
case("reconstruct-parent-is-file", "traceback", ["reconstruct", "c.h5", "-o", "notes.txt/r.h5", "-q"],
     {"c.h5": Copy("captures"), "notes.txt": Text("keep me\n")}, exit=4, says=("notes.txt",))
case("reconstruct-output-dot", "traceback", ["reconstruct", "c.h5", "-o", ".", "--force", "-q"],
     {"c.h5": Copy("captures")}, exit=4, says=())
case("reconstruct-output-empty", "usage", ["reconstruct", "c.h5", "-o", "", "-q"],
     {"c.h5": Copy("captures")}, exit=4, says=())
case("reconstruct-unwritable", "traceback", ["reconstruct", "c.h5", "-o", "/proc/cca-r.h5", "-q"],
     {"c.h5": Copy("captures")}, exit=4, says=("/proc",), seconds=5)
case("reconstruct-new-subfolder", "works", ["reconstruct", "c.h5", "-o", "new/deeper/r.h5", "-q", "--iterations", "3"],
     {"c.h5": Copy("captures")}, exit=0, writes=("new",))
case("simulate-over-config", "data-loss", ["simulate", "cfg.yaml", "-o", "cfg.yaml", "--force", "-q"],
     {"cfg.yaml": Config()}, exit=4, says=("cfg.yaml",))
case("simulate-over-config-no-force", "data-loss", ["simulate", "cfg.yaml", "-o", "cfg.yaml", "-q"],
     {"cfg.yaml": Config()}, exit=4, says=("cfg.yaml",))
case("simulate-over-foreign-h5", "data-loss", ["simulate", "cfg.yaml", "-o", "mine.h5", "--force", "-q"],
     {"cfg.yaml": Config(), "mine.h5": H5(lambda h: h.create_dataset("x", data=np.arange(3)))},
     exit=4, says=("mine.h5",))
case("simulate-unwritable", "traceback", ["simulate", "cfg.yaml", "-o", "/proc/cca/c.h5", "-q"],
     {"cfg.yaml": Config()}, exit=4, says=("/proc",))
case("simulate-over-own-captures", "works", ["simulate", "cfg.yaml", "-o", "c.h5", "--force", "-q"],
     {"cfg.yaml": Config(), "c.h5": Copy("captures")}, exit=0, writes=("c.h5",))
case("run-foreign-captures", "data-loss", RUN,
     {"cfg.yaml": Config(), "out": Folder({"captures.h5": Text("my own file\n")})}, exit=4, says=("captures.h5",))
case("run-foreign-captures-force", "data-loss", RUN + ["--force"],
     {"cfg.yaml": Config(), "out": Folder({"captures.h5": Text("my own file\n")})}, exit=4, says=("captures.h5",))
case("run-foreign-report-folder-force", "data-loss", RUN + ["--force"],
     {"cfg.yaml": Config(), "out": Folder({"report": Folder({"paper.tex": Text("x")})})}, exit=4, says=("report",))
case("run-out-dir-is-file", "traceback", RUN, {"cfg.yaml": Config(), "out": Text("a file\n")}, exit=4, says=("out",))
case("run-out-dir-config-key-is-file", "traceback", ["run", "cfg.yaml", "-q"],
     {"cfg.yaml": Config({"run.out_dir": "notes.txt"}), "notes.txt": Text("x\n")}, exit=4, says=("notes.txt",))
case("run-out-dir-unwritable", "traceback", ["run", "cfg.yaml", "--out-dir", "/proc/cca-run", "-q"],
     {"cfg.yaml": Config()}, exit=4, says=("/proc",))
case("run-truncated-recon", "messages", RUN,
     {"cfg.yaml": Config(), "out": Folder({"captures.h5": Copy("captures"), "recon.h5": Truncated("recon", 0.6)})},
     exit=4, says=("recon.h5",), not_says=("Traceback", "internal error", "another config"))
case("run-other-config", "validation", RUN,
     {"cfg.yaml": Config({"noise.seed": 7}), "out": Copy("run_dir")}, exit=4, says=("captures.h5", "--force"))
case("run-force-over-own-files", "works", RUN + ["--force"],
     {"cfg.yaml": Config({"noise.seed": 7}), "out": Copy("run_dir")}, exit=0,
     writes=("out/captures.h5", "out/recon.h5", "out/report", "out/.cca-run.lock"))
case("design-write-config-over-foreign", "data-loss",
     ["design", "--sar", "3", "--no-measure", "--write-config", "mine.yaml", "--force"],
     {"mine.yaml": Text("my: config\n")}, exit=4, says=("mine.yaml",))
case("design-write-config-parent-is-file", "traceback",
     ["design", "--sar", "3", "--no-measure", "--write-config", "notes.txt/p.yaml"],
     {"notes.txt": Text("x\n")}, exit=4, says=("notes.txt",))
case("design-write-config-is-dir", "usage", ["design", "--sar", "3", "--no-measure", "--write-config", "plans"],
     {"plans": Folder()}, exit=2, says=("plans",))
case("design-write-config-own", "works",
     ["design", "--sar", "3", "--no-measure", "--write-config", "p.yaml", "--force"], {}, exit=0, writes=("p.yaml",))
case("hdr-over-input", "data-loss", ["hdr", "raw.h5", "-o", "raw.h5", "--force", "-q"],
     {"raw.h5": Copy("captures")}, exit=4, says=("raw.h5",))
case("register-over-input", "data-loss", ["register", "hdr.h5", "-o", "hdr.h5", "--force", "-q"],
     {"hdr.h5": Copy("captures")}, exit=4, says=("hdr.h5",))
case("sweep-out-dir-is-file", "traceback",
     ["sweep", "grid", "cfg.yaml", "--set", "noise.snr_db=20,30", "--out-dir", "notes.txt"],
     {"cfg.yaml": Config(), "notes.txt": Text("x\n")}, exit=4, says=("notes.txt",))

# --- config files that are not configs ------------------------------------------------------------------------------
case("config-system-file-mapping", "messages", SIM,
     {"cfg.yaml": Text("Package: openssh-server\nStatus: install ok installed\nPriority: standard\n")},
     exit=2, says=("cfg.yaml",), not_says=("Traceback", "internal error", "openssh", "Package", "install ok"))
case("config-passwd-like", "messages", SIM,
     {"cfg.yaml": Text("root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1:daemon:/usr/sbin:/usr/sbin/nologin\n")},
     exit=2, says=("cfg.yaml",), not_says=("Traceback", "internal error", "root:x", "daemon"))
case("config-binary", "traceback", SIM, {"cfg.yaml": Bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")},
     exit=2, says=("cfg.yaml",), not_says=("Traceback", "internal error", "IHDR"))
case("config-is-directory", "usage", ["simulate", "cfgdir", "-o", "c.h5"], {"cfgdir": Folder()}, exit=2,
     says=("cfgdir",))
case("config-run-is-directory", "usage", ["run", "cfgdir", "-q"], {"cfgdir": Folder()}, exit=2, says=("cfgdir",))
case("config-fifo", "hang", ["simulate", "pipe.yaml", "-o", "c.h5"], {"pipe.yaml": Fifo()}, exit=2,
     says=("pipe.yaml",), seconds=5)
case("config-list", "validation", SIM, {"cfg.yaml": Text("- 1\n- 2\n")}, exit=2, says=("cfg.yaml", "mapping"))
case("config-scalar", "messages", SIM, {"cfg.yaml": Text("hostname.example.org\n")}, exit=2, says=("cfg.yaml",),
     not_says=("Traceback", "internal error", "hostname.example"))
case("config-billion-laughs", "resources", SIM, {"cfg.yaml": Text(
    "a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
    "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
    "e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d]\nf: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e]\n"
    "g: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f]\nh: &h [*g, *g, *g, *g, *g, *g, *g, *g, *g]\n"
    "sweep: {points: [{scene.widths_px: *h}]}\n")}, exit=2, says=("cfg.yaml",), seconds=5)
case("config-billion-laughs-in-known-keys", "resources", SIM, {"cfg.yaml": Text(
    "x0: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n"
    "sweep:\n  parameters:\n    scene.widths_px: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
    "  points: &c [{a: *b}, {a: *b}, {a: *b}, {a: *b}, {a: *b}, {a: *b}, {a: *b}, {a: *b}]\n")},
     exit=2, says=("cfg.yaml",), seconds=5)
case("config-deep-nesting", "resources", SIM, {"cfg.yaml": Text("optics: " + "[" * 3000 + "]" * 3000 + "\n")},
     exit=2, says=("cfg.yaml",), seconds=5)
case("config-long-unknown-key", "messages", SIM,
     {"cfg.yaml": Text("optics: {wavelength_m: 5.5e-7, " + "k" * 400 + ": 1}\n")},
     exit=2, says=("cfg.yaml", "optics"), not_says=("Traceback", "internal error", "k" * 100))
case("config-markup-name", "traceback", ["simulate", "[/]bad.yaml", "-o", "c.h5"],
     {"[/]bad.yaml": Config({"array.gird": 5})}, exit=2, says=("[/]bad.yaml", "array.gird"))
case("config-markup-name-red", "messages", ["simulate", "scan[red]A.yaml", "-o", "c.h5"],
     {"scan[red]A.yaml": Config({"array.gird": 5})}, exit=2, says=("scan[red]A.yaml",))
case("config-markup-key", "traceback", SIM, {"cfg.yaml": Config({"optics.[/]x": 1})}, exit=2, says=("[/]x",))
case("config-markup-value", "messages", SIM, {"cfg.yaml": Config({"noise.model": "[bold]loud[/]"})}, exit=2,
     says=("noise.model", "[bold]loud[/]"))
case("config-missing", "validation", ["simulate", "nope.yaml", "-o", "c.h5"], exit=2, says=("nope.yaml",))
case("config-tabs", "validation", SIM, {"cfg.yaml": Text("optics:\n\twavelength_m: 1\n")}, exit=2,
     says=("cfg.yaml", "YAML"))
case("config-utf16", "messages", SIM, {"cfg.yaml": Bytes("optics: {}\n".encode("utf-16"))}, exit=2,
     says=("cfg.yaml",))

# --- config values ---------------------------------------------------------------------------------------------------
VALUES = [
    ("optics.wavelength_m", float("nan")), ("optics.wavelength_m", -1), ("optics.wavelength_m", 0),
    ("optics.wavelength_m", "red"), ("optics.focal_length_m", 0), ("optics.aperture_diameter_m", "18 mm"),
    ("optics.pixel_pitch_m", [2e-6]), ("optics.distance_m", None), ("optics.distance_m", float("-inf")),
    ("scene.size_px", 0), ("scene.size_px", 12.7), ("scene.size_px", "big"), ("scene.kind", "Resolution_Chart"),
    ("scene.widths_px", [0]), ("scene.widths_px", "4,3,2"), ("scene.phase_max_rad", float("nan")),
    ("scene.surface_roughness_rad", -1), ("scene.usaf_groups", [1.5]), ("scene.ridge_period_m", float("inf")),
    ("array.grid", 0), ("array.grid", -3), ("array.grid", 2.5), ("array.grid", "three"), ("array.overlap", 1.0),
    ("array.overlap", -0.1), ("array.overlap", "61%"), ("array.overlap", float("nan")),
    ("noise.snr_db", float("nan")), ("noise.snr_db", float("inf")), ("noise.model", "Gaussian"),
    ("noise.read_noise_e", -1), ("noise.photons_per_unit", 0), ("noise.seed", 1.5), ("noise.seed", "one"),
    ("simulate.store", "disk"), ("run.stages", "simulate"), ("run.stages", ["reconstruct", "simulate"]),
    ("run.stages", ["simulat"]), ("run.stages", ["simulate", "simulate"]), ("run.stages", ["ingest"]),
    ("run.stages", ["simulate", "ingest"]), ("reconstruct.iterations", 0), ("reconstruct.iterations", 1.5),
    ("reconstruct.iterations", True), ("reconstruct.tol", float("nan")), ("reconstruct.tol", -1),
    ("reconstruct.engine", "altmn"), ("reconstruct.engine", None), ("reconstruct.options", [1, 2]),
    ("reconstruct.options", "fast"), ("report.mtf_threshold", 0), ("report.mtf_threshold", 1.5),
    ("report.mtf_threshold", float("nan")), ("report.baselines", [{"kind": "lens"}]),
    ("report.baselines", [{"kind": "telescope"}]), ("report.baselines", "passive"), ("report.speckle_region", [0, 1]),
    ("report.speckle_region", [0, float("nan"), 0, 1]), ("optix", {}), ("optics.wavelenght_m", 5e-7),
    ("optics", [1, 2]), ("optics", 5), ("sweep.study", "foo"), ("sweep.parameters", {"array.grid": 5}),
    ("multiplex", {"n_mux": 100, "source_overlap": 0.66}), ("multiplex", {"source_overlap": 0}),
    ("multiplex", {"camera_grid": [0, 7], "source_overlap": 0.66}),
    ("multiplex", {"pattern_list": [[99]], "source_overlap": 0.66}), ("registration", {"crop_xywh": [0, 0, -1, -1]}),
    ("hdr", {"min_weight": 0}), ("ingest", {"manifest": 5}),
]
for key, value in VALUES:
    section = key.split(".")[0]
    config_case(f"value-{key}={value!r}", "validation", {key: value}, [key if "." in key else section])
config_case("array-grid-and-sar", "validation", {"array.sar": 3.0}, ["array.grid", "array.sar"])
config_case("array-sar-below-one", "validation", {"array.grid": DROP, "array.sar": 0.5}, ["array.sar"])
config_case("array-sar-inf", "validation", {"array.grid": DROP, "array.sar": float("inf")}, ["array.sar"])
config_case("scene-image-without-path", "validation", {"scene.kind": "image"}, ["scene"])

OPTIONS = [
    ("altmin", {"bogus": 1}, "bogus"), ("altmin", {"tau": 1}, "tau"), ("altmin", {"chunk": 0}, "chunk"),
    ("altmin", {"threads": 0}, "threads"), ("altmin", {"threads": 1.5}, "threads"),
    ("momentum", {"beta": 3}, "beta"), ("momentum", {"eta": float("inf")}, "eta"),
    ("momentum", {"cost": "l2"}, "cost"), ("momentum", {"position_steps": []}, "position_steps"),
    ("momentum", {"pupil_recovery": True}, "pupil_recovery"), ("momentum", {"pupil_order": 5}, "pupil_order"),
    ("momentum", {"batch": 0}, "batch"), ("momentum", {"alpha": "a lot"}, "alpha"),
    ("momentum", {"position_refinement": 1}, "position_refinement"), ("momentum", {"chunk": 4}, "chunk"),
]
for engine, options, key in OPTIONS:
    config_case(f"options-{engine}-{key}={list(options.values())[0]!r}", "validation",
                {"reconstruct.engine": engine, "reconstruct.options": options}, [key])


def _loads_as(key: str, expected):
    def check(folder: Path, result) -> None:
        from cca_cli.config.load import load_config

        config = load_config(folder / "cfg.yaml")
        value = config.reconstruct.options[key] if key in config.reconstruct.options else getattr(
            config.reconstruct, key)
        assert value == expected and type(value) is type(expected), (value, expected)
    return check


case("options-alpha-1e-1-is-a-number", "works", SIM,
     {"cfg.yaml": Config({"reconstruct.engine": "momentum", "reconstruct.options": {"alpha": "1e-1"}})},
     exit=0, writes=("c.h5",), check=_loads_as("alpha", 0.1))
case("options-batch-integral-float", "works", SIM,
     {"cfg.yaml": Config({"reconstruct.engine": "momentum", "reconstruct.options": {"batch": 12.0}})},
     exit=0, writes=("c.h5",), check=_loads_as("batch", 12))
case("iterations-1e1-is-ten", "works", SIM, {"cfg.yaml": Config({"reconstruct.iterations": "1e1"})},
     exit=0, writes=("c.h5",), check=_loads_as("iterations", 10))
case("options-bool-false", "works", SIM,
     {"cfg.yaml": Config({"reconstruct.engine": "momentum", "reconstruct.options": {"position_refinement": False}})},
     exit=0, writes=("c.h5",), check=_loads_as("position_refinement", "none"))
case("options-from-reconstruct-config", "silent", ["reconstruct", "c.h5", "-o", "r.h5", "-c", "cfg.yaml", "-q"],
     {"c.h5": Copy("captures"),
      "cfg.yaml": Config({"reconstruct.engine": "momentum", "reconstruct.options": {"position_refinement": "no"}})},
     exit=2, says=("cfg.yaml", "position_refinement"))

# --- resources -------------------------------------------------------------------------------------------------------
config_case("sar-1000", "resources", {"array.grid": DROP, "array.sar": 1000}, ["memory"], exit=5, seconds=10)
config_case("grid-101-headline", "resources", {"array.grid": 101, **HEADLINE_SIZES}, ["memory", "GB"], exit=5,
            env={"CCA_MEMORY_LIMIT": "4G"}, seconds=10)
config_case("grid-101-run", "resources", {"array.grid": 101, **HEADLINE_SIZES}, ["memory"], exit=5,
            argv=RUN, env={"CCA_MEMORY_LIMIT": "4G"}, seconds=10)
config_case("size-px-100000", "resources", {"scene.size_px": 100000}, ["memory"], exit=5, seconds=10)
config_case("field-width-1km", "resources", {"scene.field_width_m": 1000.0}, ["memory"], exit=5, seconds=10)
config_case("pixel-pitch-tiny", "resources", {"optics.pixel_pitch_m": 1e-300}, ["memory"], exit=5, seconds=10)
config_case("distance-tiny", "resources", {"optics.distance_m": 1e-9}, ["memory"], exit=5, seconds=10)
config_case("multiplex-huge", "resources",
            {"multiplex": {"camera_grid": [2000, 2000], "source_grid": [3, 3], "source_overlap": 0.66}},
            ["memory"], exit=5, seconds=10)


def _disk_full(monkeypatch, folder: Path) -> None:
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 ** 9, 10 ** 9 - 10 ** 4, 10 ** 4))


case("disk-too-small-simulate", "resources", SIM, {"cfg.yaml": Config()}, exit=5, says=("c.h5", "disk"),
     patch=_disk_full)
case("disk-too-small-run", "resources", RUN, {"cfg.yaml": Config()}, exit=5, says=("disk",), patch=_disk_full)


def _huge_sparse(path: Path) -> None:
    import h5py

    with h5py.File(path, "r+") as handle:
        old = handle["/measurements/intensity"]
        attrs = dict(old.attrs)
        del handle["/measurements/intensity"]
        new = handle.create_dataset("/measurements/intensity", shape=(9, 200_000, 200_000), dtype="f4",
                                    chunks=(1, 1024, 1024), fillvalue=1.0)
        new.attrs.update(attrs)


case("reconstruct-huge-declared-dataset", "resources", REC, {"in.h5": Copy("captures", _huge_sparse)}, exit=5,
     says=("in.h5", "memory"), seconds=10)
case("reconstruct-centres-far-out", "resources", REC,
     {"in.h5": Copy("captures", set_data("/geometry/spectrum_centres_yx_px", lambda a: a * 1e6))}, exit=5,
     says=("in.h5", "memory"), seconds=10)
case("design-sar-1e9", "resources", ["design", "--sar", "1e9", "--no-measure"], exit=0, seconds=5)
case("design-sar-1e300", "resources", ["design", "--sar", "1e300", "--no-measure", "--json"], exit=0, seconds=5)
case("design-feature-tiny", "resources", ["design", "--feature-m", "1e-30", "--no-measure"], exit=0, seconds=5)
case("design-field-huge", "resources", ["design", "--sar", "3", "--field-width-m", "1000", "--no-measure"],
     exit=0, seconds=5)
case("sweep-dry-run-huge-grid", "resources",
     ["sweep", "grid", "cfg.yaml", "--set", "array.grid=3,100001", "--dry-run", "--out-dir", "sw"],
     {"cfg.yaml": Config()}, exit=0, seconds=10)

# --- input files ---------------------------------------------------------------------------------------------------
INPUTS = {
    "missing": {},
    "text": {"in.h5": Text("hello\n")},
    "empty": {"in.h5": Bytes(b"")},
    "plain-hdf5": {"in.h5": H5(lambda h: h.create_dataset("x", data=np.arange(3)))},
    "truncated-half": {"in.h5": Truncated("captures", 0.5)},
    "truncated-tenth": {"in.h5": Truncated("captures", 0.1)},
    "truncated-end": {"in.h5": Truncated("captures", 0.98)},
    "directory": {"in.h5": Folder()},
    "newer-schema": {"in.h5": Copy("captures", set_attr("/", "cca_schema", "cca/2"))},
}
for name, files in INPUTS.items():
    case(f"reconstruct-input-{name}", "validation" if name != "truncated-end" else "traceback", REC, files, exit=3,
         says=("in.h5",))
    case(f"report-input-{name}", "validation" if name != "truncated-end" else "traceback", REP,
         {k: (v if not isinstance(v, Truncated) else Truncated("recon", v.fraction)) for k, v in files.items()},
         exit=3, says=("in.h5",))
case("reconstruct-input-fifo", "hang", REC, {"in.h5": Fifo()}, exit=3, says=("in.h5",), seconds=5)
case("reconstruct-given-recon", "validation", REC, {"in.h5": Copy("recon")}, exit=3, says=("in.h5", "/measurements"))
case("report-given-captures", "validation", REP, {"in.h5": Copy("captures")}, exit=3,
     says=("in.h5", "expected 'reconstruct'", "give the recon.h5 that cca reconstruct writes",
           "run cca reconstruct on it first"))
case("report-given-a-sweep-table", "validation", REP, {"in.h5": Copy("recon", set_attr("/", "stage", "sweep"))},
     exit=3, says=("in.h5", "give the recon.h5 that cca reconstruct writes"), not_says=("Traceback", "internal error", "holds captures"))
case("reconstruct-intensity-inf", "validation", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: np.where(a > 0.3, np.inf, a)))},
     exit=3, says=("in.h5", "Inf"))
case("reconstruct-intensity-2d", "validation", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: a[0]))}, exit=3, says=("in.h5",))
case("reconstruct-intensity-complex", "silent", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: a.astype(np.complex64) * 1j))},
     exit=3, says=("in.h5", "/measurements/intensity"))
case("reconstruct-weight-wrong-shape", "validation", REC,
     {"in.h5": Copy("captures", lambda p: _add_weight(p, 1.0, (9, 4, 4)))}, exit=3, says=("in.h5", "weight"))
case("reconstruct-no-geometry", "validation", REC, {"in.h5": Copy("captures", drop("/geometry"))}, exit=3,
     says=("in.h5", "geometry"))
case("reconstruct-geometry-attr-missing", "validation", REC,
     {"in.h5": Copy("captures", drop("/geometry@wavelength_m"))}, exit=3, says=("in.h5", "wavelength_m"))
case("reconstruct-centres-nan", "traceback", REC,
     {"in.h5": Copy("captures", set_data("/geometry/spectrum_centres_yx_px", lambda a: a * np.nan))}, exit=3,
     says=("in.h5", "spectrum_centres_yx_px"))
case("reconstruct-one-centre-inf", "traceback", REC,
     {"in.h5": Copy("captures", set_data("/geometry/spectrum_centres_yx_px",
                                         lambda a: np.where(np.arange(a.size).reshape(a.shape) == 3, np.inf, a)))},
     exit=3, says=("in.h5", "spectrum_centres_yx_px"))
case("reconstruct-centres-wrong-shape", "validation", REC,
     {"in.h5": Copy("captures", set_data("/geometry/spectrum_centres_yx_px", lambda a: a[:, :1]))}, exit=3,
     says=("in.h5", "spectrum_centres_yx_px"))
case("reconstruct-pupil-radius-zero", "validation", REC,
     {"in.h5": Copy("captures", set_attr("/geometry", "pupil_radius_px", 0.0))}, exit=3, says=("in.h5", "pupil"))
case("reconstruct-pupil-radius-nan", "traceback", REC,
     {"in.h5": Copy("captures", set_attr("/geometry", "pupil_radius_px", np.nan))}, exit=3, says=("in.h5", "pupil"))
case("reconstruct-pupil-radius-text", "traceback", REC,
     {"in.h5": Copy("captures", set_attr("/geometry", "pupil_radius_px", "big"))}, exit=3,
     says=("in.h5", "pupil_radius_px"))
case("reconstruct-images-mismatch", "validation", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: a[:5]))}, exit=3,
     says=("in.h5", "5 images"))
def _region_recovered(folder: Path, result) -> None:
    import h5py

    with h5py.File(folder / "in.h5", "r") as captures, h5py.File(folder / "r.h5", "r") as recon:
        assert recon["/recon/region_px"][1, 2:].tolist() == list(captures["/measurements/intensity"].shape[1:])
        assert np.isfinite(recon["/recon/intensity"][()]).all()


# Non-square images cannot wrap on a square grid: they are a window, padded with a guard band as recorded frames are.
case("reconstruct-non-square", "works", REC + ["--iterations", "5"],
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: a[:, :, :a.shape[-1] * 3 // 4]))},
     exit=0, writes=("r.h5",), check=_region_recovered)
def _intensity_as_group(path: Path) -> None:
    import h5py

    with h5py.File(path, "r+") as handle:
        del handle["/measurements/intensity"]
        handle.create_group("/measurements/intensity")


case("reconstruct-intensity-is-group", "traceback", REC, {"in.h5": Copy("captures", _intensity_as_group)}, exit=3,
     says=("in.h5", "/measurements/intensity"))
case("reconstruct-markup-input-name", "traceback", ["reconstruct", "cap[/].h5", "-o", "r.h5", "-q"], exit=3,
     says=("cap[/].h5",))
case("reconstruct-markup-output-name", "messages",
     ["reconstruct", "c.h5", "-o", "scan[red]A.h5", "-q", "--iterations", "3"],
     {"c.h5": Copy("captures")}, exit=0, writes=("scan[red]A.h5",),
     check=lambda folder, result: _stdout_has(result, "scan[red]A.h5"))


def _stdout_has(result, text: str) -> None:
    assert text in " ".join(result.stdout.split()) or text in result.stdout, result.stdout


case("report-no-history", "traceback", REP, {"in.h5": Copy("recon", drop("/history"))}, exit=3,
     says=("in.h5", "/history"))
case("report-no-history-change", "traceback", REP, {"in.h5": Copy("recon", drop("/history/change"))}, exit=3,
     says=("in.h5", "/history/change"))
case("report-no-recon-attrs", "traceback", REP,
     {"in.h5": Copy("recon", drop("/recon@hires_size", "/recon@lowres_size"))}, exit=3,
     says=("in.h5", "hires_size"))
case("report-no-engine-attr", "silent", REP, {"in.h5": Copy("recon", drop("/recon@engine"))}, exit=3,
     says=("in.h5", "engine"))
case("report-recon-attr-text", "traceback", REP, {"in.h5": Copy("recon", set_attr("/recon", "hires_size", "big"))},
     exit=3, says=("in.h5", "hires_size"))
case("report-centres-nan", "traceback", REP,
     {"in.h5": Copy("recon", set_data("/geometry/spectrum_centres_yx_px", lambda a: a * np.nan))}, exit=3,
     says=("in.h5", "spectrum_centres_yx_px"))
case("report-bars-garbage", "traceback", REP,
     {"in.h5": Copy("recon", set_data("/truth/bars", lambda a: a[:, :3]))}, exit=3, says=("in.h5", "/truth/bars"))
case("report-no-observed", "validation", REP, {"in.h5": Copy("recon", drop("/observed"))}, exit=3,
     says=("in.h5", "/observed/centre"))
case("report-spectrum-1d", "traceback", REP,
     {"in.h5": Copy("recon", set_data("/recon/spectrum", lambda a: a[0]))}, exit=3, says=("in.h5", "/recon/spectrum"))
case("report-truth-wrong-shape", "traceback", REP,
     {"in.h5": Copy("recon", set_data("/truth/object", lambda a: a[:10, :7]))}, exit=3, says=("in.h5", "/truth/object"))

# --- cca info -------------------------------------------------------------------------------------------------------
INFO_FILES = {
    "missing": ({}, 3), "text": ({"in.h5": Text("hello\n")}, 3), "empty": ({"in.h5": Bytes(b"")}, 3),
    "truncated": ({"in.h5": Truncated("recon", 0.5)}, 3), "truncated-end": ({"in.h5": Truncated("recon", 0.97)}, 3),
    "directory": ({"in.h5": Folder()}, 3), "fifo": ({"in.h5": Fifo()}, 3),
}
for name, (files, code) in INFO_FILES.items():
    case(f"info-{name}", "traceback" if "truncated" in name else ("hang" if name == "fifo" else "validation"),
         ["info", "in.h5"], files, exit=code, says=("in.h5",), seconds=5)
case("info-dev-null", "validation", ["info", "/dev/null"], exit=3, says=("/dev/null",))
case("info-report-folder", "validation", ["info", "rep"], {"rep": Copy("report")}, exit=3, says=("rep",))
case("info-plain-hdf5", "works", ["info", "in.h5"], {"in.h5": H5(lambda h: h.create_dataset("x", data=[1, 2]))},
     exit=0)
case("info-binary-attribute", "traceback", ["info", "in.h5"],
     {"in.h5": Copy("recon", set_attr("/", "config", np.void(b"\xff\xfe\x00garbage")))}, exit=0)
case("info-undecodable-bytes", "traceback", ["info", "in.h5"],
     {"in.h5": Copy("recon", set_attr("/geometry", "kind", np.bytes_(b"\xff\xfe\xfd")))}, exit=0)
case("info-dangling-link", "works", ["info", "in.h5"],
     {"in.h5": Copy("recon", lambda p: _soft_link(p))}, exit=0)
case("info-markup-dataset-name", "messages", ["info", "in.h5"],
     {"in.h5": Copy("recon", lambda p: _markup_dataset(p))}, exit=0,
     check=lambda folder, result: _stdout_has(result, "[/]weird"))
case("info-markup-file-name", "traceback", ["info", "a[/]b.h5"], {"a[/]b.h5": Text("x")}, exit=3, says=("a[/]b.h5",))


def _soft_link(path: Path) -> None:
    import h5py

    with h5py.File(path, "r+") as handle:
        handle["gone"] = h5py.SoftLink("/no/such/thing")


def _markup_dataset(path: Path) -> None:
    import h5py

    with h5py.File(path, "r+") as handle:
        handle.create_dataset("[/]weird", data=[1])

# --- command-line options --------------------------------------------------------------------------------------------
for option, value in (("--tau", "inf"), ("--tau", "nan"), ("--tau", "-1"), ("--iterations", "0"),
                      ("--iterations", "1.5"), ("--tol", "nan"), ("--engine", "nope"), ("--tau", "abc")):
    case(f"reconstruct-option{option}={value}", "usage", ["reconstruct", "c.h5", "-o", "r.h5", option, value, "-q"],
         {"c.h5": Copy("captures")}, exit=2, says=(option,))
case("report-threshold-abc", "usage", ["report", "in.h5", "-o", "rep", "--threshold", "abc"],
     {"in.h5": Copy("recon")}, exit=2, says=("--threshold",))
for option, value in (("--noise-floor", "-1"), ("--saturation-level", "nan"), ("--saturation-level", "0")):
    case(f"hdr-option{option}={value}", "usage", ["hdr", "raw.h5", "-o", "h.h5", option, value, "-q"],
         {"raw.h5": Copy("captures")}, exit=2, says=(option,))
for crop in ("1,2,3", "a,b,c,d", "0,0,-5,-5", "0,0,10,12.5"):
    case(f"register-crop={crop}", "usage", ["register", "h.h5", "-o", "g.h5", "--crop", crop, "-q"],
         {"h.h5": Copy("captures")}, exit=2, says=("--crop",))
case("register-ransac-inf", "usage", ["register", "h.h5", "-o", "g.h5", "--ransac-threshold-px", "inf", "-q"],
     {"h.h5": Copy("captures")}, exit=2, says=("--ransac-threshold-px",))
case("unknown-command", "usage", ["simulat", "cfg.yaml"], exit=2, says=("simulat",))
case("missing-argument", "usage", ["reconstruct"], exit=2, says=("captures",))
case("unknown-option", "usage", ["run", "--bogus"], exit=2, says=("--bogus",))
case("report-missing-argument", "usage", ["report", "-o", "rep"], exit=2, says=("recon",))

SWEEP = ["sweep", "grid", "cfg.yaml", "--out-dir", "sw"]
for text in ("noequals", "=1", "array.overlap=", "bogus.key=1", "run.out_dir=x", "array.grid.x=1", "array=1",
             "noise.seed=-1", "array.overlap=1.5,2"):
    case(f"sweep-set={text}", "usage", SWEEP + ["--set", text], {"cfg.yaml": Config()}, exit=2,
         says=(text.split("=")[0] or "--set",))
case("sweep-nothing-to-sweep", "usage", SWEEP, {"cfg.yaml": Config()}, exit=2, says=("cfg.yaml", "sweep"))
case("sweep-study-mismatch", "usage", ["sweep", "overlap", "cfg.yaml", "--out-dir", "sw"],
     {"cfg.yaml": Config({"sweep": {"study": "sar", "parameters": {"array.grid": [1, 3]}}})}, exit=2,
     says=("cfg.yaml", "sweep.study"))
case("sweep-scheduler-notaurl", "traceback", SWEEP + ["--set", "noise.snr_db=20,30", "--scheduler", "notaurl"],
     {"cfg.yaml": Config()}, exit=2, says=("--scheduler", "notaurl"))
case("sweep-scheduler-not-dask", "hang",
     SWEEP + ["--set", "noise.snr_db=20,30", "--scheduler", "tcp://127.0.0.1:{http_port}"],
     {"cfg.yaml": Config()}, exit=2, says=("--scheduler",), env={"CCA_SCHEDULER_TIMEOUT": "1"}, seconds=15)
case("sweep-scheduler-closed-port", "usage",
     SWEEP + ["--set", "noise.snr_db=20,30", "--scheduler", "tcp://127.0.0.1:{dead_port}"],
     {"cfg.yaml": Config()}, exit=2, says=("--scheduler",), env={"CCA_SCHEDULER_TIMEOUT": "1"}, seconds=15)
case("sweep-dry-run", "works", SWEEP + ["--set", "noise.snr_db=20,30", "--dry-run"], {"cfg.yaml": Config()}, exit=0)
case("sweep-dry-run-invalid-point", "works", SWEEP + ["--set", "array.overlap=0.5,1.5", "--dry-run"],
     {"cfg.yaml": Config()}, exit=0, check=lambda folder, result: _stdout_has(result, "invalid"))
case("sweep-markup-in-set", "traceback", SWEEP + ["--set", "scene.kind=[/]x,usaf", "--dry-run"],
     {"cfg.yaml": Config()}, exit=0, check=lambda folder, result: _stdout_has(result, "[/]x"))

DESIGN = ["design", "--no-measure"]
for args, says in ((["--sar", "inf"], "--sar"), (["--sar", "nan"], "--sar"), (["--sar", "-1"], "--sar"),
                   (["--sar", "0"], "--sar"), (["--sar", "3", "--overlap", "1"], "--overlap"),
                   (["--sar", "3", "--overlap", "nan"], "--overlap"),
                   (["--sar", "3", "--overlap", "-0.5"], "--overlap"),
                   (["--sar", "3", "--wavelength-m", "0"], "--wavelength-m"),
                   (["--sar", "3", "--wavelength-m", "inf"], "--wavelength-m"),
                   (["--sar", "3", "--distance-m", "-5"], "--distance-m"),
                   (["--sar", "3", "--pixel-pitch-m", "nan"], "--pixel-pitch-m"),
                   (["--sar", "2", "--feature-m", "1e-3"], "target"), ([], "target"),
                   (["--sar", "3", "--sensor-px", "0"], "--sensor-px"),
                   (["--sar", "3", "--sensor-px", "-5"], "--sensor-px"),
                   (["--sar", "3", "--field-width-m", "inf"], "--field-width-m"),
                   (["--sar", "3", "--field-width-m", "0"], "--field-width-m"),
                   (["--sar", "3", "--iterations", "0", "--write-config", "p.yaml"], "--iterations"),
                   (["--sar", "3", "--engine", "pie"], "--engine"),
                   (["--sar", "abc"], "--sar"), (["--beat-lens-m", "nan"], "--beat-lens-m")):
    case("design" + "".join(args).replace("--", "-"), "usage", DESIGN + args, exit=2, says=(says,))

# --- manifests -------------------------------------------------------------------------------------------------------
ING = ["ingest", "m.yaml", "-o", "raw.h5", "-q"]
MANIFESTS = {
    "system-file-mapping": (Text("Package: openssh-server\nStatus: install ok installed\n"), ("openssh", "Package")),
    "passwd-like": (Text("root:x:0:0:root:/root:/bin/bash\n"), ("root:x",)),
    "binary": (Bytes(b"\x89HDF\r\n\x1a\n\x00\x00\xff\xfe"), ("HDF",)),
    "empty": (Text(""), ()),
    "billion-laughs": (Text("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
                            "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c]\n"
                            "e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]\nf: &f [*e, *e, *e, *e, *e, *e, *e, *e]\n"
                            "images: [{path: x.png, exposure_s: 1, grid: *f}]\n"), ()),
    "images-empty": (Text("optics: {wavelength_m: 5e-7, focal_length_m: 0.1, aperture_diameter_m: 0.004, "
                          "pixel_pitch_m: 2e-6, distance_m: 10}\nimages: []\n"), ()),
    "image-missing": (Text("optics: {wavelength_m: 5e-7, focal_length_m: 0.1, aperture_diameter_m: 0.004, "
                           "pixel_pitch_m: 2e-6, distance_m: 10}\nimages: [{path: gone.png, stage_x_mm: 0, "
                           "stage_y_mm: 0}]\n"), ()),
    "long-value": (Text("values: " + "x" * 300 + "\nimages: []\n"), ("x" * 80,)),
}
for name, (maker, hidden) in MANIFESTS.items():
    case(f"manifest-{name}", "messages", ING, {"m.yaml": maker}, exit=None, says=("m.yaml",),
         not_says=("Traceback", "internal error",) + hidden, seconds=5)
case("manifest-missing", "validation", ING, exit=3, says=("m.yaml",))
case("manifest-is-directory", "validation", ["ingest", "mdir", "-o", "raw.h5", "-q"], {"mdir": Folder()}, exit=None,
     says=("mdir",))
case("manifest-fifo", "hang", ING, {"m.yaml": Fifo()}, exit=None, says=("m.yaml",), seconds=5)
case("manifest-csv-without-sidecar", "validation", ["ingest", "m.csv", "-o", "raw.h5", "-q"],
     {"m.csv": Text("path,exposure_s,row,col\na.png,1,0,0\n")}, exit=3, says=("m.csv",))
case("ingest-over-manifest", "data-loss", ["ingest", "lab/manifest.yaml", "-o", "lab/manifest.yaml", "--force", "-q"],
     {"lab": Copy("manifest_dir")}, exit=4, says=("manifest.yaml",))
case("ingest-over-an-image", "data-loss",
     ["ingest", "lab/manifest.yaml", "-o", "lab/view_r0c0.png", "--force", "-q"],
     {"lab": Copy("manifest_dir")}, exit=4, says=("view_r0c0.png",))
case("ingest-works", "works", ["ingest", "lab/manifest.yaml", "-o", "raw.h5", "-q"], {"lab": Copy("manifest_dir")},
     exit=0, writes=("raw.h5",))



def _lab_edit(*, replace: str | None = None, add: tuple = (), board: bool = False):
    """Edit of the library's lab folder: ``replace`` (a view) becomes an 8-bit PNG; ``add`` appends image entries
    (with an ``eight_bit`` flag: their files are 8-bit, else 16-bit); ``board`` adds a checkerboard section."""
    def edit(folder: Path) -> None:
        import yaml

        from cca_cli.io.images import write_image

        rng = np.random.default_rng(7)
        manifest = yaml.safe_load((folder / "manifest.yaml").read_text())
        if replace is not None:
            write_image(folder / replace, rng.integers(0, 255, (32, 32)).astype(np.uint8), bit_depth=8)
        for entry in add:
            entry = dict(entry)
            if entry.pop("eight_bit"):
                write_image(folder / entry["path"], rng.integers(0, 255, (32, 32)).astype(np.uint8), bit_depth=8)
            else:
                write_image(folder / entry["path"], rng.integers(0, 60, (32, 32)).astype(np.uint16), bit_depth=16)
            manifest["images"].append(entry)
        if board:
            manifest["checkerboard"] = {"pattern": [4, 3]}
        (folder / "manifest.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return edit


def _eight_bit_boards_stored(folder: Path, result) -> None:
    import h5py

    with h5py.File(folder / "raw.h5") as handle:
        assert handle["/registration/board_views"].shape == (9, 32, 32)
    assert "read at their own depth" in " ".join(result.stderr.split())


LAB_ING = ["ingest", "lab/manifest.yaml", "-o", "raw.h5", "-q"]
case("ingest-one-capture-8-bit", "silent", LAB_ING, {"lab": Copy("manifest_dir", _lab_edit(replace="view_r1c1.png"))},
     exit=3, says=("view_r1c1.png", "8-bit", "16-bit", "same bit depth"))
for kind in ("dark", "flat"):
    case(f"ingest-{kind}-8-bit", "silent", LAB_ING,
         {"lab": Copy("manifest_dir", _lab_edit(add=({"path": f"{kind}.png", "kind": kind, "exposure_s": 0.01,
                                                      "eight_bit": True},)))},
         exit=3, says=(f"{kind}.png", "8-bit", "16-bit", "same bit depth"))
case("ingest-dark-row-states-another-depth", "silent", LAB_ING,
     {"lab": Copy("manifest_dir", _lab_edit(add=({"path": "dark.png", "kind": "dark", "exposure_s": 0.01,
                                                  "bit_depth": 14, "eight_bit": False},)))},
     exit=2, says=("manifest.yaml", "bit depth 14 (dark.png)", "sensor.bit_depth is 12"))
case("ingest-8-bit-calibration-views", "works", LAB_ING,
     {"lab": Copy("manifest_dir", _lab_edit(board=True, add=tuple(
         {"path": f"board_r{r}c{c}.png", "kind": "calibration", "exposure_s": 0.02, "grid": [r, c], "eight_bit": True}
         for r in range(3) for c in range(3))))},
     exit=0, writes=("raw.h5",), check=_eight_bit_boards_stored)

# --- exports ---------------------------------------------------------------------------------------------------------


def _is_float_tiff(name: str):
    def check(folder: Path, result) -> None:
        import h5py
        import tifffile

        with h5py.File(folder / "r.h5") as handle:
            expected = np.abs(handle["/recon/object"][()]).astype(np.float32)
        with tifffile.TiffFile(folder / name) as tif:
            assert np.array_equal(tif.pages[0].asarray(), expected)
    return check


case("export-format-tiff-any-suffix", "works", ["export", "r.h5", "-o", "x.dat", "--format", "tiff"],
     {"r.h5": Copy("recon")}, exit=0, writes=("x.dat",), check=_is_float_tiff("x.dat"))

# --- run folders: resume, temporaries, locks ------------------------------------------------------------------------
DEAD_PID = 4_194_309  # above Linux's largest pid_max: no process has it


def _no_temporaries(folder: Path, result) -> None:
    left = sorted(p.name for p in (folder / "out").iterdir() if ".tmp-" in p.name)
    assert left == [".notes.tmp-1"], left


case("run-cleans-stale-temporaries", "faults", RUN,
     {"cfg.yaml": Config(), "out": Folder({".captures.h5.tmp-4194309": Bytes(b"partial"),
                                            ".report.tmp-4194309": Folder({"a.png": Bytes(b"x")}),
                                            ".notes.tmp-1": Text("not cca's: kept\n")})},
     exit=0, writes=("out",), check=_no_temporaries)
case("run-stale-lock-taken-over", "faults", RUN,
     {"cfg.yaml": Config(), "out": Folder({".cca-run.lock": Text(json.dumps({"pid": DEAD_PID, "host": "*"}))})},
     exit=0, writes=("out",), check=lambda folder, result: None)
def _hold_lock(monkeypatch, folder: Path):
    """Hold the run folder's lock as a live run would (released when the case ends)."""
    import fcntl
    import os

    fd = os.open(folder / "out" / ".cca-run.lock", os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return lambda: os.close(fd)


case("run-live-lock", "faults", RUN,
     {"cfg.yaml": Config(), "out": Folder({".cca-run.lock": Text(json.dumps({"pid": 1, "host": "*"}))})},
     exit=6, says=("out", "pid 1"), patch=_hold_lock)
case("run-lock-of-a-reused-pid", "faults", RUN,
     {"cfg.yaml": Config(), "out": Folder({".cca-run.lock": Text(json.dumps({"pid": 1, "host": "*"}))})},
     exit=0, writes=("out",))
case("run-report-input-missing", "validation", ["run", "cfg.yaml", "--out-dir", "out", "-q"],
     {"cfg.yaml": Config({"run.stages": ["report"]}), "out": Folder()}, exit=3, says=("recon.h5",))
case("run-resumes-after-report-deleted", "works", RUN,
     {"cfg.yaml": Config(), "out": Copy("run_dir", lambda p: __import__("shutil").rmtree(p / "report"))},
     exit=0, writes=("out/report", "out/.cca-run.lock"),
     check=lambda folder, result: _stdout_has(result, "reconstruct skipped"))


# --- faults (in-process) ---------------------------------------------------------------------------------------------
def _enospc_on_write(monkeypatch, folder: Path) -> None:
    """The disk fills after the first 4 kB of any HDF5 file written."""
    from cca_cli.io import h5

    class FillingDisk:
        def __init__(self, raw):
            self.raw, self.written = raw, 0

        def write(self, data):
            self.written += len(data)
            if self.written > 4096:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.raw.write(data)

        def __getattr__(self, name):
            return getattr(self.raw, name)

    original = h5._DiskSink.__init__

    def init(self, path):
        original(self, path)
        self._file = FillingDisk(self._file)

    monkeypatch.setattr(h5._DiskSink, "__init__", init)


def _enospc_on_text(monkeypatch, folder: Path) -> None:
    original = Path.write_text

    def write_text(self, *args, **kwargs):
        if ".tmp-" in str(self):
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", write_text)


def _interrupt_reconstruction(monkeypatch, folder: Path) -> None:
    from cca_cli.library import recovery

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(recovery, "run_engine", interrupted)


case("disk-full-simulate-keeps-old", "faults", ["simulate", "cfg.yaml", "-o", "c.h5", "--force", "-q"],
     {"cfg.yaml": Config({"noise.seed": 3}), "c.h5": Copy("captures")}, exit=5, says=("c.h5", "space"),
     patch=_enospc_on_write)
case("disk-full-reconstruct", "faults", ["reconstruct", "c.h5", "-o", "r.h5", "-q", "--iterations", "3"],
     {"c.h5": Copy("captures")}, exit=5, says=("r.h5", "space"), patch=_enospc_on_write)
case("disk-full-report-keeps-old", "faults", ["report", "recon.h5", "-o", "rep", "--force", "--no-figures"],
     {"recon.h5": Copy("recon"), "rep": Copy("report")}, exit=5, says=("rep", "space"), patch=_enospc_on_text)
case("interrupt-reconstruct", "faults", ["reconstruct", "c.h5", "-o", "r.h5", "--force", "-q"],
     {"c.h5": Copy("captures"), "r.h5": Copy("recon")}, exit=130, says=("interrupted",),
     patch=_interrupt_reconstruction)


# --- more careless use ---------------------------------------------------------------------------------------------
def _diverging_engine(monkeypatch, folder: Path) -> None:
    from cca_cli.library import recovery

    run_engine = recovery.run_engine

    def diverged(engine, *, on_iteration=None, **kwargs):
        spectrum, history = run_engine(engine, on_iteration=on_iteration, **kwargs)
        return spectrum * np.nan, history

    monkeypatch.setattr(recovery, "run_engine", diverged)


case("simulate-no-photons", "silent", SIM,
     {"cfg.yaml": Config({"noise.model": "poisson", "noise.photons_per_unit": 1e-30})}, exit=2,
     says=("photons_per_unit",))
case("reconstruct-diverges", "silent", ["reconstruct", "c.h5", "-o", "r.h5", "-q", "--iterations", "3"],
     {"c.h5": Copy("captures")}, exit=1, says=("diverged",), patch=_diverging_engine)
case("reconstruct-intensity-strings", "validation", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: a.astype("S8")))}, exit=3,
     says=("in.h5", "/measurements/intensity"))
case("reconstruct-empty-stack", "validation", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", lambda a: a[:0]))}, exit=3,
     says=("in.h5", "no images"))
case("run-ingest-manifest-missing", "validation", RUN,
     {"cfg.yaml": Config({"run.stages": ["ingest", "reconstruct", "report"], "ingest": {"manifest": "gone.yaml"}})},
     exit=3, says=("gone.yaml",))
case("scene-image-missing", "validation", SIM,
     {"cfg.yaml": Config({"scene.kind": "image", "scene.image_path": "missing.png"})}, exit=3, says=("missing.png",))
case("scene-image-not-an-image", "validation", SIM,
     {"cfg.yaml": Config({"scene.kind": "image", "scene.image_path": "notes.png"}), "notes.png": Text("hello\n")},
     exit=3, says=("notes.png",))
case("hdr-given-captures", "validation", ["hdr", "c.h5", "-o", "h.h5", "-q"], {"c.h5": Copy("captures")}, exit=3,
     says=("c.h5", "expected 'ingest'", "give the raw.h5 that cca ingest writes"))
case("register-given-recon", "validation", ["register", "r.h5", "-o", "g.h5", "-q"], {"r.h5": Copy("recon")},
     exit=3, says=("r.h5",))
case("sweep-set-list-value", "usage", SWEEP + ["--set", "scene.widths_px=[4,3]"], {"cfg.yaml": Config()}, exit=2,
     says=("scene.widths_px",))
case("design-write-config-exists", "data-loss", ["design", "--sar", "3", "--no-measure", "--write-config", "p.yaml"],
     {"p.yaml": Text("# Written by `cca design`.\nrun: {}\n")}, exit=4, says=("p.yaml", "--force"))
case("report-to-symlinked-report", "data-loss", ["report", "recon.h5", "-o", "rep", "--force", "--no-figures"],
     {"recon.h5": Copy("recon"), "elsewhere": Copy("report"), "rep": Symlink("elsewhere")}, exit=4, says=("rep",))
case("run-report-is-a-file", "data-loss", RUN + ["--force"],
     {"cfg.yaml": Config(), "out": Folder({"report": Text("my report, typed by hand\n")})}, exit=4,
     says=("report",))
case("manifest-duplicate-key", "silent", ING,
     {"m.yaml": Text("values: intensity\nvalues: amplitude\nimages: []\n")}, exit=2, says=("m.yaml", "twice"))
config_case("options-null", "validation", {"reconstruct.options": None}, ["reconstruct.options"])
config_case("section-null", "validation", {"optics": None}, ["optics"])
case("chart-does-not-fit", "validation", SIM, {"cfg.yaml": Config({"scene.size_px": 1})}, exit=2, says=("scene",))
case("aperture-larger-than-the-sensor-samples", "validation", SIM,
     {"cfg.yaml": Config({"optics.aperture_diameter_m": 10})}, exit=2, says=("optics",))
case("report-threshold-negative", "usage", ["report", "in.h5", "-o", "rep", "--threshold", "-0.2"],
     {"in.h5": Copy("recon")}, exit=2, says=("--threshold",))
case("info-symlink", "works", ["info", "link.h5"], {"r.h5": Copy("recon"), "link.h5": Symlink("r.h5")}, exit=0)
case("run-config-is-hdf5", "messages", ["run", "c.h5", "-q"], {"c.h5": Copy("captures")}, exit=2, says=("c.h5",),
     not_says=("Traceback", "internal error", "HDF"))
case("reconstruct-config-is-hdf5", "messages", ["reconstruct", "c.h5", "-o", "r.h5", "-c", "c.h5", "-q"],
     {"c.h5": Copy("captures")}, exit=2, says=("c.h5",))
case("manifest-is-a-run-config", "messages", ["ingest", "cfg.yaml", "-o", "raw.h5", "-q"], {"cfg.yaml": Config()},
     exit=2, says=("cfg.yaml",))
case("config-is-a-manifest", "messages", ["simulate", "lab/manifest.yaml", "-o", "c.h5", "-q"],
     {"lab": Copy("manifest_dir")}, exit=2, says=("manifest.yaml",))
case("workers-huge", "resources", ["sweep", "grid", "cfg.yaml", "--set", "noise.snr_db=20,30", "--workers", "100000",
                                   "--out-dir", "sw"], {"cfg.yaml": Config()}, exit=2, says=("--workers",))
BOTH_CLUSTERS = ["--workers", "2", "--scheduler", "tcp://127.0.0.1:{dead_port}"]
case("workers-and-scheduler-sweep", "usage", ["sweep", "grid", "cfg.yaml", "--set", "noise.snr_db=20,30", "--out-dir",
                                              "sw", *BOTH_CLUSTERS], {"cfg.yaml": Config()}, exit=2,
     says=("--workers", "--scheduler", "exclude each other"), seconds=5)
case("workers-and-scheduler-run", "usage", RUN + BOTH_CLUSTERS, {"cfg.yaml": Config()}, exit=2,
     says=("--workers", "--scheduler", "exclude each other"), seconds=5)
case("workers-and-scheduler-reconstruct", "usage", REC + BOTH_CLUSTERS, {"in.h5": Copy("captures")}, exit=2,
     says=("--workers", "--scheduler", "exclude each other"), seconds=5)


def _no_probe_left(folder: Path, result) -> None:
    assert not list((folder / "out").glob(".cca-probe*"))


case("run-cleans-a-stale-probe", "faults", RUN,
     {"cfg.yaml": Config(), "out": Folder({".cca-probe.tmp-4194309": Bytes(b"")})}, exit=0, writes=("out",),
     check=_no_probe_left)
case("report-markup-output-name", "messages", ["report", "recon.h5", "-o", "rep[red]x", "--no-figures"],
     {"recon.h5": Copy("recon")}, exit=0, writes=("rep[red]x",),
     check=lambda folder, result: _stdout_has(result, "rep[red]x"))
case("run-markup-out-dir", "messages", ["run", "cfg.yaml", "--out-dir", "o[red]ut", "-q"], {"cfg.yaml": Config()},
     exit=0, writes=("o[red]ut",), check=lambda folder, result: _stdout_has(result, "o[red]ut/captures.h5"))
case("input-name-not-utf8", "messages", ["reconstruct", "bad\udcff.h5", "-o", "r.h5", "-q"], exit=3, says=("bad",))


# --- dead captures, misleading causes, one file listed twice ---------------------------------------------------------
def _dead(*indices):
    def edit(a):
        a = a.copy()
        a[list(indices)] = 0
        return a
    return edit


case("capture-dead-centre", "silent", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", _dead(4)))}, exit=3,
     says=("in.h5", "image 4", "centre", "row 1, col 1"))
case("capture-dead-one-of-nine", "silent", REC,
     {"in.h5": Copy("captures", set_data("/measurements/intensity", _dead(1)))}, exit=3,
     says=("in.h5", "image 1 (row 0, col 1)", "5%"))
for value in (0.25, -0.25):  # a dead frame less a scalar black level holds one negative value
    case(f"capture-constant-{value}", "silent", REC,
         {"in.h5": Copy("captures", set_data("/measurements/intensity",
                                             lambda a, v=value: np.where(np.arange(len(a))[:, None, None] == 7, v, a)))},
         exit=3, says=("in.h5", "image 7 (row 2, col 1)", "one value"),
         not_says=("Traceback", "internal error", "black level"))


def _camera_dies(index: int):
    """The simulated camera records nothing (all zero) at capture ``index``: a dead capture in captures.h5."""
    def patch(monkeypatch, folder: Path) -> None:
        from cca_cli.library import simulation

        record = simulation.record

        def dead(*args, **kwargs):
            images = record(*args, **kwargs)
            images[index] = 0
            return images

        monkeypatch.setattr(simulation, "record", dead)
    return patch


def _dead_capture_left_out(folder: Path, result) -> None:
    import h5py

    text = " ".join(result.stderr.split())  # the terminal may wrap the warning
    assert text.count("left out") == 1 and "image 3 (row 0, col 3) holds one value (0)" in text, result.stderr
    assert "the recovery uses the other 24" in text, result.stderr
    with h5py.File(folder / "out" / "recon.h5", "r") as handle:
        assert handle["/geometry/spectrum_centres_yx_px"].shape == (24, 2)
        assert handle["/geometry"].attrs["centre_index"] == 11  # the centre (2, 2), one place earlier
        assert np.asarray(handle["/geometry/grid_indices"])[11].tolist() == [2, 2]
        assert handle["/recon"].attrs["dropped_captures"].tolist() == [3]
        assert np.isfinite(handle["/recon/intensity"][()]).all()
    document = json.loads((folder / "out" / "report" / "report.json").read_text())
    assert document["dropped_captures"] == [3] and document["n_images"] == 24


case("capture-dead-left-out", "works", RUN, {"cfg.yaml": Config({"array.grid": 5})}, exit=0, writes=("out",),
     patch=_camera_dies(3), check=_dead_capture_left_out, seconds=40)


def _resolve_as_before_python_3_13(monkeypatch, folder: Path) -> None:
    """``Path.resolve`` as Python 3.10–3.12 have it: a symbolic link that loops raises RuntimeError."""
    import os

    original = Path.resolve

    def resolve(self, strict=False):
        try:
            os.stat(self)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise RuntimeError(f"Symlink loop from {str(self)!r}") from None
        return original(self, strict=strict)

    monkeypatch.setattr(Path, "resolve", resolve)


LOOP_MANIFEST = ("optics: {wavelength_m: 5.5e-7, focal_length_m: 0.1, aperture_diameter_m: 4.6e-3, "
                 "pixel_pitch_m: 2.5e-6, distance_m: 10}\nimages: [{path: loop.png, stage_x_mm: 0, stage_y_mm: 0}]\n")
case("manifest-image-symlink-loop", "traceback", ING, {"m.yaml": Text(LOOP_MANIFEST), "loop.png": Symlink("loop.png")},
     exit=3, says=("loop.png", "symbolic link"), patch=_resolve_as_before_python_3_13)
case("reconstruct-input-symlink-loop", "traceback", REC, {"in.h5": Symlink("in.h5")}, exit=3,
     says=("in.h5", "symbolic link"), patch=_resolve_as_before_python_3_13)
case("report-truth-other-size", "traceback", REP,
     {"in.h5": Copy("recon", set_data("/truth/object", lambda a: a[:32, :32]))}, exit=3,
     says=("in.h5", "/truth/object", "/truth/bars"))
case("report-truth-zero", "traceback", REP,
     {"in.h5": Copy("recon", set_data("/truth/object", lambda a: np.zeros((1, 1), a.dtype)))}, exit=3,
     says=("in.h5", "/truth/object"))
case("report-bars-not-a-layout", "traceback", REP,
     {"in.h5": Copy("recon", set_data("/truth/bars", lambda a: np.where(np.arange(8) == 3, 0, a)))}, exit=3,
     says=("in.h5", "/truth/bars"))


def _edit_manifest(change):
    """An edit of the library's lab manifest (``change(data, folder)`` alters the YAML mapping in place)."""
    import yaml

    def edit(folder: Path) -> None:
        path = folder / "manifest.yaml"
        data = yaml.safe_load(path.read_text())
        change(data, folder)
        path.write_text(yaml.safe_dump(data, sort_keys=False))
    return edit


def _optics(**values):
    return _edit_manifest(lambda data, folder: data["optics"].update(values))


def _stage_positions(far_mm: float):
    """Each row at its stage position (mm) instead of grid indices, the last one ``far_mm`` along x."""
    def change(data, folder):
        pitch = data.pop("stage_pitch_mm")
        for entry in data["images"]:
            row, col = entry.pop("grid")
            entry.update(stage_x_mm=(col - 1) * pitch, stage_y_mm=(row - 1) * pitch)
        data["images"][-1]["stage_x_mm"] = far_mm
    return _edit_manifest(change)


def _same_file(row: int, as_row: int, how: str = "path"):
    """Row ``row`` names row ``as_row``'s image: its path, a hard link or a symbolic link to that file."""
    import os

    def change(data, folder):
        entry, other = data["images"][row], data["images"][as_row]
        if how == "path":
            entry["path"] = other["path"]
            return
        mine = folder / entry["path"]
        mine.unlink()
        if how == "hard-link":
            os.link(folder / other["path"], mine)
        else:
            mine.symlink_to(other["path"])
    return _edit_manifest(change)


def _second_exposure_same_file(data, folder):
    """Every position gets a 40 ms frame of its own (a copy), except (0, 0), whose 40 ms row names its 10 ms file."""
    import shutil

    longer = []
    for entry in data["images"]:
        longer.append({**entry, "exposure_s": 0.04, "path": entry["path"].replace(".png", "_40ms.png")})
        shutil.copy(folder / entry["path"], folder / longer[-1]["path"])
    longer[0]["path"] = data["images"][0]["path"]
    data["images"] += longer


LAB_ING = ["ingest", "lab/manifest.yaml", "-o", "raw.h5", "-q"]
case("manifest-aperture-huge", "messages", LAB_ING, {"lab": Copy("manifest_dir", _optics(aperture_diameter_m=1000.0))},
     exit=2, says=("manifest.yaml", "optics.aperture_diameter_m", "not a plausible aperture diameter", "1000e-3"),
     not_says=("Traceback", "memory"))
case("manifest-aperture-large", "messages", LAB_ING, {"lab": Copy("manifest_dir", _optics(aperture_diameter_m=5.0))},
     exit=2, says=("manifest.yaml", "pupil", "optics.aperture_diameter_m"), not_says=("Traceback", "memory"))
case("manifest-aperture-tiny", "messages", LAB_ING, {"lab": Copy("manifest_dir", _optics(aperture_diameter_m=1e-9))},
     exit=2, says=("manifest.yaml", "pupil", "optics.aperture_diameter_m"), not_says=("Traceback", "memory"))
case("manifest-stage-position-far", "messages", LAB_ING, {"lab": Copy("manifest_dir", _stage_positions(1e9))},
     exit=2, says=("manifest.yaml", "x 1e+09", "view_r2c2.png", "stage_x"), not_says=("Traceback", "memory"))
case("manifest-stage-pitch-far", "messages", LAB_ING,
     {"lab": Copy("manifest_dir", _edit_manifest(lambda data, folder: data.update(stage_pitch_mm=1.8e9)))},
     exit=2, says=("manifest.yaml", "stage_pitch_mm"), not_says=("Traceback", "memory"))
case("manifest-stage-positions-work", "works", LAB_ING, {"lab": Copy("manifest_dir", _stage_positions(1.8))},
     exit=0, writes=("raw.h5",))
case("run-manifest-aperture-huge", "messages", ["run", "cfg.yaml", "--out-dir", "out", "-q"],
     {"cfg.yaml": Text("run: {stages: [ingest, hdr, reconstruct, report]}\ningest: {manifest: lab/manifest.yaml}\n"),
      "lab": Copy("manifest_dir", _optics(aperture_diameter_m=1000.0))},
     exit=2, says=("manifest.yaml", "optics.aperture_diameter_m"), not_says=("Traceback", "memory"), writes=("out",))
case("reconstruct-pupil-radius-huge", "messages", REC,
     {"in.h5": Copy("captures", set_attr("/geometry", "pupil_radius_px", 1e6))}, exit=3,
     says=("in.h5", "pupil_radius_px"), not_says=("Traceback", "internal error", "memory"))
config_case("snr-db-minus-100", "messages", {"noise.snr_db": -100}, ["noise.snr_db", "swamp", "-10"], argv=RUN,
            not_says=("Traceback", "black level"))
config_case("snr-db-below-floor", "validation", {"noise.snr_db": -10.5}, ["noise.snr_db", "-10"])
case("snr-db-at-floor-works", "works", SIM, {"cfg.yaml": Config({"noise.snr_db": -10})}, exit=0, writes=("c.h5",))


def _report_json_back(folder: Path, result) -> None:
    _stdout_has(result, "reconstruct skipped")
    document = json.loads((folder / "out" / "report" / "report.json").read_text())
    assert json.loads(document["provenance"]["inputs"])[0]["path"].endswith("recon.h5")


case("run-report-json-deleted", "works", RUN,
     {"cfg.yaml": Config({"report.figures": True}), "out": Copy("run_dir", lambda p: (p / "report" / "report.json").unlink())},
     exit=0, writes=("out/report", "out/.cca-run.lock"), check=_report_json_back)
case("manifest-same-file-two-positions", "silent", LAB_ING, {"lab": Copy("manifest_dir", _same_file(1, 0))}, exit=2,
     says=("manifest.yaml", "view_r0c0.png", "(row 0, col 0)", "(row 0, col 1)"))
case("manifest-hard-link-two-positions", "silent", LAB_ING,
     {"lab": Copy("manifest_dir", _same_file(4, 2, "hard-link"))}, exit=2,
     says=("manifest.yaml", "view_r1c1.png", "view_r0c2.png", "(row 1, col 1)", "(row 0, col 2)"))
case("manifest-symlink-two-positions", "silent", LAB_ING,
     {"lab": Copy("manifest_dir", _same_file(8, 0, "symlink"))}, exit=2,
     says=("manifest.yaml", "view_r2c2.png", "view_r0c0.png"))
case("manifest-same-file-two-exposures", "silent", LAB_ING,
     {"lab": Copy("manifest_dir", _edit_manifest(_second_exposure_same_file))}, exit=2,
     says=("manifest.yaml", "view_r0c0.png", "(row 0, col 0)", "exposures 0.01 s and 0.04 s"))


# --- trust: sweeps into an earlier sweep's folder, failing points, damaged checkpoints and tiles ---------------------
def _sweep_point_id(snr_db: float, seed: int) -> str:
    from cca_cli.config.load import parse_config
    from cca_cli.config.model import SweepSection
    from cca_cli.stages.sweep import expand_points

    from micro import micro_config

    spec = SweepSection(points=[{"noise.snr_db": snr_db, "noise.seed": seed}])
    return expand_points(parse_config(micro_config()), spec, Path("sw"))[0].point_id


def _sweep_table_holds(*values):
    def check(folder: Path, result) -> None:
        import csv

        with open(folder / "sw" / "sweep.csv") as handle:
            rows = list(csv.DictReader(handle))
        assert sorted(float(r["noise.snr_db"]) for r in rows) == sorted(values), rows
        assert {r["status"] for r in rows} <= {"ok", "cached"}, rows
        assert (folder / "sw" / "figures" / "rmse_vs_noise_snr_db.png").is_file()
    return check


SWEEP_MORE = ["sweep", "grid", "cfg.yaml", "--set", "noise.snr_db=30", "--out-dir", "sw", "-q", "--workers", "1"]
case("sweep-adds-to-an-earlier-sweep", "data-loss", SWEEP_MORE,
     {"cfg.yaml": Config(), "sw": SweepFolder({"noise.snr_db": [10, 20]})}, exit=0,
     # the new point follows the folder's two (index 2, seed 1 + 2): no noise draw of the table repeats
     writes=("sw/sweep.csv", "sw/sweep.h5", "sw/figures", f"sw/points/{_sweep_point_id(30, 3)}"),
     check=_sweep_table_holds(10, 20, 30), seconds=120)
case("sweep-into-another-base-config", "data-loss", SWEEP_MORE,
     {"cfg.yaml": Config(), "sw": SweepFolder({"noise.snr_db": [10, 20]}, {"reconstruct.iterations": 5})}, exit=4,
     says=("sw", "another base config", "--force"))
case("sweep-over-another-key", "data-loss", SWEEP_MORE,   # one table and its figures cannot plot both keys
     {"cfg.yaml": Config(), "sw": SweepFolder({"array.overlap": [0.55, 0.65]})}, exit=4,
     says=("sw", "sweep over array.overlap", "this one varies", "noise.snr_db", "--out-dir"), seconds=120)
case("sweep-into-another-study", "data-loss", SWEEP_MORE,
     {"cfg.yaml": Config(), "sw": SweepFolder({"noise.snr_db": [10, 20]}, study="noise")}, exit=4,
     says=("sweep.h5", "noise study", "--force"))
case("sweep-points-fail", "traceback",   # points that fail only when they run (a scene image no reader takes)
     ["sweep", "grid", "cfg.yaml", "--set", "noise.snr_db=20,30", "--out-dir", "sw", "-q", "--workers", "1"],
     {"cfg.yaml": Config({"scene.kind": "image", "scene.image_path": "scene.png"}), "scene.png": Text("not an image")},
     exit=1, says=("2 of 2 points failed", "sw/sweep.csv"), writes=("sw",), seconds=120)
case("sweep-points-invalid", "traceback",   # a chart that fits no point: refused before anything runs
     ["sweep", "grid", "cfg.yaml", "--set", "scene.size_px=20,12.7", "--out-dir", "sw", "-q", "--workers", "1"],
     {"cfg.yaml": Config()}, exit=2, says=("2 of 2 points of the sweep are invalid", "does not fit"), writes=())


def _started_afresh(folder: Path, result) -> None:
    import h5py

    assert "damaged" in result.stderr and "resuming" not in result.stderr, result.stderr
    with h5py.File(folder / "r.h5", "r") as handle:
        assert np.isfinite(handle["/recon/spectrum"][()]).all()
        assert handle["/history/residual"].shape == (20,)


RESUME = ["reconstruct", "c.h5", "-o", "r.h5", "--iterations", "20", "--checkpoint-every", "1", "-q"]
case("checkpoint-nan", "silent", RESUME,
     {"c.h5": Copy("captures"),
      "r.h5.checkpoint": Checkpoint("c.h5", 20, set_data("/checkpoint/spectrum", lambda a: a * np.nan))},
     exit=0, writes=("r.h5", "r.h5.checkpoint"), check=_started_afresh)
case("checkpoint-spectrum-of-another-shape", "silent", RESUME,
     {"c.h5": Copy("captures"), "r.h5.checkpoint": Checkpoint("c.h5", 20, set_data("/checkpoint/spectrum",
                                                                                  lambda a: a[:1]))},
     exit=0, writes=("r.h5", "r.h5.checkpoint"), check=_started_afresh)
case("checkpoint-history-nan", "silent", RESUME,
     {"c.h5": Copy("captures"),
      "r.h5.checkpoint": Checkpoint("c.h5", 20, set_data("/history/residual", lambda a: a * np.nan))},
     exit=0, writes=("r.h5", "r.h5.checkpoint"), check=_started_afresh)

TILED = ["reconstruct", "c.h5", "-o", "r.h5", "-c", "tiles.yaml", "-q", "--workers", "1"]
TILES_CONFIG = Text("reconstruct: {iterations: 5, tiles: {size_px: 40, overlap_px: 16}}\n")


def _tile_redone(folder: Path, result) -> None:
    assert "tile_000_000.h5 is damaged" in " ".join(result.stderr.split()), result.stderr
    assert (folder / "r.h5").is_file() and not (folder / "r.h5.tiles").exists()


for name, damaged in (("truncated", Truncated("recon", 0.3)), ("empty", Bytes(b"")),
                      ("without-datasets", Copy("recon"))):
    case(f"tile-file-{name}", "traceback", TILED,
         {"c.h5": Simulated({"simulate.store": "sensor"}), "tiles.yaml": TILES_CONFIG,
          "r.h5.tiles/tile_000_000.h5": damaged}, exit=0, writes=("r.h5", "r.h5.tiles"), check=_tile_redone,
         seconds=120)
case("tile-file-not-cca", "data-loss", TILED,
     {"c.h5": Simulated({"simulate.store": "sensor"}), "tiles.yaml": TILES_CONFIG,
      "r.h5.tiles/tile_000_000.h5": Text("my notes\n")}, exit=4, says=("tile_000_000.h5", "move it away"))
