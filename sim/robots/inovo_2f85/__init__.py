"""Robot folder inovo_2f85 (MJCF, scene.xml, README.md with provenance); a package only so its files ship."""
