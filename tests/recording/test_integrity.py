"""Indexed, verifiable recordings: what other MCAP readers see, what `inspect`, `replay`,
`recover` and `cat` say about complete, cut, bit-flipped and header-only files, the arithmetic
version in the header, `--version`, and terminal manners (no traceback, no `\\r` in logs)."""

from __future__ import annotations

import io
import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcsm import StochasticMap, wire
from mcsm.cli import (
    EXIT_CUT,
    EXIT_DAMAGED,
    EXIT_DIVERGED,
    EXIT_OK,
    EXIT_OTHER_ARITHMETIC,
    EXIT_USAGE,
)
from mcsm.cli import main as mcsm_main
from mcsm.core import ARITHMETIC_VERSION
from mcsm.errors import McsmError
from mcsm.log.progress import Progress
from mcsm.log.reader import RecordingReader
from mcsm.log.recover import recover
from mcsm.log.replay import replay
from mcsm.log.topics import (
    INPUT_TOPICS,
    TOPIC_CHECKPOINT,
    TOPIC_CONFIG,
    RecordingError,
    decode_input,
    schema_bytes,
)
from mcsm.log.writer import Recorder
from mcsm.map.state import MapState
from mcsm_client.client import MapClient

from tests.recording.test_recording import record_session
from tests.service.daemon_util import Daemon, noisy_at, start_daemon

N = 16


