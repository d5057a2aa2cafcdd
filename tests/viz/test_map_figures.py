"""Map figures: the disc splatting kernel against brute force, the top view's coverage, the written PNGs."""

from __future__ import annotations

import re

import numpy as np
import pytest
from matplotlib.image import imread

from surfelslam.kernels.splat import splat_discs, splat_discs_ref
from surfelslam.viz import map_figures as mf


def _splat(args, shape):
    depth = np.full(shape, np.inf)
    index = np.full(shape, -1, np.int32)
    splat_discs(*args, depth, index)
    return depth, index


def test_splat_matches_brute_force_reference():
    rng = np.random.default_rng(3)
    n, shape = 60, (32, 48)
    args = (rng.uniform(-4, 52, n), rng.uniform(-4, 36, n), rng.uniform(1, 3, n), rng.uniform(0.2, 6, n),
            rng.normal(0, 0.05, n), rng.normal(0, 0.05, n), rng.uniform(0, 0.2, n))
    depth, index = _splat(args, shape)
    depth_ref, index_ref = splat_discs_ref(*args, shape)
    np.testing.assert_array_equal(index, index_ref)
    np.testing.assert_array_equal(depth, depth_ref)
    assert (index >= 0).mean() > 0.3  # the discs overlap and cover a good part of the image


def test_nearest_disc_wins_whatever_the_order():
    zeros = np.zeros(2)
    for depths in ([1.0, 2.0], [2.0, 1.0]):
        args = (np.array([10.0, 11.0]), np.array([10.0, 10.5]), np.array(depths), np.array([4.0, 4.0]), zeros,
                zeros, zeros)
        _, index = _splat(args, (20, 20))
        assert index[10, 10] == int(np.argmin(depths))


def _flat_square(side_m=1.0, spacing_m=0.01):
    """A horizontal square of surfels in the z = 0 plane, normals +z, radius 0.75 spacing: ``(P, N, r)``."""
    c = np.arange(spacing_m / 2, side_m, spacing_m)
    x, y = np.meshgrid(c, c)
    pos = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (len(pos), 1))
    return pos, nrm, np.full(len(pos), 0.75 * spacing_m, np.float32)


def test_flat_square_seen_from_the_top_fills_its_area():
    pos, nrm, rad = _flat_square()
    cam = mf.top_view(pos, None, nrm, width=400, height=300)
    np.testing.assert_allclose(np.abs(cam.R_cam_world[2]), [0, 0, 1], atol=1e-6)  # looking straight down
    index, depth, shade = mf.render(cam, pos, nrm, rad, radius_scale=1.0)
    side_px = (1.0 + 2 * (0.75 - 0.5) * 0.01) * cam.px_per_m  # centres span 0.99 m, discs reach 0.25 cm further
    assert (index >= 0).sum() == pytest.approx(side_px**2, rel=0.03)
    u, v, _ = cam.to_pixels(pos)
    inner = index[int(v.min()) + 2:int(v.max()) - 1, int(u.min()) + 2:int(u.max()) - 1]
    assert (inner >= 0).all()  # no holes between touching discs
    assert shade.min() == shade.max() > mf.AMBIENT  # one flat surface: one Lambert shade


def _small_map():
    """A floor and a wall of surfels, and a camera path above the floor looking at the wall (world y is down)."""
    floor, n_floor, r_floor = _flat_square(2.0, 0.04)
    floor = floor[:, [0, 2, 1]]  # the floor in the y = 0 plane, normals -y (up)
    n_floor = -n_floor[:, [0, 2, 1]]
    wall, n_wall, r_wall = _flat_square(2.0, 0.04)
    wall = wall[:, [0, 1, 2]] * [1, -1, 1] + [0, 0, 2.0]  # the z = 2 plane, above the floor, normals -z
    n_wall = -n_wall
    pos, nrm = np.vstack([floor, wall]), np.vstack([n_floor, n_wall])
    n = len(pos)
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, :3, 3] = np.column_stack([np.linspace(0.5, 1.5, 10), np.full(10, -1.2), np.full(10, 0.3)])
    rng = np.random.default_rng(0)
    return dict(position=pos, normal=nrm, colour=rng.uniform(0, 255, (n, 3)).astype(np.float32),
                confidence=rng.uniform(0, 20, n).astype(np.float32), first_seen=np.arange(n, dtype=np.int32) // 50,
                radius=np.r_[r_floor, r_wall]), poses


def test_framing_camera_sees_the_whole_map():
    m, poses = _small_map()
    up = mf.up_axis(m["position"], poses, m["normal"])
    np.testing.assert_allclose(up, [0, -1, 0], atol=1e-6)
    cam = mf.perspective_view(m["position"], poses, m["normal"], width=200, height=150)
    u, v, z = cam.to_pixels(m["position"])
    assert (z > 0).all() and (u >= 0).all() and (u < 200).all() and (v >= 0).all() and (v < 150).all()


