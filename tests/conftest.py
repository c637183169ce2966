"""Shared fixtures. Data under ../shared (beside the repository) is optional: tests that need
it skip, saying why, when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def shared_path(*parts: str) -> Path:
    """Path under ../shared, or a pytest skip naming what is missing."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} is absent (the shared data/models folder beside the repository)")
    return p


def slam_encoder() -> str:
    """The encoder model a SLAM run loads by default, or a pytest skip when it is not cached."""
    from legslam.models import resolve
    from legslam.slam import SLAMConfig

    model = SLAMConfig().encoder_model
    try:
        resolve(model)
    except FileNotFoundError as e:
        pytest.skip(f"the SLAM's encoder is not cached ({e})")
    return model


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The ../shared folder beside the repository root; skips when it is absent."""
    return shared_path()


@pytest.fixture(scope="session")
def small_synthetic(tmp_path_factory) -> Path:
    """A small built-in scene (12 frames, 160x120), generated once per test session."""
    from legslam.datasets import synthetic

    return synthetic.generate(tmp_path_factory.mktemp("synthetic"), n_frames=12, width=160, height=120, seed=0)


@pytest.fixture(scope="session")
def language_run(tmp_path_factory):
    """(scene, run folder, pipeline result) of a run with language features on a 20-frame
    160x120 built-in scene, made once per session; skips when the SLAM's encoder is not
    cached. Tests that change the run folder work on a copy."""
    from legslam.datasets import open as open_dataset, synthetic
    from legslam.pipeline import run
    from legslam.slam import SLAMConfig

    slam_encoder()
    scene = synthetic.generate(tmp_path_factory.mktemp("scene"), n_frames=20, width=160, height=120, seed=5)
    out = tmp_path_factory.mktemp("run")
    result = run(open_dataset(scene), out, SLAMConfig(pca_keyframes=2, final_iters=60))
    return scene, out, result
