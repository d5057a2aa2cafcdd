"""Joint geometric + photometric ICP: kernel vs numerical reference, pyramid helpers, recovery where geometric
ICP is degenerate, brightness changes, and the auto / on / off switches of the tracker and ``register``."""

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.errors import ConfigError
from surfelslam.geometry import se3
from surfelslam.kernels import icp as kicp
from surfelslam.kernels import photometric as kph
from surfelslam.kernels.threads import set_parallel
from surfelslam.slam import DenseSlam, HybridSlam, SlamConfig
from surfelslam.slam.config import TrackingConfig
from surfelslam.synth import make_scene, render
from surfelslam.synth.trajectories import look_at
from surfelslam.tracking.icp import ICPConfig, icp, photometric_term
from surfelslam.tracking.photometric import IntensityPyramid, PhotometricTerm, intensity_from_rgb, intensity_pyramid
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.types import Intrinsics

from helpers import INTR


def test_intensity_in_one_pass_is_the_numpy_form_bit_for_bit():
    """The one-pass kernel gives the numpy form's float32 values bit for bit (every level of one channel against a
    grid of the other two, and random images), NaN exactly where the mask is False; other inputs take the numpy
    form."""
    x = np.arange(256, dtype=np.uint8)
    grid = np.stack(np.meshgrid(x, x, indexing="ij"), -1)
    for k in (0, 1, 77, 128, 254, 255):
        for order in ([0, 1, 2], [2, 0, 1], [1, 2, 0]):
            rgb = np.concatenate([grid, np.full((256, 256, 1), k, np.uint8)], -1)[:, :, order]
            assert np.array_equal(intensity_from_rgb(rgb), kph.intensity_from_rgb(rgb))
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    valid = rng.random((48, 64)) > 0.4
    expected = kph.intensity_from_rgb(rgb)
    expected[~valid] = np.nan
    got = intensity_from_rgb(rgb[:, ::-1], valid[:, ::-1])  # strided views are taken too
    assert got.dtype == np.float32 and np.array_equal(got, expected[:, ::-1], equal_nan=True)
    assert np.count_nonzero(np.isnan(got)) == np.count_nonzero(~valid) > 0
    as_float = rgb.astype(np.float32)  # not uint8: the numpy form
    assert np.array_equal(intensity_from_rgb(as_float, valid), expected, equal_nan=True)


def _slanted_textured_plane(fy: float = 70.0):
    """A slanted plane seen by a 80x60 camera, with a smooth texture, its vertex map and intensity."""
    H, W, fx, cx, cy = 60, 80, 70.0, 39.5, 29.5
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = 1.0 + 0.002 * u + 0.001 * v
    X = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1).astype(np.float32)
    img = (0.5 + 0.2 * np.sin(u / 3.0) * np.cos(v / 4.0)).astype(np.float32)
    return X, img, (fx, fy, cx, cy)


@pytest.mark.parametrize("fy", [70.0, -70.0])
def test_photometric_kernel_matches_numerical_reference(fy):
    """Normal equations of the intensity residuals equal those from the numerically differentiated projection
    (negative fy included); invalid target pixels, occluded points and the brightness offset are handled alike."""
    X, img, (fx, fy, cx, cy) = _slanted_textured_plane(fy)
    rng = np.random.default_rng(0)
    src_int = img + 0.03 * rng.standard_normal(img.shape).astype(np.float32)
    src_int[5, :] = np.nan  # an invalid source row
    tgt_int = img.copy()
    tgt_int[20:24, 30:35] = np.nan  # a hole in the target (e.g. unrendered)
    tgt_vertex = X.copy()
    tgt_vertex[40:, :, 2] += 0.5  # the lower part of the target is far behind: occlusion gate
    igg = kph.pack_target(tgt_int)
    T = se3.exp(np.array([0.01, -0.02, 0.005, 0.01, 0.005, -0.01]))
    for stride in (1, 2):
        out = np.zeros(kicp.N_STATS)
        out[28:] = [1.0, 2.0, 3.0, 4.0, 5.0]  # the geometric counters must stay untouched
        aux = np.zeros(kph.N_AUX)
        kph.accumulate_photometric(X, src_int, tgt_vertex, igg, T, fx, fy, cx, cy, 0.1, 0.02, 2.0, 0.7, 0.01, out, aux,
                                   stride)
        J, e, h = kph.photometric_system_ref(X, src_int, tgt_vertex, igg, T, fx, fy, cx, cy, 0.1, 0.02, 2.0, 0.01,
                                             stride)
        assert 100 < len(e) < X[::stride, ::stride, 0].size * 0.8  # pairs dropped by the gates
        assert 0 < h.min() < 1  # some residuals Huber-weighted
        H = 0.7 * (J * h[:, None]).T @ J
        g = 0.7 * (J * h[:, None]).T @ e
        Hk, gk = kicp.unpack_normal_equations(out)
        np.testing.assert_allclose(Hk, H, rtol=1e-7, atol=1e-7 * np.abs(H).max())
        np.testing.assert_allclose(gk, g, rtol=1e-7, atol=1e-7 * np.abs(g).max())
        assert out[27] == pytest.approx(0.7 * float(np.sum(h * e * e)), rel=1e-9)
        assert list(out[28:]) == [1.0, 2.0, 3.0, 4.0, 5.0]
        assert aux[2] == len(e) and aux[0] == pytest.approx(h.sum())
        assert aux[1] / aux[0] == pytest.approx(float(np.sum(h * (e * 0.02 + 0.01)) / h.sum()), rel=1e-6)


