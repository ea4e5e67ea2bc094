"""Synthetic targets with known layouts: bar resolution chart and USAF-1951 chart.

Only numpy is used; nothing here depends on the rest of :mod:`cca_cli`.
"""

from cca_cli.targets.charts import (
    DEFAULT_WIDTHS,
    BarChart,
    BarGroup,
    Box,
    chart_groups_for_grid,
    resolution_chart,
)
from cca_cli.targets.usaf import UsafChart, UsafElement, usaf1951_chart, usaf_lp_per_mm

__all__ = [
    "DEFAULT_WIDTHS",
    "BarChart",
    "BarGroup",
    "Box",
    "chart_groups_for_grid",
    "resolution_chart",
    "UsafChart",
    "UsafElement",
    "usaf1951_chart",
    "usaf_lp_per_mm",
]
