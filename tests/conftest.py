"""Shared fixtures and hypothesis profiles (``HYPOTHESIS_PROFILE=ci`` for more examples)."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis.configuration import set_hypothesis_home_dir
from hypothesis.database import DirectoryBasedExampleDatabase

# The independent reference models live beside the tests.
sys.path.insert(0, str(Path(__file__).parent))

# Hypothesis's folder (example database, caches) beside the repository, not in whatever
# folder pytest was started from (an unusable default location is a HypothesisWarning, which
# the suite turns into an error); no database where the checkout is read-only.
_HOME = Path(__file__).resolve().parents[1] / ".hypothesis"
set_hypothesis_home_dir(_HOME)
_DATABASE = (
    DirectoryBasedExampleDatabase(_HOME / "examples") if os.access(_HOME.parent, os.W_OK) else None
)

settings.register_profile(
    "dev",
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    database=_DATABASE,
)
settings.register_profile(
    "ci",
    max_examples=200,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    database=_DATABASE,
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture
def without_matplotlib(monkeypatch: pytest.MonkeyPatch) -> None:
    """matplotlib is not installed, as in the bare wheel: ``importlib.util.find_spec`` (how
    the commands decide whether to draw figures) does not find it."""
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a, **k: None if name == "matplotlib" else real(name, *a, **k),
    )


def write_emps_mat(path: Path, **overrides: object) -> Path:
    """A small EMPS-format .mat file (50 samples, 1 ms) with variables replaced, or removed
    where the override is None."""
    import numpy as np
    from scipy.io import savemat

    n = 50
    mat: dict[str, object] = {
        "t": (np.arange(n) * 1e-3)[:, None],
        "qg": np.linspace(0.0, 1e-3, n)[:, None],
        "qm": np.linspace(0.0, 1e-3, n)[:, None],
        "vir": np.zeros((n, 1)),
        "gtau": np.array([[35.0]]),
        "kp": np.array([[160.0]]),
        "kv": np.array([[243.0]]),
    }
    for k, v in overrides.items():
        if v is None:
            del mat[k]
        else:
            mat[k] = v
    savemat(str(path), mat)
    return path
