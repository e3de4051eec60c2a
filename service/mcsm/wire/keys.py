"""The key space of one map: ``<prefix>/<map>/<leaf>[/<namespace>]`` (``schemas/KEYS.md``).

:class:`Keys` names every key expression of a map; :func:`map_keys` checks a map's name and
prefix; :data:`REQUEST_LEAVES` lists the request leaves the server answers (and which take a
namespace), as plain data: :func:`route` turns a concrete request key into its leaf and
namespace with it. The table of operations (:mod:`mcsm.map.ops`) is checked against it; this
package knows no operation table.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

from mcsm.core.names import NAMESPACE_RULE, is_namespace
from mcsm.errors import BadMessage
from mcsm.wire.checks import short

DEFAULT_PREFIX = "mcsm"
DEFAULT_MAP = "default"

REQUEST_LEAVES: Mapping[str, bool] = {
    "update": True, "remove": True, "submap": False, "retract": False, "reinstate": False,
    "relinearize": False, "verdict": False, "query": False, "info": False}
"""Every request leaf the server answers, in the table's order, and whether it is also served
on ``<leaf>/<namespace>`` (writes only that namespace's frames). Plain data, so that routing
needs no table of operations; ``tests/wire/test_ops.py`` checks that the table
(:mod:`mcsm.map.ops`) serves exactly these."""

_MAP_RE = re.compile(r"[A-Za-z0-9_.+-]{1,64}")
_PREFIX_RE = re.compile(r"[A-Za-z0-9_.+-]{1,64}(/[A-Za-z0-9_.+-]{1,64}){0,7}")


# --------------------------------------------------------------------------------------------
# Key expressions
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Keys:
    """The key expressions of one map (``<prefix>/<map>/...``); see ``schemas/KEYS.md``.

    ``update`` and ``remove`` write any frame; ``update_as(ns)`` and ``remove_as(ns)``
    (``.../update/<ns>``) write only frames of namespace ``ns``: the shipped access-control
    lists grant a robot's identity its own namespace's keys alone (``deploy/``).
    """

    prefix: str
    map: str

    def _k(self, leaf: str) -> str:
        return f"{self.prefix}/{self.map}/{leaf}"

    @property
    def base(self) -> str:
        """``<prefix>/<map>``: every key of the map is under it."""
        return f"{self.prefix}/{self.map}"

    @property
    def all(self) -> str:
        """``<prefix>/<map>/**``: the server's one queryable (one arrival order per map)."""
        return self._k("**")

    @property
    def update(self) -> str:
        return self._k("update")

    @property
    def remove(self) -> str:
        return self._k("remove")

    def update_as(self, namespace: str) -> str:
        """Update key restricted to frames ``a`` in ``namespace`` (checked by the server)."""
        return self._k(f"update/{check_namespace(namespace)}")

    def remove_as(self, namespace: str) -> str:
        """Remove key restricted to frames in ``namespace`` (checked by the server)."""
        return self._k(f"remove/{check_namespace(namespace)}")

    @property
    def query(self) -> str:
        return self._k("query")

    @property
    def info(self) -> str:
        return self._k("info")

    @property
    def submap(self) -> str:
        return self._k("submap")

    @property
    def retract(self) -> str:
        return self._k("retract")

    @property
    def reinstate(self) -> str:
        return self._k("reinstate")

    @property
    def verdict(self) -> str:
        return self._k("verdict")

    @property
    def relinearize(self) -> str:
        return self._k("relinearize")

    @property
    def events(self) -> str:
        return self._k("events")

    def alive(self, server_id: str) -> str:
        """Liveliness token of one live server serving this map."""
        return self._k(f"alive/{server_id}")

    @property
    def alive_any(self) -> str:
        return self._k("alive/*")

    def request(self, leaf: str, namespace: str = "") -> str:
        """The request key of operation leaf ``leaf`` (see :mod:`mcsm.map.ops`), restricted to
        ``namespace`` if given (``.../update/robot1``)."""
        return self._k(f"{leaf}/{check_namespace(namespace)}" if namespace else leaf)

    # No replication keys: standbys follow the map's log in NATS JetStream
    # (:mod:`mcsm.serve.replication`), never through Zenoh.

    def route(self, key: str) -> tuple[str, str]:
        """``(leaf, namespace)`` of a concrete request key of this map (:func:`route`).

        Raises
        ------
        BadMessage
            If ``key`` is not one of the map's request keys (wildcards included).
        """
        return route(self, key)


def check_namespace(namespace: str) -> str:
    """Return ``namespace`` if it is a valid frame-name segment (``robot1``), else raise."""
    if not is_namespace(namespace):
        raise BadMessage("namespace", NAMESPACE_RULE,
                         short(namespace))
    return namespace


def map_keys(map_name: str = DEFAULT_MAP, prefix: str = DEFAULT_PREFIX) -> Keys:
    """Key expressions of map ``map_name`` under ``prefix``; checks both names.

    Raises
    ------
    BadMessage
        If the map name is not 1-64 characters from ``[A-Za-z0-9_.+-]`` or the prefix is not
        1-8 such segments joined by ``/``.
    """
    if not isinstance(map_name, str) or not _MAP_RE.fullmatch(map_name):
        raise BadMessage("map", "a map name of 1-64 characters from [A-Za-z0-9_.+-]",
                         short(map_name))
    if not isinstance(prefix, str) or not _PREFIX_RE.fullmatch(prefix):
        raise BadMessage("prefix", "1-8 segments of [A-Za-z0-9_.+-] joined by '/'",
                         short(prefix))
    return Keys(prefix=prefix, map=map_name)


def route(keys: Keys, key: str) -> tuple[str, str]:
    """``(leaf, namespace)`` of a concrete request key of the map ``keys``: ``("update",
    "robot1")`` for ``.../update/robot1``, ``("info", "")`` for ``.../info``.

    Raises
    ------
    BadMessage
        If ``key`` is not one of the map's request keys (wildcards included: a request must
        name one concrete key).
    """
    head = keys.base + "/"
    rest = key[len(head):] if key.startswith(head) else ""
    leaf, sep, ns = rest.partition("/")
    namespaced = REQUEST_LEAVES.get(leaf)
    if namespaced is not None:
        if not sep:
            return leaf, ""
        if namespaced and is_namespace(ns):
            return leaf, ns
    plain = [lf for lf, spaced in REQUEST_LEAVES.items() if not spaced]
    spaced = [lf for lf, spaced in REQUEST_LEAVES.items() if spaced]
    raise BadMessage("key", f"one of {keys.base}/{{{','.join(spaced)}}}[/<namespace>], "
                     f"{', '.join(plain)} (no wildcards)", short(key))
