"""Migrations of older ``.cara`` schema versions to the current one (in memory, on read).

Each migration takes a :class:`~carapost.io.cara_read.CaraDoc` of version ``v`` and patches it
into version ``next``; :func:`migrate` chains them up to :data:`CARA_VERSION`. The file itself is
never modified: saving the loaded take writes the current version.

Version history (also in ``docs/formats/cara.md``):

* **0.9** — ``/tracks/obs_xy`` stored as float64; no ``/tracks/obs_q`` (target-track quality)
  and no ``/tracks/xyz_stabilized``.
* **1.0** — ``obs_xy`` float32; ``obs_q`` and ``xyz_stabilized`` added.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .cara_read import CaraDoc
from .cara_schema import CARA_VERSION

__all__ = ["MIGRATIONS", "migrate", "oldest_readable"]

Version = tuple[int, int]
Migration = Callable[[CaraDoc], list[str]]


def _migrate_0_9(doc: CaraDoc) -> list[str]:
    """0.9 -> 1.0: float32 observations, empty target-track quality and stabilized positions."""
    messages = []
    obs = doc.array("tracks/obs_xy")
    if obs.ndim != 4 or obs.shape[-1] != 2:
        raise doc.error(f"dataset '/tracks/obs_xy' has shape {obs.shape}, expected (frames, points, cameras, 2)")
    F, P, C = obs.shape[:3]
    if obs.dtype != np.float32:
        doc.put("tracks/obs_xy", obs.astype(np.float32))
        messages.append("2D observations converted from float64 to float32")
    added = []
    if not doc.has("tracks/obs_q"):
        doc.put("tracks/obs_q", np.full((F, P, C), np.nan, np.float32))
        added.append("target-track quality")
    if not doc.has("tracks/xyz_stabilized"):
        doc.put("tracks/xyz_stabilized", np.full((F, P, 3), np.nan, np.float64))
        added.append("stabilized positions")
    if added:
        messages.append(f"{' and '.join(added)} added (empty)")
    return messages


#: ``from_version: (to_version, migration)``.
MIGRATIONS: dict[Version, tuple[Version, Migration]] = {
    (0, 9): ((1, 0), _migrate_0_9),
}


def oldest_readable() -> Version:
    return min(MIGRATIONS) if MIGRATIONS else CARA_VERSION


def migrate(doc: CaraDoc, version: Version) -> list[str]:
    """Patch ``doc`` from ``version`` up to the current version.

    Returns
    -------
    list of str
        One message per migration step, naming what changed.

    Raises
    ------
    CaraError
        If ``version`` is older than the current one and no migration starts from it.
    """
    messages: list[str] = []
    v = version
    while v < CARA_VERSION:
        if v not in MIGRATIONS:
            if v[0] == CARA_VERSION[0]:
                break  # an older minor version of this major: readable as it is
            lo = oldest_readable()
            raise doc.error(f"format {v[0]}.{v[1]} is too old to read: this version migrates files from "
                            f"format {lo[0]}.{lo[1]} on")
        nxt, fn = MIGRATIONS[v]
        steps = fn(doc)
        messages.append(f"{doc.path.name}: migrated from format {v[0]}.{v[1]} to {nxt[0]}.{nxt[1]}"
                        + (f": {'; '.join(steps)}" if steps else ""))
        v = nxt
    return messages
