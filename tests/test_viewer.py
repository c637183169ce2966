"""`--viewer rerun`: a few frames of the synthetic scene recorded to an .rrd file and read
back, and the errors of a missing SDK or a misused option. The recording tests skip when the
rerun SDK is absent (scripts/setup.sh installs it: pip install 'legslam[viewer]')."""

import json
import sys
from collections import defaultdict

import cv2
import numpy as np
import pytest

from legslam.cli import main
from legslam.datasets import open as open_dataset
from legslam.pipeline import run
from legslam.slam import SLAMConfig

def needs_rerun():
    pytest.importorskip("rerun", minversion="0.41",
                        reason="rerun-sdk >= 0.41 is not installed (pip install 'legslam[viewer]')")


QUICK = "final_iters = 3\nmap_iters_keyframe = 3\nmap_iters_frame = 1\n"


def logged_frames(rrd) -> dict:
    """Entity path -> the sorted frame numbers it was logged at ("static" if static)."""
    from rerun.chunk import RrdReader

    frames = defaultdict(list)
    for chunk in RrdReader(rrd).stream():
        if chunk.is_static:
            frames[chunk.entity_path] = "static"
        else:
            frames[chunk.entity_path] += chunk.to_record_batch().column("frame").to_pylist()
    return {k: v if v == "static" else sorted(v) for k, v in frames.items()}


def last_logged(rrd, entity: str, column: str):
    """The last value of a column (one logged batch) at an entity."""
    from rerun.chunk import RrdReader

    rows = [v for c in RrdReader(rrd).stream() if c.entity_path == entity
            for v in c.to_record_batch().column(column).to_pylist()]
    return rows[-1]


def test_cli_run_records_frames_poses_and_the_map(small_synthetic, tmp_path, capsys):
    needs_rerun()
    (tmp_path / "quick.toml").write_text(QUICK)
    rrd = tmp_path / "run.rrd"
    assert main(["run", str(small_synthetic), "--no-features", "--max-frames", "5", "--quiet", "--sync",
                 "--config", str(tmp_path / "quick.toml"), "--out", str(tmp_path / "out"),
                 "--viewer", "rerun", "--viewer-save", str(rrd)]) == 0
    assert rrd.stat().st_size > 100_000  # five 160x120 frames of colour and depth, and a map
    frames = logged_frames(rrd)
    every = list(range(5))
    for path in ("/world/camera", "/world/camera/image/rgb", "/world/camera/image/depth",
                 "/world/trajectory", "/world/ground_truth", "/stats/gaussians"):
        assert frames[path] == every, (path, frames.get(path))
    assert frames["/world/camera/image"] == "static"  # the pinhole
    # The map at every keyframe and once more at the end, after the final iterations.
    keyframes = json.loads((tmp_path / "out" / "metrics.json").read_text())["keyframe_frames"]
    assert frames["/world/gaussians"] == frames["/map/render"] == sorted(keyframes + [4])
    assert "/map/features" not in frames  # --no-features


def test_with_a_mapping_thread_the_map_is_recorded_at_the_end(small_synthetic, tmp_path):
    needs_rerun()
    rrd = tmp_path / "run.rrd"
    assert main(["run", str(small_synthetic), "--no-features", "--max-frames", "5", "--quiet",
                 "--realtime", "--out", str(tmp_path / "out"),
                 "--viewer", "rerun", "--viewer-save", str(rrd)]) == 0
    frames = logged_frames(rrd)
    assert frames["/world/camera/image/rgb"] == list(range(5))
    assert frames["/world/gaussians"] == frames["/map/render"] == [4]


class ColourEncoder:
    """A stand-in image encoder: 9-d features of an 8x6 patch grid, from colour alone."""

    def encode(self, rgb):
        small = cv2.resize(rgb, (8, 6), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
        return np.concatenate([small, small ** 2, 1 - small], axis=-1)


def test_features_are_recorded_once_there_is_a_compression(small_synthetic, tmp_path, monkeypatch):
    needs_rerun()
    from legslam import viewer

    monkeypatch.setattr(viewer, "MAX_POINTS", 5000)  # below the map's size: a subset is shown
    rrd = tmp_path / "run.rrd"
    cfg = SLAMConfig(feature_dim=4, pca_keyframes=1, final_iters=3, map_iters_keyframe=3,
                     map_iters_frame=1)
    result = run(open_dataset(small_synthetic, max_frames=4), tmp_path / "out", cfg,
                 encoder=ColourEncoder(), viewer=viewer.RerunViewer(save=rrd))
    frames = logged_frames(rrd)
    assert frames["/map/features"][-1] == 3
    assert "viewer (per frame, and the final map)" in result["timings"]
    colours = np.array(last_logged(rrd, "/map/features", "Image:buffer")[0])
    assert colours.std() > 10  # the features vary over the view, and so do their colours
    assert result["metrics"]["gaussians"] > 5000
    assert len(last_logged(rrd, "/world/gaussians", "Points3D:positions")) == 5000


def test_missing_sdk_and_misused_options_are_user_errors(small_synthetic, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` fails as if not installed
    assert main(["run", str(small_synthetic), "--no-features", "--out", str(tmp_path),
                 "--viewer", "rerun"]) == 2
    assert "pip install 'legslam[viewer]'" in capsys.readouterr().err
    assert main(["run", str(small_synthetic), "--viewer-save", str(tmp_path / "x.rrd")]) == 2
    assert "--viewer-save needs --viewer rerun" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["demo", "--viewer", "glfw"])
    assert e.value.code == 2
    assert "invalid choice: 'glfw'" in capsys.readouterr().err


def test_no_display_or_no_such_folder_are_user_errors(small_synthetic, tmp_path, monkeypatch, capsys):
    needs_rerun()
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    args = ["run", str(small_synthetic), "--no-features", "--out", str(tmp_path), "--viewer", "rerun"]
    assert main(args) == 2
    assert "no display for the rerun viewer: record with --viewer-save" in capsys.readouterr().err
    assert main(args + ["--viewer-save", str(tmp_path / "nowhere" / "x.rrd")]) == 2
    assert "cannot record to" in capsys.readouterr().err


def test_loops_that_hold_are_drawn_between_their_keyframes(tmp_path):
    needs_rerun()
    from types import SimpleNamespace

    from legslam.viewer import RerunViewer

    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = np.arange(5)
    loops = SimpleNamespace(poses=list(poses), held=[])
    slam = SimpleNamespace(loops=loops)
    rrd = tmp_path / "loops.rrd"
    viewer = RerunViewer(save=str(rrd))
    viewer.rec.set_time("frame", sequence=0)
    viewer._log_loops(slam)  # no loop yet: nothing drawn
    loops.held = [SimpleNamespace(old=0, new=4), SimpleNamespace(old=1, new=3)]
    viewer.rec.set_time("frame", sequence=1)
    viewer._log_loops(slam)
    viewer._log_loops(slam)  # unchanged: not logged again
    loops.held = loops.held[:1]  # a later optimisation dropped the second loop
    viewer.rec.set_time("frame", sequence=2)
    viewer._log_loops(slam)
    viewer.rec.flush()
    viewer.rec.disconnect()
    assert logged_frames(rrd)["/world/loop_edges"] == [1, 2]
    strip = last_logged(rrd, "/world/loop_edges", "LineStrips3D:strips")
    assert np.allclose(np.array(strip, dtype=float), [[0, 0, 0], [4, 0, 0]])
