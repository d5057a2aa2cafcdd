"""Rigid-body geometry (SE(3)) and pinhole camera projection."""
