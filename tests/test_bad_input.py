"""What a user can get wrong, and what legslam does about it: each case asserts the exit code,
that the message names the problem and the file, and that what should survive does (the
trajectory and map load, the input folder is unchanged). docs/bad-input.md lists the cases."""

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from legslam import render
from legslam.cli import main
from legslam.datasets import DatasetError, open as open_dataset
from legslam.eval import read_tum
from legslam.map import GaussianMap
from legslam.run_folder import replace_atomically
from legslam.slam import SLAM, SLAMConfig

FAST = ["--no-features", "--quiet", "--final-iters", "5"]


@pytest.fixture
def scene(small_synthetic, tmp_path):
    """A copy of the 12-frame built-in scene that a test may damage."""
    return Path(shutil.copytree(small_synthetic, tmp_path / "scene"))


def _digest(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _outputs_load(out: Path, frames: int) -> None:
    _, poses = read_tum(out / "trajectory.txt")
    assert len(poses) == frames and np.isfinite(poses).all()
    GaussianMap.load(out / "map.ply")


def _strict_json(path: Path) -> dict:
    def refuse(name):
        raise AssertionError(f"{path} holds {name}, which is not JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


# 1. Empty or unreadable image files ------------------------------------------------------

@pytest.mark.parametrize("damage", ["empty", "a folder"])
def test_an_empty_or_unreadable_image_is_skipped_by_name(scene, tmp_path, capsys, damage):
    bad = scene / "color" / "000004.png"
    bad.unlink()
    if damage == "empty":
        bad.write_bytes(b"")
    else:  # reading it fails with an OSError, as a file without read permission does
        bad.mkdir()
    out = tmp_path / "run"
    assert main(["run", str(scene), "--out", str(out), *FAST]) == 0
    err = capsys.readouterr().err
    assert "frame 4 skipped" in err and str(bad) in err
    _outputs_load(out, 12)
    assert _strict_json(out / "metrics.json")["unreadable_frames"] == [4]
    assert main(["odometry", str(scene), "--out", str(tmp_path / "odo.txt"), "--quiet"]) == 0
    assert len(read_tum(tmp_path / "odo.txt")[1]) == 11  # the unreadable frame left out
    assert main(["eval", str(out)]) == 0
    assert _strict_json(out / "eval.json")["unreadable_frames"] == [4]


# 2. Depth out of range ---------------------------------------------------------------------

def _with_float_depth(source: Path, to: Path, scale_of) -> Path:
    """A copy of the scene at `source` with its depth as float .npy files (metres), frame k's
    multiplied by scale_of(k)."""
    shutil.copytree(source, to)
    for k, png in enumerate(sorted((to / "depth").glob("*.png"))):
        metres = cv2.imread(str(png), cv2.IMREAD_UNCHANGED) / 5000.0
        np.save(png.with_suffix(".npy"), (metres * scale_of(k)).astype(np.float32))
        png.unlink()
    return to


def test_a_frame_in_millimetres_is_named_and_kept_out_of_the_map(small_synthetic, tmp_path, capsys):
    metres = _with_float_depth(small_synthetic, tmp_path / "m", lambda k: 1.0)
    mm = _with_float_depth(small_synthetic, tmp_path / "mm", lambda k: 1000.0 if k == 5 else 1.0)
    assert main(["run", str(metres), "--out", str(tmp_path / "clean"), *FAST]) == 0
    capsys.readouterr()
    assert main(["run", str(mm), "--out", str(tmp_path / "run"), *FAST]) == 0
    err = capsys.readouterr().err
    assert "frame 5" in err and "looks like millimetres" in err
    m, c = _strict_json(tmp_path / "run" / "metrics.json"), _strict_json(tmp_path / "clean" / "metrics.json")
    assert m["frames_depth_out_of_range"] == 1 and c["frames_depth_out_of_range"] == 0
    # Kept out of the map: about the clean run's map, not one grown from a room 1000x larger.
    assert abs(m["gaussians"] - c["gaussians"]) < 0.2 * c["gaussians"]
    assert m["every_5"]["psnr"] > c["every_5"]["psnr"] - 2
    _outputs_load(tmp_path / "run", 12)


def test_all_depth_beyond_depth_max_is_said_so(small_synthetic, tmp_path, capsys):
    scene = _with_float_depth(small_synthetic, tmp_path / "far-scene", lambda k: 1e6)
    out = tmp_path / "far"
    assert main(["run", str(scene), "--out", str(out), *FAST]) == 0
    err = capsys.readouterr().err
    assert "the map is empty: of 12 frames, 0 had no depth and 12 depth outside depth_min..depth_max" in err
    assert _strict_json(out / "metrics.json")["gaussians"] == 0


# 3. --out on the input ---------------------------------------------------------------------

def test_an_output_folder_that_is_or_holds_the_input_is_refused(scene, capsys):
    before = _digest(scene)
    for out in (scene, scene.parent):
        assert main(["run", str(scene), "--out", str(out), "--overwrite", *FAST]) == 2
        assert f"the output folder {out} is (or holds) the input" in capsys.readouterr().err
    # odometry's file: never one of the sequence's own.
    assert main(["odometry", str(scene), "--out", str(scene / "groundtruth.txt")]) == 2
    assert "is a file of the input sequence" in capsys.readouterr().err
    assert _digest(scene) == before


# 4. SIGTERM and SIGHUP ---------------------------------------------------------------------

@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_termination_signal_stops_a_run_and_keeps_its_work(small_synthetic, tmp_path, sig):
    out = tmp_path / "run"
    (tmp_path / "slow.toml").write_text("map_iters_keyframe = 40\nmap_iters_frame = 20\n")
    cmd = [sys.executable, "-m", "legslam.cli", "run", str(small_synthetic), "--out", str(out),
           "--no-features", "--config", str(tmp_path / "slow.toml")]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    first_frame = threading.Event()

    def read_stderr():  # the first progress line comes after the first frame is done
        for line in proc.stderr:
            lines.append(line)
            if line.startswith("frame "):
                first_frame.set()

    reader = threading.Thread(target=read_stderr)
    reader.start()
    assert first_frame.wait(timeout=120), "".join(lines)
    proc.send_signal(sig)
    proc.wait(timeout=120)
    reader.join(timeout=10)
    err = "".join(lines)
    assert proc.returncode == 128 + sig, err
    assert f"stopped by {signal.Signals(sig).name}" in err and "stopped after" in err
    _, poses = read_tum(out / "trajectory.txt")
    assert 1 <= len(poses) < 12
    GaussianMap.load(out / "map.ply")
    assert not list(out.glob(".*tmp*")), "a temporary file left behind"


def test_a_file_is_replaced_whole_or_not_at_all(tmp_path):
    target = tmp_path / "metrics.json"
    target.write_text("old")

    def interrupted(tmp):
        Path(tmp).write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        replace_atomically(target, interrupted)
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["metrics.json"]


# 5. feature_dim --------------------------------------------------------------------------

def test_feature_dim_beyond_the_encoder_is_refused_up_front(scene, tmp_path, capsys):
    from conftest import slam_encoder

    (tmp_path / "huge.toml").write_text("feature_dim = 1000000000\n")
    assert main(["run", str(scene), "--out", str(tmp_path / "a"), "--config", str(tmp_path / "huge.toml")]) == 2
    assert "feature_dim must be in [1, 4096], got 1000000000" in capsys.readouterr().err
    slam_encoder()
    (tmp_path / "big.toml").write_text("feature_dim = 500\n")
    t0 = time.perf_counter()
    assert main(["run", str(scene), "--out", str(tmp_path / "b"), "--config", str(tmp_path / "big.toml")]) == 2
    err = capsys.readouterr().err
    assert "feature_dim is 500, more than the 384 dimensions the encoder" in err
    assert time.perf_counter() - t0 < 20 and not (tmp_path / "b" / "trajectory.txt").exists()


# 6. A damaged run folder -------------------------------------------------------------------

@pytest.fixture(scope="module")
def a_run(tmp_path_factory):
    from legslam.datasets import synthetic

    scene = synthetic.generate(tmp_path_factory.mktemp("s"), n_frames=8, width=80, height=60, seed=2)
    out = tmp_path_factory.mktemp("r") / "run"
    assert main(["run", str(scene), "--out", str(out), *FAST]) == 0
    return out


def _damaged(a_run, tmp_path, name, damage) -> Path:
    run = Path(shutil.copytree(a_run, tmp_path / "run"))
    damage(run / name)
    return run


def _nan_in_map(path):
    m = GaussianMap.load(path)
    m.opacity_logits[3] = np.nan
    m.save(path)


@pytest.mark.parametrize("name, damage, message", [
    ("map.ply", _nan_in_map, "map.ply: property opacity of Gaussian 3 is nan"),
    ("camera.json", lambda p: p.write_text("{not json"), "camera.json cannot be read as JSON"),
    ("camera.json", lambda p: p.write_text('{"width": 80, "height": 60}'), "camera.json has no field 'K'"),
    ("trajectory.txt", lambda p: p.write_text(p.read_text().replace("0.", "nan", 1)), "trajectory.txt"),
])
def test_a_damaged_run_folder_is_named_by_file_and_field(a_run, tmp_path, capsys, name, damage, message):
    run = _damaged(a_run, tmp_path, name, damage)
    for command in (["render", str(run), "--out", str(tmp_path / "views")], ["eval", str(run)],
                    ["query", str(run), "--example", "0:1,1"]):
        assert main(command) == 2, command
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (command, err)


# 7. Sizes beyond memory --------------------------------------------------------------------

def test_a_view_too_large_for_memory_is_an_error_not_an_abort(a_run, tmp_path, capsys):
    assert main(["render", str(a_run), "--size", "100000x100000", "--intrinsics", "500,500,50,50",
                 "--out", str(tmp_path / "v")]) == 2
    assert "a 100000x100000 view needs about" in capsys.readouterr().err
    m = GaussianMap.load(a_run / "map.ply")
    with pytest.raises(ValueError, match="100000x100000 image is too large"):
        render(m.means, m.log_scales, m.quats, m.opacity_logits, m.sh, np.eye(3), np.eye(4), 100000, 100000)


# 8. A second run into the same --out -------------------------------------------------------

def test_a_second_run_needs_overwrite_and_replaces_only_the_runs_files(a_run, scene, tmp_path, capsys):
    out = Path(shutil.copytree(a_run, tmp_path / "run"))
    (out / "eval.json").write_text("{}")
    (out / "queries").mkdir()
    (out / "notes.txt").write_text("mine")
    before = _digest(out)
    assert main(["run", str(scene), "--out", str(out), *FAST]) == 2
    assert f"the output folder {out} is not empty" in capsys.readouterr().err
    assert _digest(out) == before
    assert main(["run", str(scene), "--out", str(out), "--overwrite", *FAST]) == 0
    assert not (out / "eval.json").exists() and not (out / "queries").exists()
    assert (out / "notes.txt").read_text() == "mine"
    _outputs_load(out, 12)


# 9. Smaller ones -----------------------------------------------------------------------------

def test_an_unwritable_output_folder_is_said_before_any_work(scene, tmp_path, capsys, monkeypatch):
    import tempfile

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    assert main(["run", str(scene), "--out", str(tmp_path / "ro"), *FAST]) == 2
    assert f"cannot write into the output folder {tmp_path / 'ro'}: Permission denied" in capsys.readouterr().err


def test_a_depth_scale_of_zero_is_an_error(scene, capsys):
    cam = json.loads((scene / "camera.json").read_text())
    (scene / "camera.json").write_text(json.dumps({**cam, "depth_scale": 0}))
    with pytest.raises(DatasetError, match="depth scale must be a positive number, got 0"):
        open_dataset(scene)


def test_a_nan_quaternion_names_file_and_line(scene):
    gt = scene / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    data = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
    row = lines[data[3]].split()
    row[-2] = "nan"
    lines[data[3]] = " ".join(row)
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=f"{gt}:{data[3] + 1}: .*non-finite"):
        open_dataset(scene)


def test_a_missing_ground_truth_pose_is_noted_and_ate_covers_the_others(scene, tmp_path, capsys):
    _, poses = open_dataset(scene).gt_trajectory()
    rows = poses.reshape(len(poses), 16)
    rows[2] = np.inf  # the plain-folder format's (and ScanNet's) way to say "no pose here"
    (scene / "groundtruth.txt").unlink()
    np.savetxt(scene / "poses.txt", rows)
    out = tmp_path / "run"
    assert main(["run", str(scene), "--out", str(out), *FAST]) == 0
    printed = capsys.readouterr().out
    m = _strict_json(out / "metrics.json")
    assert "ate_rmse_cm" in m and "11 of 12 frames" in m["ate_note"] and "frame 2" in m["ate_note"]
    assert "note: ATE over the 11 of 12 frames" in printed


def test_black_frames_give_valid_json_with_the_reason_psnr_is_missing(scene, tmp_path):
    for png in (scene / "color").glob("*.png"):
        cv2.imwrite(str(png), np.zeros((120, 160, 3), np.uint8))
    for png in (scene / "depth").glob("*.png"):
        cv2.imwrite(str(png), np.zeros((120, 160), np.uint16))
    out = tmp_path / "run"
    assert main(["run", str(scene), "--out", str(out), *FAST]) == 0
    m = _strict_json(out / "metrics.json")
    assert m["every_5"]["psnr"] is None and "infinite PSNR" in m["every_5"]["psnr_note"]


def test_an_unlikely_camera_is_warned_about(scene, capsys):
    cam = json.loads((scene / "camera.json").read_text())
    (scene / "camera.json").write_text(json.dumps({**cam, "cx": 900.0, "fx": 2.0}))
    assert main(["odometry", str(scene), "--out", str(scene.parent / "t.txt"), "--quiet",
                 "--max-frames", "2"]) == 0
    err = capsys.readouterr().err
    assert "principal point (900.0" in err and "field of view" in err and str(scene) in err


def test_slam_refuses_a_zero_size_and_integer_depth():
    with pytest.raises(ValueError, match="width and height must be positive, got 0x48"):
        SLAM(SLAMConfig(features=False), np.diag([50.0, 50, 1]), 0, 48)
    slam = SLAM(SLAMConfig(features=False), np.array([[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]]), 64, 48)
    with pytest.raises(ValueError, match="depth must be float metres, got uint16 .*millimetres"):
        slam.step(np.zeros((48, 64, 3), np.uint8), np.full((48, 64), 1500, np.uint16))


# 9. The user's own recordings ------------------------------------------------------------

@pytest.fixture(scope="module")
def shots():
    pytest.importorskip("rosbags", reason="rosbags is an optional extra: pip install 'legslam[bags]'")
    from recordings import synthetic_shots

    return synthetic_shots(4, 64, 48)


def test_a_bag_without_depth_or_camera_info_says_what_is_missing(shots, tmp_path, capsys):
    from recordings import write_bag

    s, K = shots
    nodepth = write_bag(tmp_path / "colour-only.bag", s, K, depth=None)
    assert main(["run", str(nodepth), "--out", str(tmp_path / "a"), *FAST]) == 2
    err = capsys.readouterr().err
    assert f"{nodepth}: no depth image topic" in err and "/camera/rgb/image_color  (sensor_msgs/Image rgb8" in err
    noinfo = write_bag(tmp_path / "no-info.bag", s, K, info=False)
    assert main(["run", str(noinfo), "--out", str(tmp_path / "b"), *FAST]) == 2
    err = capsys.readouterr().err
    assert f"{noinfo}: no sensor_msgs/CameraInfo for /camera/rgb/image_color" in err and "--intrinsics fx,fy,cx,cy" in err
    intrinsics = ",".join(str(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    assert main(["run", str(noinfo), "--out", str(tmp_path / "b"), "--intrinsics", intrinsics, *FAST]) == 0
    assert json.loads((tmp_path / "b" / "camera.json").read_text())["K"] == K.tolist()
    with pytest.raises(SystemExit) as e:  # argparse's exit
        main(["run", str(noinfo), "--out", str(tmp_path / "c"), "--intrinsics", "1,2,3", *FAST])
    assert e.value.code == 2 and "expected fx,fy,cx,cy (four numbers), got '1,2,3'" in capsys.readouterr().err


def test_a_ros2_bag_folder_named_like_a_ros1_file_says_to_rename_it(shots, tmp_path, capsys):
    from recordings import write_bag

    s, K = shots
    bag = write_bag(tmp_path / "rec.bag", s, K, storage="sqlite3")  # a folder: metadata.yaml, .db3
    assert main(["run", str(bag), "--out", str(tmp_path / "run"), *FAST]) == 2
    err = capsys.readouterr().err
    assert f"{bag} is a ROS2 bag folder whose name ends in .bag" in err and "rename the folder (to rec" in err
    renamed = bag.rename(tmp_path / "rec")
    assert main(["run", str(renamed), "--out", str(tmp_path / "run"), *FAST]) == 0


@pytest.mark.parametrize("storage", ["ros1", "sqlite3", "mcap"])
def test_a_truncated_bag_is_named(shots, tmp_path, capsys, storage):
    from recordings import write_bag

    s, K = shots
    bag = write_bag(tmp_path / ("rec.bag" if storage == "ros1" else "rec"), s, K, storage=storage)
    f = bag if storage == "ros1" else next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])  # a recording cut short
    assert main(["run", str(bag), "--out", str(tmp_path / "run"), *FAST]) == 2
    err = capsys.readouterr().err
    assert f"cannot read bag {bag} (cut short, or not a bag?)" in err and "Traceback" not in err


def test_depth_of_another_size_without_its_camera_is_refused(shots, tmp_path, capsys):
    from recordings import Shot, write_bag

    s, K = shots
    small = [Shot(x.rgb, np.ascontiguousarray(x.depth[::2, ::2]), x.t) for x in s]  # 32x24 depth
    bag = write_bag(tmp_path / "sizes.bag", small, K)
    assert main(["run", str(bag), "--out", str(tmp_path / "run"), *FAST]) == 2
    err = capsys.readouterr().err
    assert (f"{bag}: depth images (/camera/depth/image) are 32x24 and colour images (/camera/rgb/image_color) "
            "64x48") in err


def test_a_damaged_phone_capture_is_named(shots, tmp_path, capsys):
    from recordings import write_stray

    s, K = shots
    stray = write_stray(tmp_path / "stray", s, K, s)
    (stray / "odometry.csv").unlink()
    assert main(["run", str(stray), "--out", str(tmp_path / "a"), *FAST]) == 2
    assert f"missing file {stray / 'odometry.csv'}" in capsys.readouterr().err
    stray = write_stray(tmp_path / "stray2", s, K, s)
    short = write_stray(tmp_path / "short", s[:2], K, s[:2])
    shutil.copy(short / "rgb.mp4", stray / "rgb.mp4")  # a video of 2 frames for 4 depth images
    assert main(["run", str(stray), "--out", str(tmp_path / "b"), *FAST]) == 2
    assert f"{stray / 'rgb.mp4'} has 2 frames, too few for depth frame 3" in capsys.readouterr().err
