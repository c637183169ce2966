"""`legslam eval RUN`: the sequence opened at the run's image size, and its errors."""

import json

from legslam.cli import main


def test_eval_matches_a_downscaled_run_and_rejects_other_sizes(small_synthetic, tmp_path, capsys):
    quick = tmp_path / "quick.toml"
    quick.write_text("final_iters = 3\nmap_iters_keyframe = 3\nmap_iters_frame = 1\n")
    out = tmp_path / "run"
    assert main(["run", str(small_synthetic), "--downscale", "2", "--max-frames", "4", "--no-features",
                 "--quiet", "--config", str(quick), "--out", str(out)]) == 0
    assert main(["eval", str(out), "--every", "2"]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["views"] == 2 and report["psnr"] > 10
    cam = json.loads((out / "camera.json").read_text())
    (out / "camera.json").write_text(json.dumps({**cam, "width": 70}))
    capsys.readouterr()
    assert main(["eval", str(out)]) == 2
    assert "the run's images are 70x60 but" in capsys.readouterr().err
    assert main(["eval", str(out), "--every", "0"]) == 2
    assert "--every must be at least 1" in capsys.readouterr().err