@pytest.mark.heavy  # make test-all: compiles the parallel twin, which only compute.parallel_kernels uses
def test_photometric_kernel_parallel_twin_is_bit_identical():
    X, img, (fx, fy, cx, cy) = _slanted_textured_plane()
    igg = kph.pack_target(img)
    T = se3.exp(np.array([0.01, -0.02, 0.005, 0.01, 0.005, -0.01]))
    outs = []
    for parallel in (False, True):
        set_parallel(parallel)
        try:
            out, aux = np.zeros(kicp.N_STATS), np.zeros(kph.N_AUX)
            kph.accumulate_photometric(X, img, X, igg, T, fx, fy, cx, cy, 0.1, 0.02, 2.0, 1.0, 0.0, out, aux, 1)
            outs.append(np.concatenate([out, aux]))
        finally:
            set_parallel(False)
    np.testing.assert_array_equal(outs[0], outs[1])


def test_intensity_pyramid_helpers_match_numpy_references():
    rng = np.random.default_rng(1)
    img = rng.random((41, 57)).astype(np.float32)
    img[rng.random(img.shape) < 0.2] = np.nan
    half = kph.halve_intensity(img)
    ref = kph.halve_intensity_ref(img)
    assert half.shape == (20, 28)
    np.testing.assert_array_equal(np.isnan(half), np.isnan(ref))
    np.testing.assert_allclose(half[~np.isnan(half)], ref[~np.isnan(ref)], rtol=1e-6)
    for got, want in zip(kph.gradients(img), kph.gradients_ref(img), strict=True):
        np.testing.assert_array_equal(got, want)
    packed = kph.pack_target(img)
    np.testing.assert_array_equal(packed[..., 0], img)
    np.testing.assert_array_equal(packed[..., 1], kph.gradients_ref(img)[0])
    np.testing.assert_array_equal(packed[..., 2], kph.gradients_ref(img)[1])
    # a linear ramp: central differences give its slope exactly (NaN on the border)
    ramp = np.tile(0.01 * np.arange(10, dtype=np.float32), (6, 1))
    gx, gy = kph.gradients(ramp)
    np.testing.assert_allclose(gx[:, 1:-1], 0.01, rtol=1e-5)
    assert np.isnan(gx[:, 0]).all() and np.isnan(gy[0]).all() and np.all(gy[1:-1] == 0)
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[0, 0] = 255
    rgb[1, 1] = (255, 0, 0)
    np.testing.assert_allclose(intensity_from_rgb(rgb), [[1.0, 0.0], [0.0, 0.299]], atol=1e-6)
    pyr = intensity_pyramid(img, 3, gradients=True)
    assert [p.shape for p in pyr.intensity] == [(41, 57), (20, 28), (10, 14)] and len(pyr.packed) == 3


def _plane_pair(T_t_s, brightness: float = 0.0):
    scene = make_scene("plane")
    T_w_t = look_at(np.array([1.5, 0.0, 1.5]), np.array([0.0, 0.1, 1.4]))[0]
    rt = render(scene, T_w_t, INTR)
    rs = render(scene, T_w_t @ T_t_s, INTR)
    pre = Preprocessor(INTR, PreprocessConfig())
    i_t = intensity_pyramid(intensity_from_rgb(rt.rgb, rt.depth_m > 0), 4, gradients=True)
    i_s = intensity_pyramid(np.clip(intensity_from_rgb(rs.rgb) + brightness, 0, 1), 4, gradients=False)
    return pre.process(rs.depth_m.copy()), pre.process(rt.depth_m.copy()), i_s, i_t


