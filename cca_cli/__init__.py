"""cca: long-distance sub-diffraction imaging with coherent camera arrays (macroscopic Fourier ptychography).

The command line is ``cca`` (``cca --help``). From Python, ``import cca_cli as cca`` gives:

- geometry: ``camera_scan``, ``stage_scan``, ``led_array``, ``led_grid_sines``;
- scenes: ``resolution_chart``, ``usaf_chart``;
- imaging and recovery: ``simulate`` (object → intensities), ``reconstruct`` (intensities → ``Reconstruction``);
- files: ``load``, ``save`` (``CaptureSet``, ``Reconstruction``), ``export`` (TIFF, PNG, .npy);
- metrics: ``contrast``, ``mtf20``, ``usaf_reading``, ``rmse``.

Arrays in, arrays out, SI units at the boundary. See :mod:`cca_cli.api` for the documentation and examples;
the names are imported on first use, so ``cca --help`` stays fast.
"""

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "CaptureGeometry",
    "CaptureSet",
    "Reconstruction",
    "camera_scan",
    "stage_scan",
    "led_array",
    "led_grid_sines",
    "resolution_chart",
    "usaf_chart",
    "simulate",
    "reconstruct",
    "load",
    "save",
    "export",
    "contrast",
    "mtf20",
    "usaf_reading",
    "rmse",
]


def __getattr__(name: str):
    if name in __all__:
        from cca_cli import api

        return getattr(api, name)
    raise AttributeError(f"module 'cca_cli' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
