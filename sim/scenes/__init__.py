"""Scenes: the glass object library, scenario suites (YAML) and seeded object placement.

- :mod:`sim.scenes.meshes`: procedural watertight meshes (trimesh).
- :mod:`sim.scenes.objects`: the object library (``list_objects``, ``get_object``), mass and collision hulls.
- :mod:`sim.scenes.hulls`: cached CoACD convex decomposition (``hull_cache/`` ships with the repo).
- :mod:`sim.scenes.scenario`: scenario specs from ``suites/*.yaml`` (``list_scenarios``, ``get_scenario``).
- :mod:`sim.scenes.placement`: seeded, gap-constrained x/y/yaw sampling (``place_objects``).

The MuJoCo world itself is built by :func:`sim.world.build_world`.
"""
