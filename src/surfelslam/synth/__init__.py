"""Synthetic RGB-D data with exact ground truth: textured indoor scenes, ray casting, trajectories, noise.

Main entry points: :func:`make_scene`, :func:`make_trajectory`, :func:`render`,
:func:`surfelslam.synth.writer.iter_frames` and :func:`surfelslam.synth.writer.generate_sequence`.
"""

from surfelslam.synth.render import RenderOutput, render
from surfelslam.synth.scenes import SCENES, Scene, make_scene
from surfelslam.synth.trajectories import STYLES, make_trajectory

__all__ = ["SCENES", "STYLES", "RenderOutput", "Scene", "make_scene", "make_trajectory", "render"]
