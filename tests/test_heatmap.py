"""Per-AP heatmaps with their uncertainty (issue 41): the field and its standard error
(graphslam.core.radiomap.field), the faded AP panels of radio_map.png, and the service's
``GET /v1/heatmap/{bssid}.png`` over real HTTP."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from graphslam.core.radiomap.field import FieldGrid, rss_field
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import ConfigError
from graphslam.io.heatmap import MAX_STD_ERROR_DB, faded, heatmap_png, heatmap_rgba

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
B = "02:00:00:00:00:0b"  # a BSSID as the service sees them (colons in the URL path)


def _line_map() -> RadioMap:
    """AP "a" along y = 0: x 0..20 dense readings that agree (-60 +- 1 dB, 5 per m), x 40..60 sparse
    ones as noisy (one per 2 m), x 80..100 dense ones that disagree (-35 / -85 in turn); AP ``B``
    heard everywhere at -70. Nothing between the stretches."""
    rng = np.random.default_rng(3)
    xa, xb, xd = np.arange(0.0, 20.0, 0.2), np.arange(40.0, 60.1, 2.0), np.arange(80.0, 100.0, 0.2)
    ra = -60.0 + rng.normal(0.0, 1.0, len(xa))
    rb = -60.0 + rng.normal(0.0, 1.0, len(xb))
    rd = np.where(np.arange(len(xd)) % 2 == 0, -35.0, -85.0)
    x = np.concatenate([xa, xb, xd])
    rss = np.concatenate([ra, rb, rd])
    scans = [{"a": float(r), B: -70.0} for r in rss]
    return RadioMap.from_scans(scans, np.column_stack([x, np.zeros_like(x)]), session_ids="s",
                               t_ns=np.arange(len(x)), frame="site")


def _cells(f, x0: float, x1: float) -> np.ndarray:
    """Cells of the row y = 0 whose centre x lies in [x0, x1]."""
    cx = f.origin[0] + (np.arange(f.mean_dbm.shape[0]) + 0.5) * f.cell_m
    j = int((0.0 - f.origin[1]) // f.cell_m)
    return (cx >= x0) & (cx <= x1), j


def test_standard_error_shrinks_where_more_readings_agree_and_is_nan_outside() -> None:
    rm = _line_map()
    f = rss_field(rm, "a", cell_m=1.0, bandwidth_m=1.5)
    assert f.mean_dbm.shape == f.std_error_db.shape == f.weight.shape and f.n_heard == len(rm)
    (dense, j), (sparse, _), (disagree, _), (gap, _) = (_cells(f, 3, 17), _cells(f, 43, 57), _cells(f, 83, 97),
                                                       _cells(f, 28, 32))
    se = f.std_error_db[:, j]
    assert np.isfinite(se[dense]).all() and np.isfinite(f.mean_dbm[dense, j]).all()
    assert np.abs(f.mean_dbm[dense, j] + 60.0).max() < 1.0
    assert np.nanmedian(se[dense]) < 0.5 < MAX_STD_ERROR_DB
    # sparse, as noisy: fewer effective readings, a larger error (NaN where fewer than 2)
    assert np.nanmedian(se[sparse]) > 1.5 * np.median(se[dense])
    assert (f.n_eff[sparse, j].max() < f.n_eff[dense, j].min())
    # dense but disagreeing: the mean is their average, the error far larger than where they agree
    assert np.abs(np.median(f.mean_dbm[disagree, j]) + 60.0) < 2.0
    assert np.median(se[disagree]) > 5 * np.median(se[dense]) and np.median(se[disagree]) > MAX_STD_ERROR_DB
    # no fingerprint near: outside, NaN (and outside the grid's rows far from y = 0)
    assert gap.any() and np.isnan(f.mean_dbm[gap, j]).all() and np.isnan(f.std_error_db[gap, j]).all()
    assert f.outside[gap, j].all() and not f.outside[dense, j].any()
    # an AP heard the same everywhere: the mean is exact, the error 0
    b = rss_field(rm, B, cell_m=1.0, bandwidth_m=1.5)
    inside = ~b.outside
    np.testing.assert_allclose(b.mean_dbm[inside], -70.0, atol=1e-9)
    assert np.nanmax(b.std_error_db) < 1e-6


def test_field_matches_the_kernel_sums_written_out() -> None:
    # one cell by brute force: the binned positions, the normalised truncated kernel, its weights
    rm = _line_map()
    f = rss_field(rm, "a", cell_m=1.0, bandwidth_m=1.5)
    grid = FieldGrid(rm.xy, 1.0)
    k = grid.kernel(1.5)
    r = len(k) // 2
    ij = np.clip(((rm.xy - grid.lo) / 1.0).astype(int), 0, grid.n - 1)
    rss = np.asarray(rm.fingerprints.values.tocsc()[:, rm.bssids.index("a")].toarray()).ravel() + rm.missing_dbm
    for cx in (10.0, 50.0, 90.0):
        c = ((np.array([cx, 0.0]) - grid.lo) / 1.0).astype(int)
        d = np.abs(ij - c)
        near = (d <= r).all(axis=1)
        w = np.where(near, k[np.minimum(d[:, 0], r) + r] * k[np.minimum(d[:, 1], r) + r], 0.0)
        W = w.sum()
        m = (w * rss).sum() / W
        n_eff = W**2 / (w**2).sum()
        se = np.sqrt((w * (rss - m) ** 2).sum() / W / (n_eff - 1))
        assert f.weight[c[0], c[1]] == pytest.approx(W)
        assert f.mean_dbm[c[0], c[1]] == pytest.approx(m)
        assert f.n_eff[c[0], c[1]] == pytest.approx(n_eff)
        assert f.std_error_db[c[0], c[1]] == pytest.approx(se, rel=1e-6, abs=1e-9)


def test_field_errors() -> None:
    rm = _line_map()
    with pytest.raises(ConfigError, match="no fingerprint of the radio map heard access point zz"):
        rss_field(rm, "zz")
    with pytest.raises(ConfigError, match="xy must be"):
        rss_field(rm, "a", xy=np.zeros((3, 2)))
    with pytest.raises(ConfigError, match="bandwidth"):
        rss_field(rm, "a", bandwidth_m=-1.0)


def test_heatmap_fades_uncertain_cells_and_writes_a_located_png() -> None:
    rm = _line_map()
    f = rss_field(rm, "a", cell_m=1.0, bandwidth_m=1.5)
    rgba = heatmap_rgba(f)
    fade = faded(f)
    (dense, j), (disagree, _) = _cells(f, 3, 17), _cells(f, 83, 97)
    assert not fade[dense, j].any() and fade[disagree, j].all()
    assert (rgba[f.outside, 3] == 0).all() and (rgba[~f.outside, 3] > 0).all()
    # faded: lighter than the same RSS unfaded
    plain = heatmap_rgba(f, max_std_error_db=np.inf)  # fades only the cells of unknown error (n_eff < 2)
    known = fade & np.isfinite(f.std_error_db)
    assert known.sum() >= 10 and not faded(f, np.inf)[known].any()
    assert (rgba[known][:, :3].astype(int).sum(axis=1) > plain[known][:, :3].astype(int).sum(axis=1)).all()
    data = heatmap_png(f, frame="site")
    assert data.startswith(PNG_SIGNATURE)
    _check_located_picture(data, f, rgba, "site")
    # a frame name beyond Latin-1 (tEXt's alphabet) is written as UTF-8 text, not a failure
    with Image.open(io.BytesIO(heatmap_png(f, frame="楼 €"))) as im:
        assert im.text["frame"] == "楼 €" and im.text["bssid"] == "a"


def _check_located_picture(data: bytes, f, rgba: np.ndarray, frame: str) -> None:  # type: ignore[no-untyped-def]
    """The heatmap PNG reads on its own: the cells where ``panel_px`` says (whole pixels each, as
    ``heatmap_rgba`` colours them), metre axes, a colour bar in dBm, a scale bar, a title."""
    from graphslam.io.png import VIRIDIS, colour_map

    with Image.open(io.BytesIO(data)) as im:
        text = dict(im.text)
        img = np.asarray(im.convert("RGB")).astype(int)
    nx, ny = f.mean_dbm.shape
    s = int(text["px_per_cell"])
    left, top, right, bottom = (int(v) for v in text["panel_px"].split())
    assert (right - left, bottom - top) == (nx * s, ny * s) and text["bssid"] == "a" and text["frame"] == frame
    assert img.shape[1] > right + 60 and img.shape[0] > bottom + 20 and left >= 40 and top >= 40  # room for the rest
    x0, x1, y0, y1 = (float(v) for v in text["extent_m"].split())
    assert (x0, x1, y0, y1) == pytest.approx(f.extent, abs=1e-3)
    assert str(MAX_STD_ERROR_DB).rstrip("0").rstrip(".") in text["faded"]
    assert f"RSS of a over the radio map ({frame} frame, metres)" in text["Title"] and "faded" in text["Title"]
    # every cell inside the surveyed area: its colour, at its place (column i from the left, row j from the bottom)
    inside = np.argwhere(~f.outside)
    for i, j in inside[:: max(1, len(inside) // 50)]:
        px = img[bottom - j * s - s // 2 - 1, left + i * s + s // 2]
        assert np.abs(px - rgba[i, j, :3].astype(int)).max() <= 1, (i, j)
    # the colour bar right of the cells: viridis from its dark end (bottom) to its light end (top)
    dark, light = colour_map(np.array([-100.0, -30.0]), -100.0, -30.0, VIRIDIS).astype(int)
    bar = img[top + 1:bottom, right + 16:right + 29]  # inside its outline
    assert (np.abs(bar[-1] - dark).max(axis=1) <= 40).all() and (np.abs(bar[0] - light).max(axis=1) <= 40).all()
    shade = bar.sum(axis=(1, 2))
    assert (np.diff(shade) <= 0).all() and shade[0] > shade[-1]  # light at the top, dark at the bottom
    # axes: tick labels (dark text) under the cells and left of them; a scale bar (black) under the ticks
    assert (img[bottom + 3:bottom + 20, left:right] < 100).any() and (img[top:bottom, :left - 4] < 100).any()
    under = img[bottom + 24:, left:]
    assert (np.abs(under).max(axis=2) < 30).sum() > 40


def test_radio_map_picture_fades_uncertain_ap_cells(tmp_path: Path) -> None:
    from graphslam.viz import radiomap_picture

    rm = _line_map()
    pic = radiomap_picture.radio_map_picture(rm, aps=["a"], cell_m=1.0, bandwidth_m=1.5)
    assert any(f"faded: standard error > {MAX_STD_ERROR_DB:g} dB" in text for _, text, _ in pic.captions)
    crowded = radiomap_picture.radio_map_picture(rm, aps=["a", B], cell_m=1.0, size_px=(600, 400))
    assert sum(f"faded: s.e. > {MAX_STD_ERROR_DB:g} dB" in text for _, text, _ in crowded.captions) == 2
    path = pic.save(tmp_path / "rm.png")
    with Image.open(path) as im:
        assert im.size == pic.size and im.size[0] == radiomap_picture.SIZE_PX[0]


def test_service_serves_an_aps_heatmap_png_per_map_generation(tmp_path: Path) -> None:
    import time

    import httpx

    from graphslam.io.radiomap_io import write_radio_map
    from graphslam.service.server import reloading_app, start_background_server

    rm = _line_map()
    path = tmp_path / "map.parquet"
    write_radio_map(rm, path)
    app = reloading_app(path, None, k=3, search_processes=0, token="s3cret")
    auth = {"Authorization": "Bearer s3cret"}
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        assert c.get("/v1/heatmap/a.png").status_code == 401  # the token, as on every /v1 route
        a = c.get("/v1/heatmap/a.png", headers=auth)
        assert a.status_code == 200 and a.headers["content-type"] == "image/png"
        assert a.content.startswith(PNG_SIGNATURE) and a.content == heatmap_png(rss_field(rm, "a"), frame="site")
        field = rss_field(rm, "a")
        _check_located_picture(a.content, field, heatmap_rgba(field), "site")
        r = c.get(f"/v1/heatmap/{B}.png", headers=auth)
        assert r.status_code == 200 and Image.open(io.BytesIO(r.content)).text["bssid"] == B
        missing = c.get("/v1/heatmap/ff:ff:ff:ff:ff:ff.png", headers=auth)
        assert missing.status_code == 404 and "ff:ff:ff:ff:ff:ff" in missing.json()["detail"]
        # cached per AP for this map; a reload brings a new map and a new cache
        first = app.current.state.heatmaps
        assert set(first._pngs) == {"a", B} and first._pngs["a"] == a.content
        assert c.get("/v1/heatmap/a.png", headers=auth).content == a.content
        moved = RadioMap.from_scans([{"a": -50.0, B: -60.0}] * 3, [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]],
                                    session_ids="s", t_ns=np.arange(3), frame="site")
        write_radio_map(moved, path)
        app.reload_now()
        deadline = time.monotonic() + 30
        while app.generation < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert app.generation == 1 and app.current.state.heatmaps is not first
        again = c.get("/v1/heatmap/a.png", headers=auth)
        assert again.status_code == 200 and again.content == heatmap_png(rss_field(moved, "a"), frame="site")


def test_site_service_serves_a_floors_heatmap(tmp_path: Path) -> None:
    import httpx

    from graphslam.io.radiomap_io import write_radio_map
    from graphslam.service.server import served_app, start_background_server

    rm = _line_map()
    other = RadioMap.from_scans([{"c": -50.0}] * 3, [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], session_ids="s",
                                t_ns=np.arange(3), frame="site-b")
    for name, m in (("bldg/F1", rm), ("bldg/F2", other)):
        (tmp_path / "site" / name).mkdir(parents=True)
        write_radio_map(m, tmp_path / "site" / name / "radio_map.parquet")
    app = served_app(tmp_path / "site", None, search_processes=0, token="t")
    auth = {"Authorization": "Bearer t"}
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        assert c.get(f"/v1/maps/bldg/F1/heatmap/{B}.png").status_code == 401
        r = c.get(f"/v1/maps/bldg/F1/heatmap/{B}.png", headers=auth)
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert r.content == heatmap_png(rss_field(rm, B), frame="site")
        r = c.get("/v1/maps/bldg/F2/heatmap/c.png", headers=auth)
        assert r.status_code == 200 and Image.open(io.BytesIO(r.content)).text["frame"] == "site-b"
        nope = c.get("/v1/maps/bldg/F2/heatmap/a.png", headers=auth)  # an AP of another floor
        assert nope.status_code == 404 and "floor 'bldg/F2'" in nope.json()["detail"]
        nope = c.get("/v1/maps/F9/heatmap/a.png", headers=auth)
        assert nope.status_code == 404 and "no floor 'F9'" in nope.json()["detail"]
