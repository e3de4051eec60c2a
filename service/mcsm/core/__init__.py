"""The core: AT algebra, merges and the stochastic map, on a compiled kernel. No I/O.

Every computation that changes map state runs in the compiled kernel (:mod:`mcsm.core.kernel`)
with a fixed order of operations; the numpy functions of :mod:`mcsm.core.at` and
:mod:`mcsm.core.quat` serve clients, reports and tests (their last bits may depend on the CPU).
"""

from mcsm.core.at import compound, identity, invert, mean_and_cov, merge, merge_correlated
from mcsm.core.smap import RemoveResult, StochasticMap, Submap, UpdateResult, Verdict

#: Version of the core's arithmetic: every state-changing computation of one version gives the
#: same bits on every CPU. Recordings carry it; a recording made by another version cannot be
#: verified bit for bit (1: the numpy/BLAS core before the compiled kernel, machine-bound).
ARITHMETIC_VERSION = 2

__all__ = ["ARITHMETIC_VERSION", "StochasticMap", "UpdateResult", "RemoveResult", "Submap",
           "Verdict",
           "compound", "invert", "identity", "merge", "merge_correlated", "mean_and_cov"]
