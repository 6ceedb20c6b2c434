"""Shared test settings.

Tiny diffusion components live in `tests/dummies.py` (`get_dummy_components()`); fixtures that
only one module needs live in that module.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# The suite runs as `pytest -n 2` on 2 cores: one intra-op thread per worker avoids
# oversubscription, which costs more than it gains on these tiny models.
torch.set_num_threads(1)

SHARED_MSTAR = Path(os.environ.get("SAR_ZERO123_MSTAR", Path(__file__).resolve().parents[1] / ".." / "shared"
                                   / "data" / "mstar")).resolve()


@pytest.fixture(scope="session")
def mstar_root() -> Path:
    """The real MSTAR folder (`../shared/data/mstar`), or skip when it is absent."""
    if not (SHARED_MSTAR / "index.csv").is_file():
        pytest.skip(f"real MSTAR data not found at {SHARED_MSTAR}")
    return SHARED_MSTAR
