"""Routing of request keys on the server's one queryable per map, and namespace names."""

from __future__ import annotations

import pytest
from mcsm import wire
from mcsm.errors import BadMessage


def test_route_accepts_concrete_request_keys_only() -> None:
    k = wire.map_keys("m", "fleet/a")
    assert k.all == "fleet/a/m/**"
    good = {
        "fleet/a/m/update": ("update", ""), "fleet/a/m/update/robot1": ("update", "robot1"),
        "fleet/a/m/remove": ("remove", ""), "fleet/a/m/remove/r.2:x": ("remove", "r.2:x"),
        "fleet/a/m/query": ("query", ""), "fleet/a/m/info": ("info", ""),
        "fleet/a/m/submap": ("submap", ""),
    }
    for key, want in good.items():
        assert k.route(key) == want
    assert k.update_as("robot1") == "fleet/a/m/update/robot1"
    assert k.remove_as("robot1") == "fleet/a/m/remove/robot1"
    bad = ["fleet/a/m/*", "fleet/a/m/**", "fleet/a/m/up$*", "fleet/a/m/update/*",
           "fleet/a/m/update/robot1/x", "fleet/a/m/query/x", "fleet/a/m/events",
           "fleet/a/m/alive/abc", "fleet/a/*/update", "fleet/a/other/update", "fleet/a/m",
           "fleet/a/m/update/", "fleet/a/m/update/$*"]
    for key in bad:
        with pytest.raises(BadMessage, match="no wildcards"):
            k.route(key)
    for ns in ("", "a/b", "*", "a b", "x" * 129):
        with pytest.raises(BadMessage):
            k.update_as(ns)
