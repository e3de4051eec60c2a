"""What the lease's TTL costs under the partition tests' load: a summary of the runs of
``tests/service/test_partitions.py`` kept in a pytest ``--basetemp`` directory.

For each run (its ``partition.json``, written by the test, and its servers' logs): the lease
TTL, the seconds from the heal to each side's first fresh ack, and every time a server stopped
being primary (``not serving it any more``), took over (``took over as primary``) or refused
an update with ``NotReplicated`` (its lease not valid, or the log did not take it), split by
phase: before the cut, during it, after the heal. With the primary's side holding the NATS
majority nothing forces a change of primary before the cut or during it, unless a leader of
the lease bucket or the map's stream was on the cut-off node (JetStream then elects another,
4-9 s, longer than the lease); a change before the cut, under load alone, is a false takeover.

Run the matrix with the TTL to measure, then summarise (both on the same machine, in one
sitting, to compare)::

    MCSM_TEST_LEASE_TTL=1 .venv/bin/python -m pytest -q tests/service/test_partitions.py \\
        --basetemp=/tmp/ttl1
    .venv/bin/python benchmarks/partition_summary.py /tmp/ttl1 [/tmp/ttl2 ...]
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
from datetime import datetime
from pathlib import Path

_LINE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) \w+ [\w.]+: (.*)$")
_EVENTS = {"stops": "not serving it any more", "takeovers": "took over as primary",
           "refusals": "NotReplicated"}


def _events(log: Path) -> list[tuple[float, str]]:
    out = []
    for line in log.read_text(errors="replace").splitlines():
        m = _LINE.match(line)
        if m is None:
            continue
        for what, text in _EVENTS.items():
            if text in m.group(2):
                t = datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
                out.append((t, what))
    return out


def summarise(base: Path) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    for run in sorted(p.parent for p in base.glob("*/partition.json")
                      if not p.parent.is_symlink()):  # pytest's "...current" links
        d = json.loads((run / "partition.json").read_text())
        counts = {f"{w} {ph}": 0 for w in _EVENTS for ph in ("before", "during", "after")}
        for log in [run / "p.log", *sorted(run.glob("s[0-9].log"))]:
            if not log.exists():
                continue
            for t, what in _events(log):
                ph = "before" if t < d["t_cut"] else "during" if t < d["t_heal"] else "after"
                counts[f"{what} {ph}"] += 1
        rows.append({"run": f"{d['kind']}-{d['primary_side']}-{d['standbys']}",
                     "ttl": d["lease_ttl_s"], "heal": max(d["heal_to_fresh_ack_s"]), **counts})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("basetemp", type=Path, nargs="+")
    args = ap.parse_args()
    for base in args.basetemp:
        rows = summarise(base)
        if not rows:
            print(f"{base}: no partition.json")
            continue
        keys = [k for k in rows[0] if k not in ("run", "ttl", "heal")]
        print(f"{base}: {len(rows)} runs, lease TTL {rows[0]['ttl']} s")
        print(f"{'run':24s} {'heal->ack s':>11s} " + " ".join(f"{k:>17s}" for k in keys))
        for r in rows:
            print(f"{r['run']:24s} {r['heal']:11.1f} " + " ".join(f"{r[k]:17d}" for k in keys))
        heals = [float(str(r["heal"])) for r in rows]
        print(f"heal -> fresh ack on both sides: median {statistics.median(heals):.1f} s, "
              f"worst {max(heals):.1f} s")
        print("totals: " + ", ".join(f"{k} {sum(int(str(r[k])) for r in rows)}" for k in keys))


if __name__ == "__main__":
    main()
