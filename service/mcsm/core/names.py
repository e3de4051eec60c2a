"""The one rule for frame names, shared by the core and the wire codec.

A frame name is 1-128 characters: one or more segments of ``[A-Za-z0-9_.:+-]`` joined by
``/`` (the ROS/tf convention, ``robot1/base_link``); no empty segment, so no leading, trailing
or doubled ``/``. The first segment of a name with a ``/`` is its *namespace*: a robot's
credentials let it write only frames of its own namespace (``schemas/KEYS.md``).
"""

from __future__ import annotations

import re
from typing import TypeGuard

_SEGMENT = r"[A-Za-z0-9_.:+-]"
FRAME_RULE = f"a frame name of 1-128 characters: segments of {_SEGMENT} joined by '/'"
NAMESPACE_RULE = f"one frame-name segment of {_SEGMENT}"
_FRAME_RE = re.compile(rf"{_SEGMENT}+(?:/{_SEGMENT}+)*")
_NAMESPACE_RE = re.compile(rf"{_SEGMENT}+")
MAX_FRAME_CHARS = 128


def is_frame_name(name: object) -> TypeGuard[str]:
    """True if ``name`` is a ``str`` that follows :data:`FRAME_RULE`."""
    return (isinstance(name, str) and 0 < len(name) <= MAX_FRAME_CHARS
            and _FRAME_RE.fullmatch(name) is not None)


def is_namespace(name: object) -> TypeGuard[str]:
    """True if ``name`` is one segment of a frame name (``robot1``): a namespace."""
    return (isinstance(name, str) and 0 < len(name) <= MAX_FRAME_CHARS
            and _NAMESPACE_RE.fullmatch(name) is not None)


def namespace_of(name: str) -> str:
    """The namespace of a frame name (its first ``/`` segment), or ``""`` if it has none."""
    head, sep, _ = name.partition("/")
    return head if sep else ""


__all__ = ["FRAME_RULE", "NAMESPACE_RULE", "MAX_FRAME_CHARS", "is_frame_name", "is_namespace",
           "namespace_of"]
