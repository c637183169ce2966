"""`legslam eval RUN`: the sequence opened at the run's image size, mIoU by text and by example
(semantic_eval), and the errors. The mIoU tests use conftest's `language_run` (skipped when the
default encoder is not cached); the text model is a fake with known embeddings."""

import json
import shutil

import cv2
import numpy as np
import pytest

import legslam.cli.text_model
from legslam.cli import main
from legslam.datasets import open as open_dataset
from legslam.eval import NoPrototypes, by_example, by_text, read_tum
from legslam.features import PCA
from legslam.features.text import TEMPLATES
from legslam.map import GaussianMap

SEMANTIC_KEYS = ("semantic_route", "miou", "miou_by_example")


@pytest.fixture(scope="module")
def plain_run(small_synthetic, tmp_path_factory):
    """A run without language features, at half the scene's size."""
    tmp = tmp_path_factory.mktemp("plain")
    quick = tmp / "quick.toml"
    quick.write_text("final_iters = 3\nmap_iters_keyframe = 3\nmap_iters_frame = 1\n")
    assert main(["run", str(small_synthetic), "--downscale", "2", "--max-frames", "4", "--no-features",
                 "--quiet", "--config", str(quick), "--out", str(tmp / "run")]) == 0
    return tmp / "run"


@pytest.fixture
def run_copy(language_run, tmp_path):
    """A copy of the language run, to write eval.json into or change."""
    scene, out, _ = language_run
    shutil.copytree(out, tmp_path / "run")
    return scene, tmp_path / "run"


def _eval(run, *args) -> dict:
    assert main(["eval", str(run), *args]) == 0
    return json.loads((run / "eval.json").read_text())


def _unit(f):
    return f / np.maximum(np.linalg.norm(f, axis=-1, keepdims=True), 1e-12)


def _ious(preds, gts, num_classes):
    """Per-class IoU over all the views by counting, NaN for a class that occurs nowhere."""
    p, g = np.concatenate([x.ravel() for x in preds]), np.concatenate([x.ravel() for x in gts])
    p, g = p[g >= 0], g[g >= 0]
    out = []
    for c in range(num_classes):
        tp, fp, fn = np.sum((p == c) & (g == c)), np.sum((p == c) & (g != c)), np.sum((p != c) & (g == c))
        out.append(tp / (tp + fp + fn) if tp + fp + fn else np.nan)
    return np.array(out)


def _argmax_labels(features, queries):
    pred = (_unit(features) @ _unit(queries).T).argmax(axis=2)
    pred[~features.any(axis=2)] = -1
    return pred


# --- the scorer on feature maps with known answers --------------------------------------

def _known_views():
    """Frames 0, 3, 6, 9 of 10x10 labels over classes a-d (class c's features point along
    axis c, plus noise). Class a and b first show at frame 0, c at frame 3 (2 px at frame 0
    are below the 5 px of min_fraction 0.05), d only as 3 px at frame 6: no prototype."""
    rng = np.random.default_rng(0)
    labels = {i: np.zeros((10, 10), np.int32) for i in (0, 3, 6, 9)}
    labels[0][5:] = 1
    labels[0][9, :2] = 2
    labels[3][:3] = 2
    labels[6][:, 4:] = 1
    labels[6][0, :3] = 3
    labels[6][9] = -1
    labels[9][:, :3], labels[9][:, 3:6] = 2, 1
    views = {}
    for i, lab in labels.items():
        f = np.eye(5, dtype=np.float32)[np.maximum(lab, 0)] + 0.6 * rng.standard_normal((10, 10, 5)).astype(np.float32)
        if i == 6:
            f[4, :5] = 0  # nothing rendered: a miss of class a
        views[i] = (f, lab)
    return views