@pytest.mark.parametrize("brightness", [0.0, 0.08])
def test_photometric_term_makes_a_textured_plane_trackable(brightness):
    """A single plane leaves 3 DoF free: geometric ICP reports it degenerate; with the intensity term the motion
    is recovered to under a millimetre, also when the source is brighter (auto-exposure: the offset is estimated)."""
    T_t_s = se3.exp(np.concatenate([np.radians([0.0, 0.0, 2.0]), [0.0, 0.03, 0.0]]))
    p_s, p_t, i_s, i_t = _plane_pair(T_t_s, brightness)
    cfg = ICPConfig()
    geometric = icp(p_s, p_t, cfg=cfg)
    assert geometric.degenerate
    term = photometric_term(i_s, i_t, cfg)
    res = icp(p_s, p_t, cfg=cfg, photometric=term)
    t_err, r_err = se3.pose_error(res.T_target_source, T_t_s)
    assert res.converged and not res.degenerate, res.reason
    assert t_err < 1e-3 and r_err < 0.05, (t_err, r_err)
    assert term.pairs > 1000 and term.offset == pytest.approx(-brightness, abs=0.01)
    assert se3.pose_error(geometric.T_target_source, T_t_s)[0] > 10 * t_err
    if brightness:  # without the offset the brightness change biases the pose
        fixed = photometric_term(i_s, i_t, replace(cfg, photometric_brightness_offset=False))
        biased = icp(p_s, p_t, cfg=cfg, photometric=fixed)
        assert se3.pose_error(biased.T_target_source, T_t_s)[0] > 2 * t_err


def test_photometric_settings_and_switches():
    for bad in ({"photometric_weight": -1.0}, {"photometric_sigma": 0.0}, {"photometric_huber": -2.0}):
        with pytest.raises(ConfigError, match="photometric"):
            ICPConfig(**bad)
    with pytest.raises(ConfigError, match="photometric"):
        TrackingConfig(photometric="yes")
    pyr = IntensityPyramid([np.zeros((4, 4), np.float32)])
    with pytest.raises(ConfigError, match="gradients"):
        PhotometricTerm(pyr, pyr, 0.02, 2.0, 0.1)
    on_cfg = SlamConfig(tracking=TrackingConfig(photometric="on"))
    off_cfg = SlamConfig(tracking=TrackingConfig(photometric="off"))
    zero_w = SlamConfig(icp=ICPConfig(photometric_weight=0.0))
    assert DenseSlam(INTR, SlamConfig()).photometric  # auto, colour registered
    assert not DenseSlam(INTR, SlamConfig(), colour_registered=False).photometric  # auto, 7-Scenes
    assert DenseSlam(INTR, on_cfg, colour_registered=False).photometric
    assert not DenseSlam(INTR, off_cfg).photometric and not DenseSlam(INTR, zero_w).photometric
    assert HybridSlam(INTR, SlamConfig()).photometric
    assert not HybridSlam(INTR, SlamConfig(), colour_registered=False).photometric
    # metrics.json says which it was
    assert DenseSlam(INTR, on_cfg).finish().metrics["photometric"] is True
    assert DenseSlam(INTR, off_cfg).finish().metrics["photometric"] is False


def test_source_intensity_is_on_the_tracking_levels_grid():
    """640x480 input is tracked at its 320x240 level: the intensity pyramid has the tracking pyramid's shapes, and
    a frame prepared ahead gives the same pyramid as one prepared in ``process``."""
    from surfelslam.slam.frontend import DenseFrontEnd
    from surfelslam.types import RGBDFrame

    big = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    slam = DenseFrontEnd(big, SlamConfig())
    rng = np.random.default_rng(0)
    frame = RGBDFrame(0, 0.0, rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), np.ones((480, 640), np.float32))
    pyr = slam.source_intensity(frame)
    want = [(k.height, k.width) for k in slam.mapper.pre.level_intrinsics[slam.track_level:]][: slam.cfg.icp.levels]
    assert slam.track_level == 1 and [p.shape for p in pyr.intensity] == want
    # level 0 is the 2x2 block mean of the full-resolution intensity
    full = intensity_from_rgb(frame.rgb)
    np.testing.assert_allclose(pyr.intensity[0], full.reshape(240, 2, 320, 2).mean(axis=(1, 3)), rtol=1e-5)
    prepared = slam.prepare(frame)
    np.testing.assert_array_equal(prepared.intensity.intensity[1], pyr.intensity[1])