def test_figures_written_with_colour_bars_trajectory_and_scale_bar(tmp_path, monkeypatch):
    monkeypatch.setattr(mf, "FIGURE_SIZE_PX", (480, 360))  # drawing and PNG encoding dominate: keep it small
    monkeypatch.setattr(mf, "IMAGE_SIZE_PX", (200, 150))
    m, poses = _small_map()
    paths = mf.save_map_figures(tmp_path, m["position"], m["normal"], m["colour"], m["confidence"],
                                m["first_seen"], poses[0], title="test", trajectory_T_world_cam=poses,
                                radius=m["radius"])
    assert [p.name for p in paths] == ["map_camera.png", "map_top.png"]
    for p in paths:
        img = imread(p)
        assert img.shape[:2] == (mf.FIGURE_SIZE_PX[1], mf.FIGURE_SIZE_PX[0])
        assert img[..., :3].std() > 0.05  # something was drawn
    assert not list(tmp_path.glob(".*.tmp"))  # written through a temp file, none left behind

    fig = mf.map_figure(mf.top_view(m["position"], poses, m["normal"]), **m, trajectory_T_world_cam=poses)
    panels = fig.axes
    insets = [child for ax in panels for child in ax.child_axes]
    assert len(panels) == 4 and len(insets) == 2 + 1  # colour bars and the normal key
    assert {"confidence (accumulated weight)", "first seen (frame index)"} <= {ax.get_ylabel() for ax in insets}
    assert all(any(ln.get_label() == "camera path" for ln in ax.lines) for ax in panels)
    for ax in panels:  # the scale bar's label, e.g. "0.5 m"
        assert any(re.fullmatch(r"[\d.]+ m", t.get_text()) for t in ax.findobj(lambda a: hasattr(a, "get_text")))


def test_point_cloud_without_normals_or_spread_gets_no_colour_bars():
    m, poses = _small_map()
    n = len(m["position"])
    fig = mf.map_figure(mf.perspective_view(m["position"], poses), m["position"], np.zeros((n, 3), np.float32),
                        m["colour"], np.ones(n, np.float32), np.zeros(n, np.int32))
    assert [len(ax.child_axes) for ax in fig.axes] == [0, 0, 0, 0]
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[:3] == ["by normal (none in this map)", "by confidence (all 1)", "by time (all 0)"]
    with pytest.raises(ValueError, match="unknown colour mode"):
        mf.point_colours("height", m["normal"], m["confidence"], m["first_seen"], m["colour"])


def test_one_view_is_written_alone_and_an_unknown_view_is_one_line(tmp_path):
    from surfelslam.errors import ConfigError

    rng = np.random.default_rng(0)
    pos = rng.uniform(-1, 1, (200, 3)).astype(np.float32)
    args = (pos, np.tile([0.0, 0.0, -1.0], (200, 1)), np.full((200, 3), 128.0), np.ones(200), np.zeros(200), np.eye(4))
    written = mf.save_map_figures(tmp_path, *args, views=("camera",))
    assert [p.name for p in written] == ["map_camera.png"] and sorted(tmp_path.iterdir()) == written
    with pytest.raises(ConfigError, match="map figure views: unknown side; known: camera, top"):
        mf.save_map_figures(tmp_path / "x", *args, views=("side", "top"))
    assert not (tmp_path / "x").exists()


def test_panel_pixels_draw_what_imshow_draws_at_the_panel_size():
    """The map figures' panels (PanelPixels) put each pixel where imshow at the panel's own size puts it: the whole
    1600x1200 canvas equal, corners marked so that a flip or a one-pixel shift would show."""
    from surfelslam.viz.save import new_figure

    w, h = mf.IMAGE_SIZE_PX
    img = np.random.default_rng(1).integers(0, 256, (h, w, 4), dtype=np.uint8)
    img[..., 3] = 255
    img[:5, :5, :3] = (255, 0, 0)  # top left
    img[-5:, -5:, :3] = (0, 0, 255)  # bottom right
    canvases = []
    for pixels in (False, True):
        fig = new_figure((mf.FIGURE_SIZE_PX[0] / mf.style.DPI, mf.FIGURE_SIZE_PX[1] / mf.style.DPI))
        fig.subplots_adjust(**mf.PANEL_LAYOUT)
        for k in range(4):
            ax = fig.add_subplot(2, 2, k + 1)
            if pixels:
                ax.add_artist(mf.PanelPixels(ax, img))
                ax.set_aspect("equal")
            else:
                ax.imshow(img, interpolation="nearest")
            ax.set_xlim(-0.5, w - 0.5)
            ax.set_ylim(h - 0.5, -0.5)
        fig.canvas.draw()
        canvases.append(np.asarray(fig.canvas.buffer_rgba()).copy())
    reference, ours = canvases
    red = (reference[..., :3] == (255, 0, 0)).all(axis=-1)
    half_h, half_w = red.shape[0] // 2, red.shape[1] // 2
    assert all(red[r:r + half_h, c:c + half_w].any() for r in (0, half_h) for c in (0, half_w))  # each panel's
    np.testing.assert_array_equal(ours, reference)
