"""The contract of the engine's Python bindings (crates/legslam-py/src/convert.rs): every entry
runs the engine behind a guard that turns a panic into RuntimeError, bindings name the argument
whose shape or dtype is wrong, and options keep their kinds."""

import os
import sys
import threading
import time

import numpy as np
import pytest

from legslam import _core

K = np.array([[60.0, 0, 31.5], [0, 60, 23.5], [0, 0, 1]])
W, H = 64, 48


def _frame():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    depth = np.full((H, W), 2.0, np.float32)
    return rgb, depth


def _gaussians(n=5):
    rng = np.random.default_rng(1)
    return dict(means=np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), np.full(n, 2.0)]).astype(np.float32),
                log_scales=np.full((n, 3), -3.0, np.float32),
                quats=np.tile(np.array([1.0, 0, 0, 0], np.float32), (n, 1)),
                opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32),
                features=np.zeros((n, 2), np.float32))


def _entries():
    """name -> a call of that entry with valid arguments. Objects are made before panics are
    injected, so that each call reaches only its own entry."""
    rgb, depth = _frame()
    mapper = _core.MapperCore({"levels": 1, "finest_level": 0, "grow_level": 0, "num_features": 2})
    mapper.add_keyframe(rgb.astype(np.float32) / 255, depth, K, np.eye(4))
    tracker = _core.TrackerCore({"levels": 2, "finest_level": 0, "min_inliers": 10})
    reference = tracker.prepare_reference(rgb, depth, K, np.eye(4))
    odometry = _core.OdometryCore({"levels": 2, "finest_level": 0, "min_inliers": 10}, np.eye(4), True)
    tsdf = _core.TsdfCore(0.05, 0.2, 64.0, 0.1, 10.0)
    g = _gaussians()
    rendered = _core.render(*g.values(), K, np.eye(4), W, H, 0, True, True, True)
    return {
        "mapper_options": lambda: _core.mapper_options({"window": 3}),
        "tracker_options": lambda: _core.tracker_options(),
        "register_depth": lambda: _core.register_depth(depth, K, K, np.eye(4), W, H),
        "scaled_intrinsics": lambda: _core.scaled_intrinsics(K, W, H, 0.5),
        "render": lambda: _core.render(*g.values(), K, np.eye(4), W, H, 0, True, True, True),
        "Render.backward": lambda: rendered.backward(d_color=np.ones((H, W, 3), np.float32)),
        "MapperCore": lambda: _core.MapperCore({"levels": 1, "finest_level": 0, "grow_level": 0}),
        "MapperCore.add_keyframe": lambda: mapper.add_keyframe(rgb.astype(np.float32) / 255, depth, K, np.eye(4)),
        "MapperCore.set_features": lambda: mapper.set_features(0, np.zeros((2, 2, 2), np.float32)),
        "MapperCore.train": lambda: mapper.train(1),
        "MapperCore.render": lambda: mapper.render(np.eye(4), K, W, H),
        "MapperCore.config": lambda: mapper.config(),
        "MapperCore.keyframe_poses": lambda: mapper.keyframe_poses(),
        "MapperCore.keyframe_exposures": lambda: mapper.keyframe_exposures(),
        "MapperCore.export": lambda: mapper.export(),
        "MapperCore.correct_keyframes": lambda: mapper.correct_keyframes(np.eye(4)[None]),
        "TrackerCore": lambda: _core.TrackerCore({"levels": 2}),
        "TrackerCore.config": lambda: tracker.config(),
        "TrackerCore.prepare_reference": lambda: tracker.prepare_reference(rgb, depth, K, np.eye(4)),
        "TrackerCore.track": lambda: tracker.track(reference, rgb, depth, K, np.eye(4)),
        "OdometryCore": lambda: _core.OdometryCore({}, np.eye(4), True),
        "OdometryCore.step": lambda: odometry.step(rgb, depth, K),
        "TsdfCore": lambda: _core.TsdfCore(0.05, 0.2, 64.0, 0.1, 10.0),
        "TsdfCore.integrate": lambda: tsdf.integrate(depth, K, np.eye(4)),
        "TsdfCore.raycast": lambda: tsdf.raycast(K, W, H, np.eye(4), depth),
        "pose_graph_options": lambda: _core.pose_graph_options({"robust_scale": 2.0}),
        "optimize_pose_graph": lambda: _core.optimize_pose_graph(
            np.stack([np.eye(4), np.eye(4)]), [(0, 1, np.eye(4), np.eye(6), "odometry")]),
    }


def _module_entries() -> set:
    """Every function, constructor and method the module offers (getters excluded: they read a
    value and run no engine code)."""
    names = set()
    for name in dir(_core):
        obj = getattr(_core, name)
        if name.startswith("_") or not callable(obj):
            continue
        if not isinstance(obj, type):
            names.add(name)
            continue
        if getattr(obj, "__text_signature__", None) is not None:  # constructible from Python
            names.add(name)
        names |= {f"{name}.{m}" for m in vars(obj) if not m.startswith("_") and callable(getattr(obj, m))}
    return names


def test_every_entry_turns_an_engine_panic_into_runtime_error():
    entries = _entries()
    assert set(entries) == _module_entries(), "an entry without a case here (or a stale case)"
    for name, call in entries.items():
        call()  # works without the injected panic
        _core._inject_panic(True)
        try:
            with pytest.raises(RuntimeError, match="failed internally"):
                call()
        finally:
            _core._inject_panic(False)


