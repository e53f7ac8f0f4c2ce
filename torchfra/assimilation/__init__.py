"""Calibration from recordings: the ensemble Kalman analysis, the hierarchical master/slave filter
(paper Eqs. 21-23) with linear or polynomial slave, the restart filter and the exact grid posterior."""
from torchfra.assimilation.analysis import AnalysisInfo, analysis
from torchfra.assimilation.exact import GridPosterior, SweepMap, data_fit, grid_posterior
from torchfra.assimilation.filters import (
                      FilterResult,
                      LinearSlave,
                      PolynomialSlave,
                      hierarchical_filter,
                      innovation_flags,
                      sequential_filter,
                      summarize,
)

__all__ = ["AnalysisInfo", "analysis", "GridPosterior", "SweepMap", "grid_posterior", "FilterResult", "LinearSlave",
           "PolynomialSlave", "hierarchical_filter", "innovation_flags", "sequential_filter", "summarize"]
