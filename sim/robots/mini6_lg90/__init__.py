"""Robot folder mini6_lg90 (MJCF / robot.yaml, README.md with provenance); a package only so its files ship."""
