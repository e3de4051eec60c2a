"""The table of operations (``mcsm.map.ops``) against the codec, the schemas and ``KEYS.md``:
every operation is named once and everything else agrees with the table."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import pytest
from mcsm import wire
from mcsm.errors import BadMessage, Forbidden, McsmError
from mcsm.map import ops
from mcsm.serve.replication import TAKEOVER

from tests.wire_cases import good_samples

N = 8


def _schema(name: str) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(resources.files("mcsm.schemas").joinpath(name).read_text())
    return data


def _sub() -> wire.SubmapData:
    import numpy as np

    edges = np.zeros((2, N, 7))
    edges[..., 3] = 1.0
    return wire.SubmapData("q0", ("q0", "q1"), (False, False), edges)


# the arguments after the request id that each operation's client encoder takes
ARGS: dict[str, tuple[Any, ...]] = {
    "update": ("w", "r", good_samples(N)), "remove": ("r",), "import": (_sub(),),
    "retract": ("u1",), "reinstate": ("u1",), "verdict": ("u1",), "query": ("w", "r"),
    "info": (), "export": ("w",), "relinearize": ("w",)}


def test_every_operation_has_its_arguments_here() -> None:
    assert set(ARGS) == set(ops.OPS)


def test_the_wires_request_leaves_are_the_tables() -> None:
    """The codec routes keys from plain data (it knows no table): the leaves it lists, their
    order (the error message's) and which take a namespace are exactly the table's."""
    assert list(wire.REQUEST_LEAVES) == list(ops.BY_LEAF)
    assert dict(wire.REQUEST_LEAVES) == {
        leaf: served[0].namespaced for leaf, served in ops.BY_LEAF.items()}
    assert all(len({o.namespaced for o in served}) == 1 for served in ops.BY_LEAF.values())


@pytest.mark.parametrize("name", sorted(ops.OPS))
def test_encode_route_decode_round_trip(name: str) -> None:
    """The client's encoder, the server's routing and decoder give back the operation."""
    op = ops.OPS[name]
    k = wire.map_keys("m", "mcsm")
    payload = op.encode("rid-1", *ARGS[name])
    assert k.route(k.request(op.leaf)) == (op.leaf, "")
    got, req = ops.decode_request(op.leaf, payload, N)
    assert got is op and isinstance(req, op.request)
    assert req.request_id == "rid-1"
    if op.changes_state:
        assert op.topic in ops.INPUT_TOPICS.values() and ops.TOPIC_OPS[op.topic] == name
        assert (op.change is None) != (op.retract is None)  # applied to the map, or the window
        again = ops.decode_input(name, payload, N)
        assert ops.fingerprint(name, req) == ops.fingerprint(name, again)
        assert len(ops.fingerprint(name, req)) == 32
        assert op.answer is None
    else:
        assert op.answer is not None and op.topic is None
        with pytest.raises(McsmError):
            ops.decode_input(name, payload, N)


def test_fingerprints_tell_operations_and_requests_apart() -> None:
    u = ops.decode_input("update", wire.encode_update("a", "w", "r", good_samples(N)), N)
    u2 = ops.decode_input("update", wire.encode_update("b", "w", "r2", good_samples(N)), N)
    r = ops.decode_input("retract", wire.encode_retract("c", "u1"), N)
    assert ops.fingerprint("update", u) != ops.fingerprint("update", u2)
    assert ops.fingerprint("retract", r) != ops.fingerprint("reinstate", r)
    with pytest.raises(McsmError):
        ops.fingerprint("remove", u)  # not a remove request
    with pytest.raises(McsmError, match="cannot be recorded"):
        ops.decode_input("import", wire.encode_submap_export("e", "w"), N)


def test_namespaced_keys_are_the_tables() -> None:
    k = wire.map_keys("m", "mcsm")
    for op in ops.OPS.values():
        key = k.request(op.leaf, "robot1")
        if op.namespaced:
            assert k.route(key) == (op.leaf, "robot1")
        else:
            with pytest.raises(BadMessage, match="no wildcards"):
                k.route(key)
    upd = ops.decode_input("update", wire.encode_update("a", "robot2/base", "r",
                                                        good_samples(N)), N)
    with pytest.raises(Forbidden):
        ops.OPS["update"].check_namespace(upd, "robot1", "mcsm/m/update/robot1")
    ops.OPS["update"].check_namespace(upd, "robot2", "mcsm/m/update/robot2")


def test_schemas_and_keys_md_name_the_tables_operations() -> None:
    recorded = [o.name for o in ops.RECORDED]
    assert _schema("ack.json")["properties"]["op"]["enum"] == recorded
    # plus the one event that is no input: a standby taking over (mcsm.serve.replication)
    assert _schema("event.json")["properties"]["op"]["enum"] == [*recorded, TAKEOVER]
    keys_md = (Path(__file__).resolve().parents[2] / "schemas" / "KEYS.md").read_text()
    for op in ops.OPS.values():
        assert f"`<prefix>/<map>/{op.leaf}`" in keys_md
        if op.namespaced:
            assert f"`<prefix>/<map>/{op.leaf}/<ns>`" in keys_md
        if op.topic is not None:
            assert f"| `{op.topic}` | `record_input.json` |" in keys_md


def test_retract_events_validate_against_the_event_schema() -> None:
    from jsonschema import Draft202012Validator

    for name in ("retract", "reinstate"):
        ev = wire.Event("m", 3, name, name, (), None, 5, None, {"target": "u1", "changed": {}})
        Draft202012Validator(_schema("event.json")).validate(
            {**wire.message_dict(ev), "v": wire.VERSION})
