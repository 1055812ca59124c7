"""Scenes: the glass object library, scenario suites (YAML) and seeded object placement.

- :mod:`sim.scenes.meshes`: procedural watertight meshes (trimesh).
- :mod:`sim.scenes.objects`: the object library (``list_objects``, ``get_object``): the paper's objects and lab
  glassware (``GLASSWARE``), substances (density, refractive index), mass and collision hulls.
- :mod:`sim.scenes.hulls`: cached CoACD convex decomposition (``hull_cache/`` ships with the repo) and the
  cavity check of the hulls (``cavity_open_fraction``).
- :mod:`sim.scenes.fixtures`: opaque static fixtures (test-tube rack, tray) that hold glassware.
- :mod:`sim.scenes.scenario`: scenario specs from ``suites/*.yaml`` (``list_scenarios``, ``get_scenario``).
- :mod:`sim.scenes.placement`: seeded, gap-constrained x/y/yaw sampling (``place_objects``, ``place_scene`` with
  the fixture's pose).

The MuJoCo world itself is built by :func:`sim.world.build_world`.
"""
