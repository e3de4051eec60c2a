"""The wire codec: bit-exact round trips, the malformed-payload table, and the JSON Schemas."""

from __future__ import annotations

import base64
import dataclasses
import json
from importlib import resources
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator
from mcsm import wire
from mcsm.core.at import identity
from mcsm.core.quat import qexp
from mcsm.errors import (
    BadMessage,
    InvalidSamples,
    LimitExceeded,
    McsmError,
    SampleCountMismatch,
    UnknownFrame,
    UnsupportedVersion,
)

from tests.wire_cases import CASES, decode_for, good_samples

SCHEMA_FILES = sorted(p.name for p in resources.files("mcsm.schemas").iterdir()
                      if p.name.endswith(".json"))


def random_samples(rng: np.random.Generator, n: int) -> np.ndarray:
    x = np.empty((n, 7))
    x[:, :3] = 1e3 * rng.standard_normal((n, 3))
    x[:, 3:] = qexp(rng.standard_normal((n, 3)))
    x[rng.random(n) < 0.5, 3:] *= -1.0  # both quaternion signs
    return x


@settings(deadline=None, max_examples=30)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 300))
def test_update_round_trip_is_bit_exact(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    x = random_samples(rng, n)
    req = wire.decode_update(wire.encode_update("id-1", "a:1", "b.2", x, sender="s"), n)
    assert req.samples.tobytes() == x.tobytes()
    assert (req.request_id, req.a, req.b, req.sender, req.point) == ("id-1", "a:1", "b.2", "s",
                                                                     False)
    assert req.samples.flags.writeable and req.samples.flags.c_contiguous


@settings(deadline=None, max_examples=20)
@given(seed=st.integers(0, 2**32 - 1))
def test_point_submap_and_replies_round_trip(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 50))
    p = rng.standard_normal((n, 3))
    req = wire.decode_update(wire.encode_update("p", "a", "lm", p), n)
    assert req.point and req.samples.tobytes() == p.tobytes()
    edges = np.stack([identity(n), random_samples(rng, n), random_samples(rng, n)])
    sub = wire.SubmapData("r", ("r", "f1", "p2"), (False, False, True), edges)
    imp = wire.decode_submap_request(wire.encode_submap_import("i", sub, sender="x"), n)
    assert isinstance(imp, wire.SubmapImportRequest)
    assert imp.submap.edges.tobytes() == edges.tobytes()
    assert (imp.submap.frames, imp.submap.is_point) == (sub.frames, sub.is_point)
    rep = wire.decode_submap_reply(wire.encode_submap_reply(wire.SubmapReply("i", 4, sub)))
    assert rep.submap.edges.tobytes() == edges.tobytes() and rep.seq == 4
    mean, cov = rng.standard_normal(7), rng.standard_normal((6, 6))
    q = wire.decode_query_reply(wire.encode_query_reply(
        wire.QueryReply("q", "a", "b", 9, samples=edges[1], mean=mean, cov=cov)))
    assert q.samples is not None and q.samples.tobytes() == edges[1].tobytes()
    assert q.mean is not None and q.mean.tobytes() == mean.tobytes()
    assert q.cov is not None and q.cov.tobytes() == cov.tobytes()


def test_ack_info_event_error_round_trip() -> None:
    ack = wire.Ack("r-1", 12, "update", "loop_closure", "w", ("a",), (), True)
    assert wire.decode_ack(wire.encode_ack(ack)) == ack
    info = wire.MapInfo("default", 100, {"n_samples": 100, "method": "joint"}, 3, "ab" * 32,
                        ("w", "r"), {"w": ("w", "r")}, 2, {"BadMessage": 2}, "zid", "x.mcap", 1)
    assert wire.decode_info_reply(wire.encode_info_reply(info)) == info
    many = {f"r{i}": (f"r{i}", f"s{i}") for i in range(500)}  # more maps entries than requests
    big = wire.MapInfo("m", 10, {}, 1, "d", tuple(f for v in many.values() for f in v), many, 0,
                       {}, "z", "")
    assert wire.decode_info_reply(wire.encode_info_reply(big)).components == many
    # a map of more than 100,000 frames (the largest submap) still has a readable info
    frames = tuple(f"f{i}" for i in range(250_000))
    huge = wire.MapInfo("m", 10, {}, 1, "d", frames, {"f0": frames}, 0, {}, "z", "")
    assert wire.decode_info_reply(wire.encode_info_reply(huge)).n_frames == 250_000
    with pytest.raises(BadMessage):  # requests keep the submap's bound
        wire.unpack(wire.pack({"v": wire.VERSION, "frames": list(frames)}))
    ev = wire.Event("default", 5, "remove", "remove", ("r",), None, 123, None)
    assert wire.decode_event(wire.encode_event(ev)) == ev
    err = wire.decode_error(wire.encode_error(UnknownFrame("ghost"), "r-2"))
    assert isinstance(err, UnknownFrame) and "ghost" in str(err)
    assert err.fields["name"] == "ghost"


