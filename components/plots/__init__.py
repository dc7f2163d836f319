"""The figures of pidc as files readable offline (matplotlib, Agg canvas, no pyplot).

Inputs are numpy arrays (θ in the order and physical units of :mod:`components.core.weather`); every plotting
function returns a :class:`matplotlib.figure.Figure`, written with :func:`save_figure` (atomic, closes it).

* Task I: :func:`marginal_histograms` (1st analysis), :func:`corner_plot` (2nd), :func:`ppc_sheet` (3rd),
  :func:`coverage_plot` (4th), :func:`superiority_boxplot` (5th), :func:`parameter_heatmaps` (per parameter),
  :func:`truth_profile_plot` (per parameter and true value), :func:`named_heatmap` (named weathers);
* Task II: :func:`corner_compare`, :func:`marginals_overlay`, :func:`held_out_curve`, :func:`image_grid`;
* Task III: :func:`boxplots_by_level`, :func:`roc_curves`, :func:`relation_marginals` (one target, ``pidc relate``);
* training: :func:`loss_curves`;
* highest-density regions from samples: :func:`hdr_log_threshold` and its 2-D grid counterpart.

Used by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and the ``pidc`` CLI.
"""

from components.plots.calibration import coverage_plot, model_styles, superiority_boxplot
from components.plots.canvas import new_figure, save_figure
from components.plots.corner import corner_compare, corner_plot, corner_ranges
from components.plots.deconvolution import held_out_curve
from components.plots.hdr import grid_density, grid_hdr_thresholds, hdr_log_threshold, in_hdr
from components.plots.images import image_grid, ppc_sheet
from components.plots.marginals import marginal_hdr_histograms, marginal_histograms
from components.plots.named import named_heatmap
from components.plots.overlay import marginals_overlay
from components.plots.parameters import parameter_heatmaps
from components.plots.profile import truth_profile_plot
from components.plots.relation import relation_marginals
from components.plots.relative import boxplots_by_level, roc_curves
from components.plots.training import best_epoch, loss_curves

__all__ = [
    "save_figure",
    "named_heatmap",
    "new_figure",
    "hdr_log_threshold",
    "in_hdr",
    "grid_density",
    "grid_hdr_thresholds",
    "marginal_hdr_histograms",
    "marginal_histograms",
    "corner_ranges",
    "corner_plot",
    "corner_compare",
    "marginals_overlay",
    "held_out_curve",
    "coverage_plot",
    "model_styles",
    "superiority_boxplot",
    "parameter_heatmaps",
    "truth_profile_plot",
    "ppc_sheet",
    "image_grid",
    "loss_curves",
    "best_epoch",
    "boxplots_by_level",
    "roc_curves",
    "relation_marginals",
]
