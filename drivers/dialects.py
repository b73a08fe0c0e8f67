"""The K-Team serial dialects by name: ``[buses.kteam] dialect`` and ``[real] kteam_dialect``.

- ``koala1``: the classic Koala / Koala II (:data:`koala_bridge.drivers.kteam.KOALA1`).
- ``koala25``: the Koala 2.5 (:data:`koala_bridge.drivers.koala25.KOALA25`).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from koala_bridge.drivers.koala25 import KOALA25
from koala_bridge.drivers.kteam import KOALA1, Dialect

__all__ = ["DIALECTS", "dialect"]

DIALECTS: Mapping[str, Dialect] = MappingProxyType({"koala1": KOALA1, "koala25": KOALA25})


def dialect(name: str) -> Dialect:
    """The dialect called ``name`` (the classic Koala's with other ranges, ``[buses.kteam]
    max_speed`` and the IR count: :func:`~koala_bridge.drivers.kteam.command_specs`).

    Raises:
        ValueError: ``name`` is not one of :data:`DIALECTS`.
    """
    if name not in DIALECTS:
        raise ValueError(f"unknown K-Team dialect {name!r} (one of {', '.join(DIALECTS)})")
    return DIALECTS[name]