def test_bindings_name_the_argument_with_the_wrong_shape_or_dtype():
    rgb, depth = _frame()
    mapper = _core.MapperCore({})
    with pytest.raises(ValueError, match=r"rgb must have shape 48x64x3, got \[48, 64\]"):
        mapper.add_keyframe(depth, depth, K, np.eye(4))
    with pytest.raises(ValueError, match="depth must be a float32 array, got dtype uint16"):
        mapper.add_keyframe(rgb.astype(np.float32), depth.astype(np.uint16), K, np.eye(4))
    with pytest.raises(ValueError, match="K must have shape 3x3"):
        mapper.render(np.eye(4), K[:2], W, H)
    with pytest.raises(ValueError, match=r"K must be a pinhole matrix"):
        mapper.render(np.eye(4), K.T, W, H)
    with pytest.raises(ValueError, match="pose must be a 4x4 numpy array"):
        mapper.render([[1.0]], K, W, H)
    with pytest.raises(ValueError, match="width and height must be positive, got -1x48"):
        mapper.render(np.eye(4), K, -1, H)
    tracker = _core.TrackerCore({})
    with pytest.raises(ValueError, match="reference depth must be a float32 array, got dtype uint16"):
        # Millimetres are never taken as metres.
        tracker.prepare_reference(rgb, depth.astype(np.uint16), K, np.eye(4))


def test_options_keep_their_kinds_from_python_to_the_engine():
    opts = _core.tracker_options({"iterations": [3, 2], "estimate_gain": False, "max_depth": 5})
    assert opts["iterations"] == [3, 2] and opts["estimate_gain"] is False and opts["max_depth"] == 5.0
    assert isinstance(_core.mapper_options()["window"], int)
    assert _core.mapper_options()["lr_sh"] == 0.0025, "reals read back as the decimal they were set to"
    for bad, message in (({"estimate_gain": 1}, "estimate_gain must be true or false, got 1"),
                         ({"levels": 2.0}, "levels must be a whole number >= 0, got 2.0"),
                         ({"levels": -1}, "levels must be a whole number >= 0, got -1"),
                         ({"iterations": 4}, "iterations must be a list of whole numbers"),
                         ({"max_depth": "far"}, "max_depth must be a number, got 'far'"),
                         ({"max_depth": float("nan")}, "max_depth must be finite"),
                         ({"lost": 1}, 'unknown tracker option "lost"')):
        with pytest.raises(ValueError, match=message):
            _core.tracker_options(bad)


def test_keyframe_corrections_are_checked_by_name_and_value():
    rgb, depth = _frame()
    mapper = _core.MapperCore({"levels": 1, "finest_level": 0, "grow_level": 0})
    mapper.add_keyframe(rgb.astype(np.float32) / 255, depth, K, np.eye(4))
    with pytest.raises(ValueError, match=r"corrections must have shape Nx4x4, got \[4, 4\]"):
        mapper.correct_keyframes(np.eye(4))
    with pytest.raises(ValueError, match="2 corrections for 1 keyframes"):
        mapper.correct_keyframes(np.stack([np.eye(4)] * 2))
    skew = np.eye(4)
    skew[0, 1] = 0.5
    with pytest.raises(ValueError, match="correction 0 rotation must be orthonormal"):
        mapper.correct_keyframes(skew[None])
    assert mapper.correct_keyframes(np.eye(4)[None]) == mapper.num_gaussians


def test_learning_rate_scales_reach_their_groups_and_are_checked_by_name_and_value():
    rgb, depth = _frame()

    def first_step(lr_scale):
        mapper = _core.MapperCore({"levels": 1, "finest_level": 0, "grow_level": 0})
        mapper.add_keyframe(rgb.astype(np.float32) / 255, depth, K, np.eye(4))
        before = mapper.export()
        mapper.train(1, lr_scale=lr_scale)
        after = mapper.export()
        return {g: np.abs(after[g] - before[g]).sum() for g in ("means", "log_scales", "sh")}

    one, both = first_step(1.0), first_step(2.0)
    by_group = first_step({"sh": 2.0, "means": 0.5})
    # Adam's first step is the rate times the gradient's sign.
    for group, want in (("sh", 2.0), ("means", 0.5), ("log_scales", 1.0)):
        assert one[group] > 0
        assert by_group[group] / one[group] == pytest.approx(want, rel=1e-2), group
        assert both[group] / one[group] == pytest.approx(2.0, rel=1e-2), group
    mapper = _core.MapperCore({"levels": 1, "finest_level": 0, "grow_level": 0})
    mapper.add_keyframe(rgb.astype(np.float32) / 255, depth, K, np.eye(4))
    with pytest.raises(ValueError, match='no learning-rate group "colour"'):
        mapper.train(1, lr_scale={"colour": 2.0})
    with pytest.raises(ValueError, match="learning-rate scale of sh must be > 0"):
        mapper.train(1, lr_scale={"sh": 0.0})
    with pytest.raises(ValueError, match="must be > 0"):
        mapper.train(1, lr_scale=-1.0)


def _map_pool_threads() -> dict:
    """Thread id -> nice value of the process's mapper pool threads (Linux /proc)."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            if open(f"/proc/self/task/{tid}/comm").read().startswith("legslam-map"):
                out[int(tid)] = os.getpriority(os.PRIO_PROCESS, int(tid))
        except OSError:  # the thread ended meanwhile (a dropped pool's threads exit on their own time)
            continue
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="thread priorities are set on Linux only")
def test_a_background_mappers_threads_give_way_to_the_others():
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    for background, nice in ((True, min(mine + 10, 19)), (False, mine)):
        before = set(_map_pool_threads())
        mapper = _core.MapperCore(threads=2, background=background)
        deadline = time.monotonic() + 5  # rayon starts its threads as the pool is built
        while len(set(_map_pool_threads()) - before) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        new = {t: n for t, n in _map_pool_threads().items() if t not in before}
        assert len(new) == 2 and set(new.values()) == {nice}, (background, new, mine)
        del mapper
