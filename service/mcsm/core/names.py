"""The one rule for frame names, shared by the core and the wire codec.

A frame name is 1-128 characters: one or more segments of ``[A-Za-z0-9_.:+-]`` joined by
``/`` (the ROS/tf convention, ``robot1/base_link``); no empty segment, so no leading, trailing
or doubled ``/``. The first segment of a name with a ``/`` is its *namespace*: a robot's
credentials let it write only frames of its own namespace (``schemas/KEYS.md``).
"""

from __future__ import annotations

import re

FRAME_RULE = ("a frame name of 1-128 characters: segments of [A-Za-z0-9_.:+-] "
              "joined by '/'")
_FRAME_RE = re.compile(r"[A-Za-z0-9_.:+-]+(?:/[A-Za-z0-9_.:+-]+)*")
MAX_FRAME_CHARS = 128


def is_frame_name(name: object) -> bool:
    """True if ``name`` is a ``str`` that follows :data:`FRAME_RULE`."""
    return (isinstance(name, str) and 0 < len(name) <= MAX_FRAME_CHARS
            and _FRAME_RE.fullmatch(name) is not None)


def namespace_of(name: str) -> str:
    """The namespace of a frame name (its first ``/`` segment), or ``""`` if it has none."""
    head, sep, _ = name.partition("/")
    return head if sep else ""


__all__ = ["FRAME_RULE", "MAX_FRAME_CHARS", "is_frame_name", "namespace_of"]
