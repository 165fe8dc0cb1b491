"""HIA paths (raster, way-points, mouse CSV), the block schedule, and rendering along a path."""

import json

import numpy as np
import pytest
from matplotlib import cbook

from rtctl.errors import SceneError
from rtctl.render.cli import main
from rtctl.render.factory import make_renderer
from rtctl.render.image import load_image
from rtctl.render.path import PathPlayer, at_speed, from_csv, parse_path, raster, through

HOPPER = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)


def test_raster_moves_at_constant_speed_and_covers_the_lines():
    p = raster(200, 100, speed=2000.0, rate=1000.0, step=33.0)
    steps = np.hypot(np.diff(p.x), np.diff(p.y))
    corner = np.abs(np.diff(p.x)) * np.abs(np.diff(p.y)) > 0      # steps that turn a corner
    np.testing.assert_allclose(steps[~corner], 2.0, rtol=1e-12)   # 2000 px/s at 1 kHz
    assert np.all(steps[corner] < 2.0)
    np.testing.assert_allclose(np.unique(p.y[:-1][np.diff(p.y) == 0]), [16.5, 49.5, 82.5])  # the scan lines
    assert p.x.min() == 0.0 and p.x.max() == 199.0
    total = 3 * 199 + 2 * 33
    assert len(p) == total // 2 + 1 and p.t[1] == 1e-3  # 2 px per update


def test_through_is_linear_between_way_points():
    pts = [(0.0, 0.0), (30.0, 40.0), (30.0, 0.0)]
    p = through(pts, [0.0, 0.05, 0.1], rate=200.0)
    np.testing.assert_allclose(p.t, np.arange(21) / 200.0)
    np.testing.assert_allclose(p.x[:11], np.linspace(0, 30, 11))
    np.testing.assert_allclose(p.y[10:], np.linspace(40, 0, 11))
    with pytest.raises(SceneError, match="strictly increasing"):
        through(pts, [0.0, 0.0, 0.1])


def test_mouse_csv_with_header_and_duplicate_events(tmp_path):
    f = tmp_path / "mouse.csv"
    f.write_text("x,y,t\n0,0,0.000\n5,0,0.005\n7,0,0.005\n10,10,0.010\n")
    p = from_csv(f, rate=1000.0)
    np.testing.assert_allclose(p.x, [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10])
    np.testing.assert_allclose(p.y[5:], [0, 2, 4, 6, 8, 10])
    g = tmp_path / "plain.csv"
    g.write_text("0,1,2\n0.002,3,4\n")
    np.testing.assert_allclose(from_csv(g, 1000.0).x, [1, 2, 3])
    h = tmp_path / "bad.csv"
    h.write_text("a,b\n1,2\n")
    with pytest.raises(SceneError, match="must name columns t, x and y"):
        from_csv(h)
    with pytest.raises(SceneError, match="cannot read"):
        from_csv(tmp_path / "missing.csv")


