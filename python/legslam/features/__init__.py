"""Language features: dense DINOv2 patch features (ONNX), PCA compression, feature targets,
and the text side of queries (CLIP tokenizer, CLIP text tower, Talk2DINO projection).

    enc = Encoder("default", input_size=224, threads=1)   # `legslam models fetch` first
    pca = PCA(64).partial_fit(enc.encode(rgb))            # ... more keyframes; pca.save("pca.npz")
    with AsyncExtractor(enc, pca) as ex:                  # off the tracking thread
        ex.submit(keyframe_id, rgb)
        for r in ex.poll():                               # r.features: (h, w, 64)
            target = feature_target(r.features, height, width)

Queries against a rendered feature map are in `legslam.query`.
"""

from legslam.features.encoder import Encoder, l2_normalize
from legslam.features.extractor import AsyncExtractor, FeatureResult
from legslam.features.pca import PCA
from legslam.features.target import feature_target
from legslam.features.text import TEMPLATES, Talk2DinoProjection, TextEncoder
from legslam.features.tokenizer import Tokenizer, tokenize

__all__ = [
    "AsyncExtractor",
    "Encoder",
    "FeatureResult",
    "PCA",
    "TEMPLATES",
    "Talk2DinoProjection",
    "TextEncoder",
    "Tokenizer",
    "feature_target",
    "l2_normalize",
    "tokenize",
]
