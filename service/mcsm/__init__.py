"""mcsm: the Monte Carlo stochastic map server.

The math (``mcsm.core``) needs numpy only; the wire codec, server and recorder live in their
own modules so that importing the core pulls in neither zenoh, msgpack nor mcap.
"""

from mcsm.core import (
    RemoveResult,
    StochasticMap,
    Submap,
    UpdateResult,
    compound,
    identity,
    invert,
    mean_and_cov,
    merge,
    merge_correlated,
)

__version__ = "0.1.0"

__all__ = ["StochasticMap", "UpdateResult", "RemoveResult", "Submap", "compound", "invert",
           "identity", "merge", "merge_correlated", "mean_and_cov", "__version__"]
