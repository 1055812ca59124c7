"""Robot folder inovo_arm (MJCF, scene.xml, README.md with provenance); a package only so its files ship."""
