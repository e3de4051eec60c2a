"""Recording and replay: MCAP layout, checkpoints, divergence, truncation, shipped recordings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcsm import StochasticMap, wire
from mcsm.cli import main as mcsm_main
from mcsm.core.quat import qexp
from mcsm.log.reader import RecordingReader
from mcsm.log.replay import replay
from mcsm.log.topics import (
    INPUT_TOPICS,
    TOPIC_CHECKPOINT,
    TOPIC_CONFIG,
    TOPIC_SNAPSHOT,
    TOPIC_SNAPSHOT_PART,
    RecordingError,
    decode_input,
    schema_bytes,
)
from mcsm.log.writer import Recorder
from mcsm.map.state import MapState
from mcsm_client.process import loopback_endpoint

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"
# shipped recordings have a .digest beside them; run-*.mcap from local `mcsm serve` runs do not
SHIPPED = sorted(p for p in RECORDINGS.glob("*.mcap") if p.with_suffix(".digest").exists())


def at(rng: np.random.Generator, n: int, t: list[float]) -> np.ndarray:
    x = np.empty((n, 7))
    x[:, :3] = np.asarray(t) + 0.05 * rng.standard_normal((n, 3))
    x[:, 3:] = qexp(0.01 * rng.standard_normal((n, 3)))
    return x


def record_session(path: Path, n: int, count: int, seed: int, checkpoint_every: int = 5,
                   close: bool = True, **options: object) -> tuple[MapState, list[bytes]]:
    """Drive Recorder + MapState exactly as the server's worker does, without Zenoh."""
    rng = np.random.default_rng(seed)
    rec = Recorder(path)
    st = MapState("default", StochasticMap(n, **options))  # type: ignore[arg-type]
    rec.config(st, checkpoint_every)
    payloads = []
    for i in range(count):
        if i % 4 == 3:
            payload = wire.encode_update(f"id{i}", "p0", f"p{i}", at(rng, n, [float(i), 0, 0]))
        else:
            payload = wire.encode_update(f"id{i}", f"p{i}", f"p{i + 1}", at(rng, n, [1, 0, 0]))
        ack = st.apply("update", decode_input("update", payload, n))
        rec.input("update", st.name, ack.seq, 1_000 + i, "test", f"id{i}", payload)
        if ack.seq % checkpoint_every == 0:
            rec.checkpoint(st.name, ack.seq, st.map.state_digest(), "periodic")
        payloads.append(payload)
    if close:
        rec.checkpoint(st.name, st.seq, st.map.state_digest(), "close")
        rec.close()
    return st, payloads


