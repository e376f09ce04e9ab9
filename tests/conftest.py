import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

# CI (CI=true) replays the same examples on every run, so a landing never hangs on a new random
# draw; developers' runs explore new ones (and keep any failure in .hypothesis/)
settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI") == "true":
    settings.load_profile("ci")

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
