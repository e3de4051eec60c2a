"""The server under floods and full disks: bounded memory, ``Busy``, reads first, exit 3.

Real ``mcsm serve`` processes on loopback:

* **Flood**: 40 maximum-size updates (N = 100,000 samples, 5.6 MB each) sent at once to a
  server with ``--queue-bytes 48M``: every one is either acknowledged or refused with
  ``Busy`` (some are), the server's peak resident memory (``VmHWM``) stays under 1 GB
  (0.69 GB measured; the same flood without a byte bound reached 1.6 GB: docs/recordings.md),
  and ``info`` sent from another client during the flood is answered within 1 s each time.
* **Full disk**: the recording lives on a 1 MiB tmpfs mounted in a private mount namespace
  (``unshare --user --map-root-user --mount``: works as root and, where user namespaces are
  allowed, unprivileged; elsewhere the test falls back to a file-size limit, ``prlimit
  --fsize``, whose writes fail with EFBIG, and says so). The server stops with exit code 3,
  a one-line message and no traceback; every acknowledged input is in the file, which reads
  as cut (not damaged) and replays.
"""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from mcsm import wire
from mcsm.errors import McsmError
from mcsm.recording import RecordingReader, replay
from mcsm_client.client import MapClient

from tests.service.daemon_util import STARTUP_DEADLINE_S, Daemon, noisy_at, start_daemon

FLOOD_N = 100_000  # wire.MAX_SAMPLES: the largest update
FLOOD_REQUESTS = 40
FLOOD_RSS_BOUND_KB = 1024 * 1024  # 1 GB


def _peak_rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    raise AssertionError("no VmHWM in /proc")


def test_a_flood_of_maximum_size_updates_is_bounded_busy_and_reads_go_first(
        tmp_path: Path, daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(FLOOD_N), "--queue-bytes", "48M")
    daemons.append(d)
    rng = np.random.default_rng(24001)
    x = noisy_at(rng, FLOOD_N, [1.0, 0.0, 0.0])
    payloads = [wire.encode_update(f"f{i}", f"p{i}", f"p{i + 1}", x)
                for i in range(FLOOD_REQUESTS)]
    assert len(payloads[0]) > 5_500_000
    with MapClient(connect=d.endpoint, timeout_s=60) as c, \
            MapClient(connect=d.endpoint, timeout_s=5) as q:
        q.info()
        pending = [c.session.get(c.keys.update, payload=p, timeout=120) for p in payloads]
        latencies = []
        for _ in range(5):  # while the flood is being applied
            t0 = time.monotonic()
            info = q.info()
            latencies.append(time.monotonic() - t0)
            if info.seq + info.rejected_by_error.get("Busy", 0) >= FLOOD_REQUESTS:
                break
        kinds = []
        for h in pending:
            replies = list(h)
            assert len(replies) == 1
            r = replies[0]
            kinds.append("ack" if r.ok is not None else
                         type(wire.decode_error(r.err.payload.to_bytes())).__name__)
        final = q.info()
    peak = _peak_rss_kb(d.proc.pid)
    assert set(kinds) == {"ack", "Busy"}, kinds
    assert final.seq == kinds.count("ack")
    assert max(latencies) < 1.0, latencies
    assert peak < FLOOD_RSS_BOUND_KB, f"peak RSS {peak / 1e6:.2f} GB"


def _full_disk_wrapper(disk: Path, out: Path, size: int) -> tuple[list[str], str]:
    """A command prefix that runs the server with ``disk`` full after ``size`` bytes, and
    what it is: a tmpfs in a private mount namespace, or else a file-size limit."""
    probe = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                            f"mount -t tmpfs -o size={size} tmpfs {disk}"],
                           capture_output=True, timeout=30) if shutil.which("unshare") else None
    if probe is not None and probe.returncode == 0:
        script = ('mount -t tmpfs -o size="$MCSM_DISK_SIZE" tmpfs "$MCSM_DISK" || exit 97; '
                  '"$@"; rc=$?; cp "$MCSM_DISK"/*.mcap "$MCSM_OUT"/; exit $rc')
        return (["unshare", "--user", "--map-root-user", "--mount", "--pid", "--fork",
                 "--kill-child", "sh", "-c", script, "sh"], "tmpfs")
    if shutil.which("prlimit"):
        return ["prlimit", f"--fsize={size}"], "file-size limit (EFBIG)"
    pytest.fail("neither a tmpfs in a user namespace nor prlimit is available here")


def test_a_full_disk_stops_the_server_with_exit_3_and_keeps_every_ack(
        tmp_path: Path, daemons: list[Daemon]) -> None:
    disk, out = tmp_path / "disk", tmp_path / "out"
    disk.mkdir()
    out.mkdir()
    n, size = 200, 1 << 20  # 11 kB per update: the disk is full after about 90
    prefix, how = _full_disk_wrapper(disk, out, size)
    d = Daemon(disk / "full.mcap", extra_args=["--samples", str(n)], log_path=tmp_path / "d.log",
               cwd=tmp_path, env={"MCSM_DISK": str(disk), "MCSM_OUT": str(out),
                                  "MCSM_DISK_SIZE": str(size)},
               ready_timeout_s=STARTUP_DEADLINE_S)
    d.cmd = [*prefix, *d.cmd]
    daemons.append(d)
    d.start()
    rng = np.random.default_rng(24002)
    acked: list[str] = []
    failure = None
    with MapClient(connect=d.endpoint, timeout_s=10) as c:
        for k in range(400):
            try:
                c.update(f"p{k}", f"p{k + 1}", noisy_at(rng, n, [1.0, 0.0, 0.0]),
                         request_id=f"u{k}")
            except McsmError as exc:
                failure = exc
                break
            acked.append(f"u{k}")
    assert failure is not None and "recording failed" in str(failure), (how, failure)
    assert 50 < len(acked) < 400
    assert d.proc.wait(timeout=30) == 3, (how, d.log_text())
    d.stop()
    log = d.log_text()
    assert "Traceback" not in log and "could not be written" in log, log[-2000:]
    rec = out / "full.mcap" if how == "tmpfs" else disk / "full.mcap"
    reader = RecordingReader(rec)
    ids = [item.data["id"] for item in reader if item.topic == "/mcsm/in/update"]
    assert ids[:len(acked)] == acked and len(ids) <= len(acked) + 1, how
    assert reader.cut and reader.damage is None, (how, reader.tail_error)
    rep = replay(rec)
    assert rep.divergence is None and rep.n_inputs == len(ids)
