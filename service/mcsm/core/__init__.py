"""Pure numpy core: quaternion kernels, AT algebra, merges and the stochastic map. No I/O."""

from mcsm.core.at import compound, identity, invert, mean_and_cov, merge, merge_correlated
from mcsm.core.smap import RemoveResult, StochasticMap, Submap, UpdateResult

__all__ = ["StochasticMap", "UpdateResult", "RemoveResult", "Submap", "compound", "invert",
           "identity", "merge", "merge_correlated", "mean_and_cov"]
