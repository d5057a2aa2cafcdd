"""The settings' tiers and what a run's config.toml holds: the user settings, the package version and the expert
constants that differ from their defaults; loading it rebuilds the same config; removed keys say what replaced
them; one relocalisation setting for every tracker; the hybrid's back-end profile."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest

from surfelslam.backend.loops import LoopConfig, loop_candidates
from surfelslam.backend.place_recognition import DescriptorIndex
from surfelslam.backend.sparse_slam import BACK_END_PROFILE, with_profile
from surfelslam.errors import ConfigError
from surfelslam.settings import (
    VERSION_KEY,
    dumps_toml,
    from_dict,
    is_user_setting,
    iter_tables,
    load_config,
    package_version,
    preset_names,
)
from surfelslam.slam import SlamConfig
from surfelslam.slam.config import TrackingConfig, relocalise_due
from surfelslam.slam.hybrid_profile import HYBRID_PROFILE, hybrid_sparse_config

#: The issue's bound on a default run's config.toml.
MAX_DEFAULT_KEYS = 80


def _keys(text: str) -> list[str]:
    """``table.key`` of every setting in TOML text."""
    out, table = [], ""
    for line in text.splitlines():
        if line.startswith("["):
            table = line.strip("[]") + "."
        elif "=" in line:
            out.append(table + line.split("=")[0].strip())
    return out


def test_a_default_config_toml_holds_the_user_settings_and_the_version_only():
    text = dumps_toml(SlamConfig())
    keys = _keys(text)
    n_user = sum(is_user_setting(f) and not dataclasses.is_dataclass(getattr(sub, f.name))
                 and getattr(sub, f.name) is not None
                 for _, sub in iter_tables(SlamConfig()) for f in dataclasses.fields(sub))
    assert len(keys) == n_user + 1 <= MAX_DEFAULT_KEYS
    assert keys[0] == VERSION_KEY and tomllib.loads(text)[VERSION_KEY] == package_version() != ""
    assert {"tracker", "preprocess.max_depth_m", "tracking.max_width_px", "tracking.relocalise_after_failures",
            "hybrid.loop_correction", "fusion.max_width_px", "map_reuse.save"} <= set(keys)
    assert "icp.max_condition_number" not in keys  # an expert constant at its default
    assert from_dict(SlamConfig, tomllib.loads(text)) == SlamConfig()


def test_an_expert_override_is_written_and_read_back():
    cfg = load_config(SlamConfig, None, ["icp.max_condition_number=5000", "orb.loop_icp.sigma_m=0.004",
                                         "sparse.graph.robust_scale_sigma=2.0"])
    text = dumps_toml(cfg)
    keys = _keys(text)
    assert {"icp.max_condition_number", "orb.loop_icp.sigma_m", "sparse.graph.robust_scale_sigma"} <= set(keys)
    assert len(keys) == len(_keys(dumps_toml(SlamConfig()))) + 3
    back = from_dict(SlamConfig, tomllib.loads(text))
    assert back == cfg and back.icp.max_condition_number == 5000.0 and back.orb.loop_icp.sigma_m == 0.004
    # a table whose defaults come from its parent (orb's edge refinement) is compared with those, not the class's
    assert "feature_weight" not in text and back.orb.loop_icp.feature_weight == 0.3
    full = dumps_toml(cfg, full=True)
    assert len(_keys(full)) > 250 and from_dict(SlamConfig, tomllib.loads(full)) == cfg


@pytest.mark.parametrize("name", ["fast", "accurate", "hybrid-full"])
def test_presets_round_trip_through_their_config_toml(name):
    assert name in preset_names()
    cfg = load_config(SlamConfig, name)
    assert cfg != SlamConfig() and from_dict(SlamConfig, tomllib.loads(dumps_toml(cfg))) == cfg


@pytest.mark.parametrize(("text", "message"), [
    ("[hybrid]\nrelocalise_after_failures = 5\n",
     "[hybrid] relocalise_after_failures was removed: one setting for every tracker: [tracking] "
     "relocalise_after_failures"),
    ("[sparse]\nrelocalise_after_failures = 5\n", "[sparse] relocalise_after_failures was removed"),
    ("[orb.loop_icp.icp]\nlevels = 2\n", "[orb.loop_icp] icp was removed: the keyframe-edge ICP is a constant"),
    ("[hybrid]\nloop_nearby = 5\n", "[hybrid] loop_nearby was removed: set [sparse.loop] n_nearby (unset: the "
                                    "running tracker's own, the hybrid's 3)"),
    ("[hybrid]\nguided_match_deg = 3.0\n", "[hybrid] guided_match_deg was removed: the hybrid's is a constant "
                                           "(2.6 deg, GUIDED_MATCH_DEG in surfelslam/slam/hybrid_profile.py)"),
    ('version = 3\n', "version must be a string, got 3"),
])
def test_a_removed_key_names_what_replaced_it(text, message):
    with pytest.raises(ConfigError) as info:
        from_dict(SlamConfig, tomllib.loads(text))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_any_version_is_accepted():
    assert from_dict(SlamConfig, {VERSION_KEY: "0.0.1", "tracker": "orb"}) == SlamConfig(tracker="orb")


@pytest.mark.parametrize(("n", "failures", "due"), [(3, 2, False), (3, 3, True), (3, 9, True), (0, 0, False),
                                                    (0, 50, False), (1, 1, True)])
def test_one_relocalisation_setting_for_every_tracker(n, failures, due):
    assert relocalise_due(TrackingConfig(relocalise_after_failures=n), failures) is due


def test_the_hybrids_back_end_profile():
    """The hybrid's sparse back end: [sparse] with the hybrid's profile for its unset keys and the hybrid's constants,
    the values the former [hybrid] copies gave; the orb's are the back end's own."""
    cfg = SlamConfig()
    assert cfg.sparse.keyframe_threshold is None and cfg.sparse.loop.n_nearby is None  # unset: per tracker
    sp = hybrid_sparse_config(cfg, 262.5)
    assert (sp.keyframe_threshold, sp.keyframe_min_gap_frames) == (0.12, 3)
    assert (sp.loop.n_nearby, sp.loop.n_random, sp.loop.n_retrieved) == (3, 0, 2)
    orb = with_profile(cfg.sparse, BACK_END_PROFILE)
    assert (orb.keyframe_threshold, orb.keyframe_min_gap_frames, orb.loop.n_nearby, orb.loop.n_random) == (0.1, 1, 5, 5)
    assert orb.loop.n_retrieved == 3
    assert sp.graph.edge_information == "isotropic" and sp.features_reference_width_px == 0
    assert sp.features.depth_edge_rel == 0.0
    assert sp.features.guided_radius_px == pytest.approx(262.5 * np.tan(np.radians(2.6)))  # 2.6 deg: 11.9 px
    assert sp.graph.odometry_information == pytest.approx(0.003 ** -2)  # 3 mm, the refined loop edges' floor
    assert sp.graph.robust_scale_sigma == pytest.approx(0.03 * np.sqrt(100.0))
    assert sp.features.n_features == cfg.sparse.features.n_features  # the rest is [sparse]'s
    assert hybrid_sparse_config(cfg, -262.5) == sp  # a negative focal length (flipped y) gives the same radius


def test_the_loop_candidates_each_tracker_checks():
    """The candidates of keyframe 20 (19 has the odometry edge; 16 older ones, all in the index): the hybrid checks
    its 3 nearby keyframes and at most 2 retrieved ones, none drawn at random; the orb tracker 5 nearby, at most 3
    retrieved and 5 random; a set n_retrieved is the running tracker's either way."""
    rng_desc = np.random.default_rng(3)
    index = DescriptorIndex(LoopConfig().retrieval)
    descs = [rng_desc.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(20)]
    for d in descs:
        index.add(d)
    query = np.concatenate([descs[k][:100] for k in (2, 5, 8)])  # shares descriptors with keyframes 2, 5 and 8

    def sources(sparse_cfg):
        cands = loop_candidates(20, query, index, np.random.default_rng(0), sparse_cfg.loop)
        return {s: sorted(c.kf_id for c in cands if c.source == s) for s in ("nearby", "retrieved", "random")}

    hybrid = sources(hybrid_sparse_config(SlamConfig(), 262.5))
    assert hybrid["nearby"] == [16, 17, 18] and len(hybrid["retrieved"]) == 2 and hybrid["random"] == []
    assert set(hybrid["retrieved"]) <= {2, 5, 8}
    orb = sources(with_profile(SlamConfig().sparse, BACK_END_PROFILE))
    assert orb["nearby"] == [14, 15, 16, 17, 18] and orb["retrieved"] == [2, 5, 8] and len(orb["random"]) == 5
    set3 = from_dict(SlamConfig, {"sparse": {"loop": {"n_retrieved": 3}}})
    assert sources(hybrid_sparse_config(set3, 262.5))["retrieved"] == [2, 5, 8]


