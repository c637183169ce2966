"""The SLAM loop end to end on the built-in synthetic scene, with bounds that a broken tracker
or mapper cannot meet: each is compared against a run with that part disabled."""

import json
import logging
import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_viewer import ColourEncoder

from legslam.cli import main
from legslam.cli.progress import Progress
from legslam.datasets import open as open_dataset
from legslam.eval import ate, read_tum
from legslam.map import GaussianMap
from legslam.pipeline import run
from legslam.slam import SLAM, SLAMConfig


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from legslam.datasets import synthetic

    return synthetic.generate(tmp_path_factory.mktemp("scene"), n_frames=24, width=160, height=120, seed=3)


def psnr_of(result):
    return result["metrics"]["every_5"]["psnr"]


@pytest.fixture(scope="module")
def mapped(scene, tmp_path_factory):
    cfg = SLAMConfig(features=False, final_iters=30)
    return run(open_dataset(scene), tmp_path_factory.mktemp("mapped"), cfg)


def test_slam_tracks_and_maps_the_synthetic_scene(mapped, scene):
    m = mapped["metrics"]
    seq = open_dataset(scene)
    gt = np.stack([seq[i].pose for i in range(len(seq))])
    # A tracker that never moves scores the camera's own spread; ours is far below it.
    still = ate(gt, np.repeat(np.eye(4)[None], len(gt), axis=0))["rmse"]
    assert m["ate_rmse_cm"] < 1 and m["ate_rmse_cm"] < 0.1 * 100 * still, (m["ate_rmse_cm"], still)
    assert m["lost_frames"] == 0 and m["keyframes"] >= 2
    assert m["every_5"]["psnr"] > 27, m
    assert m["every_5"]["depth_l1_cm"] < 3, m
    assert m["every_5"]["ssim"] > 0.9, m


def test_mapping_improves_the_map(mapped, scene, tmp_path):
    frozen = SLAMConfig(features=False, map_iters_keyframe=0, map_iters_frame=0, final_iters=0)
    unmapped = run(open_dataset(scene), tmp_path, frozen)
    assert psnr_of(mapped) > psnr_of(unmapped) + 2.0, (psnr_of(mapped), psnr_of(unmapped))


def test_outputs_are_written(mapped):
    out = Path(mapped["out"])
    stamps, poses = read_tum(out / "trajectory.txt")
    assert len(poses) == mapped["metrics"]["frames"] == 24
    timings = json.loads((out / "timings.json").read_text())
    for stage in ("preprocessing", "tracking", "mapping"):
        assert timings[stage]["count"] == 24
    assert timings["fps_live"] >= timings["fps"] > 0  # the final iterations come after the frames
    # synchronous: the keyframes' iterations while frames come in, then the final ones
    cfg, its = mapped["slam"].config, timings["mapping_iterations"]
    assert its["while_frames_came_in"] == cfg.map_iters_keyframe * mapped["metrics"]["keyframes"], its
    assert its["final"] == cfg.final_iters + round(cfg.final_iters_per_frame * 24), its
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["gaussians"] > 1000 and metrics["map_full_at_frame"] is None
    # Why each keyframe was made, one reason per keyframe frame; the first starts the map.
    reasons, frames = metrics["keyframe_reasons"], metrics["keyframe_frames"]
    assert len(reasons) == len(frames) == metrics["keyframes"] and frames[0] == 0
    assert reasons[0] == "first" and set(reasons[1:]) <= {"moved", "turned", "coverage", "gap"}
    # Synchronous: every frame after the first is tracked against the surface from the one before.
    assert metrics["surface_reference_age"] == {"mean": 1.0, "frames": {"1": 23}}
    assert (out / "map.ply").stat().st_size > 1000
    assert any((out / "renders").glob("*_input_render.png"))


def test_slam_rejects_bad_frames(scene):
    seq = open_dataset(scene)
    f = seq[0]
    slam = SLAM(SLAMConfig(features=False), f.K, 160, 120)
    with pytest.raises(ValueError, match="rgb must be 120x160x3 uint8"):
        slam.step(f.rgb[:60], f.depth)
    with pytest.raises(ValueError, match="depth must be 120x160"):
        slam.step(f.rgb, f.depth[:, :80])
    # NaN and zero depth are invalid pixels, not errors.
    depth = f.depth.copy()
    depth[:10] = np.nan
    depth[10:20] = 0
    assert slam.step(f.rgb, depth).state == "init"


def test_config_files_and_unknown_options(tmp_path):
    (tmp_path / "c.toml").write_text("keyframe_translation = 0.2\n[mapper]\nwindow = 4\n"
                                     "[tracker]\nmax_depth = 8\n")
    cfg = SLAMConfig.from_file(tmp_path / "c.toml")
    assert cfg.keyframe_translation == 0.2 and cfg.mapper.window == 4 and cfg.tracker.max_depth == 8
    slam = SLAM(cfg, np.eye(3) * [[100], [100], [1]], 64, 48)
    assert slam.mapper.config()["window"] == 4, "a section's option reaches the engine"
    assert slam.tracking.tracker.config["max_depth"] == 8
    # Keyframes are aligned with the tracker's options, `covisibility_coarser` levels coarser.
    covis = slam.covisibility.tracker.config
    assert covis["max_depth"] == 8 and covis["finest_level"] == slam.tracking.tracker.config["finest_level"] + 1
    (tmp_path / "bad.json").write_text('{"keyframe_translaton": 0.2}')
    with pytest.raises(ValueError, match="unknown option.*keyframe_translaton"):
        SLAMConfig.from_file(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="unknown mapper option.*windw"):
        SLAMConfig(features=False, mapper={"windw": 3})
    # A config file reads back what a run wrote into config.json.
    (tmp_path / "again.json").write_text(json.dumps(cfg.to_dict()))
    assert SLAMConfig.from_file(tmp_path / "again.json") == cfg


def test_the_command_runs_in_real_time_unless_told_or_configured_otherwise(tmp_path, capsys):
    from legslam.cli import build_parser
    from legslam.cli.run import run_config

    def mapping_thread(*options):
        return run_config(build_parser().parse_args(["run", "somewhere", *options])).mapping_thread

    (tmp_path / "sync.toml").write_text("mapping_thread = false\nfinal_iters = 7\n")
    (tmp_path / "other.json").write_text('{"final_iters": 7}')
    (tmp_path / "list.json").write_text("[1, 2]")
    assert mapping_thread() and mapping_thread("--realtime")
    assert not mapping_thread("--sync")
    # A config file's mode holds unless an option says otherwise; one without keeps the default.
    assert not mapping_thread("--config", str(tmp_path / "sync.toml"))
    assert mapping_thread("--config", str(tmp_path / "sync.toml"), "--realtime")
    assert mapping_thread("--config", str(tmp_path / "other.json"))
    assert not mapping_thread("--config", str(tmp_path / "other.json"), "--sync")
    with pytest.raises(SystemExit):
        mapping_thread("--sync", "--realtime")
    assert "not allowed with argument" in capsys.readouterr().err
    with pytest.raises(ValueError, match="holds options by name, not list"):
        SLAMConfig.from_file(tmp_path / "list.json")
    # The library's own default stays synchronous (a run that repeats itself).
    assert not SLAMConfig().mapping_thread


