"""sar_zero123: noise-tolerant novel-view SAR synthesis via denoising diffusion.

Heavy submodules (diffusers, transformers) are imported lazily so that `import sar_zero123`
and the data/simulator layers stay cheap. ``SIM_PRIOR_ROTATED`` names the multi-view SAR prior bundled with
the package: ``SARZero123Pipeline.from_pretrained(SIM_PRIOR_ROTATED)`` (see
``sar_zero123/pretrained/README.md``).
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "SARZero123Pipeline": "sar_zero123.model.pipeline",
    "SARZero123PipelineOutput": "sar_zero123.model.pipeline",
    "build_sar_zero123": "sar_zero123.model.build",
    "PoseProjection": "sar_zero123.model.conditioning",
    "embed_pose": "sar_zero123.model.conditioning",
    "SAREncoder": "sar_zero123.encoder",
    "SIM_PRIOR_ROTATED": "sar_zero123.pretrained",
    "SIM_PRIOR_IDENTITY": "sar_zero123.pretrained",
    "resolve_pretrained": "sar_zero123.pretrained",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'sar_zero123' has no attribute {name!r}")