def test_by_example_prototypes_support_and_scores_on_known_feature_maps():
    views = _known_views()
    score = by_example(list(views), lambda i: views[i][1], lambda i: views[i][0], list("abcd"), min_fraction=0.05)
    assert score.support == [0, 3]
    expected = np.stack([sum(_unit(views[i][0])[views[i][1] == c].sum(0) for i in (0, 3)) for c in range(3)])
    np.testing.assert_array_equal(score.class_ids, [0, 1, 2])
    np.testing.assert_allclose(score.queries, _unit(expected), atol=1e-6)
    for i, (f, lab) in views.items():
        score.add(i, f, lab)
    r = score.report()
    preds = [_argmax_labels(views[i][0], expected) for i in (6, 9)]
    iou = _ious(preds, [views[i][1] for i in (6, 9)], 4)
    assert r["semantic_route"] == "by_example" and r["semantic_views"] == 2 and "miou" not in r
    np.testing.assert_allclose([r["iou_by_example"][n] for n in "abcd"], iou)
    assert r["iou_by_example"]["d"] == 0.0  # present, never predicted
    assert r["miou_by_example"] == pytest.approx(np.mean(iou))
    hits = sum(np.sum((p == views[i][1]) & (views[i][1] >= 0)) for p, i in zip(preds, (6, 9)))
    assert r["pixel_acc_by_example"] == pytest.approx(hits / (100 + 90))
    assert 0.3 < r["miou_by_example"] < 1  # the noise costs something, the features still separate
    with pytest.raises(NoPrototypes, match="covers 100%"):
        by_example(list(views), lambda i: views[i][1], lambda i: views[i][0], min_fraction=1.0)


def test_by_text_scores_every_view_over_the_whole_class_list():
    views = _known_views()
    queries = np.eye(4, 5, dtype=np.float32)
    score = by_text(queries, list("abcd"))
    for i, (f, lab) in views.items():
        score.add(i, f, lab)
    r = score.report()
    iou = _ious([_argmax_labels(f, queries) for f, _ in views.values()], [lab for _, lab in views.values()], 4)
    assert r["semantic_route"] == "text" and r["semantic_views"] == 4 and "support_frames" not in r
    assert r["miou"] == pytest.approx(np.nanmean(iou))
    np.testing.assert_allclose([r["iou"][n] for n in "abcd"], iou)


# --- the command on the synthetic run ---------------------------------------------------

def test_by_example_miou_on_the_synthetic_run_drops_with_scrambled_features(run_copy, capsys):
    _, run = run_copy
    r = _eval(run, "--every", "2", "--semantic", "example")
    present = [n for n, v in r["iou_by_example"].items() if v is not None]
    assert "| iou_by_example[table] |" in capsys.readouterr().out
    print(f"by-example mIoU {r['miou_by_example']:.3f}, pixel acc {r['pixel_acc_by_example']:.3f}, "
          f"support {r['support_frames']}, {len(present)} classes present")
    assert "miou" not in r and r["semantic_route"] == "by_example"
    assert r["semantic_views"] == r["every_2"]["count"] - len(r["support_frames"]) > 0
    # Any constant prediction scores at most 1/len(present).
    assert 3 / len(present) < r["miou_by_example"] <= 1
    m = GaussianMap.load(run / "map.ply")
    m.features = m.features[np.random.default_rng(0).permutation(len(m))]
    m.save(run / "map.ply")
    scrambled = _eval(run, "--every", "2", "--semantic", "example")
    print(f"scrambled features: by-example mIoU {scrambled['miou_by_example']:.3f}")
    assert scrambled["miou_by_example"] < 0.5 * r["miou_by_example"]


def test_auto_falls_back_to_by_example_with_a_note_and_off_skips(run_copy, tmp_path, capsys):
    _, run = run_copy
    r = _eval(run, "--every", "4", "--text-model", str(tmp_path / "none.onnx"))
    assert "miou_by_example" in r and "miou" not in r
    assert "NOT open-vocabulary" in capsys.readouterr().out
    r = _eval(run, "--every", "4", "--semantic", "off")
    assert not any(k in r for k in SEMANTIC_KEYS)
    assert main(["eval", str(run), "--semantic", "text", "--text-model", str(tmp_path / "none.onnx")]) == 2
    assert "CLIP text model" in capsys.readouterr().err


class FakeTextEncoder:
    """Stands in for legslam.features.TextEncoder: every prompt of a class name encodes to
    that name's entry of `embeddings`."""

    embeddings: dict = {}

    def __init__(self, model, threads=None):
        pass

    def encode(self, texts):
        prompt_of = {t.format(n): n for n in self.embeddings for t in TEMPLATES}
        return np.stack([self.embeddings[prompt_of[t]] for t in texts]).astype(np.float32)


