"""The reference pass of a robot capture: the same cameras over the empty workspace (issue 43, ``reference`` mode).

A real robot flies its capture path once before the objects are placed; in simulation the same world is rendered
with the objects hidden. :func:`objects_hidden` moves every object's visual geoms into geom group
:data:`HIDDEN_GROUP`, which neither the MuJoCo rig (:mod:`sim.cameras.rig`, groups 0, 2, 4) nor the PBR scene builder
(:data:`sim.render.scene.RENDERED_GROUPS`) renders, and restores them on exit (also on an exception). Physics is
untouched: the objects stay where they are, only their appearance is removed.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

#: a geom group no renderer draws
HIDDEN_GROUP = 5


@contextmanager
def objects_hidden(world: Any) -> Iterator[Any]:
    """Within the block, ``world``'s objects (``world.objects[*].visual_geom_ids``) are invisible to every renderer."""
    ids = np.array(sorted({int(g) for o in world.objects for g in o.visual_geom_ids}), dtype=int)
    saved = np.asarray(world.model.geom_group[ids]).copy()
    try:
        world.model.geom_group[ids] = HIDDEN_GROUP
        yield world
    finally:
        world.model.geom_group[ids] = saved
