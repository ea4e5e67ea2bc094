"""cca: long-distance sub-diffraction imaging with coherent camera arrays."""

__version__ = "0.1.0"
