"""Chunked snapshots (mcsm.log.snapchunks): a snapshot larger than the part size is a header and
bounded parts, read back by replay, --restore, recover, inspect and cat; a snapshot that cannot
be read back never makes a reader skip the records after it.

The part size is lowered through ``MCSM_SNAPSHOT_CHUNK_BYTES`` so that a 60-frame map
(N = 16: 54 kB of edges) spans a dozen parts. In-process, as the server's worker drives
``Recorder`` and ``MapState`` (the Driver of test_split).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator
from mcap.records import Message
from mcsm.cli import EXIT_OK, EXIT_USAGE
from mcsm.cli import main as mcsm_main
from mcsm.log import reader, snapchunks
from mcsm.log.reader import RecordingReader
from mcsm.log.recover import recover
from mcsm.log.replay import replay
from mcsm.log.topics import TOPIC_SNAPSHOT, TOPIC_SNAPSHOT_PART, RecordingError, schema_bytes
from mcsm.log.writer import Recorder
from mcsm.map.carry import decode_snapshot

from tests.recording import test_split
from tests.recording.test_split import Driver, _state
from tests.service.daemon_util import free_port

CHUNK = 4096


def _record(path: Path, n_updates: int = 100, disk_every: int = 40
            ) -> tuple[Driver, dict[int, str]]:
    """A 60-odd-frame map, a snapshot every ``disk_every`` inputs, and inputs after the last
    one; returns the driver and the live digest after each seq that was snapshotted."""
    rec = Recorder(path)
    dr = Driver(rec, _state(), seed=8801, disk_every=disk_every)
    rec.config(dr.st, 5)
    digests: dict[int, str] = {}
    for k in range(n_updates):
        dr.update(k)
        if dr.st.seq % disk_every == 0:
            digests[dr.st.seq] = dr.st.digest()
    dr.close()
    return dr, digests


def _parts(path: Path) -> list[tuple[int, int]]:
    """(byte offset, part number) of every snapshot part record, in file order."""
    rd = RecordingReader(path)
    out = []
    for r in rd.raw():
        if isinstance(r, Message) and rd.channels[r.channel_id].topic == TOPIC_SNAPSHOT_PART:
            out.append((rd.record_offset, len(out)))
    return out


@pytest.fixture
def small_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(snapchunks.CHUNK_BYTES_ENV, str(CHUNK))


def test_a_chunked_snapshot_replays_and_restores_bit_identical(
        tmp_path: Path, small_chunks: None) -> None:
    path = tmp_path / "run.mcap"
    dr, digests = _record(path)
    final = dr.st.digest()
    assert dr.st.seq > max(digests)  # inputs follow the last snapshot
    rd = RecordingReader(path)
    heads = [r for r in rd.raw() if isinstance(r, Message)
             and rd.channels[r.channel_id].topic == TOPIC_SNAPSHOT]
    parts = _parts(path)
    assert len(heads) == len(digests) == 2
    assert len(parts) >= 2 * 10  # each snapshot spans more than ten parts
    assert all(len(r.data) < CHUNK + 200 for r in heads)
    snaps = [i.data for i in RecordingReader(path) if i.topic == TOPIC_SNAPSHOT]
    assert [s["seq"] for s in snaps] == sorted(digests)
    assert all(s["format"] == 2 and s["chunked"]["chunk_bytes"] == CHUNK for s in snaps)
    assert all(s["chunked"]["parts"] > 10 for s in snaps)
    # replay from the start verifies both snapshots; --restore starts from the last one
    whole = replay(path)
    assert whole.identical and whole.complete and whole.checkpoints_ok > 2
    assert whole.states["default"].digest() == final and whole.n_inputs == dr.st.seq
    sink = Recorder(tmp_path / "restored.mcap")
    fast = replay(path, from_snapshot=True, sink=sink)
    sink.close()
    assert fast.identical and fast.snapshots_loaded == 1
    assert fast.n_skipped == max(digests) and fast.n_inputs == dr.st.seq - max(digests)
    assert fast.states["default"].digest() == final
    again = replay(tmp_path / "restored.mcap")  # the restored server's file (chunked too)
    assert again.identical and again.snapshots_loaded == 1
    assert again.states["default"].digest() == final
    assert _parts(tmp_path / "restored.mcap")
    # the header and the parts as written match their schemas
    validators = {t: Draft202012Validator(json.loads(schema_bytes(f))) for t, f in
                  ((TOPIC_SNAPSHOT, "record_snapshot.json"),
                   (TOPIC_SNAPSHOT_PART, "record_snapshot_part.json"))}
    checked = 0
    for r in rd.raw():
        if isinstance(r, Message) and rd.channels[r.channel_id].topic in validators:
            d = snapchunks.unpack_body(r.data)
            v = validators[rd.channels[r.channel_id].topic]
            assert list(v.iter_errors(d)) == [], d.get("part")
            checked += 1
    assert checked == len(heads) + len(parts)
    head = snapchunks.unpack_body(heads[0].data)
    assert "state" not in head and "verdicts" not in head
    for bad in ({**head, "format": 1}, {k: v for k, v in head.items() if k != "chunked"}):
        assert list(validators[TOPIC_SNAPSHOT].iter_errors(bad)) != []  # the schema tells
    assert mcsm_main(["inspect", str(path)]) == EXIT_OK
    assert mcsm_main(["cat", str(path)]) == EXIT_OK
    assert mcsm_main(["replay", str(path)]) == EXIT_OK


def test_the_chunked_and_the_single_record_snapshot_hold_the_same_state(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    got = {}
    for name, chunk in (("one", 1 << 26), ("many", CHUNK)):
        monkeypatch.setenv(snapchunks.CHUNK_BYTES_ENV, str(chunk))
        _record(tmp_path / f"{name}.mcap", n_updates=40)
        got[name] = next(i.data for i in RecordingReader(tmp_path / f"{name}.mcap")
                         if i.topic == TOPIC_SNAPSHOT)
    one, many = got["one"], got["many"]
    assert one["format"] == 1 and "chunked" not in one and not _parts(tmp_path / "one.mcap")
    assert many["format"] == 2
    a, b = decode_snapshot(one["state"], 16), decode_snapshot(many["state"], 16)
    assert len(a["components"]) == len(b["components"]) == 1
    for ca, cb in zip(a["components"], b["components"], strict=True):
        assert ca["frames"] == cb["frames"] and ca["edges"].shape == cb["edges"].shape
        assert ca["edges"].tobytes() == cb["edges"].tobytes()
    strip = ("format", "chunked", "state", "time_ns")
    assert ({k: v for k, v in one.items() if k not in strip}
            == {k: v for k, v in many.items() if k not in strip})
    # edges=False checks the stream and keeps only the shapes
    light = next(i.data for i in RecordingReader(tmp_path / "many.mcap", edges=False)
                 if i.topic == TOPIC_SNAPSHOT)
    assert light["state"]["components"][0]["edges"] == {
        "dtype": "<f8", "shape": list(a["components"][0]["edges"].shape)}


def test_a_split_recording_with_chunked_snapshots(tmp_path: Path, small_chunks: None) -> None:
    test_split.test_a_split_recording_replays_as_a_set_and_file_by_file(tmp_path)
    assert _parts(tmp_path / "run_0001.mcap")


def test_a_file_cut_inside_a_chunked_snapshot_replays_up_to_it(
        tmp_path: Path, small_chunks: None) -> None:
    path = tmp_path / "run.mcap"
    _, digests = _record(path, n_updates=60)  # one snapshot, at seq 40, then 20 inputs
    (seq,) = digests
    parts = _parts(path)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: parts[len(parts) // 2][0] + 5])
    rep = replay(cut)
    assert rep.identical and rep.cut and not rep.complete
    assert rep.states["default"].seq == seq and rep.states["default"].digest() == digests[seq]
    assert "has " in str(rep.tail_error) and "parts" in str(rep.tail_error)
    rd = RecordingReader(cut)
    list(rd)
    assert rd.pending_snapshot is not None and f"seq {seq}" in rd.pending_snapshot
    fast = replay(cut, from_snapshot=True)  # no complete snapshot: restore replays it all
    assert fast.snapshots_loaded == 0 and fast.states["default"].digest() == digests[seq]
    rec = recover(cut, tmp_path / "recovered.mcap")
    assert rec.source_cut
    again = replay(tmp_path / "recovered.mcap")
    assert again.identical and again.complete and again.states["default"].seq == seq


def test_a_damaged_part_never_drops_the_inputs_after_it_silently(
        tmp_path: Path, small_chunks: None) -> None:
    path = tmp_path / "run.mcap"
    dr, digests = _record(path, n_updates=60)
    (seq,) = digests
    parts = _parts(path)
    raw = bytearray(path.read_bytes())
    raw[parts[3][0] + 200] ^= 0xFF  # inside part 3's chunk: its CRC no longer matches
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(raw))
    rep = replay(bad)  # stops at the damage, as any damage, and says so
    assert rep.damage is not None and rep.states["default"].seq == seq
    # recover copies the intact chunks after the damage: a snapshot with a gap, then inputs
    rec = recover(bad, tmp_path / "recovered.mcap")
    assert rec.chunks_after_damage > 0 and rec.n_inputs == dr.st.seq  # only a part lost
    for restore in (False, True):
        with pytest.raises(RecordingError) as err:
            replay(tmp_path / "recovered.mcap", from_snapshot=restore)
        msg = str(err.value)
        assert "recovered.mcap" in msg and f"seq {seq}" in msg and "byte" in msg, msg
        assert "cannot be read back" in msg or "part 4" in msg, msg
    assert mcsm_main(["replay", str(tmp_path / "recovered.mcap")]) == EXIT_USAGE
    assert mcsm_main(["inspect", str(tmp_path / "recovered.mcap")]) == EXIT_USAGE
    assert mcsm_main(["cat", str(tmp_path / "recovered.mcap")]) == EXIT_USAGE
    # a server does not start from it (it would serve the state before the snapshot)
    new = tmp_path / "new.mcap"
    assert mcsm_main(["serve", "--listen", f"tcp/127.0.0.1:{free_port()}", "--restore",
                      str(tmp_path / "recovered.mcap"), "--record", str(new)]) == EXIT_USAGE
    assert not new.exists()


def test_a_record_too_large_to_read_back_fails_loudly(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A single-record snapshot larger than the reader's limit (the 1 GiB of before, scaled
    down): replay used to stop there and report the rest as damage; --restore served the state
    before it. Now both raise, naming the file and the byte."""
    monkeypatch.setenv(snapchunks.CHUNK_BYTES_ENV, str(1 << 26))  # one record per snapshot
    path = tmp_path / "run.mcap"
    _, digests = _record(path, n_updates=60)
    big = max(len(r.data) for r in RecordingReader(path).raw() if isinstance(r, Message))
    monkeypatch.setattr(reader, "MAX_RECORD_BYTES", big - 1)
    for restore in (False, True):
        with pytest.raises(RecordingError) as err:
            replay(path, from_snapshot=restore)
        msg = str(err.value)
        assert str(path) in msg and "byte" in msg and "not read" in msg, msg


