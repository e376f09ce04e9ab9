import logging
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


@pytest.fixture
def log_lines() -> list[str]:
    """Messages of the package logger (a handler of its own: the CLI tests may have turned
    propagation to the root logger, which caplog listens to, off)."""
    lines: list[str] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = lambda record: lines.append(record.getMessage())
    logger = logging.getLogger("dloe_sfm")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield lines
    logger.removeHandler(handler)
    logger.setLevel(level)
