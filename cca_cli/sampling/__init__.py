"""Array geometry: overlap, step, synthetic aperture ratio and the sampling grids."""

from cca_cli.sampling.grid import BandLayout, ScanGrid, band_layout, smallest_fft_size, square_scan
from cca_cli.sampling.overlap import grid_for_sar, overlap_for, step_m, synthetic_aperture_ratio

__all__ = [
    "BandLayout",
    "ScanGrid",
    "band_layout",
    "smallest_fft_size",
    "square_scan",
    "grid_for_sar",
    "overlap_for",
    "step_m",
    "synthetic_aperture_ratio",
]
