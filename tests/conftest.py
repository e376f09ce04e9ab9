from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
ASSETS = REPO / "assets"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` beside the repo (CI and developers); tests that need it skip without it."""
    if not (SHARED / "data").is_dir():
        pytest.skip("../shared/data is not beside the repo")
    return SHARED


@pytest.fixture(scope="session")
def assets_dir() -> Path:
    return ASSETS


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)