@pytest.mark.parametrize("case_id,op,build,error,map_level", CASES, ids=[c[0] for c in CASES])
def test_malformed_payload_table_decoder(case_id: str, op: str, build: Any, error: str,
                                         map_level: bool) -> None:
    n = 16
    payload = build(n)
    if map_level:
        decode_for(op, payload, n)  # passes the codec; the map refuses it (service tests)
        return
    with pytest.raises(McsmError) as info:
        decode_for(op, payload, n)
    assert type(info.value).__name__ == error, info.value
    # the error survives the trip through an error reply with its type and message
    back = wire.decode_error(wire.encode_error(info.value, "x"))
    assert type(back) is type(info.value) and back.message == info.value.message


def test_payload_length_is_checked_before_unpacking() -> None:
    big = b"\x00" * (wire.MAX_PAYLOAD_BYTES + 1)
    with pytest.raises(LimitExceeded):
        wire.decode_update(big, 10)
    # a bin header claiming 4 GiB in a short payload is refused, not allocated
    with pytest.raises(BadMessage):
        wire.unpack(b"\xc6\xff\xff\xff\xff" + b"\x00" * 16)
    # nesting bombs are refused cleanly
    with pytest.raises(BadMessage):
        wire.unpack(b"\x91" * 200_000)


def test_specific_error_fields() -> None:
    x = good_samples(10)
    with pytest.raises(SampleCountMismatch) as e1:
        wire.decode_update(wire.encode_update("i", "a", "b", x), 11)
    assert (e1.value.fields["expected"], e1.value.fields["got"]) == (11, 10)
    with pytest.raises(UnsupportedVersion) as e2:
        wire.decode_info(msgpack.packb({"v": 99}))
    assert e2.value.fields["supported"] == 1
    x[4, 3:7] = [0.0, 0.0, 0.0, 0.0]
    with pytest.raises(InvalidSamples, match="sample"):
        wire.decode_update(wire.encode_update("i", "a", "b", x), 10)


def test_keys_and_names() -> None:
    k = wire.map_keys("lab.1", "fleet/site-a")
    assert (k.update, k.events, k.alive("z1")) == ("fleet/site-a/lab.1/update",
                                                  "fleet/site-a/lab.1/events",
                                                  "fleet/site-a/lab.1/alive/z1")
    for bad_map in ("", "a/b", "a*", "x" * 65):
        with pytest.raises(BadMessage):
            wire.map_keys(bad_map)
    with pytest.raises(BadMessage):
        wire.map_keys("m", "bad/**")


# ----------------------------------------------------------------------------- JSON Schemas
def _jsonable(obj: Any) -> Any:
    """msgpack values as a JSON view: bin fields as base64 strings (the schemas' convention)."""
    if isinstance(obj, bytes):
        return base64.b64encode(obj).decode()
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


def _schema(name: str) -> dict[str, Any]:
    return json.loads(resources.files("mcsm.schemas").joinpath(name).read_text())


@pytest.mark.parametrize("name", SCHEMA_FILES)
def test_schemas_are_valid_and_versioned(name: str) -> None:
    s = _schema(name)
    Draft202012Validator.check_schema(s)
    assert s["properties"]["v"] == {"const": 1, "description": s["properties"]["v"]["description"]}
    assert "v" in s["required"] and s["additionalProperties"] is False


