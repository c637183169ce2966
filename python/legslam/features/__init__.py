"""Language features: dense DINOv2 patch features (ONNX), PCA compression, feature targets,
and the text side of queries (CLIP tokenizer, CLIP text tower, Talk2DINO projection)."""

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
