"""The pose-graph backend: the SGD of Olson, Leonard & Teller (2006), an exact-minimum polish, graph files.

Depends on numpy, scipy and numba only. Every optimizer yields an `Iteration` per iteration so callers can
record the whole optimization.
"""

from optimizer.cost import chi2
from optimizer.errors import GraphError, GraphFileError, OptimizerError
from optimizer.graph import PoseGraph
from optimizer.iteration import Iteration

__all__ = ["GraphError", "GraphFileError", "Iteration", "OptimizerError", "PoseGraph", "chi2"]
