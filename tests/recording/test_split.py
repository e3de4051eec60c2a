"""Split recordings, what snapshots carry, and the bounds on a recorder's and a window's memory.

In-process (``Recorder`` + ``MapState`` driven as the server's worker drives them, no Zenoh):
a recording split into files replays as a set and file by file (also with a retraction right
after a split of an update before it); sets with a gap or mixed files are refused by name;
remembered ids survive restore after restore with their receive times; chunk indexes spill to
disk and the summary still indexes every chunk; a failed write leaves a cut file, never a
damaged one; the retract window stays within its byte budget and says when a target fell out.
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcsm import StochasticMap, wire
from mcsm.cli import EXIT_USAGE
from mcsm.cli import main as mcsm_main
from mcsm.errors import InvalidOperation
from mcsm.log.chunkwriter import ChunkPerInputWriter
from mcsm.log.reader import RecordingReader
from mcsm.log.recset import resolve
from mcsm.log.replay import replay
from mcsm.log.topics import TOPIC_OPS, RecordingError, decode_input
from mcsm.log.writer import Recorder
from mcsm.map import ops
from mcsm.map.history import nbytes
from mcsm.map.state import MapState
from mcsm.serve.lanes import Full, Lanes

from tests.recording.test_recording import at

N = 16
T0 = 1_700_000_000_000_000_000  # receive times (ns): what the id TTL counts from


class Driver:
    """Apply and record inputs as the server's worker does (checkpoints, disk snapshots)."""

    def __init__(self, rec: Recorder, st: MapState, seed: int, disk_every: int = 20,
                 checkpoint_every: int = 5) -> None:
        self.rec, self.st = rec, st
        self.rng = np.random.default_rng(seed)
        self.disk_every, self.cp_every = disk_every, checkpoint_every
        self.sent: list[tuple[str, str, bytes]] = []  # (op, id, payload) of applied inputs
        self.t = T0
        self.j = 0  # the chain's last pose

    def send(self, op: str, payload: bytes) -> wire.Ack:
        st = self.st
        req = decode_input(op, payload, st.n_samples)
        self.t += 10**6
        ack = st.apply(op, req, time_ns=self.t, payload=payload)
        self.rec.input(op, st.name, ack.seq, self.t, "test", req.request_id, payload)
        if ack.seq % self.cp_every == 0:
            self.rec.checkpoint(st.name, ack.seq, st.digest(), "periodic")
        if self.disk_every and ack.seq % self.disk_every == 0:
            self.rec.snapshot(st)
        self.sent.append((op, req.request_id, payload))
        return ack

    def update(self, k: int) -> wire.Ack:
        if k % 4 == 3:  # a loop closure back to the start
            x = self.st.map.query("p0", f"p{self.j}")[self.rng.permutation(N)]
            return self.send("update", wire.encode_update(f"u{k}", "p0", f"p{self.j}", x))
        self.j += 1
        return self.send("update", wire.encode_update(f"u{k}", f"p{self.j - 1}", f"p{self.j}",
                                                      at(self.rng, N, [1.0, 0.0, 0.0])))

    def close(self) -> None:
        self.rec.checkpoint(self.st.name, self.st.seq, self.st.digest(), "close")
        self.rec.close()


def _state(**kw: Any) -> MapState:
    return MapState("default", StochasticMap(N), snapshot_every=5, snapshots_kept=3, **kw)