def _messages(n: int) -> dict[str, bytes]:
    x = good_samples(n)
    sub = wire.SubmapData("w", ("w", "r"), (False, False), np.stack([identity(n), x]))
    return {
        "update_request.json": wire.encode_update("i", "w", "r", x, sender="me"),
        "point_update_request.json": wire.encode_update("i", "w", "p", good_samples(n, 3)),
        "remove_request.json": wire.encode_remove("i", "r"),
        "query_request.json": wire.encode_query("i", "w", "r", "marginal"),
        "query_reply.json": wire.encode_query_reply(wire.QueryReply("i", "w", "r", 1,
                                                                    samples=x)),
        "info_request.json": wire.encode_info("i"),
        "info_reply.json": wire.encode_info_reply(wire.MapInfo(
            "m", n, {"n_samples": n}, 1, "d", ("w",), {"w": ("w",)}, 0, {}, "z", "f")),
        "submap_export_request.json": wire.encode_submap_export("i", "w"),
        "submap_import_request.json": wire.encode_submap_import("i", sub),
        "submap_reply.json": wire.encode_submap_reply(wire.SubmapReply("i", 1, sub)),
        "ack.json": wire.encode_ack(wire.Ack("i", 1, "update", "loop_closure", "w", (),
                                             verdict=wire.Verdict("rejected", 30.5, 6, 16.8,
                                                                  "", 12), relin={
            "trigger": "gate", "time_s": 0.01, "components": [{
                "root": "w", "frames": 2, "variables": 3, "factors": 2, "iterations": 2,
                "cost_before": 40.0, "cost_after": 2.5, "trimmed": 0, "skipped": ""}]})),
        "retract_request.json": wire.encode_retract("i", "j", sender="me"),
        "relinearize_request.json": wire.encode_relinearize("i", "w", sender="me"),
        "verdict_request.json": wire.encode_verdict_request("i", "j"),
        "error.json": wire.encode_error(UnknownFrame("r"), "i"),
        "event.json": wire.encode_event(wire.Event("m", 1, "update", "join", ("w", "r"), "w",
                                                   5, "d")),
    }


def test_every_message_validates_against_its_schema() -> None:
    msgs = _messages(5)
    wire_schemas = {n for n in SCHEMA_FILES if not n.startswith("record_")}
    assert set(msgs) == wire_schemas  # one schema per message kind, each exercised
    for name, payload in msgs.items():
        Draft202012Validator(_schema(name)).validate(_jsonable(msgpack.unpackb(payload)))


def test_every_relinearisation_report_validates_against_the_ack_schema() -> None:
    """Every trigger a map can report (the policy's recentre and readmit included) and the
    readmitted count, from real maps' reports."""
    from mcsm import StochasticMap
    from mcsm.core.relinearize import Policy

    v = Draft202012Validator(_schema("ack.json"))
    n, rng = 40, np.random.default_rng(5)
    reports = []
    for pol in (Policy(recentre=True), Policy(every=2, gap=1)):
        m = StochasticMap(n, gate=None, relinearize=pol)
        for k in range(4):
            reports.append(m.update(f"x{k}", f"x{k + 1}", good_samples(n)).relin)
        reports.append(m.update("x0", "x4", m.query("x0", "x4")[rng.permutation(n)]).relin)
    reports.append(m.relinearize())
    done = [r.to_dict() for r in reports if r is not None]
    assert {d["trigger"] for d in done} == {"recentre", "every", "request"}
    readmitted = {**done[-1], "trigger": "readmit"}
    readmitted["components"] = [{**done[-1]["components"][0], "readmitted": 2}]
    for relin in [*done, readmitted]:
        ack = wire.encode_ack(wire.Ack("i", 1, "update", "loop_closure", "w", (), relin=relin))
        v.validate(_jsonable(msgpack.unpackb(ack)))


def test_schemas_reject_what_the_codec_rejects() -> None:
    v = Draft202012Validator(_schema("update_request.json"))
    good = _jsonable(msgpack.unpackb(wire.encode_update("i", "w", "r", good_samples(3))))
    assert v.is_valid(good)
    assert not v.is_valid({**good, "v": 2})
    assert not v.is_valid({**good, "b": "a//b"})
    assert v.is_valid({**good, "b": "robot1/base_link"})
    assert not v.is_valid({**good, "extra": 1})
    assert not v.is_valid({**good, "samples": {**good["samples"], "shape": [3, 6]}})


_leaf = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(),
                  st.text(max_size=20), st.binary(max_size=64))
_values = st.recursive(_leaf, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=10), inner, max_size=5)),
    max_leaves=20)
_near_valid = st.fixed_dictionaries(
    {"v": st.sampled_from([1, 1, 1, 2, "1", None])},
    optional={"id": _values | st.just("x"), "a": _values | st.just("w"),
              "b": _values | st.just("r"), "frame": _values | st.just("w"),
              "op": st.sampled_from(["export", "import", "x"]),
              "samples": _values | st.fixed_dictionaries(
                  {"dtype": st.sampled_from(["<f8", ">f8", 1]),
                   "shape": st.lists(st.integers(-1, 20), max_size=3),
                   "data": st.binary(max_size=600)}),
              "submap": _values, "want": _values})


