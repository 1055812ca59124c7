"""Robot folder mini6_arm (MJCF / robot.yaml, README.md with provenance); a package only so its files ship."""