def test_layout_schemas_and_readers_agree(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    st, payloads = record_session(path, 16, 12, seed=5501)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {TOPIC_CONFIG, TOPIC_CHECKPOINT, TOPIC_SNAPSHOT,
                               TOPIC_SNAPSHOT_PART, *INPUT_TOPICS.values()}
        for c in topics.values():
            assert c.message_encoding == "msgpack"
            sch = summary.schemas[c.schema_id]
            assert sch.encoding == "jsonschema"
            assert json.loads(sch.data)["title"] == sch.name
        seeking = [(ch.topic, m.data)
                   for _, ch, m in reader.iter_messages(log_time_order=False)]
    assert schema_bytes("record_input.json") == summary.schemas[
        topics["/mcsm/in/update"].schema_id].data
    streamed = [(r.topic, wire.pack(r.data)) for r in RecordingReader(path)]
    # the seekable reader and our streaming reader see the same records in the same order
    assert [t for t, _ in seeking] == [t for t, _ in streamed]
    assert [wire.unpack(d) for _, d in seeking] == [wire.unpack(d) for _, d in streamed]
    inputs = [wire.unpack(d) for t, d in seeking if t == "/mcsm/in/update"]
    assert [i["request"] for i in inputs] == payloads  # exact bytes as received
    assert [i["seq"] for i in inputs] == list(range(1, 13))
    rep = replay(path)
    assert rep.identical and rep.complete and rep.n_inputs == 12
    assert rep.checkpoints_ok == 3  # seq 5, 10 and the close checkpoint at 12
    assert rep.states["default"].map.state_digest() == st.map.state_digest()


def test_replay_restores_the_request_id_memory(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    st, _ = record_session(path, 8, 6, seed=5502)
    rep = replay(path)
    dup = rep.states["default"].lookup("id3")
    assert dup is not None and dup.duplicate and dup == st.lookup("id3")


def test_recorder_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(RecordingError, match="overwrite"):
        Recorder(path)
    assert path.read_bytes() == b"precious"


def _rewrite(src: Path, dst: Path, edit: str) -> None:
    """Copy a recording record by record, tampering with one thing."""
    rec = Recorder(dst)
    st = None
    for item in RecordingReader(src):
        d = dict(item.data)
        if item.topic == TOPIC_CONFIG:
            st = MapState(d["map"], StochasticMap.from_options(d["options"]))
            rec.config(st, d["checkpoint_every"])
        elif item.topic == TOPIC_CHECKPOINT:
            digest = d["digest"]
            if edit == "digest" and d["seq"] == 10:
                digest = "0" * 64
            rec.checkpoint(d["map"], d["seq"], digest, d["reason"])
        else:
            if edit == "gap" and d["seq"] == 4:
                continue
            rec.input("update", d["map"], d["seq"], d["recv_ns"], d["sender"], d["id"],
                      d["request"])
    rec.close()


@pytest.mark.parametrize("edit,expect", [("digest", "digest differs at seq 10"),
                                         ("gap", "input seq 5 follows seq 3")])
def test_divergence_is_reported_first_and_exits_1(
        tmp_path: Path, edit: str, expect: str, capsys: pytest.CaptureFixture[str]) -> None:
    src, bad = tmp_path / "good.mcap", tmp_path / "bad.mcap"
    record_session(src, 8, 12, seed=5503)
    _rewrite(src, bad, edit)
    rep = replay(bad)
    assert not rep.identical and expect in str(rep.divergence)
    assert mcsm_main(["replay", str(bad), "--no-progress"]) == 1
    assert "DIVERGED" in capsys.readouterr().out
    assert mcsm_main(["replay", str(src), "--no-progress"]) == 0


def test_serve_refuses_to_restore_a_diverging_recording(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    src, bad = tmp_path / "good.mcap", tmp_path / "bad.mcap"
    record_session(src, 8, 12, seed=5506)
    _rewrite(src, bad, "digest")
    ep = loopback_endpoint()
    code = mcsm_main(["serve", "--listen", ep, "--restore", str(bad), "--record",
                      str(tmp_path / "new.mcap"), "--log-level", "ERROR"])
    assert code == 2
    assert "replay diverged" in capsys.readouterr().err
    assert not (tmp_path / "new.mcap").exists()  # no half-restored recording left behind


def test_truncated_at_every_cut_recovers_complete_records(tmp_path: Path) -> None:
    """Cut an unclosed recording at many byte offsets: never a traceback, and replay holds
    exactly the inputs whose records are complete before the cut (as mcap's own non-seeking
    reader, in file order, also finds)."""
    path = tmp_path / "open.mcap"
    st, payloads = record_session(path, 8, 10, seed=5504, close=False)  # like a SIGKILL
    data = path.read_bytes()
    full = StochasticMap(8)
    digests = [full.state_digest()]
    for p in payloads:
        req = decode_input("update", p, 8)
        full.update(req.a, req.b, req.samples)
        digests.append(full.state_digest())
    cut_path = tmp_path / "cut.mcap"
    for cut in range(len(data) // 3, len(data) + 1, max(1, len(data) // 40)):
        cut_path.write_bytes(data[:cut])
        rep = replay(cut_path)
        assert rep.identical and not rep.complete
        assert rep.tail_error is not None
        with open(cut_path, "rb") as f:
            n_theirs = 0
            try:
                for _, ch, _ in NonSeekingReader(f).iter_messages(log_time_order=False):
                    n_theirs += ch.topic.startswith("/mcsm/in/")
            except Exception:  # noqa: BLE001 - mcap's reader ends a cut file with an error
                pass
        assert rep.n_inputs == n_theirs
        if "default" not in rep.states:  # cut inside the config record
            assert rep.n_inputs == 0
            continue
        assert rep.states["default"].map.state_digest() == digests[rep.n_inputs]


def test_unreadable_files_give_a_clear_error(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        replay(junk)
    assert mcsm_main(["replay", str(junk), "--no-progress"]) == 2
    assert mcsm_main(["inspect", str(junk)]) == 2
    err = capsys.readouterr().err
    assert "cannot read" in err and "Traceback" not in err
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert mcsm_main(["replay", str(empty), "--no-progress"]) == 2


def test_inspect_summarises(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "r.mcap"
    record_session(path, 8, 7, seed=5505, checkpoint_every=3)
    assert mcsm_main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "complete" in out and "operations: 7 (update 7); last seq 7" in out
    assert "checkpoints: 3" in out
    assert mcsm_main(["inspect", str(path), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["complete"] and js["maps"]["default"]["ops"] == {"update": 7}


def test_machine_bound_maps_are_named(tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    """method=paper in the quaternion space runs on numpy: inspect and replay say so."""
    path = tmp_path / "paper.mcap"
    record_session(path, 8, 9, seed=5506, method="paper", space="quaternion")
    assert mcsm_main(["inspect", str(path)]) == 0
    assert "machine family that recorded it" in capsys.readouterr().out
    assert mcsm_main(["replay", str(path), "--no-progress"]) == 0
    assert "machine family that recorded it" in capsys.readouterr().out
    portable = tmp_path / "joint.mcap"
    record_session(portable, 8, 9, seed=5506, method="paper")  # tangent chart: the kernel
    assert mcsm_main(["replay", str(portable), "--no-progress"]) == 0
    assert "machine family" not in capsys.readouterr().out


def _digest_file(mcap: Path) -> dict[str, tuple[int, str]]:
    out = {}
    for line in mcap.with_suffix(".digest").read_text().splitlines():
        name, seq, digest = line.split()
        out[name] = (int(seq), digest)
    return out


def test_shipped_recordings_exist() -> None:
    assert {p.stem for p in SHIPPED} >= {"loop-small", "two-maps", "killed"}


@pytest.mark.parametrize("mcap", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_recording_replays_to_its_digest(mcap: Path) -> None:
    rep = replay(mcap)
    hint = ("if the core's arithmetic changed on purpose, regenerate the recordings: "
            ".venv/bin/python tests/recording/make_recordings.py")
    assert rep.identical, f"{rep.divergence}; {hint}"
    assert not rep.other_arithmetic, f"recorded by another arithmetic version; {hint}"
    got = {name: (s.seq, s.map.state_digest()) for name, s in rep.states.items()}
    assert got == _digest_file(mcap), hint
    assert rep.complete == (mcap.stem != "killed")


@pytest.mark.parametrize("mcap", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_truncated_copy_of_shipped_recording(mcap: Path, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    cut = tmp_path / mcap.name
    data = mcap.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rep = replay(cut)
    assert rep.identical and not rep.complete
    full = _digest_file(mcap)
    assert sum(s.seq for s in rep.states.values()) < sum(v[0] for v in full.values())
    # the recovered prefix is exactly the state the full file has after as many inputs
    prefix = replay(mcap, stop_after=rep.n_inputs)
    assert rep.final_digests() == prefix.final_digests()
    assert mcsm_main(["replay", str(cut), "--no-progress"]) == 4  # cut: its own exit code
    out = capsys.readouterr().out
    assert "CUT" in out and "identical" not in out


def test_recording_without_the_gate_key_replays_without_a_gate(tmp_path: Path) -> None:
    """Recorded options without ``gate`` (every recording made before the gate's default
    became 0.99, and every ``--gate none`` one) mean no gate on replay, bit for bit: a closure
    50 m off, which the default gate refuses, is applied on replay as it was when recorded."""
    n = 40
    rng = np.random.default_rng(12)
    inputs = [wire.encode_update(f"id{i}", f"p{i}", f"p{i + 1}", at(rng, n, [1, 0, 0]))
              for i in range(6)]
    inputs.append(wire.encode_update("far", "p0", "p6", at(rng, n, [56.0, 0, 0])))
    digests = {}
    for label, opts in (("off", {"gate": None}), ("default", {})):
        path = tmp_path / f"{label}.mcap"
        rec = Recorder(path)
        st = MapState("default", StochasticMap(n, **opts))  # type: ignore[arg-type]
        rec.config(st, 100)
        for k, payload in enumerate(inputs):
            ack = st.apply("update", decode_input("update", payload, n))
            rec.input("update", st.name, ack.seq, 1_000 + k, "test", f"id{k}", payload)
        assert ack.kind == ("loop_closure" if label == "off" else "rejected")
        rec.checkpoint(st.name, st.seq, st.digest(), "close")
        rec.close()
        configs = [i.data for i in RecordingReader(path) if i.topic == TOPIC_CONFIG]
        assert ("gate" in configs[0]["options"]) == (label == "default")
        rep = replay(path)
        assert rep.identical and rep.checkpoints_ok == 1
        assert rep.states["default"].map.gate == (None if label == "off" else 0.99)
        digests[label] = rep.states["default"].digest()
    local = StochasticMap(n, gate=None)
    for payload in inputs:
        r = decode_input("update", payload, n)
        local.update(r.a, r.b, r.samples)
    assert digests["off"] == local.state_digest() != digests["default"]


def test_inspect_says_which_checkpoints_it_lists(capsys: pytest.CaptureFixture[str]) -> None:
    """A recording with more than 5 checkpoints: the text lists 5 and says so."""
    shipped = Path(__file__).parents[2] / "recordings" / "loop-small.mcap"
    assert mcsm_main(["inspect", str(shipped)]) == 0
    out = capsys.readouterr().out
    n = int(out.split("checkpoints: ")[1].split()[0])
    assert n > 5
    assert f"checkpoints: {n} (the first 3 and the last 2 of {n} listed; --json lists all)" \
        in out
    assert out.count("\n    seq ") == 5
    # --json lists every one, in order
    assert mcsm_main(["inspect", str(shipped), "--json"]) == 0
    maps = json.loads(capsys.readouterr().out)["maps"]
    cps = [c for m in maps.values() for c in m["checkpoints"]]
    assert len(cps) == n and [c[0] for c in cps] == sorted(c[0] for c in cps)
    assert all(len(c[1]) == 64 for c in cps)  # seq, digest, reason


@pytest.mark.parametrize("command", ["replay", "inspect", "recover", "cat", "plot", "export",
                                     "export-foxglove", "view", "serve", "router"])
def test_every_reading_command_has_a_description(command: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        mcsm_main([command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    # usage, a blank line, then the description (argparse prints it only when given)
    first = out.split("\n\n")[1]
    assert not first.startswith(("positional arguments", "options")), out[:400]
    assert len(first) > 40
