"""File input/output: images, trajectories, PLY, atomic writes."""
