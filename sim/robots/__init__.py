"""Simulated robot models: one folder per robot (MJCF, scene.xml, README with provenance, robot.yaml)."""
