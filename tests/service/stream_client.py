"""One client process of the replicated-fleet tests: streams acknowledged updates on its own
chain until a stop file appears.

``python -m tests.service.stream_client ENDPOINT MAP NO N ACKS STOPFILE TIMEOUT_S``: updates
``c<no>/k -> c<no>/k+1`` with request ids ``c<no>-<k>`` and a TIMEOUT_S deadline each (the
client retries through takeovers and partitions with the same id). After each ack it appends
``request_id seq server time duplicate sent`` to ACKS (flushed; ``time``: ``time.time()`` when
the ack arrived; ``sent``: when the update was first sent, so no server acknowledged it
before then). Exit 0 when every update it sent was acknowledged.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import numpy as np
from mcsm_client.client import MapClient
from mcsm_client.sampling import sample_planar


def main(argv: list[str]) -> int:
    ep, map_name, no, n, acks, stop, timeout = argv
    # the client's retries (with their reasons) in this process's log, for a failing test
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    c_no, n_samples, stop_path = int(no), int(n), Path(stop)
    rng = np.random.default_rng(2000 + c_no)
    cov = np.diag([0.05**2, 0.05**2, 0.0005**2])
    with MapClient(map=map_name, connect=ep, timeout_s=float(timeout)) as c, \
            open(acks, "a") as out:
        for k in range(100_000):
            if stop_path.exists():
                break
            x = sample_planar([1.0, 0.0, 0.0], cov, n_samples=n_samples, rng=rng)
            sent = time.time()
            ack = c.update(f"c{c_no}/{k}", f"c{c_no}/{k + 1}", x, request_id=f"c{c_no}-{k}")
            out.write(f"{ack.request_id} {ack.seq} {ack.server} {time.time():.6f} "
                      f"{int(ack.duplicate)} {sent:.6f}\n")
            out.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
