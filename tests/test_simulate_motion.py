"""The simulator's moving objects and scene cut: known motion in the ground truth, occlusion, the cut frame's
truth, determinism and argument errors (nrhdr_core.simulate, `nrhdr simulate`)."""
import json

import numpy as np
import pytest

from gst_plugins import cli
from nrhdr_core import io, profile, simulate

H, W = 48, 64
STILL = simulate.Motion(pan=0.0, tilt=0.0, zoom=1.0, fov=0.8)


def scene_a():
    """60 x 80: the 48 x 64 view at fov 0.8 samples it 1:1 (no anti-aliasing filter)."""
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float32)
    return (1.0 + 0.5 * np.sin(xx / 3.0) * np.cos(yy / 4.0)).astype(np.float32)


def scene_b():
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float32)
    return (0.2 + (xx > 40) * 8.0 + yy / 60.0).astype(np.float32)


def truths(d, n):
    return [io.read_exr(d / "truth" / f"frame_{i:05d}.exr")[0] for i in range(n)]


def clip(tmp_path, name, frames=5, **kw):
    kw.setdefault("motion", STILL)
    simulate.simulate_clip(scene_a(), tmp_path / name, profile.default(H, W, seed=1), frames=frames, seed=4,
                           progress=False, **kw)
    return truths(tmp_path / name, frames)


def distance(x, y):
    yy, xx = np.mgrid[0:H, 0:W]
    return np.hypot(xx - x, yy - y)


@pytest.mark.parametrize("kind", ["disc", "patch"])
def test_object_moves_exactly_v_pixels_per_frame_and_occludes(tmp_path, kind):
    v = (3, -2)
    o = simulate.MovingObject(kind=kind, x=20.0, y=30.0, vx=v[0], vy=v[1], size=12, source=(0.3, 0.6))
    t = clip(tmp_path, "o", objects=[o])
    bg = clip(tmp_path, "bg")
    k = simulate.exposure_scale(scene_a(), profile.default(H, W, seed=1), 0.0)
    for i in range(5):
        cx, cy = 20 + v[0] * i, 30 + v[1] * i
        d = distance(cx, cy)
        inside = d <= 6 - 1.5            # fully covered (a patch covers the disc inscribed in it)
        outside = np.maximum(np.abs(np.mgrid[0:H, 0:W][1] - cx), np.abs(np.mgrid[0:H, 0:W][0] - cy)) >= 6 + 1
        assert np.array_equal(t[i][outside], bg[i][outside])          # the background is untouched around it
        if kind == "disc":
            level = np.float32(np.float32(simulate.OBJECT_BRIGHT * np.median(scene_a())) * np.float32(k))
            assert np.all(t[i][inside] == level)
        else:
            assert t[i][inside].std() > 0.05 * t[i][inside].mean()   # the scene's texture, not a flat level
            assert not np.array_equal(t[i][inside], bg[i][inside])
        if i:
            ys, xs = np.nonzero(inside)
            assert np.array_equal(t[i][ys, xs], t[i - 1][ys - v[1], xs - v[0]])   # the same pixels, moved by v


def test_later_objects_occlude_earlier_ones(tmp_path):
    bright = simulate.MovingObject(kind="disc", x=30.0, y=24.0, size=20, level=simulate.OBJECT_BRIGHT)
    dark = simulate.MovingObject(kind="disc", x=34.0, y=24.0, size=10, level=simulate.OBJECT_DARK)
    t = clip(tmp_path, "o", frames=1, objects=[bright, dark])[0]
    both = distance(34, 24) <= 3.5
    only_bright = (distance(30, 24) <= 8.5) & (distance(34, 24) >= 6.5)
    assert np.ptp(t[both]) == 0 and np.ptp(t[only_bright]) == 0
    assert t[both][0] == pytest.approx(t[only_bright][0] * simulate.OBJECT_DARK / simulate.OBJECT_BRIGHT, rel=1e-6)


def test_cut_frame_truth_is_the_second_scenes_view(tmp_path):
    prof = profile.default(H, W, seed=1)
    motion = simulate.Motion(pan=0.1, tilt=0.0, zoom=1.0, fov=0.8)
    o = simulate.MovingObject(x=30.0, y=20.0, vx=2.0, size=8)
    t = clip(tmp_path, "c", frames=6, motion=motion, objects=[o], cut_frame=3, cut_scene=scene_b())
    info = json.loads((tmp_path / "c" / "clip.json").read_text())
    kb = simulate.exposure_scale(scene_b(), prof, 0.0)
    assert info["cut"]["frame"] == 3 and info["cut"]["exposure_scale"] == kb
    for i in range(3, 6):     # the second shot: the same camera path over scene b, exposed for it, no object
        expect = simulate.view(scene_b(), H, W, i / 5, motion) * np.float32(kb)
        assert np.array_equal(t[i], expect)
    plain = clip(tmp_path, "p", frames=6, motion=motion, objects=[o])
    assert all(np.array_equal(t[i], plain[i]) for i in range(3))     # the first shot is the clip without a cut


def test_default_cut_turns_the_scene_by_180_degrees(tmp_path):
    t = clip(tmp_path, "c", frames=3, cut_frame=1)
    k = simulate.exposure_scale(scene_a(), profile.default(H, W, seed=1), 0.0)
    expect = simulate.view(scene_a()[::-1, ::-1].copy(), H, W, 0.5, STILL) * np.float32(k)
    assert np.array_equal(t[1], expect)
    assert not np.array_equal(t[0], t[1])


