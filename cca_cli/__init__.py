"""cca: long-distance sub-diffraction imaging with coherent camera arrays (macroscopic Fourier ptychography).

The command line is ``cca`` (``cca --help``). From Python, ``import cca_cli as cca`` gives:

- geometry: ``camera_scan``, ``stage_scan``, ``led_array``, ``led_grid_sines``;
- scenes: ``resolution_chart``, ``usaf_chart``;
- imaging and recovery: ``simulate`` (object → intensities), ``reconstruct`` (intensities → ``Reconstruction``);
- wide fields: ``reconstruct_tiles`` (overlapping tiles on Dask, a pupil per tile);
- files: ``load``, ``save`` (``CaptureSet``, ``Reconstruction``), ``export`` (TIFF, PNG, .npy);
- metrics: ``contrast``, ``mtf20``, ``usaf_reading``, ``rmse``.

Arrays in, arrays out, SI units at the boundary. See :mod:`cca_cli.api` for the documentation and examples;
the names are imported on first use, so ``cca --help`` stays fast.
"""

from cca_cli.version import __version__  # noqa: F401 - the package's version, listed by __all__


def _api():
    import importlib

    return importlib.import_module("cca_cli.api")


def __getattr__(name: str):
    # The public names are api.__all__ (one list); they load on first use so that `cca --help` stays fast.
    if name.startswith("__") and name != "__all__":
        raise AttributeError(f"module 'cca_cli' has no attribute {name!r}")
    api = _api()
    if name == "__all__":
        return ["__version__", *api.__all__]
    if name in api.__all__:
        return getattr(api, name)
    raise AttributeError(f"module 'cca_cli' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_api().__all__))
