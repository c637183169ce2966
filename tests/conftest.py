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


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The ../shared folder beside the repository root; skips when it is absent."""
    return shared_path()


@pytest.fixture(scope="session")
def small_synthetic(tmp_path_factory) -> Path:
    """A small built-in scene (12 frames, 160x120), generated once per test session."""
    from legslam.datasets import synthetic

    return synthetic.generate(tmp_path_factory.mktemp("synthetic"), n_frames=12, width=160, height=120, seed=0)
