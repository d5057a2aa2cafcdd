"""The reference page's old import path: :mod:`surfelslam.settings.reference`."""

from surfelslam.settings.reference import reference_markdown

__all__ = ["reference_markdown"]