def test_a_set_sparse_key_applies_to_the_running_tracker_and_the_constants_stay():
    """A [sparse] key of the profile set in a config is the hybrid's too (one key, one meaning); the [sparse] keys the
    hybrid's constants replace stay the orb's."""
    cfg = from_dict(SlamConfig, {"sparse": {"keyframe_min_gap_frames": 2, "loop": {"n_random": 0},
                                            "graph": {"edge_information": "estimated"}}})
    sp = hybrid_sparse_config(cfg, 262.5)
    assert (sp.keyframe_min_gap_frames, sp.loop.n_random) == (2, 0)
    assert (sp.keyframe_threshold, sp.loop.n_nearby) == (HYBRID_PROFILE.keyframe_threshold, HYBRID_PROFILE.loop_nearby)
    assert sp.graph.edge_information == "isotropic"
    orb = with_profile(cfg.sparse, BACK_END_PROFILE)
    assert (orb.keyframe_min_gap_frames, orb.loop.n_random, orb.loop.n_nearby) == (2, 0, 5)
    assert orb.graph.edge_information == "estimated"


def test_the_presets_are_declared_package_data():
    """pyproject.toml ships every preset in the wheel (``make wheel-check`` installs one and runs ``--config fast``)."""
    from pathlib import Path

    from surfelslam.settings import presets_dir

    root = Path(__file__).resolve().parents[1]
    data = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    package_dir = root / "src" / "surfelslam" / "settings"
    shipped = {p.name for pattern in data["surfelslam.settings"] for p in package_dir.glob(pattern)}
    assert shipped == {f"{name}.toml" for name in preset_names()} == {"accurate.toml", "fast.toml", "hybrid-full.toml"}
    assert Path(str(presets_dir())) == package_dir / "presets"