def test_player_hands_over_the_update_in_force_at_each_block():
    r = make_renderer("frequency").prepare(load_image(HOPPER))
    p = raster(512, 600, speed=5000.0, rate=1000.0)
    player = PathPlayer(r, p, fs=48000.0, block=32)
    k = np.arange(3000)
    expect = np.minimum((k * 32 * 1000) // 48000, len(p) - 1)   # exact integer form of floor(t_k * rate)
    np.testing.assert_array_equal(player.schedule(3000), expect)
    pending, frames = r.empty(), r.render_path(p.x, p.y)
    fresh = [player.step(int(i), pending) for i in k[:300]]
    assert sum(fresh) == len(np.unique(expect[:300]))           # one hand-over per new update
    np.testing.assert_array_equal(pending, frames[expect[299]])


def test_render_path_equals_updates_one_by_one():
    r = make_renderer("beat").prepare(load_image(HOPPER))
    p = through([(0, 0), (511, 599)], [0.0, 0.2], rate=500.0)
    frames = r.render_path(p.x, p.y)
    out = r.empty()
    for i in (0, 37, 100):
        r.update(p.x[i], p.y[i], out)
        np.testing.assert_array_equal(out, frames[i])


def test_cli_renders_a_mouse_path(tmp_path, capsys):
    f = tmp_path / "mouse.csv"
    f.write_text("t,x,y\n0,100,100\n0.5,400,500\n")
    assert main([HOPPER, "--method", "roi", "--path", str(f), "--rate", "200", "--out", str(tmp_path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["path"] == {"spec": str(f), "updates": 101, "rate_hz": 200.0, "duration_s": 0.5,
                         "start": [100.0, 100.0], "end": [400.0, 500.0]}
    frames = np.load(tmp_path / "params.npy")
    assert frames.shape == (101, 16, 5)


def test_way_points_at_a_speed_take_their_length_over_the_speed():
    p = at_speed([(0, 0), (30, 40), (30, 0)], speed=500.0, rate=1000.0)  # 50 px, then 40 px
    assert p.t[-1] == pytest.approx(90 / 500.0) and len(p) == 181
    steps = np.hypot(np.diff(p.x), np.diff(p.y))
    corner = 100  # the sample at 0.1 s is the corner itself
    np.testing.assert_allclose(np.delete(steps, [corner - 1, corner]), 0.5, rtol=1e-9)
    assert (p.x[corner], p.y[corner]) == pytest.approx((30.0, 40.0))
    with pytest.raises(SceneError, match="same point"):
        at_speed([(1, 1), (1, 1)], 10.0)


def test_parse_path_names_every_form(tmp_path):
    r = parse_path("raster", 200, 100, speed=2000.0, step=33.0)
    q = raster(200, 100, speed=2000.0, step=33.0)
    np.testing.assert_array_equal(r.x, q.x) and np.testing.assert_array_equal(r.y, q.y)
    p = parse_path(" 0,0 ; 30,40 ;30,0 ", 200, 100, speed=500.0)
    np.testing.assert_array_equal(p.x, at_speed([(0, 0), (30, 40), (30, 0)], 500.0).x)
    p = parse_path("0,0@0;30,40@0.05;30,0@0.1", 200, 100, rate=200.0)
    np.testing.assert_array_equal(p.y, through([(0, 0), (30, 40), (30, 0)], [0, 0.05, 0.1], 200.0).y)
    wp = tmp_path / "way.csv"
    wp.write_text("# a square\nx,y\n0,0\n10,0\n10,10\n")
    p = parse_path(str(wp), 200, 100, speed=1000.0)
    assert p.t[-1] == pytest.approx(0.02) and (p.x[-1], p.y[-1]) == (10.0, 10.0)
    for spec, words in (("rastr", "'rastr': no such file; give 'raster'"),
                        ("0,0;1,1@0.5", "a time (X,Y@T) for every way-point or for none"),
                        ("0,0;a,1", "way-point 2 'a,1' must be X,Y or X,Y@T"),
                        ("5,5", "at least two way-points"),
                        (str(tmp_path), "not a regular file")):
        with pytest.raises(SceneError, match=words.replace("(", r"\(").replace(")", r"\)")):
            parse_path(spec, 200, 100)


@pytest.mark.parametrize("spec, n, end", [
    ("raster", None, None),
    ("48,48;463,48;463,551", None, (463.0, 551.0)),
    ("48,48@0;463,551@0.25", 251, (463.0, 551.0)),
], ids=["raster", "way-points-at-speed", "timed-way-points"])
def test_cli_renders_raster_and_way_point_paths(tmp_path, capsys, spec, n, end):
    from rtctl.cli import main as rtctl_main

    code = rtctl_main(["render", HOPPER, "--method", "roi", "--path", spec, "--speed", "4000",
                       "--out", str(tmp_path), "--json"])
    assert code == 0
    d = json.loads(capsys.readouterr().out)
    path = {"raster": raster(512, 600, 4000.0, 1000.0, step=32.0),  # lines one HIA (32 px) apart
            "timed-way-points": through([(48, 48), (463, 551)], [0.0, 0.25])}.get(
        "raster" if spec == "raster" else "timed-way-points" if "@" in spec else "",
        at_speed([(48, 48), (463, 48), (463, 551)], 4000.0))
    assert d["path"]["updates"] == len(path) and d["path"]["spec"] == spec
    if n is not None:
        assert len(path) == n
    if end is not None:  # the last update falls within one step (speed / rate) of the last way-point
        assert np.hypot(*(np.array(d["path"]["end"]) - end)) <= 4000.0 / 1000.0
    frames = np.load(tmp_path / "params.npy")
    r = make_renderer("roi", grid=(4, 4), hia=32).prepare(load_image(HOPPER))
    np.testing.assert_array_equal(frames, r.render_path(path.x, path.y))
    code = rtctl_main(["render", HOPPER, "--path", "0,0;1,1@2"])
    assert code == 2 and "a time (X,Y@T) for every way-point" in capsys.readouterr().err


def test_cli_beat_normalisation_is_a_choice(capsys):
    from rtctl.cli import main as rtctl_main

    for norm, want in ((None, "field"), ("image", "image")):
        code = rtctl_main(["render", HOPPER, "--method", "beat", "--json"] + (["--normalize", norm] if norm else []))
        assert code == 0
        d = json.loads(capsys.readouterr().out)
        assert d["normalize"] == want
    # the default display (6 x 8 at 1.5 mm): 9 x 12 mm over 12.6 mm^2
    code = rtctl_main(["render", HOPPER, "--method", "beat", "--json"])
    assert json.loads(capsys.readouterr().out)["max_count"][0] == 8
    code = rtctl_main(["render", HOPPER, "--method", "roi", "--normalize", "image"])
    assert code == 2 and "--normalize applies to --method beat only" in capsys.readouterr().err