def test_a_header_announcing_more_than_the_file_is_refused() -> None:
    asm = snapchunks.Assembler("x.mcap", 10_000)
    with pytest.raises(snapchunks.SnapshotError, match="in a file of 10000 bytes"):
        asm.start({"map": "m", "seq": 1, "chunked": {"parts": 1, "bytes": 1 << 40,
                                                     "body_bytes": 10, "crc32": 0}}, 7)
    with pytest.raises(snapchunks.SnapshotError, match="without its header"):
        asm.part({"map": "m", "seq": 1, "part": 0, "data": b"x"}, 9)


def test_a_map_over_the_window_budget_is_not_copied_for_the_window(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The retract window's snapshot of a map whose edges alone exceed the budget would be
    dropped at once; it is no longer taken (no whole-map copy every --snapshot-every
    operations), and the window is the same as when it was taken and dropped."""
    from mcsm.core.smap import StochasticMap
    from mcsm.map.history import History
    from mcsm.map.state import MapState

    def run(name: str) -> tuple[list[tuple[int, int]], str, list[int]]:
        calls: list[int] = []  # frames of the map at each snapshot
        real = StochasticMap.snapshot

        def counting(self: StochasticMap) -> dict[str, object]:
            calls.append(self.n_frames)
            return real(self)

        with monkeypatch.context() as m:
            m.setattr(StochasticMap, "snapshot", counting)
            st = MapState("default", StochasticMap(16), snapshot_every=5, snapshots_kept=3,
                          retract_window_bytes=8 * 1024)  # 9 frames of N = 16
            rec = Recorder(tmp_path / f"{name}.mcap")
            dr = Driver(rec, st, seed=8802, disk_every=0)
            rec.config(st, 5)
            seen = []
            for k in range(40):
                dr.update(k)
                seen.append((st.history.window_start, len(st.history.snapshots)))
            dr.close()
        return seen, st.digest(), calls

    now, digest, calls = run("now")
    with monkeypatch.context() as m:
        m.setattr(History, "too_big", lambda self, smap: False)
        before, digest_before, calls_before = run("before")
    assert now == before and digest == digest_before
    assert len(calls) < len(calls_before)
    assert max(calls) * 56 * 16 <= 8 * 1024 < max(calls_before) * 56 * 16
    assert now[-1] == (40, 0)  # no window: the map alone is over the budget
    assert replay(tmp_path / "now.mcap").states["default"].digest() == digest