def test_random_objects_follow_the_seed_and_their_speed():
    a = simulate.random_objects(6, H, W, 8, speed=5.0, size=10, kind="mixed", seed=3)
    assert a == simulate.random_objects(6, H, W, 8, speed=5.0, size=10, kind="mixed", seed=3)
    assert a != simulate.random_objects(6, H, W, 8, speed=5.0, size=10, kind="mixed", seed=4)
    assert [o.kind for o in a] == ["patch", "disc", "disc"] * 2
    assert [o.level for o in a if o.kind == "disc"] == [simulate.OBJECT_BRIGHT, simulate.OBJECT_DARK] * 2
    for o in a:
        assert np.hypot(o.vx, o.vy) == pytest.approx(5.0)
        xm, ym = o.centre(3.5)                       # mid-clip: inside the view's central 70 %
        assert 0.15 * W <= xm <= 0.85 * W and 0.15 * H <= ym <= 0.85 * H


def test_objects_are_deterministic_in_the_clip(tmp_path):
    objs = simulate.random_objects(4, H, W, 3, speed=6.0, size=14, seed=2)
    a = clip(tmp_path, "a", frames=3, objects=objs)
    b = clip(tmp_path, "b", frames=3, objects=objs)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert (tmp_path / "a" / "clip.raw").read_bytes() == (tmp_path / "b" / "clip.raw").read_bytes()
    assert json.loads((tmp_path / "a" / "clip.json").read_text())["objects"][0]["kind"] == "patch"


@pytest.mark.parametrize("kw, match", [
    ({"cut_frame": 5}, "cut_frame must be an integer in 1..4"),
    ({"cut_frame": 0}, "cut_frame"),
    ({"cut_frame": 2.0}, "cut_frame"),
    ({"objects": [simulate.MovingObject(kind="star")]}, r"objects\[0\]: kind"),
    ({"objects": [simulate.MovingObject(vx=float("nan"))]}, r"objects\[0\]: vx"),
    ({"objects": [simulate.MovingObject(size=0.5)]}, r"objects\[0\]: size"),
    ({"objects": [simulate.MovingObject(level=0.0)]}, r"objects\[0\]: level"),
    ({"objects": [simulate.MovingObject(source=(0.5, 2.0))]}, r"objects\[0\]: source"),
    ({"objects": ["disc"]}, r"objects\[0\] must be a simulate.MovingObject"),
    ({"cut_scene": np.ones((8, 8))}, "cut_scene is given but cut_frame is not"),
    ({"cut_frame": 2, "cut_scene": np.full((8, 8), np.nan)}, "cut scene: 64 scene values are NaN"),
])
def test_bad_motion_arguments_are_refused_before_writing(tmp_path, kw, match):
    with pytest.raises(ValueError, match=match):
        simulate.simulate_clip(scene_a(), tmp_path / "c", profile.default(H, W), frames=5, progress=False, **kw)
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("kw, match", [({"kind": "star"}, "object kind must be one of disc, patch, mixed"),
                                       ({"count": -1}, "objects must be an integer in 0..1000"),
                                       ({"speed": float("inf")}, "object speed")])
def test_random_objects_errors(kw, match):
    args = {"count": 2, "height": H, "width": W, "frames": 4, "speed": 2.0, "size": 8.0, **kw}
    with pytest.raises(ValueError, match=match):
        simulate.random_objects(**args)


def test_cli_objects_and_cut(tmp_path, capsys):
    out = tmp_path / "clip"
    rc = cli.main(["simulate", "-o", str(out), "--frames", "4", "--width", "64", "--height", "48",
                   "--objects", "3", "--object-speed", "5", "--object-size", "12", "--cut-frame", "2"])
    assert rc == 0
    info = json.loads((out / "clip.json").read_text())
    assert len(info["objects"]) == 3 and info["cut"]["frame"] == 2
    assert all(np.hypot(o["vx"], o["vy"]) == pytest.approx(5.0) for o in info["objects"])
    for args, match in ((["--cut-frame", "4"], "--cut-frame must be an integer in 1..3"),
                        (["--cut-scene", "synthetic"], "--cut-scene needs --cut-frame"),
                        (["--objects", "1001"], "--objects: 1001 is out of range"),
                        (["--object-speed", "nan"], "--object-speed: 'nan' is not a finite number")):
        capsys.readouterr()
        rc = cli.main(["simulate", "-o", str(tmp_path / "bad"), "--frames", "4", "--width", "16", "--height",
                       "12", *args])
        assert rc == 2 and match in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()


def test_live_scene_camera_renders_the_objects_and_the_cut():
    from nrhdr_core import realtime
    prof = profile.default(H, W, seed=1)
    bright = simulate.MovingObject(x=12.0, y=24.0, vx=10.0, size=16, level=simulate.OBJECT_BRIGHT)
    plain = realtime.SceneCamera(scene_a(), prof, frames=4, motion=STILL, seed=2)
    cam = realtime.SceneCamera(scene_a(), prof, frames=4, motion=STILL, seed=2, objects=[bright], cut_frame=3,
                               cut_scene=scene_b())
    for i in range(3):
        disc, away = distance(12 + 10 * i, 24) <= 6, distance(12 + 10 * i, 24) >= 10
        assert cam.frame(i)[disc].mean() > 2 * plain.frame(i)[disc].mean()        # the bright disc, moving
        assert abs(cam.frame(i)[away].mean() / plain.frame(i)[away].mean() - 1) < 0.02
    assert np.array_equal(cam.frame(3 + 4), cam.frame(3))                           # the path repeats
    second = realtime.SceneCamera(scene_b(), prof, frames=4, motion=STILL, seed=2)
    assert np.array_equal(cam.frame(3), second.frame(3))            # the cut: scene b's view, the same noise
