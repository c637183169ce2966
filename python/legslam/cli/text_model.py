"""The CLIP text model on the command line: its options, and text queries for a saved run,
shared by `legslam query` and `legslam eval`."""

from __future__ import annotations

import argparse
import zipfile

import numpy as np

from ..features import PCA, Talk2DinoProjection, TextEncoder
from ..query import text_queries
from ..run_folder import PCA_FILE, RunFolder
from .common import UserError


def add_text_model_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--text-model", default="clip_vitb16_text",
                   help="CLIP text ONNX (a cached model name or a path; see `legslam export-models`)")
    p.add_argument("--projection", default=None,
                   help="Talk2DINO projection weights (.npz) for a ViT-B/14 map")


def run_text_queries(run: RunFolder, labels: list[str], args, hint: str = "") -> np.ndarray:
    """Query vectors [C, K] for the labels, in the space of the run's map (its pca.npz);
    UserError, ending with `hint`, when the text model or the compression is missing."""
    try:
        encoder = TextEncoder(args.text_model)
    except FileNotFoundError as e:
        raise UserError(f"text queries need the CLIP text model: {e}.{hint}") from e
    pca_path = run.path / PCA_FILE
    if not pca_path.is_file():
        raise UserError(f"{run.path} has no {PCA_FILE}: text queries need the run's feature compression")
    try:
        projection = Talk2DinoProjection.load(args.projection) if args.projection else None
        pca = PCA.load(pca_path)
    except (OSError, ValueError, zipfile.BadZipFile) as e:  # not there, or not what was saved
        raise UserError(str(e)) from e
    q = text_queries(labels, encoder, projection, pca)
    k = run.map.num_features
    if q.shape[1] != k:
        raise UserError(f"the text model gives {q.shape[1]}-d queries, the map has {k}-d features")
    return q
