"""Robot folder lg90_gripper (MJCF / robot.yaml, README.md with provenance); a package only so its files ship."""