def test_config_sections_are_the_engine_options_and_a_derived_one_is_set_in_one_place():
    from legslam import _core
    from legslam.slam import DERIVED, MapperOptions, TrackerOptions
    from dataclasses import fields

    for section, cls, engine in (("mapper", MapperOptions, _core.mapper_options()),
                                 ("tracker", TrackerOptions, _core.tracker_options())):
        names = {f.name for f in fields(cls)}
        assert names | set(DERIVED[section]) == set(engine) and not names & set(DERIVED[section])
    # What SLAMConfig derives cannot be set in a section too: the error names both.
    with pytest.raises(ValueError, match="mapper.sh_degree is set from sh_degree"):
        SLAMConfig(mapper={"sh_degree": 0})
    # Kinds and values are checked before any frame, by name.
    with pytest.raises(ValueError, match="mapper.window must be an integer, got 2.5"):
        SLAMConfig(mapper={"window": 2.5})
    with pytest.raises(ValueError, match="mapper.adam_sparse must be true or false, got 1"):
        SLAMConfig(mapper={"adam_sparse": 1})
    with pytest.raises(ValueError, match="mapper: revisit must lie in \\[0, 1\\], got 2"):
        SLAMConfig(mapper={"revisit": 2.0})
    for flatness in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="mapper: .*grow_flatness must"):
            SLAMConfig(mapper={"grow_flatness": flatness})
    with pytest.raises(ValueError, match="tracker.iterations must be a list of integers"):
        SLAMConfig(tracker={"iterations": 3})
    with pytest.raises(ValueError, match="tracker: .*geometric_huber must be positive"):
        SLAMConfig(tracker={"geometric_huber": -1.0})


def test_cli_run_writes_a_trajectory_per_frame(scene, tmp_path, capsys):
    assert main(["run", str(scene), "--no-features", "--max-frames", "8", "--out", str(tmp_path), "--quiet",
                 "--final-iters", "7"]) == 0
    _, poses = read_tum(tmp_path / "trajectory.txt")
    assert len(poses) == 8
    assert json.loads((tmp_path / "config.json").read_text())["final_iters"] == 7
    assert "ATE RMSE" in capsys.readouterr().out


