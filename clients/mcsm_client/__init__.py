"""mcsm_client: the client side of mcsm.

``MapClient`` (``mcsm_client.client``) talks to ``mcsm serve`` over Zenoh; ``sampling`` draws AT
sample sets from means and covariances; ``datasets`` and ``players`` stream public pose-graph
files; ``scenario``, ``sim`` and ``multirobot`` are the simulated robots. The math is the
server's own (``mcsm.core``), imported from the same wheel.
"""
