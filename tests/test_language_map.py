"""Language features distilled into the map, end to end with the default encoder: rendered
features agree with the encoder's own at frames the map was not trained on, a by-example
query picked on one frame lights up the same class in another, and `legslam query` writes
its images. Skips when the default encoder is not in the cache (scripts/setup.sh fetches it);
the run is conftest's `language_run`."""

import numpy as np

from legslam.cli import main
from legslam.datasets import open as open_dataset
from legslam.query import heatmap, query_from_pixel


def test_rendered_features_match_the_encoder_on_frames_not_trained_on(language_run):
    scene, _, result = language_run
    slam = result["slam"]
    seq = open_dataset(scene)
    held_out = [i for i in range(len(seq)) if i not in slam.keyframe_frames]
    enc = slam._features.extractor.encoder
    cosines = []
    for i in held_out[:4]:
        grid = slam.pca.transform(enc.encode(seq[i].rgb))              # h x w x K
        rendered = slam.render(slam.poses[i], features=True)["features"]
        h, w = grid.shape[:2]
        # the rendered feature at each patch centre
        rows = ((np.arange(h) + 0.5) * rendered.shape[0] / h).astype(int)
        cols = ((np.arange(w) + 0.5) * rendered.shape[1] / w).astype(int)
        down = rendered[rows][:, cols]
        a, b = down.reshape(-1, down.shape[-1]), grid.reshape(-1, grid.shape[-1])
        cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-9)
        cosines.append(cos.mean())
    # Unrelated 64-d vectors would score ~0; a map that ignored the targets would too.
    print("mean cosine", np.mean(cosines))
    assert np.mean(cosines) > 0.6, cosines


def test_by_example_query_lights_up_the_same_class_elsewhere(language_run):
    scene, _, result = language_run
    slam = result["slam"]
    seq = open_dataset(scene)
    names = seq.class_names
    table = names.index("table")
    a, b = 2, len(seq) - 3
    labels_a = seq[a].labels
    ys, xs = np.nonzero(labels_a == table)
    pick = len(ys) // 2
    src = slam.render(slam.poses[a], features=True)["features"]
    q = query_from_pixel(src, int(xs[pick]), int(ys[pick]), radius=1)
    heat = heatmap(slam.render(slam.poses[b], features=True)["features"], q)
    on = heat[seq[b].labels == table].mean()
    off = heat[(seq[b].labels != table) & (seq[b].labels >= 0)].mean()
    assert on > off + 0.1, (on, off)


def test_query_command_writes_heat_maps_and_masks(language_run, tmp_path, capsys):
    _, out, _ = language_run
    assert main(["query", str(out), "--example", "2:80,90", "--frame", "10", "--out", str(tmp_path)]) == 0
    import cv2

    heat = cv2.imread(str(tmp_path / "example_2_80_90_frame000010_heat.png"))
    mask = cv2.imread(str(tmp_path / "example_2_80_90_frame000010_mask.png"), cv2.IMREAD_GRAYSCALE)
    assert heat.shape == (120, 160, 3) and heat.std() > 5
    assert mask.shape == (120, 160) and 0 < (mask > 0).mean() < 1
    # Text needs the CLIP text model, which is not installed here: a clear error, exit 2.
    assert main(["query", str(out), "chair", "--text-model", str(tmp_path / "none.onnx")]) == 2
    assert "--example" in capsys.readouterr().err


def test_query_command_errors(tmp_path, capsys):
    assert main(["query", str(tmp_path), "--example", "0:1,1"]) == 2
    assert "has no map.ply" in capsys.readouterr().err