def test_text_route_with_a_fake_text_encoder_gives_the_expected_miou(run_copy, monkeypatch, capsys):
    scene, run = run_copy
    seq, gmap, pca = open_dataset(scene), GaussianMap.load(run / "map.ply"), PCA.load(run / "pca.npz")
    cam = json.loads((run / "camera.json").read_text())
    _, poses = read_tum(run / "trajectory.txt")
    views = range(0, len(poses), 2)
    feats = [gmap.render(poses[i], np.array(cam["K"]), cam["width"], cam["height"]).features for i in views]
    labels = [seq[i].labels for i in views]
    names = seq.class_names
    # Text embeddings that decompress to each class's mean rendered feature (random for the
    # classes that never show): a text model that knows the scene.
    rng = np.random.default_rng(0)
    means = [sum(_unit(f)[lab == c].sum(0) for f, lab in zip(feats, labels)) for c in range(len(names))]
    emb = {n: pca.inverse_transform(_unit(m)) if np.any(m) else rng.standard_normal(pca.dim)
           for n, m in zip(names, means)}
    monkeypatch.setattr(FakeTextEncoder, "embeddings", emb)
    monkeypatch.setattr(legslam.cli.text_model, "TextEncoder", FakeTextEncoder)
    r = _eval(run, "--every", "2")
    # What text_queries makes of them: normalised, compressed, normalised.
    queries = np.stack([_unit((_unit(emb[n]) - pca.mean) @ pca.components.T) for n in names])
    iou = _ious([_argmax_labels(f, queries) for f in feats], labels, len(names))
    assert "note" not in capsys.readouterr().out
    print(f"text route (fake encoder): mIoU {r['miou']:.4f}, by hand {np.nanmean(iou):.4f}")
    assert r["semantic_route"] == "text" and "miou_by_example" not in r and r["semantic_views"] == len(views)
    # The queries here are made in float64, legslam's in float32: a pixel whose two best
    # classes score within rounding may take the other (a map from one build gave 6.4e-6).
    assert r["miou"] == pytest.approx(np.nanmean(iou), abs=1e-4)
    assert r["miou"] > 0.4


# --- sizes and errors --------------------------------------------------------------------

def test_eval_matches_a_downscaled_run_and_rejects_other_sizes(plain_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(plain_run, run)
    report = _eval(run, "--every", "2")
    assert report["every_2"]["count"] == 2 and report["every_2"]["psnr"] > 10
    cam = json.loads((run / "camera.json").read_text())
    (run / "camera.json").write_text(json.dumps({**cam, "width": 70}))
    capsys.readouterr()
    assert main(["eval", str(run)]) == 2
    assert "the run's images are 70x60 but" in capsys.readouterr().err
    assert main(["eval", str(run), "--every", "0"]) == 2
    assert "--every must be at least 1" in capsys.readouterr().err
    K = np.array(cam["K"])
    K[0, 0] *= 585 / 525  # a camera the sequence does not have (a 7-Scenes run read unregistered)
    (run / "camera.json").write_text(json.dumps({**cam, "K": K.tolist()}))
    assert main(["eval", str(run)]) == 2
    assert "the run's camera (fx" in capsys.readouterr().err


def test_a_map_without_features_has_no_semantic_metrics(plain_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(plain_run, run)
    r = _eval(run)
    assert not any(k in r for k in SEMANTIC_KEYS)
    assert "has no language features" in capsys.readouterr().out
    assert main(["eval", str(run), "--semantic", "example"]) == 2
    assert "has no language features" in capsys.readouterr().err


def test_unreadable_frames_are_left_out_by_name(plain_run, small_synthetic, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(small_synthetic, scene)
    cv2.imwrite(str(scene / "labels" / "000000.png"), np.zeros((10, 10), np.uint8))
    run = tmp_path / "run"
    shutil.copytree(plain_run, run)
    whole = _eval(run)
    assert main(["eval", str(run), "--sequence", str(scene), "--every", "1"]) == 0
    assert "frame 0 left out: " in capsys.readouterr().err
    report = json.loads((run / "eval.json").read_text())
    assert report["unreadable_frames"] == [0] and report["every_1"]["count"] == whole["frames"] - 1
    for label in sorted((scene / "labels").glob("*.png")):
        cv2.imwrite(str(label), np.zeros((10, 10), np.uint8))
    assert main(["eval", str(run), "--sequence", str(scene)]) == 2
    assert "none of the run's" in capsys.readouterr().err