def test_a_split_recording_replays_as_a_set_and_file_by_file(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "run.mcap", split_bytes=60_000)
    dr = Driver(rec, _state(retract_window_bytes=1 << 20), seed=7101)
    rec.config(dr.st, 5)
    retracted_across: list[str] = []
    closure = ""
    for k in range(90):
        before = rec.index
        dr.update(k)
        if k % 4 == 3:
            closure = f"u{k}"
        # a split just happened: retract the last loop closure, recorded in the file before
        if rec.index != before and closure and closure not in retracted_across:
            dr.send("retract", wire.encode_retract(f"r{k}", closure))
            retracted_across.append(closure)
    dr.close()
    paths = rec.paths
    assert len(paths) >= 3 and retracted_across
    assert [p.name for p in paths] == [f"run_{k:04d}.mcap" for k in range(len(paths))]
    assert resolve([tmp_path]) == paths == resolve([str(tmp_path / "run_*.mcap")])
    assert resolve(list(reversed(paths))) == paths  # set order, not argument order
    final = dr.st.digest()
    whole = replay(paths)
    assert whole.identical and whole.complete and whole.n_inputs == len(dr.sent)
    assert whole.states["default"].digest() == final
    carried: set[str] = set()
    for k, p in enumerate(paths):  # each file alone, from the snapshot it starts with
        alone = replay(p)
        assert alone.identical and alone.complete, (p.name, alone.divergence)
        assert alone.snapshots_loaded == (k > 0)
        first = next(r.data for r in RecordingReader(p) if r.topic == "/mcsm/snapshot")
        if k > 0:  # it carries the window: the retraction after the split needs it
            assert first["reason"] == "split" and first["seq"] > 0
            carried |= {e["id"] for e in first["window"]["log"]}
    assert set(retracted_across) <= carried
    assert replay(paths[1:]).states["default"].digest() == final
    # --restore from the set: only the files from the latest usable snapshot on are read
    sink = Recorder(tmp_path / "restored.mcap")
    fast = replay(paths, from_snapshot=True, sink=sink)
    sink.close()
    assert fast.identical and fast.states["default"].digest() == final
    again = replay(tmp_path / "restored.mcap")  # the restored server's file, alone
    assert again.identical and again.states["default"].digest() == final
    assert fast.files and fast.files[-1] == str(paths[-1]) and len(fast.files) < len(paths)
    st2 = fast.states["default"]
    for op, rid, payload in dr.sent:  # every id of every file is remembered
        fp = ops.fingerprint(op, decode_input(op, payload, N))
        hit = st2.lookup(rid, fp)
        assert hit is not None and hit.duplicate, rid