def test_cli_errors_are_actionable(scene, mapped, tmp_path, capsys):
    assert main(["run", str(tmp_path / "nowhere")]) == 2
    assert "nowhere" in capsys.readouterr().err
    assert main(["run", str(tmp_path), "--stride", "0"]) == 2
    assert "--stride must be at least 1" in capsys.readouterr().err
    assert main(["run", str(tmp_path), "--final-iters", "-1"]) == 2
    assert "--final-iters must be at least 0" in capsys.readouterr().err
    # Where outputs cannot go: said before any work.
    (tmp_path / "a-file").write_text("")
    for command in (["run", str(scene), "--out", str(tmp_path / "a-file")],
                    ["demo", "--out", str(tmp_path / "a-file" / "sub")],
                    ["render", mapped["out"], "--out", str(tmp_path / "a-file")]):
        assert main(command) == 2, command
        assert f"{tmp_path / 'a-file'}" in capsys.readouterr().err, command
    assert main(["odometry", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "is a folder: give a file name" in capsys.readouterr().err


def test_cli_render_and_eval_on_a_run(mapped, tmp_path, capsys):
    out = Path(mapped["out"])
    assert main(["render", str(out), "--every", "10", "--out", str(tmp_path)]) == 0
    views = sorted(tmp_path.glob("*_color.png"))
    assert len(views) == 3  # poses 0, 10, 20 of 24
    color = cv2.imread(str(views[0]))
    depth = cv2.imread(str(tmp_path / "000000_depth.png"), cv2.IMREAD_UNCHANGED)
    assert color.shape == (120, 160, 3) and color.std() > 10
    assert depth.dtype == np.uint16 and 500 < np.median(depth[depth > 0]) < 10000
    capsys.readouterr()
    assert main(["eval", str(out)]) == 0
    report = json.loads((out / "eval.json").read_text())
    # The same map and poses as the run's own evaluation: the same numbers.
    assert abs(report["ate_rmse_cm"] - mapped["metrics"]["ate_rmse_cm"]) < 1e-4
    assert abs(report["every_5"]["psnr"] - mapped["metrics"]["every_5"]["psnr"]) < 0.05
    assert "| every_5[psnr] |" in capsys.readouterr().out
    assert main(["eval", str(tmp_path)]) == 2


def test_eval_sees_the_frames_a_strided_run_saw(scene, tmp_path, capsys):
    quick = tmp_path / "quick.toml"
    quick.write_text("features = false\nfinal_iters = 3\nmap_iters_keyframe = 3\n")
    out = tmp_path / "run"
    assert main(["run", str(scene), "--stride", "3", "--max-frames", "6", "--quiet",
                 "--config", str(quick), "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert main(["eval", str(out), "--every", "1"]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["frames"] == 6
    assert abs(report["ate_rmse_cm"] - metrics["ate_rmse_cm"]) < 1e-4


def test_cli_demo_runs_end_to_end(tmp_path, capsys):
    quick = tmp_path / "quick.toml"
    quick.write_text("final_iters = 5\nmap_iters_keyframe = 3\n")
    assert main(["demo", "--frames", "6", "--no-features", "--quiet", "--config", str(quick),
                 "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "ATE RMSE" in out and "PSNR" in out
    assert "(map rendered at frames 0, 5, 10, ...)" in out
    _, poses = read_tum(tmp_path / "out" / "trajectory.txt")
    assert len(poses) == 6
    assert (tmp_path / "out" / "map.ply").is_file() and (tmp_path / "out" / "metrics.json").is_file()
    # In real time by default, the map given at least the floor's share of a synchronous run's
    # iterations.
    config = json.loads((tmp_path / "out" / "config.json").read_text())
    default = SLAMConfig()
    assert config["mapping_thread"] is True
    assert config["realtime_iters_floor"] == default.realtime_iters_floor > 0
    its = json.loads((tmp_path / "out" / "timings.json").read_text())["mapping_iterations"]
    keyframes = json.loads((tmp_path / "out" / "metrics.json").read_text())["keyframes"]
    synchronous = 3 * keyframes + 5 + round(default.final_iters_per_frame * 6)
    assert its["while_frames_came_in"] + its["final"] >= default.realtime_iters_floor * synchronous, its


def test_a_garbage_frame_is_lost_and_tracking_recovers(scene):
    seq = open_dataset(scene)
    f0 = seq[0]
    slam = SLAM(SLAMConfig(features=False, map_iters_frame=1, final_iters=0), f0.K, 160, 120)
    rng = np.random.default_rng(0)
    states = []
    for i in range(12):
        f = seq[i]
        if i == 6:  # a frame from another world: noise colour, random depth
            noise = rng.integers(0, 255, f.rgb.shape, dtype=np.uint8)
            states.append(slam.step(noise, rng.uniform(0.5, 4, f.depth.shape).astype(np.float32)).state)
        else:
            states.append(slam.step(f.rgb, f.depth).state)
    assert states[6] == "lost" and states[7:] == ["ok"] * 5, states
    gt = np.stack([seq[i].pose for i in range(12) if i != 6])
    est = np.stack([p for i, p in enumerate(slam.poses) if i != 6])
    assert ate(gt, est)["rmse"] < 0.01


def test_frames_without_valid_depth_do_not_stall_the_map(scene):
    seq = open_dataset(scene)
    f0 = seq[0]
    slam = SLAM(SLAMConfig(features=False, map_iters_frame=1, final_iters=0), f0.K, 160, 120)
    empty = np.zeros_like(f0.depth)
    assert slam.step(f0.rgb, empty).state == "init"
    assert slam.step(seq[1].rgb, np.full_like(f0.depth, np.nan)).state == "init"
    assert slam.mapper.num_gaussians == 0
    states = [slam.step(seq[i].rgb, seq[i].depth).state for i in range(2, 8)]
    assert states[0] == "init" and states[1:] == ["ok"] * 5, states
    assert slam.mapper.num_gaussians > 1000


def test_a_full_map_is_said_once_with_the_frame_it_filled_at(scene, caplog):
    seq = open_dataset(scene)

    def twelve_frames(**mapper):
        slam = SLAM(SLAMConfig(features=False, final_iters=0, mapper=mapper), seq[0].K, 160, 120)
        caplog.clear()
        for i in range(12):
            slam.step(seq[i].rgb, seq[i].depth)
        return slam, [r.message for r in caplog.records if "max_gaussians" in r.message]

    roomy, said = twelve_frames()
    assert roomy.map_full_at is None and said == []
    # Room for the first keyframe's Gaussians and a few more: the map fills later.
    probe = SLAM(SLAMConfig(features=False), seq[0].K, 160, 120)
    probe.step(seq[0].rgb, seq[0].depth)
    cap = probe.mapper.num_gaussians + 50
    full, said = twelve_frames(max_gaussians=cap)
    assert len(full.keyframe_frames) >= 2 and full.map_full_at is not None and full.map_full_at > 0
    assert full.mapper.num_gaussians <= cap
    assert len(said) == 1 and f"frame {full.map_full_at}:" in said[0] and f"{cap} Gaussians" in said[0]


def test_final_iterations_report_progress_and_train_the_same_map_in_batches(scene, monkeypatch, capsys,
                                                                            tmp_path):
    import legslam.slam.system as slam_module

    seq = open_dataset(scene)

    def mapped(batch, progress=None):
        monkeypatch.setattr(slam_module, "FINAL_BATCH", batch)
        # At a constant learning rate (annealed, each batch has its own).
        slam = SLAM(SLAMConfig(features=False, map_iters_keyframe=2, final_iters=60,
                               final_iters_per_frame=0.0, final_lr_factor=1.0), seq[0].K, 160, 120)
        for i in range(4):
            slam.step(seq[i].rgb, seq[i].depth)
        slam.finish(progress=progress)
        return slam

    calls = []
    batched = mapped(25, lambda done, total: calls.append((done, total)))
    assert calls == [(25, 60), (50, 60), (60, 60)]
    whole = mapped(1000)
    assert sum(s.iterations for s in batched.mapping_stats) == sum(s.iterations for s in whole.mapping_stats)
    a, b = batched.render(batched.poses[2]), whole.render(whole.poses[2])
    np.testing.assert_allclose(a["color"], b["color"], atol=1e-5)  # the same iterations, batched
    capsys.readouterr()
    run(seq, tmp_path, SLAMConfig(features=False, final_iters=30, final_iters_per_frame=0.0,
                                  map_iters_keyframe=2),
        progress=Progress(len(seq)))
    assert "final mapping iterations 30/30" in capsys.readouterr().err


class RecordingMapper:
    """A mapper that notes the iterations and learning-rate scales of each `train` call."""
    def __init__(self, mapper):
        self.mapper, self.iterations, self.scales = mapper, [], []

    def train(self, iterations, window=None, lr_scale=1.0):
        self.iterations.append(iterations)
        self.scales.append(lr_scale)
        return self.mapper.train(iterations, window=window, lr_scale=lr_scale)

    def __getattr__(self, name):
        return getattr(self.mapper, name)


def test_final_learning_rates_fall_by_the_configured_factor(scene, monkeypatch):
    import legslam.slam.system as slam_module

    seq = open_dataset(scene)
    monkeypatch.setattr(slam_module, "FINAL_BATCH", 25)

    def scales(frames=3, **options):
        slam = SLAM(SLAMConfig(features=False, map_iters_keyframe=2, final_iters_per_frame=0.0,
                               **options), seq[0].K, 160, 120)
        for i in range(frames):
            slam.step(seq[i].rgb, seq[i].depth)
        slam.mapper = RecordingMapper(slam.mapper)
        slam.finish()
        return slam.mapper.scales

    groups = ("means", "log_scales", "quats", "opacity", "sh", "features")
    assert scales(final_iters=100, final_lr_factor=1.0) == [dict.fromkeys(groups, 1.0)] * 4
    # Log-linear in the iterations done, per batch: 1, f^(1/4), f^(1/2), f^(3/4), every group.
    f = SLAMConfig().final_lr_factor
    assert f < 1
    for k, s in enumerate(scales(final_iters=100)):
        assert set(s) == set(groups)
        np.testing.assert_allclose(list(s.values()), f ** (k / 4), rtol=1e-12)
    # Real time, by the time spent: each group from the scale the frames trained it with down,
    # never below the factor times that scale. The budget (3 times the frames' time) holds
    # many batches, also on a loaded machine (at 0.5 a CI run beside a build got one).
    monkeypatch.setattr(slam_module, "FINAL_BATCH", 2)
    for start, geometry in ((1.0, 1.0), (3.0, 4.5)):
        timed = scales(12, final_iters=0, final_time=3.0, mapping_thread=True, final_lr_factor=0.1,
                       realtime_lr_scale=start, realtime_geometry_lr_scale=geometry,
                       realtime_iters_floor=0.0)
        assert len(timed) >= 2
        for group in groups:
            first = geometry if group in ("means", "log_scales", "quats") else start
            rates = [s[group] for s in timed]
            assert 0.95 * first < rates[0] <= first, (group, rates)
            assert all(0.1 * first <= b < a for a, b in zip(rates, rates[1:])), (group, rates)
            # Every group by the same share of its start at each batch.
            np.testing.assert_allclose([r / first for r in rates],
                                       [t["opacity"] / start for t in timed], rtol=1e-12)
    with pytest.raises(ValueError, match="final_lr_factor"):
        SLAMConfig(final_lr_factor=0.0)
    with pytest.raises(ValueError, match="realtime_lr_scale"):
        SLAMConfig(realtime_lr_scale=0.0)
    with pytest.raises(ValueError, match="realtime_geometry_lr_scale"):
        SLAMConfig(realtime_geometry_lr_scale=1e3)


def test_the_mapping_thread_trains_at_the_real_time_learning_rates(scene, monkeypatch):
    import legslam.slam.system as slam_module

    seq = open_dataset(scene)
    recorded = []

    class Recording(slam_module.ThreadedMapping):
        def __init__(self, mapper, *args, **kwargs):
            recorded.append(RecordingMapper(mapper))
            super().__init__(recorded[-1], *args, **kwargs)

    monkeypatch.setattr(slam_module, "ThreadedMapping", Recording)
    for scale, geometry in ((1.0, 1.0), (2.5, 4.0)):
        slam = SLAM(SLAMConfig(features=False, mapping_thread=True, final_iters=0, final_time=0.0,
                               realtime_lr_scale=scale, realtime_geometry_lr_scale=geometry),
                    seq[0].K, 160, 120)
        for i in range(6):
            slam.step(seq[i].rgb, seq[i].depth)
        # The first keyframe, trained a few batches before the thread stops.
        deadline = time.monotonic() + 60
        while len(recorded[-1].scales) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        slam.finish()
        assert len(recorded[-1].scales) >= 3
        want = {"means": geometry, "log_scales": geometry, "quats": geometry,
                "opacity": scale, "sh": scale, "features": scale}
        assert all(s == want for s in recorded[-1].scales), recorded[-1].scales


def test_synchronous_runs_spend_each_frames_iterations_at_the_end(scene):
    seq = open_dataset(scene)

    def final_iterations(frames, **options):
        slam = SLAM(SLAMConfig(features=False, map_iters_keyframe=2, **options), seq[0].K, 160, 120)
        for i in range(frames):
            slam.step(seq[i].rgb, seq[i].depth)
        slam.mapper = RecordingMapper(slam.mapper)
        slam.finish()
        return sum(slam.mapper.iterations)

    assert final_iterations(3, final_iters=10, final_iters_per_frame=2.0) == 16
    assert final_iterations(5, final_iters=10, final_iters_per_frame=2.0) == 20
    assert final_iterations(5, final_iters=10, final_iters_per_frame=0.0) == 10
    # Real time spends a share of the time instead (here none), with no floor.
    assert final_iterations(5, final_iters=10, final_iters_per_frame=2.0, mapping_thread=True,
                            final_time=0.0, realtime_iters_floor=0.0) == 10
    # A run cut short trains nothing.
    slam = SLAM(SLAMConfig(features=False, final_iters_per_frame=2.0), seq[0].K, 160, 120)
    slam.step(seq[0].rgb, seq[0].depth)
    slam.mapper = RecordingMapper(slam.mapper)
    slam.finish(train=False)
    assert slam.mapper.iterations == []
    default = SLAMConfig()
    assert default.map_iters_frame == 0 and default.final_iters_per_frame > 0
    with pytest.raises(ValueError, match="final_iters_per_frame"):
        SLAMConfig(final_iters_per_frame=-1.0)


def test_map_coverage_counts_only_where_the_frame_measured_depth(scene):
    # Depth on the right half only (7-Scenes' depth, registered to the colour camera, leaves the
    # image border empty): the map never covers the left half, and that alone must not make
    # every frame a keyframe.
    seq = open_dataset(scene)
    cfg = SLAMConfig(features=False, map_iters_keyframe=5, map_iters_frame=1, final_iters=0,
                     keyframe_translation=10.0, keyframe_rotation=180.0, keyframe_max_gap=1000)
    slam = SLAM(cfg, seq[0].K, 160, 120)
    for i in range(8):
        f = seq[i]
        depth = f.depth.copy()
        depth[:, :80] = 0
        assert slam.step(f.rgb, depth).state != "lost"
    assert len(slam.keyframe_frames) <= 3, slam.keyframe_frames


def test_the_inline_reference_renders_colour_only_when_asked_and_never_a_changed_map(scene):
    # The alpha every frame's coverage needs comes from a render without colour; colour and
    # depth, when the map is tracked against, from a full one: the same images as rendering
    # the map in full at that pose.
    seq = open_dataset(scene)
    slam = SLAM(SLAMConfig(features=False, final_iters=0), seq[0].K, 160, 120)
    for i in range(4):
        slam.step(seq[i].rgb, seq[i].depth)
    inline, pose = slam._mapping, slam.poses[-1]
    calls = []
    mapper = inline._mapper

    class Counting:
        def render(self, *args, **kw):
            calls.append(kw.get("color", True))
            return mapper.render(*args, **kw)

    inline._mapper = Counting()
    _, ref = inline.reference(pose)
    full = mapper.render(pose, slam.K_track, *slam.track_size)
    assert calls == [False]
    assert np.array_equal(ref.alpha, full.alpha) and (full.alpha > 0.5).mean() > 0.3
    assert np.array_equal(ref.color, full.color) and np.array_equal(ref.depth, full.depth)
    assert calls == [False, True], "colour and depth come from one full render"
    _, stale = inline.reference(pose)
    inline._mapper = mapper
    inline.after_frame(pose, keyframe=True)
    with pytest.raises(RuntimeError, match="map changed"):
        stale.color


def test_the_keyframe_policy_says_why_a_frame_becomes_a_keyframe():
    # Each threshold alone, and the first that holds when several do.
    from legslam.slam.keyframes import REASONS, KeyframePolicy
    from legslam.slam.trajectory import KeyframeView

    c = SLAMConfig()
    policy = KeyframePolicy(c)
    last = KeyframeView(np.eye(4), None, None, frame=10)

    def why(frame=11, dx=0.0, turn_deg=0.0, coverage=1.0, counts=True, last=last, empty=False):
        pose = np.eye(4)
        pose[0, 3] = dx
        a = np.radians(turn_deg)
        pose[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        return policy.wants(frame, pose, coverage, last, map_empty=empty, coverage_counts=counts)

    assert why() is None
    assert why(last=None) == why(empty=True) == "first"
    assert why(dx=2 * c.keyframe_translation) == "moved"
    assert why(turn_deg=2 * c.keyframe_rotation) == "turned"
    assert why(coverage=c.keyframe_overlap / 2) == "coverage"
    assert why(coverage=c.keyframe_overlap / 2, counts=False) is None
    assert why(frame=10 + c.keyframe_max_gap) == "gap"
    assert why(dx=1.0, turn_deg=90.0, coverage=0.0, frame=100) == "moved"
    assert why(turn_deg=90.0, coverage=0.0, frame=100) == "turned"
    assert set(REASONS) == {"first", "moved", "turned", "coverage", "gap"}


def test_real_time_makes_keyframes_no_closer_than_its_minimum_gap():
    # A camera that passes `keyframe_translation` every frame: the synchronous map takes every
    # frame, a mapping thread one every `realtime_keyframe_min_gap` frames.
    from legslam.slam.keyframes import KeyframePolicy
    from legslam.slam.trajectory import KeyframeView

    def keyframes(**options):
        policy, last, made = KeyframePolicy(SLAMConfig(**options)), None, []
        for i in range(20):
            pose = np.eye(4)
            pose[0, 3] = 0.2 * i
            if policy.wants(i, pose, 1.0, last, map_empty=False, coverage_counts=True):
                last = KeyframeView(pose, None, None, frame=i)
                made.append(i)
        return made

    assert keyframes() == list(range(20))
    assert keyframes(mapping_thread=True) == [0, 5, 10, 15]
    assert keyframes(mapping_thread=True, realtime_keyframe_min_gap=3) == list(range(0, 20, 3))
    assert keyframes(mapping_thread=True, realtime_keyframe_min_gap=1) == list(range(20))
    with pytest.raises(ValueError, match="realtime_keyframe_min_gap"):
        SLAMConfig(realtime_keyframe_min_gap=0)


def test_real_time_trains_on_until_its_map_has_had_a_share_of_a_synchronous_runs_iterations(scene):
    seq = open_dataset(scene)

    def iterations(floor, frames=6):
        cfg = SLAMConfig(features=False, mapping_thread=True, final_time=0.0, final_iters=10,
                         map_iters_keyframe=30, map_iters_frame=1, final_iters_per_frame=2.0,
                         realtime_iters_floor=floor)
        slam = SLAM(cfg, seq[0].K, 160, 120)
        for i in range(frames):
            slam.step(seq[i].rgb, seq[i].depth)
        slam.mapper = RecordingMapper(slam.mapper)
        slam.finish()
        live = sum(s.iterations for s in slam.mapping_stats) - sum(slam.mapper.iterations)
        keyframes = len(slam.keyframe_frames)
        synchronous = 30 * keyframes + 1 * (frames - keyframes) + 10 + 2 * frames
        return live, sum(slam.mapper.iterations), synchronous

    for floor in (1.0, 2.5):
        live, final, synchronous = iterations(floor)
        # final_iters at least, and as many more as bring the whole run to the floor.
        assert final == max(10, math.ceil(floor * synchronous) - live), (floor, live, final, synchronous)
        assert live + final >= floor * synchronous
    live, final, _ = iterations(0.0)
    assert final == 10
    with pytest.raises(ValueError, match="realtime_iters_floor"):
        SLAMConfig(realtime_iters_floor=-1.0)


def test_real_time_trains_on_after_the_frames_for_its_share_of_the_run(scene):
    seq = open_dataset(scene)

    def finished(final_iters=0, **options):
        slam = SLAM(SLAMConfig(features=False, final_iters=final_iters, realtime_iters_floor=0.0,
                               **options), seq[0].K, 160, 120)
        before = time.perf_counter()  # the run's clock starts between these two
        slam.step(seq[0].rgb, seq[0].depth)
        after = time.perf_counter()
        for i in range(1, 12):
            slam.step(seq[i].rgb, seq[i].depth)
        calls, start = [], time.perf_counter()
        slam.finish(progress=lambda done, total: calls.append((done, total, time.perf_counter())))
        return calls, before, after, start, time.perf_counter()

    assert finished(mapping_thread=True, final_time=0.0)[0] == []
    # Synchronous: final_iters and those per frame only.
    assert finished(mapping_thread=False, final_time=0.5, final_iters_per_frame=0.0)[0] == []
    calls, before, after, start, end = finished(mapping_thread=True, final_time=0.5)
    # Batches of 25 while open-ended, then the count once.
    assert len(calls) >= 2 and all(total is None for _, total, _ in calls[:-1]), calls
    assert [done for done, _, _ in calls[:-1]] == [25 * (k + 1) for k in range(len(calls) - 1)]
    assert calls[-1][:2] == (calls[-2][0], calls[-2][0])
    # The budget is half the time from the first frame to when finish had stopped the thread
    # (before its first batch ended): it was spent, and the last batch began within it.
    assert end - start >= 0.5 * (start - after)
    if len(calls) >= 3:
        assert calls[-3][2] - start < 0.5 * (calls[0][2] - before)
    # With final iterations too, the count is open until the time is spent: never "25/25"
    # and then more.
    calls = finished(final_iters=25, mapping_thread=True, final_time=0.5)[0]
    assert len(calls) >= 2 and calls[0][0] == 25, calls
    assert all(total is None for _, total, _ in calls[:-1]), calls
    assert calls[-1][:2] == (calls[-2][0], calls[-2][0])


def test_mapping_thread_tracks_and_maps_while_the_main_thread_tracks(mapped, scene, tmp_path):
    cfg = SLAMConfig(features=False, final_iters=60, mapping_thread=True)
    threaded = run(open_dataset(scene), tmp_path, cfg)
    m, slam = threaded["metrics"], threaded["slam"]
    # grown alike, never trained
    frozen = SLAMConfig(features=False, map_iters_keyframe=0, map_iters_frame=0, final_iters=0)
    unmapped = run(open_dataset(scene), tmp_path / "frozen", frozen)
    assert m["ate_rmse_cm"] < 1 and m["lost_frames"] == 0, m
    # the worker trained beyond the final iterations, and the map is better for it
    assert sum(s.iterations for s in slam.mapping_stats) > cfg.final_iters
    assert psnr_of(threaded) > psnr_of(unmapped) + 2.0, (psnr_of(threaded), psnr_of(unmapped))
    assert slam.reference_render_s > 0
    assert threaded["timings"]["mapping.reference_render"]["total_s"] > 0
    # The worker's references are a frame old or more, never newer; a frame may come before it
    # has finished the first.
    ages = m["surface_reference_age"]["frames"]
    assert min(int(a) for a in ages) >= 1 and 0 < sum(ages.values()) <= 23, ages
    assert m["surface_reference_age"]["mean"] == pytest.approx(
        sum(int(a) * n for a, n in ages.items()) / sum(ages.values()), abs=1e-3)


def test_mapping_thread_owns_the_map_until_finish_and_restarts_an_empty_map(scene):
    seq = open_dataset(scene)
    f0 = seq[0]
    slam = SLAM(SLAMConfig(features=False, final_iters=0, mapping_thread=True), f0.K, 160, 120)
    assert slam.step(f0.rgb, np.zeros_like(f0.depth)).state == "init"
    with pytest.raises(RuntimeError, match="finish"):
        slam.render(np.eye(4))
    deadline = time.time() + 10
    while slam.mapping.pending and time.time() < deadline:  # the empty keyframe is applied
        time.sleep(0.01)
    states = [slam.step(seq[i].rgb, seq[i].depth).state for i in range(1, 10)]
    assert states[0] == "init" and states[-4:] == ["ok"] * 4, states
    slam.finish()
    assert slam.num_gaussians > 1000 and slam.mapper.num_gaussians == slam.num_gaussians
    assert slam.render(slam.poses[-1])["color"].shape == (120, 160, 3)


def test_a_failure_in_the_mapping_thread_reaches_the_tracker():
    from legslam.slam.mapping import ThreadedMapping

    class Broken:
        num_gaussians, num_keyframes = 0, 0

        def add_keyframe(self, *args):
            self.num_gaussians = self.num_keyframes = 1
            return 0, 1

        def train(self, n, lr_scale=1.0):
            raise ValueError("engine says no")

    t = ThreadedMapping(Broken(), np.eye(3), (4, 4))
    t.add_keyframe(None, None, None, np.eye(4))
    deadline = time.time() + 10
    while t._error is None and time.time() < deadline:
        time.sleep(0.01)
    with pytest.raises(RuntimeError, match="engine says no"):
        t.reference(np.eye(4))
    with pytest.raises(RuntimeError, match="engine says no"):
        t.stop()


def test_the_mapping_thread_renders_a_reference_every_few_batches_unless_coverage_counts(monkeypatch):
    from legslam.slam import mapping
    from legslam.slam.mapping import REFERENCE_EVERY, ThreadedMapping

    class Counting:
        """A mapper that records after how many batches each reference was rendered."""
        num_gaussians, num_keyframes = 0, 0

        def __init__(self):
            self.batches, self.rendered_after, self.corrected_after = 0, [], None

        def add_keyframe(self, *args):
            self.num_gaussians = self.num_keyframes = 1
            return 0, 1

        def correct_keyframes(self, corrections):
            self.corrected_after = self.batches

        def train(self, n, lr_scale=1.0):
            self.batches += 1
            time.sleep(0.002)

        def render(self, *args):
            self.rendered_after.append(self.batches)
            return object()

    def run(coverage_iters, batches=24, correct_at=None):
        m = Counting()
        t = ThreadedMapping(m, np.eye(3), (4, 4), coverage_iters=coverage_iters)
        t.after_frame(np.eye(4), True)
        t.add_keyframe(None, None, None, np.eye(4))
        deadline = time.time() + 10
        while m.batches < batches and time.time() < deadline:
            if correct_at is not None and m.batches >= correct_at:
                t.correct_keyframes(np.eye(4)[None])
                correct_at = None
            time.sleep(0.001)
        t.stop()
        return m

    # The newest keyframe short of its iterations: the first batch, then every few.
    m = run(coverage_iters=10 ** 9)
    assert m.rendered_after == [1] + list(range(REFERENCE_EVERY, m.batches + 1, REFERENCE_EVERY))
    # Once the tracker counts the map's coverage: after every batch.
    m = run(coverage_iters=0)
    assert m.rendered_after == list(range(1, m.batches + 1))
    # A correction moves the map: the batch after it renders whatever the count.
    monkeypatch.setattr(mapping, "REFERENCE_EVERY", 10 ** 9)
    m = run(coverage_iters=10 ** 9, correct_at=5)
    assert m.corrected_after >= 5 and m.rendered_after == [1, m.corrected_after + 1]


def test_new_gaussians_are_seeded_on_a_grid_about_grow_width_wide():
    def grow_stride(width, **cfg):
        slam = SLAM(SLAMConfig(features=False, final_iters=0, **cfg), np.eye(3), width, width * 3 // 4)
        return slam.mapper.config()["grow_stride"]

    assert grow_stride(640) == 2  # trained at 320 wide
    assert grow_stride(160) == 1
    assert grow_stride(640, grow_width=80) == 4
    with pytest.raises(ValueError, match="mapper.grow_stride is set from grow_width; set that instead"):
        grow_stride(640, mapper={"grow_stride": 1})
    with pytest.raises(ValueError, match="grow_width"):
        grow_stride(640, grow_width=0)


def test_features_train_at_about_feature_width_and_below_the_colour():
    def widths(width, **cfg):
        """(colour, feature) widths of the finest training level, as the mapper is set."""
        slam = SLAM(SLAMConfig(final_iters=0, **cfg), np.eye(3), width, width * 3 // 4)
        c = slam.mapper.config()
        return width >> c["finest_level"], width >> (c["finest_level"] + c["feature_level_offset"])

    # The coarsest level at least 80 wide, one level below the colour at least, two at most.
    assert widths(640) == (320, 80)
    assert widths(600) == (600, 150)
    assert widths(1200) == (600, 150)
    assert widths(1280) == (320, 80)
    assert widths(848) == (424, 106)
    assert widths(160) == (160, 80)
    assert widths(640, feature_width=150) == (320, 160)
    assert widths(640, feature_width=320) == (320, 160)
    assert widths(640, feature_width=16) == (320, 80)
    with pytest.raises(ValueError, match="feature_width"):
        widths(640, feature_width=0)


def test_a_config_written_before_feature_width_still_reads(tmp_path, caplog):
    # Runs of the version before wrote the then mapper option into config.json (as 1, its
    # default); `legslam eval` and `--config` read such files.
    old = SLAMConfig().to_dict()
    old["mapper"]["feature_level_offset"] = 1
    (tmp_path / "config.json").write_text(json.dumps(old))
    with caplog.at_level(logging.WARNING, logger="legslam"):
        assert SLAMConfig.from_file(tmp_path / "config.json") == SLAMConfig()
    assert not caplog.records
    # A value someone chose is not silently taken for another: it is named, with what to set.
    with caplog.at_level(logging.WARNING, logger="legslam"):
        cfg = SLAMConfig(mapper={"feature_level_offset": 2})
    assert cfg == SLAMConfig()
    assert "mapper.feature_level_offset is no longer read; it is set from feature_width" in caplog.text


def test_options_out_of_range_or_of_the_wrong_type_are_named(tmp_path, capsys):
    from legslam.slam.config import _RANGES

    # Counts the engine would take as unsigned, and fractions, are all covered.
    assert {"final_iters", "map_iters_frame", "map_iters_keyframe", "keyframe_overlap"} <= set(_RANGES)
    assert SLAMConfig(keyframe_translation=1, final_iters=np.int64(3)).final_iters == 3
    for name, (low, high) in _RANGES.items():
        below = low - 1 if isinstance(low, int) else -0.5
        with pytest.raises(ValueError, match=f"{name} must be .*got {below}"):
            SLAMConfig(**{name: below})
        if high != float("inf"):
            above = high + 1 if isinstance(high, int) else high + 0.5
            with pytest.raises(ValueError, match=f"{name} must be in .*got {above}"):
                SLAMConfig(**{name: above})
    for bad in ({"keyframe_overlap": float("nan")}, {"final_iters": 2.5}, {"features": "no"},
                {"map_iters_frame": True}, {"mapper": 3}, {"encoder": 7}, {"pca_path": 1}):
        with pytest.raises(ValueError, match=f"^{next(iter(bad))} must be"):
            SLAMConfig(**bad)
    cfg = SLAMConfig(features=False)
    cfg.mapping_batch = 0  # set after the config was made: the SLAM still refuses it
    with pytest.raises(ValueError, match="mapping_batch must be at least 1, got 0"):
        SLAM(cfg, np.eye(3), 64, 48)
    # From a file, through the CLI: exit 2 before any frame is read, naming the option.
    (tmp_path / "c.toml").write_text('final_iters = "lots"\n')
    assert main(["run", str(tmp_path / "no-frames-here"), "--config", str(tmp_path / "c.toml")]) == 2
    assert "final_iters must be an integer, got 'lots'" in capsys.readouterr().err


def test_frames_follow_their_refined_keyframes(scene):
    """With keyframe pose refinement, every frame keeps its pose relative to the keyframe it was
    tracked after, keyframes end where the mapper moved them, and the trajectory stays good."""
    seq = open_dataset(scene)
    f0 = seq[0]
    cfg = SLAMConfig(features=False, final_iters=30,
                     mapper={"pose_lr_translation": 1e-3, "pose_lr_rotation": 3e-3})
    slam = SLAM(cfg, f0.K, 160, 120)
    live, kf_of = [], []
    for i in range(len(seq)):
        f = seq[i]
        r = slam.step(f.rgb, f.depth)
        live.append(r.pose)
        kf_of.append(len(slam.keyframe_frames) - 1)
    live_kf = [live[i] for i in slam.keyframe_frames]
    slam.finish()
    refined = slam.mapper.keyframe_poses()
    assert len(refined) == len(slam.keyframe_frames) >= 2
    moved = max(np.abs(refined[k] - live_kf[k]).max() for k in range(1, len(refined)))
    assert moved > 1e-5, "no keyframe pose was refined"
    np.testing.assert_array_equal(refined[0], live_kf[0])
    for i, k in enumerate(kf_of):
        before = np.linalg.inv(live_kf[k]) @ live[i]
        after = np.linalg.inv(refined[k]) @ slam.poses[i]
        np.testing.assert_allclose(after, before, atol=1e-9)
    gt = np.stack([seq[i].pose for i in range(len(seq))])
    assert ate(gt, np.stack(slam.poses))["rmse"] < 0.01


class _Regained:
    """The scene with frame i's colour scaled by gain(i, number of frames)."""

    def __init__(self, seq, gain):
        self.seq, self.gain = seq, gain

    def __getattr__(self, name):  # poses, timestamps, camera: the scene's
        return getattr(self.seq, name)

    def __len__(self):
        return len(self.seq)

    def __getitem__(self, i):
        import dataclasses

        f = self.seq[i]
        g = self.gain(i, len(self.seq))
        return dataclasses.replace(f, rgb=np.clip(f.rgb.astype(np.float32) * g, 0, 255).astype(np.uint8))


def _dimmed(seq):
    """The scene with its second half exposed 25% darker."""
    return _Regained(seq, lambda i, n: 1.0 if i < n // 2 else 0.75)


def test_trained_exposures_follow_a_darker_half_of_the_sequence(scene, tmp_path):
    seq = _dimmed(open_dataset(scene))
    plain = run(seq, tmp_path / "plain", SLAMConfig(features=False, final_iters=30))
    assert plain["slam"].frame_exposures() is None
    assert "psnr_exposed" not in plain["metrics"]["every_5"]
    cfg = SLAMConfig(features=False, final_iters=30, mapper={"exposure_lr": 0.01})
    exposed = run(seq, tmp_path / "exposed", cfg)
    e = exposed["slam"].frame_exposures()
    assert e.shape == (len(seq), 2, 3)
    np.testing.assert_array_equal(e[0], [[1, 1, 1], [0, 0, 0]])  # the first keyframe's is the map's
    # the darker frames' keyframes learned (most of) the change: mid-grey comes out darker
    late = e[-1]
    assert (late[0] * 0.5 + late[1]).mean() < 0.5 - 0.05, late
    m, p = exposed["metrics"]["every_5"], plain["metrics"]["every_5"]
    assert m["psnr_exposed"] > m["psnr"] + 1.0, m
    assert m["psnr_exposed"] > p["psnr"] + 1.0, (m, p)


def test_view_dependent_colour_is_learned_by_the_spherical_harmonics(scene, tmp_path):
    """The scene brightening from 0.8 to 1.2 as the camera walks round the table: colour that
    changes with where it is seen from. The default map (degree 3) follows it, a degree-0 map
    cannot."""
    seq = _Regained(open_dataset(scene), lambda i, n: 0.8 + 0.4 * i / (n - 1))

    def mapped_with(sh_degree):
        """PSNR, and how much brighter than the unscaled frame the map renders at the end of
        the walk than at its start."""
        cfg = SLAMConfig(features=False, final_iters=30, sh_degree=sh_degree)
        out = tmp_path / f"sh{sh_degree}"
        result = run(seq, out, cfg)
        m = GaussianMap.load(out / "map.ply")
        assert m.sh.shape[1] == (sh_degree + 1) ** 2
        _, poses = read_tum(out / "trajectory.txt")
        ratio = []
        for i in (0, len(seq) - 1):
            f = seq.seq[i]
            seen = f.depth > 0
            r = m.render(poses[i], f.K, f.rgb.shape[1], f.rgb.shape[0], features=False)
            ratio.append(r.color[seen].mean() / (f.rgb[seen] / 255.0).mean())
        return psnr_of(result), ratio[1] - ratio[0]

    assert SLAMConfig().sh_degree == 3
    psnr3, rise3 = mapped_with(3)
    psnr0, rise0 = mapped_with(0)
    assert rise3 > 0.1 and rise0 < 0.05, (rise3, rise0)  # the scene's own rise is 0.4
    assert psnr3 > psnr0 + 1.0, (psnr3, psnr0)


def _corrupt_colour(scene, tmp_path, frames) -> Path:
    """A copy of the scene whose colour images of `frames` are not images."""
    import shutil

    copy = tmp_path / "corrupt"
    shutil.copytree(scene, copy)
    colour = sorted((copy / "color").iterdir())
    for i in frames:
        colour[i].write_bytes(b"not an image")
    return copy


def test_an_unreadable_frame_is_skipped_by_name_and_the_run_goes_on(mapped, scene, tmp_path, capsys):
    copy = _corrupt_colour(scene, tmp_path, [7])
    quick = tmp_path / "quick.toml"
    quick.write_text("features = false\nfinal_iters = 30\n")
    out = tmp_path / "run"
    assert main(["run", str(copy), "--quiet", "--config", str(quick), "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "warning: frame 7 skipped: cannot decode image" in printed.err
    assert "(1 unreadable)" in printed.out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["unreadable_frames"] == [7] and metrics["lost_frames"] >= 1
    stamps, poses = read_tum(out / "trajectory.txt")
    seq = open_dataset(scene)
    assert len(poses) == len(seq) and np.allclose(stamps, [seq.timestamp(i) for i in range(len(seq))])
    # One frame fewer to track and map from: about as good as the whole run.
    assert metrics["ate_rmse_cm"] < 2 * mapped["metrics"]["ate_rmse_cm"] + 1
    assert psnr_of({"metrics": metrics}) > psnr_of(mapped) - 2
    assert main(["eval", str(out)]) == 0
    assert json.loads((out / "eval.json").read_text())["unreadable_frames"] == [7]


def test_a_run_that_stops_keeps_the_frames_done(scene, tmp_path, capsys, monkeypatch):
    import legslam.datasets.base as base

    # Too many unreadable frames in a row: a clear error, and the frames before it kept.
    monkeypatch.setattr(base, "MAX_UNREADABLE_IN_A_ROW", 3)
    out = tmp_path / "broken"
    copy = _corrupt_colour(scene, tmp_path, [5, 6, 7])
    assert main(["run", str(copy), "--no-features", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "3 frames in a row cannot be read (frames 5-7)" in err and "stopped after 7 frames" in err
    assert len(read_tum(out / "trajectory.txt")[1]) == 7
    assert len(GaussianMap.load(out / "map.ply")) > 0

    # Interrupted (Ctrl-C) once frame 4 is tracked: frames 0-4 are kept.
    class Interrupt:
        def on_frame(self, i, frame, step, slam):
            if i == 4:
                raise KeyboardInterrupt

    out = tmp_path / "interrupted"
    with pytest.raises(KeyboardInterrupt):
        run(open_dataset(scene), out, SLAMConfig(features=False), viewer=Interrupt())
    assert len(read_tum(out / "trajectory.txt")[1]) == 5
    assert len(GaussianMap.load(out / "map.ply")) > 0


def test_a_run_holds_numpy_blas_to_one_thread_and_gives_the_setting_back(scene, tmp_path):
    # OpenBLAS's spinning threads took a tenth of a core from the engine's pools.
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas_threads():
        return {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"}

    if not blas_threads():
        pytest.skip("numpy reports no BLAS thread pool here")
    seen = []

    class Watch:
        def on_frame(self, i, frame, step, slam):
            seen.append(blas_threads())

        def on_finish(self, slam):
            seen.append(blas_threads())

    with threadpool_limits(limits=2, user_api="blas"):
        run(open_dataset(scene, max_frames=4), tmp_path, SLAMConfig(features=False, final_iters=5),
            viewer=Watch())
        after = blas_threads()
    assert len(seen) == 5 and all(s == {1} for s in seen), seen
    assert after == {2}


def test_commands_name_a_damaged_map(mapped, tmp_path, capsys):
    import shutil

    run_dir = tmp_path / "run"
    shutil.copytree(mapped["out"], run_dir)
    ply = run_dir / "map.ply"
    ply.write_bytes(ply.read_bytes()[:-100])
    for command in (["render", str(run_dir), "--out", str(tmp_path / "views")], ["eval", str(run_dir)],
                    ["query", str(run_dir), "chair"]):
        assert main(command) == 2, command
        assert "map.ply is cut short" in capsys.readouterr().err, command


def test_frames_without_depth_are_counted_and_an_empty_map_is_said(scene, tmp_path, capsys):
    import shutil

    copy = tmp_path / "scene"
    shutil.copytree(scene, copy)
    depths = sorted((copy / "depth").iterdir())
    blank = np.zeros_like(cv2.imread(str(depths[0]), cv2.IMREAD_UNCHANGED))
    cv2.imwrite(str(depths[5]), blank)
    args = ["run", str(copy), "--no-features", "--quiet", "--max-frames", "8", "--final-iters", "5"]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    printed = capsys.readouterr()
    assert "warning: frame 5 has no valid depth" in printed.err and "map is empty" not in printed.err
    metrics = json.loads((tmp_path / "one" / "metrics.json").read_text())
    assert metrics["frames_without_depth"] == 1
    assert metrics["every_5"]["depth_l1_cm"] is not None  # from frame 0, frame 5 has none

    for d in depths:
        cv2.imwrite(str(d), blank)
    assert main([*args, "--out", str(tmp_path / "none")]) == 0
    printed = capsys.readouterr()
    assert "warning: the map is empty: of 8 frames, 8 had no depth and 0 depth outside" in printed.err
    assert "depth L1 n/a" in printed.out
    assert main(["eval", str(tmp_path / "none")]) == 0
    assert "| every_5[depth_l1_cm] | n/a |" in capsys.readouterr().out


class PatchColours(ColourEncoder):
    """The colour stand-in encoder, each call taking `delays[k]` seconds (as a busy machine
    makes encoding take longer some times)."""

    def __init__(self, delays=()):
        self.delays, self.calls = list(delays), 0

    def encode(self, rgb):
        time.sleep(self.delays[self.calls % len(self.delays)] if self.delays else 0.0)
        self.calls += 1
        return super().encode(rgb)


def test_a_synchronous_run_does_not_depend_on_how_long_encoding_takes(scene):
    """Keyframe features and places reach the map at fixed frames in synchronous runs: an
    encoder that now and then takes much longer than a frame's mapping gives the same map and
    trajectory, to the bit."""
    cfg = dict(feature_dim=4, pca_keyframes=2, final_iters=10, keyframe_max_gap=4)
    results = []
    for delays in ([0.0], [0.0, 1.5, 0.0, 0.0, 0.3]):
        slam = SLAM(SLAMConfig(**cfg), open_dataset(scene)[0].K, 160, 120, encoder=PatchColours(delays))
        for f in open_dataset(scene):
            slam.step(f.rgb, f.depth)
        slam.finish()
        results.append((np.stack(slam.poses), slam.gaussian_map()))
    (poses_a, map_a), (poses_b, map_b) = results
    assert len(slam.keyframe_frames) >= 5
    np.testing.assert_array_equal(poses_a, poses_b)
    assert map_a.means.shape == map_b.means.shape
    np.testing.assert_array_equal(map_a.means, map_b.means)
    np.testing.assert_array_equal(map_a.features, map_b.features)


def test_a_settled_feed_hands_a_keyframe_over_at_the_next_collect_and_the_rest_at_the_end():
    from legslam.slam.feature_feed import FeatureFeed

    got = []
    feed = FeatureFeed(SLAMConfig(feature_dim=2, pca_keyframes=1), lambda kf, grid: got.append(kf),
                       {"extraction": [], "compression": []}, PatchColours(), settled=True)
    rgb = np.full((48, 64, 3), 90, np.uint8)
    feed.submit(0, rgb)
    time.sleep(0.2)  # encoded by now, and still not the frame's to take
    feed.collect()
    assert got == []
    feed.collect()
    assert got == [0]
    feed.submit(1, rgb)
    feed.collect()
    assert got == [0]
    feed.submit(2, rgb)
    feed.drain()  # keyframe 1 due, keyframe 2 just made: both
    assert got == [0, 1, 2]


def test_real_time_encodes_every_nth_keyframe_and_makes_places_of_those(scene):
    """In real time only the first keyframe and every `realtime_feature_every`-th after it go
    to the encoder (for features and places); synchronous runs encode every one."""
    frames = list(open_dataset(scene))
    for mapping_thread, every in [(True, 1), (True, 2), (True, 3), (False, 2)]:
        encoder = PatchColours()
        cfg = SLAMConfig(feature_dim=4, pca_keyframes=1, final_iters=2, final_time=0.0,
                         keyframe_max_gap=3, realtime_keyframe_min_gap=3,
                         mapping_thread=mapping_thread, realtime_feature_every=every)
        slam = SLAM(cfg, frames[0].K, 160, 120, encoder=encoder)
        states = [slam.step(f.rgb, f.depth).state for f in frames]
        slam.finish()
        # A lost frame would be encoded too, for relocalisation; the scene loses none.
        assert "lost" not in states, states
        n = len(slam.keyframe_frames)
        assert n >= 6, slam.keyframe_frames
        encoded = list(range(0, n, every if mapping_thread else 1))
        assert encoder.calls == len(encoded), (mapping_thread, every, n)
        assert sorted(slam.places.places) == encoded, (mapping_thread, every)
        assert not slam._unplaced  # no keyframe left waiting for tokens that never come