@settings(deadline=None, max_examples=120)
@given(payload=st.binary(max_size=400) | _values.map(msgpack.packb)
       | _near_valid.map(msgpack.packb),
       op=st.sampled_from(["update", "remove", "query", "info", "submap"]))
def test_decoders_only_raise_typed_errors(payload: bytes, op: str) -> None:
    """Whatever bytes arrive, a decoder returns a checked message or raises an McsmError."""
    try:
        msg = decode_for(op, payload, 4)
    except McsmError as exc:
        assert exc.to_dict()["error"] == type(exc).__name__
    else:
        assert dataclasses.is_dataclass(msg)


def _good_ack() -> dict[str, Any]:
    verdict = wire.Verdict("accepted", 3.5, 6, 16.8, "", 17)
    ack = wire.Ack("r-1", 4, "update", "loop_closure", "w", ("a",), (), False, "zid", verdict)
    d: dict[str, Any] = msgpack.unpackb(wire.encode_ack(ack))
    assert wire.decode_ack(wire.encode_ack(ack)) == ack
    return d


@pytest.mark.parametrize("change,error,fieldname", [
    ({"seq": None}, BadMessage, "seq"),
    ({"seq": -1}, BadMessage, "seq"),
    ({"seq": True}, BadMessage, "seq"),
    ({"duplicate": 1}, BadMessage, "duplicate"),
    ({"frames_added": "a"}, BadMessage, "frames_added"),
    ({"frames_removed": [1]}, BadMessage, "frames_removed"),
    ({"component": 5}, BadMessage, "component"),
    ({"id": "x" * 129}, LimitExceeded, "id length"),
    ({"server": "x" * 129}, LimitExceeded, "server length"),
    ({"op": b"update"}, BadMessage, "op"),
    ({"extra": 1}, BadMessage, "extra"),
    ({"verdict": []}, BadMessage, "verdict"),
    ({"verdict": {"status": "maybe", "nis": None, "dof": 0, "threshold": None, "reason": "",
                  "stamp_ns": None}}, BadMessage, "verdict.status"),
    ({"verdict": {"status": "accepted"}}, BadMessage, "verdict.nis"),
    ({"verdict": {"status": "accepted", "nis": "1", "dof": 0, "threshold": None,
                  "reason": "", "stamp_ns": None}}, BadMessage, "verdict.nis"),
    ({"verdict": {"status": "accepted", "nis": None, "dof": 0, "threshold": None,
                  "reason": "", "stamp_ns": 1.5}}, BadMessage, "verdict.stamp_ns"),
    ({"verdict": {"status": "accepted", "nis": None, "dof": 0, "threshold": None,
                  "reason": "", "stamp_ns": None, "x": 1}}, BadMessage, "verdict.x"),
])
def test_derived_ack_decoder_keeps_every_check(change: dict[str, Any], error: type,
                                               fieldname: str) -> None:
    """The ack is decoded field by field from its dataclass; each field's check still refuses
    a hostile value with a typed error naming the field (None in ``change``: key left out)."""
    d = {**_good_ack(), **change}
    d = {k: v for k, v in d.items() if v is not None or k == "component"}
    with pytest.raises(error) as info:
        wire.decode_ack(msgpack.packb(d))
    assert info.value.to_dict()["fields"].get("field", info.value.to_dict()["fields"]
                                               .get("what")) == fieldname


def test_derived_optional_fields_may_be_left_out_by_older_peers() -> None:
    d = _good_ack()
    del d["server"], d["verdict"]
    ack = wire.decode_ack(msgpack.packb(d))
    assert ack.server == "" and ack.verdict is None
    ev = wire.Event("m", 1, "update", "join", ("w", "r"), "w", 5, None)
    assert "extra" not in msgpack.unpackb(wire.encode_event(ev))
    assert wire.decode_event(wire.encode_event(ev)) == ev
    with pytest.raises(BadMessage, match="digest"):
        wire.decode_event(msgpack.packb({**msgpack.unpackb(wire.encode_event(ev)),
                                         "digest": 5}))


@pytest.mark.parametrize("cls,schema", [
    (wire.Ack, "ack.json"), (wire.Event, "event.json"), (wire.MapInfo, "info_reply.json"),
    (wire.QueryReply, "query_reply.json"), (wire.SubmapReply, "submap_reply.json")])