def test_sets_with_a_gap_or_mixed_files_are_refused_by_name(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    runs = []
    for name in ("a", "b"):
        rec = Recorder(tmp_path / name / "run.mcap", split_bytes=20_000)
        dr = Driver(rec, _state(), seed=7102)
        rec.config(dr.st, 5)
        for k in range(80):
            dr.update(k)
        dr.close()
        assert len(rec.paths) >= 3
        runs.append(rec.paths)
    a, b = runs
    with pytest.raises(RecordingError, match=r"gap in the split recording: file\(s\) 1 "):
        resolve([a[0], a[2]])
    with pytest.raises(RecordingError, match="mixed set"):
        resolve([a[0], b[1]])
    lone = tmp_path / "lone.mcap"
    Driver(Recorder(lone), _state(), seed=1).rec.close()
    with pytest.raises(RecordingError, match="mixed set: this file is not part of a split"):
        resolve([a[0], lone])
    for cmd in ("replay", "inspect", "cat"):
        assert mcsm_main([cmd, str(a[0]), str(a[2])]) == EXIT_USAGE
        err = capsys.readouterr().err
        assert "gap in the split recording" in err and "Traceback" not in err
    assert mcsm_main(["recover", str(a[0]), str(b[1]), "-o", str(tmp_path / "out")]) \
        == EXIT_USAGE
    assert "mixed set" in capsys.readouterr().err and not (tmp_path / "out").exists()
    assert mcsm_main(["serve", "--restore", str(a[0]), str(a[2])]) == EXIT_USAGE
    assert "--restore: " in capsys.readouterr().err
    # a set read as a set by every command (the set in order, from a directory)
    assert mcsm_main(["replay", str(tmp_path / "a"), "--no-progress"]) == 0
    assert mcsm_main(["inspect", str(tmp_path / "a")]) == 0
    assert "split recording" in capsys.readouterr().out
    assert mcsm_main(["cat", str(tmp_path / "a"), "--json"]) == 0
    seqs = [int(line.split('"seq": ')[1].split(",")[0])
            for line in capsys.readouterr().out.splitlines()]
    assert seqs == list(range(1, 81))
    png = tmp_path / "a.png"
    assert mcsm_main(["plot", *map(str, a[1:]), "-o", str(png), "--at", "50"]) == 0
    assert "at seq 50 of 80" in capsys.readouterr().out and png.stat().st_size > 10_000
    assert mcsm_main(["recover", str(tmp_path / "a"), "-o", str(tmp_path / "rec")]) == 0
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == [p.name for p in a]
    assert replay(sorted((tmp_path / "rec").iterdir())).identical
    # a new split recording refuses a base whose numbered files exist, any one of them
    with pytest.raises(RecordingError, match="run_0000.mcap: exists"):
        Recorder(tmp_path / "a" / "run.mcap", split_bytes=20_000)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "run_0003.mcap").write_bytes(b"")
    with pytest.raises(RecordingError, match="run_0003.mcap: exists"):
        Recorder(tmp_path / "c" / "run.mcap", split_bytes=20_000)
    # a cut file before the last stops the replay there: exit 4, naming the file
    cut = tmp_path / "cut"
    shutil.copytree(tmp_path / "a", cut)
    middle = cut / a[1].name
    middle.write_bytes(middle.read_bytes()[: middle.stat().st_size // 2])
    capsys.readouterr()
    assert mcsm_main(["replay", str(cut), "--no-progress"]) == 4
    out = capsys.readouterr().out
    want = f"CUT: the file ends without a clean close ({a[1].name} (file 2 of {len(a)}):"
    assert want in out, out


def test_ids_survive_restore_after_restore_with_their_receive_times(tmp_path: Path) -> None:
    """The tester's case in process: ids remembered from a snapshot are written with every
    later snapshot, so the third file still knows the first file's ids; the TTL counts from
    the original receive times."""
    rec = Recorder(tmp_path / "one.mcap")
    dr = Driver(rec, _state(), seed=7103, disk_every=10)
    rec.config(dr.st, 5)
    for k in range(25):
        dr.update(k)
    rec.close()  # (as after a SIGKILL: no close checkpoint)
    snaps = [r.data for r in RecordingReader(tmp_path / "one.mcap") if r.topic == "/mcsm/snapshot"]
    assert len(snaps) == 2 and all("ids" in d and "window" not in d for d in snaps)
    k = 25
    for name, src in (("two.mcap", "one.mcap"), ("three.mcap", "two.mcap")):
        sink = Recorder(tmp_path / name)
        rep = replay(tmp_path / src, sink=sink, from_snapshot=True, id_ttl_s=3600)
        assert rep.identical and rep.snapshots_loaded == 1
        first = next(r.data for r in RecordingReader(tmp_path / name)
                     if r.topic == "/mcsm/snapshot")
        assert first["seq"] in (20, 30) and "window" not in first  # (restored: no window yet)
        dr.rec, dr.st = sink, rep.states["default"]
        for _ in range(12):  # the restored server goes on (a disk snapshot at 30 and 40)
            dr.update(k)
            k += 1
        sink.close()
    last = replay(tmp_path / "three.mcap", from_snapshot=True, id_ttl_s=3600)
    st = last.states["default"]
    assert last.n_inputs < 10 and st.digest() == dr.st.digest()
    t_last = dr.t
    for op, rid, payload in dr.sent:
        fp = ops.fingerprint(op, decode_input(op, payload, N))
        hit = st.lookup(rid, fp, now_ns=t_last)
        assert hit is not None and hit.duplicate and hit.seq == int(rid[1:]) + 1, rid
    # TTL from the recorded receive times: u0 was received 48 ms before the last one, u1 47
    short = replay(tmp_path / "three.mcap", from_snapshot=True, id_ttl_s=0.0475)
    st = short.states["default"]
    assert st.lookup("u0", now_ns=t_last) is None
    assert st.lookup("u1", now_ns=t_last) is not None
    # --id-memory: beyond the count the oldest go first, restored ids and replayed alike
    small = replay(tmp_path / "three.mcap", from_snapshot=True, id_ttl_s=3600, lru_size=5)
    st = small.states["default"]
    kept = [rid for _, rid, _ in dr.sent if st.lookup(rid, now_ns=t_last) is not None]
    assert kept == [rid for _, rid, _ in dr.sent[-5:]]


def test_chunk_indexes_spill_to_disk_and_still_index_every_chunk(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ChunkPerInputWriter, "SPILL_BYTES", 300)  # spill every few inputs
    path = tmp_path / "r.mcap"
    rec = Recorder(path)
    dr = Driver(rec, _state(), seed=7104)
    rec.config(dr.st, 5)
    for k in range(30):
        dr.update(k)
    spill = rec._w._ci_spill  # noqa: SLF001 - the spill file exists while recording
    assert spill is not None and spill.tell() > 300
    dr.close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count \
            == summary.statistics.message_count
        n = sum(1 for _ in reader.iter_messages())
    assert n == summary.statistics.message_count
    r = RecordingReader(path)
    assert sum(1 for _ in r) == n and r.complete and r.summary_crc


def test_a_full_disk_leaves_a_cut_file_with_every_complete_input(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mcsm.log import chunkwriter

    path = tmp_path / "r.mcap"
    rec = Recorder(path)
    dr = Driver(rec, _state(), seed=7105)
    rec.config(dr.st, 5)
    for k in range(10):
        dr.update(k)
    real = chunkwriter._write_all  # noqa: SLF001

    def full(fd: int, parts: list[bytes], total: int) -> None:  # half a record, then ENOSPC
        import os

        os.write(fd, b"".join(parts)[: total // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(chunkwriter, "_write_all", full)
    with pytest.raises(OSError, match="No space"):
        dr.update(10)
    with pytest.raises(OSError):  # closing tries nothing more: the file stays cut
        rec.close()
    monkeypatch.setattr(chunkwriter, "_write_all", real)
    r = RecordingReader(path)
    seqs = [item.data["seq"] for item in r if item.topic == "/mcsm/in/update"]
    assert seqs == list(range(1, 11)) and r.cut and r.damage is None
    copy = tmp_path / "copy.mcap"
    shutil.copy(path, copy)
    assert replay(copy).n_inputs == 10


def test_the_retract_window_stays_within_its_bytes_and_says_what_fell_out(
        tmp_path: Path) -> None:
    budget = 64 * 1024  # the 46-frame map at the end: ~41 kB; a request: 896 bytes
    path = tmp_path / "w.mcap"
    rec = Recorder(path)
    st = MapState("default", StochasticMap(N), snapshot_every=100, snapshots_kept=4,
                  retract_window_bytes=budget)
    dr = Driver(rec, st, seed=7106)
    rec.config(st, 5)
    for k in range(60):
        dr.update(k)
        h = st.history
        assert h.held_bytes <= budget, (k, h.held_bytes)
        assert sum(nbytes(s[1]) for s in h.snapshots) == sum(s[3] for s in h.snapshots)
    # taken by bytes (every ~18 inputs, budget / kept), not every 100 operations
    assert all(0 < s[0] < 60 for s in st.history.snapshots)
    start = st.history.window_start
    assert 40 < start < 60
    with pytest.raises(InvalidOperation, match=r"request 'u2' \(seq 3\) fell out of the "
                       r"retract window, which now holds the inputs after seq"):
        dr.send("retract", wire.encode_retract("r-old", "u2"))
    dr.sent.pop()  # (refused: not applied)
    dr.send("retract", wire.encode_retract("r-new", "u59"))  # inside the window: applied
    dr.close()
    rep = replay(path)  # the same window on replay: the same retraction applies
    assert rep.identical and rep.states["default"].digest() == st.digest()
    # the window comes from the recorded option, not the replaying machine's default
    again = rep.states["default"]
    assert again.history.max_bytes == budget
    assert again.history.window_start == st.history.window_start
    with pytest.raises(InvalidOperation, match=r"request 'u2' \(seq 3\) fell out"):
        again.apply("retract", decode_input("retract", wire.encode_retract("r-x", "u2"), N))
    # a map larger than the whole budget has no window, and says so
    small = MapState("default", StochasticMap(N), retract_window_bytes=budget // 8)
    small.map = st.map
    small.history.start(st.map, st.seq)
    assert small.history.snapshots == [] and small.history.window_start == st.seq
    with pytest.raises(InvalidOperation, match="the map alone is larger than the byte budget"):
        small.history.target("u59", True)


def test_reads_go_first_and_the_queue_is_bounded_in_bytes() -> None:
    q = Lanes(max_items=10, max_bytes=10_000)
    q.put("w1", 6000)
    with pytest.raises(Full) as full:
        q.put("w2", 6000)
    assert full.value.what == "request queue bytes" and full.value.limit == 10_000
    q.put("r1", 10, read=True)  # the read lane has its own bound
    q.put("w3", 1000)
    assert [q.get(0.1) for _ in range(3)] == ["r1", "w1", "w3"]
    assert q.get(0.01) is None and q.nbytes() == 0
    for k in range(10):
        q.put(k, read=True)
    with pytest.raises(Full, match="request queue length"):
        q.put("one more", read=True)


def test_the_id_memory_keeps_order_acks_and_verdicts_compactly() -> None:
    from mcsm.map.idmemory import IdMemory

    m = IdMemory(10)
    v = wire.Verdict("accepted", 1.5, 6, 12.59, "", 7)
    for k in range(5):
        m.put(f"i{k}", wire.Ack(f"i{k}", k + 1, "update", "new_frame", "r",
                                frames_added=(f"f{k}",), verdict=v), f"{k:032x}", 100 + k)
    m.put("i1", wire.Ack("i1", 9, "remove", "remove", None, frames_removed=("f1",)), "", 200)
    m.pop("i3")
    m.update("i0", wire.Ack("i0", 1, "update", "new_frame", "r", verdict=None))
    assert [rid for rid, _ in m.items()] == ["i0", "i2", "i4", "i1"] and len(m) == 4
    ack, fp, t = m.get("i2")  # type: ignore[misc]
    assert ack == wire.Ack("i2", 3, "update", "new_frame", "r", frames_added=("f2",), verdict=v)
    assert (fp, t) == (f"{2:032x}", 102)
    assert m.get("i1") == (wire.Ack("i1", 9, "remove", "remove", None,
                                    frames_removed=("f1",)), "", 200)
    assert m.oldest_time() == 100
    m.pop_oldest()
    m.pop_oldest()
    assert m.oldest_time() == 104 and "i0" not in m and m.get("i3") is None
    m.pop_oldest()
    m.pop_oldest()
    assert len(m) == 0 and m.oldest_time() is None and list(m.items()) == []
    # at capacity the oldest goes; a long row (a submap import's frames) lives aside
    many = tuple(f"frame{k}" for k in range(40))
    for k in range(25):
        m.put(f"j{k}", wire.Ack(f"j{k}", k, "import", "import", "r", frames_added=many),
              "", k)
    assert len(m) == 10 and [r for r, _ in m.items()] == [f"j{k}" for k in range(15, 25)]
    assert m.get("j20")[0].frames_added == many  # type: ignore[index]
    m.put("k", wire.Ack("k", 99, "update", "new_frame", "r"), f"{7:032x}", 99)
    rows = m.columns().rows()
    assert rows[0] == ["j16", 16, "import", "", 16] and rows[-1] == ["k", 99, "update",
                                                                      f"{7:032x}", 99]
    assert [r[0] for r in rows] == [f"j{k}" for k in range(16, 25)] + ["k"]


def test_restore_starts_early_enough_for_a_retraction_after_the_latest_snapshot(
        tmp_path: Path) -> None:
    """A retract recorded after the latest disk snapshot of an update from before it: the
    restore starts from an earlier snapshot (from the latest, the target is out of reach and
    the restore used to fail with 'replay diverged')."""
    path = tmp_path / "r.mcap"
    rec = Recorder(path)
    dr = Driver(rec, _state(), seed=7107, disk_every=10)
    rec.config(dr.st, 5)
    for k in range(22):  # disk snapshots at seq 10 and 20
        dr.update(k)
    dr.send("retract", wire.encode_retract("r-late", "u15"))  # u15 is seq 16: before 20
    rec.close()
    fast = replay(path, from_snapshot=True)
    assert fast.identical, fast.divergence
    assert fast.snapshots_loaded == 1 and fast.n_skipped == 10 and fast.n_inputs == 13
    assert fast.states["default"].digest() == dr.st.digest()
    hit = fast.states["default"].lookup("u3")
    assert hit is not None and hit.duplicate


def test_a_split_below_the_snapshot_size_gives_files_of_about_twice_it(tmp_path: Path) -> None:
    """docs/recordings.md, "Where it splits": a file is not split before its inputs take as
    many bytes as the snapshot it starts with, so snapshots are at most half of every file;
    a split size below the snapshot's gives files of two to three times the snapshot."""
    rec = Recorder(tmp_path / "run.mcap", split_bytes=1_000)  # far below a snapshot
    dr = Driver(rec, _state(), seed=7105, disk_every=0)  # only the splits' snapshots
    rec.config(dr.st, 5)
    for k in range(60):
        dr.update(k)
    dr.close()
    assert len(rec.paths) >= 3
    for p in rec.paths[1:-1]:
        with open(p, "rb") as f:
            sizes: dict[str, list[int]] = {}
            for _, ch, msg in make_reader(f).iter_messages():
                sizes.setdefault(ch.topic, []).append(len(msg.data))
        snap = sum(n for t, ns in sizes.items() if t.startswith("/mcsm/snapshot") for n in ns)
        inputs = [n for t, ns in sizes.items() if t in TOPIC_OPS for n in ns]
        size = p.stat().st_size
        assert inputs and snap > 1_000 and snap <= size / 2, (p.name, snap, size)
        # twice the bytes the file starts with, plus its summary (an index entry per input)
        assert 2 * snap < size < 3 * snap, (p.name, snap, size)


def test_split_duration_starts_a_new_file_after_that_long(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--split-duration S``: the first input after S seconds of a file (and once its inputs
    outweigh its snapshot) starts the next file; the set replays as one."""
    clock = [1000.0]
    monkeypatch.setattr("mcsm.log.writer.time.monotonic", lambda: clock[0])
    rec = Recorder(tmp_path / "run.mcap", split_s=60.0)
    dr = Driver(rec, _state(), seed=7106, disk_every=0)
    rec.config(dr.st, 5)
    for k in range(20):  # (their bytes outweigh the schemas and config the file starts with)
        dr.update(k)
    assert rec.index == 0  # no time has passed: one file, however many inputs
    clock[0] += 61.0
    dr.update(20)
    assert rec.index == 1  # the input after 60 s closed the file
    clock[0] += 30.0  # 91 s after the first file opened, 30 s after the second
    for k in range(21, 60):
        dr.update(k)
    assert rec.index == 1  # the new file's clock started at the split
    dr.close()
    assert [p.name for p in rec.paths] == ["run_0000.mcap", "run_0001.mcap"]
    assert replay(rec.paths).identical


def test_a_recording_whose_snapshots_carry_no_ids_still_restores_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """docs/recordings.md: recordings made before snapshots carried the ids restore as before,
    the ids of the inputs before the snapshot in the same file remembered."""
    monkeypatch.setattr("mcsm.log.writer.encode_ids", lambda _cols: None)  # as older writers
    rec = Recorder(tmp_path / "old.mcap")
    dr = Driver(rec, _state(), seed=7107, disk_every=10)
    rec.config(dr.st, 5)
    for k in range(25):
        dr.update(k)
    rec.close()
    monkeypatch.undo()
    snaps = [r.data for r in RecordingReader(tmp_path / "old.mcap")
             if r.topic == "/mcsm/snapshot"]
    assert snaps and all(d.get("ids") is None for d in snaps)
    rep = replay(tmp_path / "old.mcap", from_snapshot=True, id_ttl_s=3600)
    assert rep.identical and rep.snapshots_loaded == 1
    st = rep.states["default"]
    for op, rid, payload in dr.sent:
        hit = st.lookup(rid, ops.fingerprint(op, decode_input(op, payload, N)), now_ns=dr.t)
        assert hit is not None and hit.duplicate, rid
