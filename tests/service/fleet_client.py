"""One client process of the hot-standby test: streams acknowledged updates on its own chain.

``python -m tests.service.fleet_client ENDPOINT MAP CLIENT_NO COUNT N ACKS_FILE``: COUNT
updates ``c<no>/k -> c<no>/k+1`` (1 m steps along x), and after every tenth a loop closure
back nine steps, each with the request id ``c<no>-<k>`` (``c<no>-<k>L``) and a 60 s deadline
(the client retries through a takeover with the same id). After each ack it appends
``request_id seq server`` to ACKS_FILE (flushed). Exit 0 when every update was acknowledged.
"""

from __future__ import annotations

import sys

import numpy as np
from mcsm_client.client import MapClient
from mcsm_client.sampling import sample_planar


def _step(rng: np.random.Generator, n: int, x: float, sigma: float) -> np.ndarray:
    """``x`` metres along x, with ``sigma`` on x and y and a hundredth of it on the heading."""
    cov = np.diag([sigma**2, sigma**2, (0.01 * sigma) ** 2])
    return sample_planar([x, 0.0, 0.0], cov, n_samples=n, rng=rng)


def main(argv: list[str]) -> int:
    ep, map_name, no, count, n, acks = argv
    c_no, n_upd, n_samples = int(no), int(count), int(n)
    rng = np.random.default_rng(1000 + c_no)
    with MapClient(map=map_name, connect=ep, timeout_s=60.0) as c, open(acks, "a") as out:
        for k in range(n_upd):
            todo = [(f"c{c_no}/{k}", f"c{c_no}/{k + 1}", _step(rng, n_samples, 1.0, 0.05),
                     f"c{c_no}-{k}")]
            if k % 10 == 9:
                todo.append((f"c{c_no}/{k + 1}", f"c{c_no}/{k - 8}",
                             _step(rng, n_samples, -9.0, 0.3), f"c{c_no}-{k}L"))
            for a, b, t, rid in todo:
                ack = c.update(a, b, t, request_id=rid)
                out.write(f"{ack.request_id} {ack.seq} {ack.server}\n")
                out.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