def test_derived_messages_and_their_schemas_name_the_same_fields(cls: type,
                                                                 schema: str) -> None:
    """A field added to a derived message must be added to its schema too (and the reverse)."""
    keys = {spec.key or f.name for f in dataclasses.fields(cls)
            for spec in [f.metadata["wire"]]}
    props = set(_schema(schema)["properties"]) - {"v"}
    assert keys == props
    required = {spec.key or f.name for f in dataclasses.fields(cls)
                for spec in [f.metadata["wire"]] if spec.required}
    assert required == set(_schema(schema)["required"]) - {"v"}


@settings(deadline=None, max_examples=150)
@given(payload=_values.map(msgpack.packb) | st.fixed_dictionaries(
    {"v": st.just(1)}, optional={k: _values for k in (
        "id", "seq", "op", "kind", "component", "frames_added", "frames_removed", "duplicate",
        "server", "verdict", "map", "frames", "time_ns", "digest", "extra", "n_samples",
        "options", "components", "rejected", "rejected_by_error", "server_id", "recording",
        "queue_length", "verdicts", "a", "b", "samples", "mean", "cov", "submap")}
                                             ).map(msgpack.packb))
def test_reply_decoders_only_raise_typed_errors(payload: bytes) -> None:
    for decode in (wire.decode_ack, wire.decode_event, wire.decode_info_reply,
                   wire.decode_query_reply, wire.decode_submap_reply):
        try:
            msg = decode(payload)
        except McsmError as exc:
            assert exc.to_dict()["error"] == type(exc).__name__
        else:
            assert dataclasses.is_dataclass(msg)


def test_derived_info_query_and_submap_replies_keep_their_checks() -> None:
    info = wire.MapInfo("m", 10, {"n_samples": 10}, 2, "ab", ("w", "r"), {"w": ("w", "r")}, 1,
                        {"BadMessage": 1}, "zid", "x.mcap", 3, {"accepted": 2})
    d = msgpack.unpackb(wire.encode_info_reply(info))
    assert wire.decode_info_reply(msgpack.packb(d)) == info
    for change, fieldname in [({"queue_length": "3"}, "queue_length"),
                              ({"rejected_by_error": {"BadMessage": "1"}}, "rejected_by_error"),
                              ({"verdicts": {"accepted": True}}, "verdicts"),
                              ({"components": {"w": "w"}}, "components"),
                              ({"options": []}, "options"), ({"seq": -2}, "seq")]:
        with pytest.raises(BadMessage) as exc:
            wire.decode_info_reply(msgpack.packb({**d, **change}))
        assert exc.value.to_dict()["fields"]["field"] == fieldname
    old = {k: v for k, v in d.items() if k not in ("queue_length", "verdicts")}
    assert wire.decode_info_reply(msgpack.packb(old)).queue_length == 0  # an older server
    mean, cov = np.zeros(7), np.eye(6)
    mean[3] = 1.0
    q = msgpack.unpackb(wire.encode_query_reply(
        wire.QueryReply("q", "a", "b", 1, mean=mean, cov=cov)))
    with pytest.raises(BadMessage, match="mean/cov"):
        wire.decode_query_reply(msgpack.packb({k: v for k, v in q.items() if k != "cov"}))
    with pytest.raises(BadMessage, match="cov"):
        wire.decode_query_reply(msgpack.packb({**q, "cov": wire.pack_array(np.eye(5))}))
    with pytest.raises(BadMessage, match="bad a: "):
        wire.decode_query_reply(msgpack.packb({**q, "a": "a//b"}))
    with pytest.raises(InvalidSamples):
        wire.decode_query_reply(msgpack.packb({**q, "mean": wire.pack_array(
            np.full(7, np.nan))}))
    edges = np.zeros((2, 3, 7))
    edges[..., 3] = 1.0
    sub = wire.SubmapData("w", ("w", "r"), (False, False), edges)
    r = msgpack.unpackb(wire.encode_submap_reply(wire.SubmapReply("s", 4, sub)))
    assert wire.decode_submap_reply(msgpack.packb(r)).submap.frames == ("w", "r")
    with pytest.raises(BadMessage, match="submap.frames"):
        wire.decode_submap_reply(msgpack.packb({**r, "submap": {**r["submap"],
                                                                "frames": ["w", "w"]}}))
    with pytest.raises(InvalidSamples):
        bad = edges.copy()
        bad[1, 0, 3] = 2.0
        wire.decode_submap_reply(msgpack.packb({**r, "submap": {**r["submap"],
                                                                "edges": wire.pack_array(bad)}}))
