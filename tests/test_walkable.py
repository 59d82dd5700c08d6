"""Walkable-area prior (graphslam.core.tracking.walkable, graphslam.io.floor_plan): the distance
field and its derivative, the plan image's walkable pixels, and what the prior does for a tracker
whose fixes stray off the corridors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from graphslam.core.tracking.fixed_lag import FixedLagConfig, fixed_lag_smooth
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.errors import EstimationError, InputError
from graphslam.io.floor_plan import FloorPlan, load_floor_plan, read_walkable_area

from conftest import walk_epochs, walking_model


def _corridor(width_m: float = 30.0, height_m: float = 20.0) -> WalkableArea:
    """20 x 30 cells of 1 m; walkable: image rows 5-7, i.e. y in [12, 15] (cell centres 12.5-14.5)."""
    m = np.zeros((20, 30), bool)
    m[5:8, :] = True
    return WalkableArea(m, width_m, height_m, sigma_m=2.0)


def test_distance_is_zero_on_the_area_and_grows_away_from_it_also_beyond_the_plan():
    a = _corridor()
    d, g = a.distance(np.array([[10.3, 13.5], [10.3, 5.2], [10.3, 18.7], [-3.0, 13.5], [40.0, 2.0]]))
    np.testing.assert_allclose(d, [0.0, 12.5 - 5.2, 18.7 - 14.5, 3.5, (40.0 - 29.5) + (12.5 - 2.0)], atol=1e-9)
    np.testing.assert_allclose(g, [[0, 0], [0, -1], [0, 1], [-1, 0], [1, -1]], atol=1e-9)  # towards the corridor
    np.testing.assert_allclose(a.residual(np.array([[10.3, 5.2]])), (12.5 - 5.2) / 2.0)
    assert a.fraction_walkable() == pytest.approx(3 / 20)


def test_jacobian_matches_numerical_differentiation():
    rng = np.random.default_rng(4)
    m = rng.random((25, 40)) < 0.3  # an irregular area: distances in every direction
    a = WalkableArea(m, 40.0 * 0.4, 25.0 * 0.4, sigma_m=1.5)
    p = rng.uniform(-2.0, 18.0, (200, 2))
    J = a.jacobian(p)
    h = 1e-6
    num = np.stack([(a.residual(p + [h, 0]) - a.residual(p - [h, 0])) / (2 * h),
                    (a.residual(p + [0, h]) - a.residual(p - [0, h])) / (2 * h)], axis=1)
    # the field is bilinear per cell: its derivative jumps on cell edges, so compare off them
    u, v = p[:, 0] / 0.4 - 0.5, p[:, 1] / 0.4 - 0.5
    off_edges = (np.abs(u - np.round(u)) > 1e-3) & (np.abs(v - np.round(v)) > 1e-3)
    assert off_edges.sum() > 150
    np.testing.assert_allclose(J[off_edges], num[off_edges], atol=1e-5)


def test_invalid_areas_are_refused():
    with pytest.raises(EstimationError, match="no walkable cell"):
        WalkableArea(np.zeros((5, 5), bool), 5.0, 5.0)
    with pytest.raises(EstimationError, match="2-D grid"):
        WalkableArea(np.ones(5, bool), 5.0, 5.0)
    with pytest.raises(EstimationError, match="sigma_m"):
        WalkableArea(np.ones((5, 5), bool), 5.0, 5.0, sigma_m=0.0)


def _plan_png(path, background, room_rgb=(195, 235, 245, 255)):
    """A 60 x 40 px plan: background ``background`` (RGBA), a closed black outline 5 px in, a filled
    room in its left third; the corridor is the blank inside the outline."""
    px = np.zeros((40, 60, 4), np.uint8)
    px[:] = background
    px[5, 5:55] = px[34, 5:55] = (0, 0, 0, 255)
    px[5:35, 5] = px[5:35, 54] = (0, 0, 0, 255)
    px[6:34, 6:20] = room_rgb
    Image.fromarray(px, "RGBA").save(path)
    return FloorPlan(path, 30.0, 20.0, (60, 40))


@pytest.mark.parametrize("background", [(0, 0, 0, 0), (255, 255, 255, 255)])
def test_walkable_pixels_are_the_blank_the_outline_encloses(tmp_path, background):
    a = read_walkable_area(_plan_png(tmp_path / "plan.png", background), sigma_m=3.0)
    w = a.walkable
    assert w.shape == (40, 60) and a.sigma_m == 3.0
    assert w[20, 30] and w[6, 53]  # the corridor, up to the outline
    assert not w[20, 10]  # the room
    assert not w[2, 30] and not w[38, 2]  # outside the building
    assert not w[5, 30]  # the outline itself
    assert w.sum() == 28 * (53 - 20 + 1)
    # metres: x = 0.5 m per pixel, y up from the bottom edge
    assert a.distance(np.array([[15.0, 10.0]]))[0][0] == 0.0  # pixel (row 20, col 30)
    assert a.distance(np.array([[5.0, 10.0]]))[0][0] > 4.0  # in the room, 5 m from the corridor


def test_plans_that_enclose_no_blank_or_cannot_be_read_name_the_file(tmp_path):
    px = np.zeros((40, 60, 4), np.uint8)
    px[5, 5:55] = (0, 0, 0, 255)  # a wall, no outline
    Image.fromarray(px, "RGBA").save(tmp_path / "open.png")
    with pytest.raises(InputError, match="open.png.*encloses no blank"):
        read_walkable_area(FloorPlan(tmp_path / "open.png", 30.0, 20.0, (60, 40)))
    (tmp_path / "bad.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(InputError, match="bad.png"):
        read_walkable_area(FloorPlan(tmp_path / "bad.png", 30.0, 20.0, (60, 40)))
    # the size comes from floor_info.json beside the image, as for the pictures
    _plan_png(tmp_path / "p.png", (0, 0, 0, 0))
    (tmp_path / "floor_info.json").write_text('{"map_info": {"width": 30.0, "height": 20.0}}')
    assert read_walkable_area(load_floor_plan(tmp_path / "p.png", None)).height_m == 20.0


def _corridor_walk(theta: float, rng: np.random.Generator):
    """Along the corridor of ``_corridor`` (y = 13.5) at 1.2 m/s for 20 s, a step every 0.5 s,
    odometry turned by ``theta``; a fix every 2 s with std 4 m. Epochs and true positions."""
    t = np.arange(0.0, 20.0, 0.5)
    v = np.tile([1.2, 0.0], (len(t), 1))
    p = np.c_[3.0 + 1.2 * t, np.full(len(t), 13.5)]
    return walk_epochs(t, v, p, theta, np.arange(2, len(t), 4), rng), p


def test_the_prior_keeps_a_track_in_the_corridor_its_fixes_stray_from():
    m = walking_model()
    theta = 0.4
    cross: dict[str, list[float]] = {"off": [], "on": []}
    for seed in range(6):
        e, p = _corridor_walk(theta, np.random.default_rng(seed))
        x0 = np.array([e.fix_xy[0, 0], e.fix_xy[0, 1], 0.0, 0.0, 0.0, 0.0, theta])
        P0 = np.diag([16.0, 16.0, 1.0, 1.0, 0.0025, 0.0025, 0.1**2])
        cfg = FixedLagConfig(lag_s=2.0, window_s=20.0, huber_k=3.0, adaptive_rssi=False, report="best")
        for name, area in (("off", None), ("on", _corridor())):
            run = fixed_lag_smooth(m, [x0], P0, e, cfg, area=area)
            cross[name].append(float(np.abs(run.x[:, 1] - p[:, 1]).mean()))
    off, on = np.mean(cross["off"]), np.mean(cross["on"])
    assert on < 0.7 * off and on < 1.0  # across the corridor, the track keeps to it (measured 0.82 vs 1.43 m)


def test_snap_moves_only_positions_off_the_area_to_its_nearest_cell():
    a = _corridor()
    p = np.array([[10.2, 9.0], [10.2, 13.1], [-5.0, 3.0], [10.2, 19.5], [35.0, 13.5]])
    np.testing.assert_allclose(a.snap(p), [[10.5, 12.5], [10.2, 13.1], [0.5, 12.5], [10.5, 14.5], [29.5, 13.5]])
    assert (a.distance(a.snap(p))[0] == 0.0).all()


def test_track_config_applies_its_sigma_and_validates_it():
    from graphslam.core.tracking.tracker import walkable_area
    from graphslam.errors import ConfigError
    from graphslam.tracking_config import TrackConfig

    a = _corridor()
    b = walkable_area(TrackConfig(floor_plan={"sigma_m": 5.0}), a)
    assert b.sigma_m == 5.0 and a.sigma_m == 2.0 and b.residual(np.array([[0.5, 3.5]]))[0] == pytest.approx(9.0 / 5.0)
    assert walkable_area(TrackConfig(), None) is None
    for bad in (0.0, -1.0, math.inf):
        with pytest.raises(ConfigError, match="floor_plan.sigma_m"):
            TrackConfig(floor_plan={"sigma_m": bad})
    with pytest.raises(ConfigError, match="floor_plan.mode"):
        TrackConfig(floor_plan={"mode": "teleport"})


def test_the_benchmark_finds_the_plan_beside_the_walks_unless_told_otherwise(tmp_path):
    from graphslam.app.tracking_bench import floor_plan_area

    assert floor_plan_area(tmp_path) is None  # no plan there: none, not an error
    _plan_png(tmp_path / "floor_image.png", (0, 0, 0, 0))
    (tmp_path / "floor_info.json").write_text('{"map_info": {"width": 30.0, "height": 20.0}}')
    auto = floor_plan_area(tmp_path)
    assert auto is not None and auto.walkable.shape == (40, 60) and auto.width_m == 30.0
    assert floor_plan_area(tmp_path, "none") is None
    other = tmp_path / "other"
    other.mkdir()
    assert floor_plan_area(other, str(tmp_path / "floor_image.png")).height_m == 20.0
    with pytest.raises(InputError, match="missing.png"):
        floor_plan_area(other, str(tmp_path / "missing.png"))