def indexed_messages(path: Path) -> list[Any]:
    """Every message through mcap's seeking reader (chunk indexes; what Foxglove's apps use)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes, "no chunk indexes"
        return [(ch.topic, m) for _, ch, m in reader.iter_messages(log_time_order=False)]


def check_indexed(path: Path, n_inputs: int) -> None:
    msgs = indexed_messages(path)
    assert sum(t in INPUT_TOPICS.values() for t, _ in msgs) == n_inputs
    assert all(m.publish_time <= m.log_time for _, m in msgs)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    names = [s.name for s in summary.schemas.values()]
    assert len(names) == len(set(names))  # each schema registered once
    assert {"mcsm.RecordConfig", "mcsm.RecordCheckpoint", "mcsm.RecordInput"} <= set(names) \
        <= {"mcsm.RecordConfig", "mcsm.RecordCheckpoint", "mcsm.RecordInput",
            "mcsm.RecordSnapshot", "mcsm.RecordSnapshotPart"}
    assert summary.statistics is not None and summary.statistics.message_count == len(msgs)
    rd = RecordingReader(path)
    assert sum(1 for _ in rd) == len(msgs)
    assert rd.complete and rd.data_crc and rd.summary_crc
    assert rd.n_chunks and rd.n_chunks_crc == rd.n_chunks


# ------------------------------------------------------------------------ mcsm serve, real files
@pytest.fixture()
def daemons() -> Any:
    started: list[Daemon] = []
    yield started
    for d in started:
        if d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait(timeout=10)


def _send(endpoint: str, count: int) -> list[Any]:
    """``count`` updates along a chain, one after the other; their acks."""
    rng = np.random.default_rng(8801)
    with MapClient(connect=endpoint, timeout_s=10.0) as c:
        return [c.update(f"p{i}", f"p{i + 1}", noisy_at(rng, N, [1, 0, 0]), request_id=f"r{i}")
                for i in range(count)]


def test_serve_recording_is_read_completely_by_the_indexed_reader(
        tmp_path: Path, daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N), "--checkpoint-every", "5")
    daemons.append(d)
    acks = _send(d.endpoint, 23)
    assert [a.seq for a in acks] == list(range(1, 24))
    assert d.stop(signal.SIGTERM) == 0
    check_indexed(d.record, 23)
    assert mcsm_main(["inspect", str(d.record)]) == EXIT_OK
    assert mcsm_main(["replay", str(d.record), "--no-progress"]) == EXIT_OK


def test_sigkilled_recording_recovers_to_an_indexed_file_with_every_ack(
        tmp_path: Path, daemons: list[Daemon], capsys: pytest.CaptureFixture[str]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N), "--checkpoint-every", "7")
    daemons.append(d)
    acks = _send(d.endpoint, 31)
    assert [a.seq for a in acks] == list(range(1, 32))
    d.proc.send_signal(signal.SIGKILL)  # no request in flight: the file holds exactly the acks
    d.proc.wait(timeout=10)
    with pytest.raises(Exception):  # noqa: B017 - mcap's seeking reader fails on a cut file
        indexed_messages(d.record)
    assert mcsm_main(["inspect", str(d.record)]) == EXIT_CUT
    out = tmp_path / "recovered.mcap"
    assert mcsm_main(["recover", str(d.record), "-o", str(out), "--no-progress"]) == EXIT_OK
    assert "CUT" in capsys.readouterr().out
    check_indexed(out, 31)
    assert mcsm_main(["replay", str(out), "--no-progress"]) == EXIT_OK


# ------------------------------------------------------------------------ damaged files
def _header_only(src: Path, dst: Path) -> None:
    """Magic plus the header record, as a writer killed right after start() leaves it."""
    data = src.read_bytes()
    length = int.from_bytes(data[9:17], "little")
    dst.write_bytes(data[: 8 + 1 + 8 + length])


@pytest.fixture()
def files(tmp_path: Path) -> dict[str, Path]:
    full = tmp_path / "full.mcap"
    record_session(full, N, 12, seed=8802, checkpoint_every=4)
    data = full.read_bytes()
    out = {"full": full}
    out["cut"] = tmp_path / "cut.mcap"
    out["cut"].write_bytes(data[: len(data) * 6 // 10])
    with open(full, "rb") as f:  # one bit inside the chunk of input seq 6
        summary = make_reader(f).get_summary()
    assert summary is not None
    update_channel = next(c.id for c in summary.channels.values()
                          if c.topic == INPUT_TOPICS["update"])
    chunks = [c for c in summary.chunk_indexes if update_channel in c.message_index_offsets]
    flipped = bytearray(data)
    flipped[chunks[5].chunk_start_offset + chunks[5].chunk_length // 2] ^= 0x04
    out["flipped"] = tmp_path / "flipped.mcap"
    out["flipped"].write_bytes(bytes(flipped))
    out["header"] = tmp_path / "header.mcap"
    _header_only(full, out["header"])
    return out


@pytest.mark.parametrize("kind,code,word", [
    ("full", EXIT_OK, "complete"), ("cut", EXIT_CUT, "CUT"),
    ("flipped", EXIT_DAMAGED, "DAMAGED"), ("header", EXIT_CUT, "CUT")])
def test_inspect_verifies_and_reports(files: dict[str, Path], kind: str, code: int, word: str,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert mcsm_main(["inspect", str(files[kind])]) == code
    out = capsys.readouterr().out
    assert f"state:     {word}" in out
    if kind == "full":
        assert "data section CRC, summary CRC verified" in out
    if kind == "flipped":
        assert "crc validation failed" in out
    assert mcsm_main(["inspect", str(files[kind]), "--json"]) == code
    js = json.loads(capsys.readouterr().out)
    assert js["exit_code"] == code and js["complete"] == (kind == "full")
    # a header-only file does not say (its metadata record was never written)
    assert js["arithmetic_version"] == (1 if kind == "header" else ARITHMETIC_VERSION)


@pytest.mark.parametrize("kind,code,word", [
    ("full", EXIT_OK, "identical"), ("cut", EXIT_CUT, "CUT: the file ends without a clean"),
    ("flipped", EXIT_DAMAGED, "DAMAGED:"), ("header", EXIT_CUT, "CUT:")])
def test_replay_says_what_it_verified(files: dict[str, Path], kind: str, code: int, word: str,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert mcsm_main(["replay", str(files[kind]), "--no-progress"]) == code
    out = capsys.readouterr().out
    assert word in out
    if kind != "full":
        assert "identical" not in out
        rep = replay(files[kind])
        assert f"replayed {rep.n_inputs} inputs and verified {rep.checkpoints_ok} " in out
    assert "DIVERGED" not in out and "truncated" not in out
    assert mcsm_main(["replay", str(files[kind]), "--no-progress", "--json"]) == code
    js = json.loads(capsys.readouterr().out)
    assert js["exit_code"] == code and js["identical"] == (kind == "full")


@pytest.mark.parametrize("kind,code,word", [
    ("full", EXIT_OK, ""), ("cut", EXIT_CUT, "CUT (no clean close)"),
    ("flipped", EXIT_DAMAGED, "DAMAGED: bad chunk")])
def test_cat_prints_what_it_can_then_exits_cut_or_damaged(
        files: dict[str, Path], kind: str, code: int, word: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Exit codes 4 and 5 of ``cat`` (docs/recordings.md): the inputs before the cut or the
    damage are printed, then one line on stderr says why it stopped."""
    assert mcsm_main(["cat", str(files[kind]), "--json"]) == code
    out, err = capsys.readouterr()
    seqs = [json.loads(line)["seq"] for line in out.splitlines()]
    assert seqs == list(range(1, len(seqs) + 1))
    assert (len(seqs) == 12) == (kind == "full") and (kind == "full" or len(seqs) >= 5)
    assert word in err and "Traceback" not in err


