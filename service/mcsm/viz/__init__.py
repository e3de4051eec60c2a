"""Pictures of a map: ``mcsm plot`` (matplotlib PNG) and ``mcsm export foxglove`` (an MCAP scene
for Foxglove and Lichtblick); the live ``mcsm view`` is the client package's
(:mod:`mcsm_client.view`) and uses :mod:`mcsm.viz.foxglove_scene`.

:mod:`mcsm.viz.ellipse` (the one 95 % region), :mod:`mcsm.viz.layout` (paths, colours,
component shifts) and :mod:`mcsm.viz.scene` need numpy only. matplotlib and ``foxglove-sdk``
come with the optional extra ``viz`` (``pip install 'mcsm[viz]'``) and are imported only inside
the commands that need them, never by ``import mcsm`` or ``import mcsm.viz``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from mcsm.errors import McsmError

EXTRA = "viz"


class MissingExtra(McsmError):
    """An optional dependency of a picture command is not installed."""

    def __init__(self, module: str, extra: str = EXTRA) -> None:
        super().__init__(f"{module} is not installed; install the extra: "
                         f"pip install 'mcsm[{extra}]'", module=module, extra=extra)


def require(module: str) -> ModuleType:
    """Import ``module`` or raise :class:`MissingExtra` naming the ``viz`` extra."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtra(module.split(".")[0]) from None
