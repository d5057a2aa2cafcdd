"""The pre-run check that colour taken as registered lines up with depth."""

from dataclasses import dataclass, field, replace

import numpy as np
import pytest

import surfelslam as ss
from surfelslam.datasets.base import DatasetOptions
from surfelslam.geometry.camera import ColourRegistrationConfig
from surfelslam.geometry.colour_fit import ColourFit, fit_says_unregistered
from surfelslam.slam.colour_check import check_colour_registration
from surfelslam.synth.scenes import make_scene
from surfelslam.synth.trajectories import make_trajectory
from surfelslam.synth.writer import default_intrinsics, iter_frames, noise_config
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame


@dataclass
class _Frames:
    """A sequence-like list of frames with a layout."""

    frames: list
    intrinsics: Intrinsics
    layout: str = "tum"
    colour_registered: bool = True
    options: DatasetOptions = field(default_factory=DatasetOptions)
    colour_camera: ColourCamera | None = None

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> RGBDFrame:
        return self.frames[i]


@pytest.fixture(scope="module")
def office():
    intr = default_intrinsics(160, 120)
    scene = make_scene("office")
    return list(iter_frames(scene, make_trajectory("slow", 4, scene), intr, noise_config("none"))), intr


def test_shifted_colour_is_found_out_and_aligned_colour_is_not(office):
    frames, intr = office
    cfg = ColourRegistrationConfig()
    aligned = check_colour_registration(_Frames(frames, intr), cfg)
    assert aligned is not None and aligned["registered"] and aligned["frames"] == 4
    # colour from a camera 5 px to the side: as from a second, uncalibrated camera
    shifted = []
    for f in frames:
        rgb = np.roll(f.rgb, 5, axis=1)
        shifted.append(replace(f, rgb=rgb))
    moved = check_colour_registration(_Frames(shifted, intr), cfg)
    assert moved is not None and not moved["registered"]
    assert moved["edge_distance_same_pixel_px"] > 1.5 * moved["edge_distance_fitted_px"]
    # not checked: layouts with their own camera model or generated ones, sequences already unregistered, or off
    assert check_colour_registration(_Frames(shifted, intr, layout="synthetic"), cfg) is None
    assert check_colour_registration(_Frames(shifted, intr, colour_registered=False), cfg) is None
    assert check_colour_registration(_Frames(shifted, intr), replace(cfg, check=False)) is None


def test_the_api_session_for_a_sequence_runs_the_check(office):
    """``Slam.from_sequence`` sets colour up as ``surfelslam run`` does: colour that does not line up with depth
    turns the hybrid's joint feature term off, and the run's metrics say why."""
    frames, intr = office
    shifted = _Frames([replace(f, rgb=np.roll(f.rgb, 5, axis=1)) for f in frames], intr)
    for seq, registered in ((_Frames(frames, intr), True), (shifted, False)):
        slam = ss.Slam.from_sequence(seq, tracker="hybrid", warmup=False)
        assert slam.colour_check["registered"] is registered
        for f in seq.frames:
            slam.track(f)
        run = slam.finish()
        assert run.metrics["joint_features"] is registered
        assert run.metrics["colour_check"] == slam.colour_check


def test_the_gain_bound_scales_with_the_image_width():
    fit = ColourFit(ColourCamera(Intrinsics(500, 500, 320, 240, 640, 480), (0.0, 0.0, 0.0)), 1.2, 2.0, 6, 1000)
    assert not fit_says_unregistered(fit, 640, 1.0, 0.35)  # 0.8 px gained: under 1 px at 640 wide
    assert fit_says_unregistered(fit, 320, 1.0, 0.35)  # over 0.5 px at 320 wide, and 40 % of 2.0
    assert not fit_says_unregistered(fit, 320, 1.0, 0.5)  # but not half of it