def test_a_divergence_on_a_complete_file_does_not_call_it_cut(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.mcap"
    rec = Recorder(path)
    st = MapState("default", StochasticMap(N))
    rec.config(st, 5)
    rng = np.random.default_rng(8803)
    payload = wire.encode_update("i1", "a", "b", noisy_at(rng, N, [1, 0, 0]))
    st.apply("update", decode_input("update", payload, N))
    rec.input("update", "default", 1, 1, "t", "i1", payload)
    rec.checkpoint("default", 1, "0" * 64, "periodic")
    rec.close()
    assert mcsm_main(["replay", str(path), "--no-progress"]) == EXIT_DIVERGED
    out = capsys.readouterr().out
    assert "DIVERGED: map 'default': digest differs at seq 1" in out
    assert "CUT" not in out and "truncated" not in out


@pytest.mark.parametrize("kind", ["full", "cut", "flipped", "header"])
def test_recover_writes_a_clean_indexed_copy(files: dict[str, Path], kind: str, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    src, out = files[kind], tmp_path / f"rec-{kind}.mcap"
    before = replay(src)
    assert mcsm_main(["recover", str(src), "-o", str(out), "--no-progress"]) == EXIT_OK
    text = capsys.readouterr().out
    word = {"full": "complete", "cut": "CUT", "flipped": "DAMAGED", "header": "CUT"}[kind]
    assert f"{src}: {word}" in text
    with open(out, "rb") as f:  # the copy is indexed and complete, for any reader
        summary = make_reader(f).get_summary()
        assert summary is not None
    assert mcsm_main(["inspect", str(out)]) == EXIT_OK
    capsys.readouterr()
    after = replay(out)
    if kind == "flipped":
        # the intact chunks after the damage are kept; the lost input leaves a gap
        assert "intact chunks after the damage were copied" in text
        assert after.n_inputs == before.n_inputs and after.divergence is not None
        assert "follows seq 5" in after.divergence or "replay is at seq 5" in after.divergence
        assert sum(1 for r in RecordingReader(out) if r.topic in INPUT_TOPICS.values()) == 11
    else:
        assert after.complete and after.identical and after.n_inputs == before.n_inputs
        assert after.final_digests() == before.final_digests()


def test_recover_refuses_bad_paths_before_reading(files: dict[str, Path], tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    existing = tmp_path / "exists.mcap"
    existing.write_bytes(b"keep me")
    empty = tmp_path / "empty"
    empty.mkdir()
    for argv, msg in [
            (["recover", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "o.mcap")],
             "no such file"),
            (["recover", str(files["full"]), "-o", str(existing)], "refusing to overwrite"),
            (["recover", str(files["full"]), "-o", str(files["full"] / "x.mcap")],
             "does not exist"),
            # a directory names a split recording's files: one without any is refused
            (["recover", str(empty), "-o", str(tmp_path / "o.mcap")],
             "a directory without *.mcap files")]:
        assert mcsm_main(argv) == EXIT_USAGE
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err
    assert existing.read_bytes() == b"keep me"
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file")
    assert mcsm_main(["recover", str(junk), "-o", str(tmp_path / "o.mcap")]) == EXIT_USAGE
    assert "not an MCAP file" in capsys.readouterr().err
    assert not (tmp_path / "o.mcap").exists()
    # the output is checked before the input is read: junk into an existing file names the file
    assert mcsm_main(["recover", str(junk), "-o", str(existing)]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "exists; refusing to overwrite" in err and "not an MCAP" not in err
    # the library refuses an existing output before it reads, and never removes what it did
    # not create
    with pytest.raises(RecordingError, match="exists"):
        recover(junk, existing)
    assert existing.read_bytes() == b"keep me"


def test_user_mistakes_get_a_message_not_a_traceback(tmp_path: Path) -> None:
    missing = str(tmp_path / "missing.mcap")
    for argv in (["inspect", missing], ["replay", missing], ["cat", missing],
                 ["replay"], ["recover", missing], ["cat", missing, "--bogus"]):
        r = subprocess.run([sys.executable, "-m", "mcsm.cli", *argv], capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == EXIT_USAGE, (argv, r.stderr)
        assert "Traceback" not in r.stderr and r.stderr.strip(), argv


# ------------------------------------------------------------------------ arithmetic version
def _write_legacy(path: Path, src: Path) -> None:
    """Copy ``src`` as a format-1 writer did: flat, no metadata, no version in the config."""
    with open(path, "wb") as f:
        w = Writer(f, use_chunking=False)
        w.start(library="mcsm 0.1.0")
        ids = {}
        for topic, name, fn in [(TOPIC_CONFIG, "mcsm.RecordConfig", "record_config.json"),
                                (TOPIC_CHECKPOINT, "mcsm.RecordCheckpoint",
                                 "record_checkpoint.json"),
                                (INPUT_TOPICS["update"], "mcsm.RecordInput",
                                 "record_input.json")]:
            ids[topic] = w.register_channel(
                topic, "msgpack", w.register_schema(name, "jsonschema", schema_bytes(fn)))
        for item in RecordingReader(src):
            d = dict(item.data)
            d.pop("arithmetic_version", None)
            w.add_message(ids[item.topic], log_time=item.log_time_ns, data=wire.pack(d),
                          publish_time=item.log_time_ns + 1)
        w.finish()


def test_format_1_files_inspect_cat_and_recover(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A format-1 file (flat, no CRCs, no version; publish_time after log_time): inspect says
    its integrity cannot be verified, cat prints every input, recover rewrites it indexed with
    its times in order."""
    src = tmp_path / "new.mcap"
    record_session(src, N, 9, seed=8806, checkpoint_every=3)
    old = tmp_path / "old.mcap"
    _write_legacy(old, src)
    assert mcsm_main(["inspect", str(old)]) == EXIT_OK
    assert "integrity: flat layout without CRCs (format 1): integrity not verifiable" in \
        capsys.readouterr().out
    assert mcsm_main(["cat", str(old), "--json"]) == EXIT_OK
    assert [json.loads(x)["seq"] for x in capsys.readouterr().out.splitlines()] == \
        list(range(1, 10))
    out = tmp_path / "indexed.mcap"
    assert mcsm_main(["recover", str(old), "-o", str(out), "--no-progress"]) == EXIT_OK
    check_indexed(out, 9)  # every input, publish_time <= log_time, every CRC


@pytest.mark.parametrize("how", ["says-1", "no-field"])
def test_replay_of_another_arithmetic_version_says_so(
        tmp_path: Path, how: str, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "old.mcap"
    if how == "says-1":
        monkeypatch.setattr("mcsm.log.writer.ARITHMETIC_VERSION", 1)
        record_session(path, N, 9, seed=8804, checkpoint_every=3)
        monkeypatch.undo()
        assert RecordingReader(path).arithmetic_version == 1
    else:
        src = tmp_path / "new.mcap"
        record_session(src, N, 9, seed=8804, checkpoint_every=3)
        _write_legacy(path, src)
        rd = RecordingReader(path)
        assert "mcsm" not in rd.metadata and rd.arithmetic_version == 1
    assert ARITHMETIC_VERSION != 1
    code = mcsm_main(["replay", str(path), "--no-progress"])
    out = capsys.readouterr().out
    assert code == EXIT_OTHER_ARITHMETIC
    assert "OTHER ARITHMETIC: recorded by arithmetic version(s) map 'default' version 1" in out
    assert f"computes with version {ARITHMETIC_VERSION}" in out
    assert "not a divergence" in out and "DIVERGED" not in out and "identical" not in out
    assert mcsm_main(["replay", str(path), "--no-progress", "--json"]) == EXIT_OTHER_ARITHMETIC
    js = json.loads(capsys.readouterr().out)
    assert js["status"] == "other_arithmetic" and js["arithmetic_versions"] == {"default": 1}
    assert js["checkpoints_other_arithmetic"] == 4 and js["checkpoints_ok"] == 0
    # `serve --restore` (replay into a sink) migrates: the new file is of this arithmetic
    new = tmp_path / "migrated.mcap"
    sink = Recorder(new)
    rep = replay(path, sink=sink)
    sink.close()
    assert rep.divergence is None and rep.other_arithmetic == {"default": 1}
    assert mcsm_main(["replay", str(new), "--no-progress"]) == EXIT_OK
    assert replay(new).final_digests() == rep.final_digests()


def test_other_arithmetic_with_differing_digests_is_not_called_diverged(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A version-1 recording whose digests differ from this core's (as real ones will)."""
    path = tmp_path / "old.mcap"
    monkeypatch.setattr("mcsm.log.writer.ARITHMETIC_VERSION", 1)
    rec = Recorder(path)
    st = MapState("default", StochasticMap(N))
    rec.config(st, 1)
    monkeypatch.undo()
    payload = wire.encode_update("i1", "a", "b", noisy_at(np.random.default_rng(1), N, [1, 0, 0]))
    st.apply("update", decode_input("update", payload, N))
    rec.input("update", "default", 1, 1, "t", "i1", payload)
    rec.checkpoint("default", 1, "f" * 64, "periodic")  # not what this core computes
    rec.close()
    assert next(iter(RecordingReader(path))).data["arithmetic_version"] == 1
    assert mcsm_main(["replay", str(path), "--no-progress"]) == EXIT_OTHER_ARITHMETIC
    out = capsys.readouterr().out
    assert "OTHER ARITHMETIC" in out and "DIVERGED" not in out
    # the same file claiming this core's version is a divergence
    same = tmp_path / "same.mcap"
    _write_legacy(same, path)  # drops the version field ...
    for where in ("mcsm.log.reader", "mcsm.log.replay"):  # the modules that read the default
        monkeypatch.setattr(f"{where}.LEGACY_ARITHMETIC_VERSION", ARITHMETIC_VERSION)
    assert mcsm_main(["replay", str(same), "--no-progress"]) == EXIT_DIVERGED  # ... now "2"
    assert "DIVERGED: map 'default': digest differs at seq 1" in capsys.readouterr().out


# ------------------------------------------------------------------------ cat, version, progress
def test_cat_prints_inputs_as_json_lines(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "r.mcap"
    st, payloads = record_session(path, N, 6, seed=8805)
    assert mcsm_main(["cat", str(path), "--json"]) == EXIT_OK
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["seq"] for x in lines] == list(range(1, 7))
    first = wire.decode_update(payloads[0], N)
    assert lines[0]["a"] == first.a and lines[0]["b"] == first.b
    s = lines[0]["samples"]
    assert s["n"] == N and len(s["mean"]) == 7 and np.asarray(s["cov"]).shape == (6, 6)
    assert np.allclose(s["mean"][:3], first.samples[:, :3].mean(axis=0))
    assert mcsm_main(["cat", str(path), "--json", "--samples"]) == EXIT_OK
    full = json.loads(capsys.readouterr().out.splitlines()[0])
    assert np.array_equal(np.asarray(full["samples"]["samples"]), first.samples)
    assert mcsm_main(["cat", str(path)]) == EXIT_OK
    text = capsys.readouterr().out.splitlines()
    heads = [t for t in text if not t.startswith(" ")]
    assert len(heads) == 6 and heads[0].startswith(f"default seq 1 update {first.a} -> {first.b}")
    # the text shows what the docs promise: the mean on the input's line, the 6x6 tangent
    # covariance on the 6 indented lines under it
    assert text[1].startswith("  cov (tx ty tz rx ry rz)") and len(text) == 6 * 7
    cov = np.array([[float(v) for v in t[26:].split()] for t in text[1:7]])
    assert np.allclose(cov, s["cov"], rtol=1e-3)
    mean = text[0].split("mean [")[1].split("]")[0].split()
    assert np.allclose([float(v) for v in mean], s["mean"], rtol=1e-5, atol=1e-12)
    # --samples: every sample, exactly, on the indented lines
    assert mcsm_main(["cat", str(path), "--samples"]) == EXIT_OK
    text = capsys.readouterr().out.splitlines()
    assert len(text) == 6 * (N + 1)
    rows = np.array([[float(v) for v in t.split()] for t in text[1:N + 1]])
    assert np.array_equal(rows, first.samples)


@pytest.mark.parametrize("script", ["mcsm", "mcsm-client"])
def test_version_flag(script: str) -> None:
    exe = Path(sys.executable).with_name(script)
    r = subprocess.run([str(exe), "--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith(f"{script} 0.")
    assert f"arithmetic version {ARITHMETIC_VERSION}" in r.stdout


@pytest.mark.parametrize("argv", [["replay", "--help"], ["--help"]])
def test_help_lists_the_exit_codes(argv: list[str]) -> None:
    r = subprocess.run([sys.executable, "-m", "mcsm.cli", *argv],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0
    for code in range(7):
        assert f"\n  {code}  " in r.stdout
    assert "in the order 1, 5, 4, 6" in r.stdout


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_is_a_bar_on_a_terminal_and_lines_in_a_log() -> None:
    log = io.StringIO()
    p = Progress("replay x", log, every_s=0.0)
    for done in (10, 50, 100):
        p(done * 10**6, 100 * 10**6)
    text = log.getvalue()
    assert "\r" not in text
    assert text.splitlines()[-1] == "replay x: 100% (100.0 of 100.0 MB)"
    quiet = io.StringIO()
    q = Progress("replay y", quiet)  # a run shorter than every_s writes nothing
    q(5, 10)
    q(10, 10)
    assert quiet.getvalue() == ""
    tty = _Tty()
    b = Progress("replay z", tty)
    b(5, 10)
    b(10, 10)
    assert "replay z" in tty.getvalue() and "100%" in tty.getvalue()


def test_config_record_matches_its_schema(tmp_path: Path) -> None:
    from jsonschema import Draft202012Validator

    path = tmp_path / "r.mcap"
    record_session(path, N, 2, seed=8806)
    config = next(r.data for r in RecordingReader(path) if r.topic == TOPIC_CONFIG)
    assert config["arithmetic_version"] == ARITHMETIC_VERSION
    schema = json.loads(schema_bytes("record_config.json"))
    assert list(Draft202012Validator(schema).iter_errors(config)) == []
    rd = RecordingReader(path)
    list(rd)
    assert rd.metadata["mcsm"]["arithmetic_version"] == str(ARITHMETIC_VERSION)
    assert rd.metadata["mcsm"]["format"] == "mcsm recording v2"


def _record_updates(path: Path, n: int, payloads: list[bytes]) -> Any:
    """Record ``payloads`` as updates of one map (no checkpoints); the file's summary."""
    rec = Recorder(path)
    assert rec.layout == "indexed-lz4"
    rec.config(MapState("default", StochasticMap(n)), 10_000)
    for i, p in enumerate(payloads):
        rec.input("update", "default", i + 1, 1000 + i, "t", f"i{i}", p)
    rec.close()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return summary


def test_lz4_where_it_pays_and_plain_chunks_where_it_does_not(tmp_path: Path) -> None:
    """Planar samples (z, qx, qy exactly 0) compress; 3-D noise does not and is stored as it
    is. Both read back through mcap's seeking reader with the exact request bytes."""
    rng = np.random.default_rng(8807)
    n = 1000
    planar = noisy_at(rng, n, [1, 0, 0], yaw=0.1)
    planar[:, 2] = 0.0
    planar[:, 3:] = 0.0
    yaw = 0.1 + 0.01 * rng.standard_normal(n)
    planar[:, 3], planar[:, 6] = np.cos(yaw / 2), np.sin(yaw / 2)
    payloads = [wire.encode_update(f"p{i}", f"a{i}", f"a{i + 1}", planar) for i in range(3)]
    payloads += [wire.encode_update(f"s{i}", f"b{i}", f"b{i + 1}", noisy_at(rng, n, [1, 0, 0]))
                 for i in range(3)]
    path = tmp_path / "r.mcap"
    summary = _record_updates(path, n, payloads)
    with open(path, "rb") as f:
        reader = make_reader(f)
        requests = [wire.unpack(m.data)["request"] for _, ch, m in
                    reader.iter_messages(log_time_order=False) if ch.topic in INPUT_TOPICS.values()]
    assert requests == payloads
    compressions = [c.compression for c in summary.chunk_indexes]
    big = [c for c in summary.chunk_indexes if c.uncompressed_size > 10_000]
    assert [c.compression for c in big] == ["lz4"] * 3 + [""] * 3, compressions
    assert all(c.compressed_size < 0.8 * c.uncompressed_size for c in big[:3])
    rd = RecordingReader(path)
    assert sum(1 for _ in rd) == 7 and rd.complete and rd.data_crc and rd.summary_crc


def test_lz4_is_tried_again_every_64_messages_on_a_channel_that_did_not_compress(
        tmp_path: Path) -> None:
    """After a message that does not compress, the channel's next 64 are stored as they are
    (no time spent trying), and the 65th is tried again: planar samples compress again."""
    from mcsm.log.chunkwriter import ChunkPerInputWriter

    rng = np.random.default_rng(8809)
    n = 200
    planar = noisy_at(rng, n, [1, 0, 0])
    planar[:, 2] = 0.0
    planar[:, 3:] = [1.0, 0.0, 0.0, 0.0]
    payloads = [wire.encode_update("s0", "b0", "b1", noisy_at(rng, n, [1, 0, 0]))]
    payloads += [wire.encode_update(f"p{i}", f"a{i}", f"a{i + 1}", planar) for i in range(66)]
    summary = _record_updates(tmp_path / "r.mcap", n, payloads)
    inputs = [c.compression for c in summary.chunk_indexes
              if c.uncompressed_size > 3_000]  # the inputs' chunks (configs are small)
    retry = ChunkPerInputWriter.LZ4_RETRY
    assert retry == 64 and len(inputs) == 67
    assert inputs == [""] * (1 + retry) + ["lz4"] * 2, inputs


@pytest.mark.parametrize("layout", ["indexed", "indexed-lz4", "indexed-zstd", "flat"])
def test_every_layout_replays(tmp_path: Path, layout: str) -> None:
    path = tmp_path / "r.mcap"
    rng = np.random.default_rng(8808)
    rec = Recorder(path, layout=layout)
    st = MapState("default", StochasticMap(N))
    rec.config(st, 2)
    for i in range(5):
        payload = wire.encode_update(f"i{i}", f"p{i}", f"p{i + 1}", noisy_at(rng, N, [1, 0, 0]))
        ack = st.apply("update", decode_input("update", payload, N))
        rec.input("update", "default", ack.seq, 1000 + i, "t", f"i{i}", payload)
        rec.checkpoint("default", ack.seq, st.digest(), "periodic")
    rec.close()
    rep = replay(path)
    assert rep.identical and rep.complete and rep.checkpoints_ok == 5
    assert rep.final_digests() == {"default": st.digest()}
    with pytest.raises(McsmError, match="unknown recording layout"):
        Recorder(tmp_path / "x.mcap", layout="chunky")


def test_client_sim_refuses_an_unwritable_output_before_running(tmp_path: Path) -> None:
    exe = Path(sys.executable).with_name("mcsm-client")
    for flag in ("--png", "--csv"):
        r = subprocess.run([str(exe), "sim", "--in-process", "16", "--iterations", "100000",
                            flag, str(tmp_path / "missing-dir" / "out")],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == EXIT_USAGE, r.stderr
        assert "does not exist" in r.stderr and "Traceback" not in r.stderr
        assert "iteration" not in r.stdout  # refused before the run started
        taken = tmp_path / f"taken{flag}"
        taken.write_text("")
        r = subprocess.run([str(exe), "sim", "--in-process", "16", "--iterations", "100000",
                            flag, str(taken)], capture_output=True, text=True, timeout=120)
        assert r.returncode == EXIT_USAGE and "exists (--force overwrites it)" in r.stderr
        assert "iteration" not in r.stdout


def test_cat_shows_removes_imports_retracts_and_reinstates(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(8809)
    other = StochasticMap(N)
    other.update("q0", "q1", noisy_at(rng, N, [1, 0, 0]))
    other.update("q1", "q2", noisy_at(rng, N, [1, 0, 0]))
    sub = other.export_component("q0")
    payloads = [("update", wire.encode_update("u1", "a", "b", noisy_at(rng, N, [1, 0, 0]))),
                ("remove", wire.encode_remove("r1", "b")),
                ("import", wire.encode_submap_import("i1", sub)),
                ("update", wire.encode_update("u2", "a", "c", noisy_at(rng, N, [0, 1, 0]))),
                ("retract", wire.encode_retract("t1", "u2")),
                ("reinstate", wire.encode_retract("t2", "u2")),
                ("update", wire.encode_update("u3", "a", "l1",
                                              rng.normal([2.0, 1.0, 0.0], 0.1, (N, 3))))]
    path = tmp_path / "r.mcap"
    rec = Recorder(path)
    st = MapState("default", StochasticMap(N))
    rec.config(st, 100)
    for op, payload in payloads:
        ack = st.apply(op, decode_input(op, payload, N))
        rec.input(op, "default", ack.seq, 1, "t", ack.request_id, payload)
    rec.close()
    assert mcsm_main(["cat", str(path), "--json"]) == EXIT_OK
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["op"] for x in lines] == ["update", "remove", "import", "update", "retract",
                                        "reinstate", "update"]
    assert lines[1]["frame"] == "b"
    assert lines[4]["target"] == "u2" and lines[5]["target"] == "u2"
    assert all("error" not in x for x in lines)
    imp = lines[2]
    assert imp["root"] == "q0" and imp["frames"] == ["q0", "q1", "q2"]
    assert len(imp["edges"]) == 2 and np.asarray(imp["edges"][1]["cov"]).shape == (6, 6)
    assert mcsm_main(["cat", str(path)]) == EXIT_OK
    out = capsys.readouterr().out.splitlines()
    text = [t for t in out if not t.startswith(" ")]
    assert text[1].startswith("default seq 2 remove b") and "3 frames" in text[2]
    assert text[4].startswith("default seq 5 retract of u2")
    assert text[5].startswith("default seq 6 reinstate of u2")
    # a point: its mean, sender and request id on its line, its 3x3 covariance on 3 more
    assert text[6].startswith("default seq 7 update a -> l1 N=") and \
        text[6].endswith("(sender t, id u3)")
    assert [float(v) for v in text[6].split("mean [")[1].split("]")[0].split()] == \
        pytest.approx(lines[6]["samples"]["mean"], rel=1e-5)
    rows = out[out.index(text[6]) + 1:]
    assert len(rows) == 3 and rows[0].startswith("  cov (x y z) ")
    np.testing.assert_allclose([[float(v) for v in r[26:].split()] for r in rows],
                               lines[6]["samples"]["cov"], rtol=1e-3)


def test_serve_restore_migrates_a_recording_of_another_arithmetic(tmp_path: Path) -> None:
    """``mcsm serve --restore OLD.mcap`` of a version-1 file: a warning in the log, and the new
    recording carries this arithmetic's version and digests, so it replays identical."""
    src = tmp_path / "new.mcap"
    record_session(src, N, 9, seed=8807, checkpoint_every=3)
    old = tmp_path / "old.mcap"
    _write_legacy(old, src)
    d = start_daemon(tmp_path, "--samples", str(N), "--restore", str(old), name="migrated")
    try:
        assert "was recorded by arithmetic version" in d.log_text()
    finally:
        assert d.stop(signal.SIGINT) == 0, d.log_text()
    reader = RecordingReader(d.record)
    config = next(iter(reader)).data
    assert config["arithmetic_version"] == ARITHMETIC_VERSION
    assert reader.arithmetic_version == ARITHMETIC_VERSION  # (the metadata, once read)
    rep = replay(d.record)
    assert rep.identical and rep.complete and not rep.other_arithmetic
    assert rep.states["default"].seq == 9


def test_replay_reports_the_first_exit_code_in_the_order_1_5_4_6(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Several conditions at once: a cut file of another arithmetic is 4 (cut), not 6; a
    damaged one is 5; a cut file that diverges before the cut is 1."""
    from tests.recording.test_recording import _rewrite

    old = tmp_path / "old.mcap"  # indexed, with CRCs, of arithmetic version 1
    monkeypatch.setattr("mcsm.log.writer.ARITHMETIC_VERSION", 1)
    record_session(old, N, 20, seed=8808, checkpoint_every=3)
    monkeypatch.undo()
    assert mcsm_main(["replay", str(old), "--no-progress"]) == EXIT_OTHER_ARITHMETIC
    cut_old = tmp_path / "cut-old.mcap"
    cut_old.write_bytes(old.read_bytes()[: old.stat().st_size * 7 // 10])
    assert mcsm_main(["replay", str(cut_old), "--no-progress"]) == EXIT_CUT
    bad_old = tmp_path / "bad-old.mcap"
    raw = bytearray(old.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # inside a chunk: its CRC no longer matches
    bad_old.write_bytes(bytes(raw))
    assert mcsm_main(["replay", str(bad_old), "--no-progress"]) == EXIT_DAMAGED
    gap_old = tmp_path / "gap-old.mcap"  # of version 1 too: a missing seq still diverges
    monkeypatch.setattr("mcsm.log.writer.ARITHMETIC_VERSION", 1)
    _rewrite(old, gap_old, "gap")
    monkeypatch.undo()
    assert mcsm_main(["replay", str(gap_old), "--no-progress"]) == EXIT_DIVERGED
    shipped = Path(__file__).parents[2] / "recordings" / "loop-small.mcap"
    diverged = tmp_path / "diverged.mcap"
    _rewrite(shipped, diverged, "digest")  # seq 10's checkpoint says another digest
    cut = tmp_path / "diverged-cut.mcap"
    cut.write_bytes(diverged.read_bytes()[: diverged.stat().st_size * 8 // 10])
    assert mcsm_main(["replay", str(cut), "--no-progress"]) == EXIT_DIVERGED


def test_an_unwritable_output_folder_is_refused_before_any_work(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """(Tests run as root, who may write anywhere: the folder's permission check is faked.)"""
    import os

    shipped = Path(__file__).parents[2] / "recordings" / "loop-small.mcap"
    real_access = os.access
    locked = tmp_path / "locked"
    locked.mkdir()
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: Path(p) != locked and
                        real_access(p, mode, *a, **k))
    for argv in (["recover", str(shipped), "-o", str(locked / "r.mcap")],
                 ["plot", str(shipped), "-o", str(locked / "m.png")]):
        assert mcsm_main(argv) == EXIT_USAGE, argv
        err = capsys.readouterr().err
        assert "is not writable" in err and str(locked) in err, err
    assert not any(locked.iterdir())


def test_ctrl_c_is_one_line_and_exit_130(monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """Ctrl-C in a long replay (or recover, export, ...): `interrupted`, exit 130, no
    traceback."""
    def interrupted(*_: object, **__: object) -> object:
        raise KeyboardInterrupt

    monkeypatch.setattr("mcsm.log.replay.replay", interrupted)  # (replay_cmd imports it)
    shipped = Path(__file__).parents[2] / "recordings" / "loop-small.mcap"
    assert mcsm_main(["replay", str(shipped), "--no-progress"]) == 130
    assert capsys.readouterr().err == "mcsm replay: interrupted\n"
