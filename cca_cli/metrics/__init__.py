"""Image-quality metrics: bar contrast / MTF20 limit, RMSE, USAF reading, three-bar profile reading, split residual.

Depends only on numpy, scipy and :mod:`cca_cli.targets`.
"""

from cca_cli.metrics.bars import BarElement, parse_element_table, read_bar_elements, three_bar_profile_contrast
from cca_cli.metrics.contrast import (
    ContrastTable,
    bar_contrast,
    contrast_table,
    mtf_limit,
    resolution_gain,
)
from cca_cli.metrics.error import amplitude_rmse, relative_error, rmse
from cca_cli.metrics.residual import SplitResidual, split_amplitude_residual
from cca_cli.metrics.speckle import speckle_contrast
from cca_cli.metrics.usaf import (
    UsafElementContrast,
    UsafReading,
    three_bar_contrast,
    usaf_gain,
    usaf_resolution,
)

__all__ = [
    "BarElement",
    "parse_element_table",
    "read_bar_elements",
    "three_bar_profile_contrast",
    "SplitResidual",
    "split_amplitude_residual",
    "ContrastTable",
    "bar_contrast",
    "contrast_table",
    "mtf_limit",
    "resolution_gain",
    "amplitude_rmse",
    "relative_error",
    "rmse",
    "speckle_contrast",
    "UsafElementContrast",
    "UsafReading",
    "three_bar_contrast",
    "usaf_gain",
    "usaf_resolution",
]
