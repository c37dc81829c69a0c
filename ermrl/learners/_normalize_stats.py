"""Reading the observation statistics of ``VecNormalize`` saved as plain JSON.

Training writes them ([`ermrl.agents.save_normalize_stats`][ermrl.agents.save_normalize_stats]);
anything that rebuilds an agent from its files, an expert included (`ermrl.learners._expert`), reads
them back here.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["STATS_FORMAT", "load_normalize_stats"]

STATS_FORMAT = "ermrl.vecnormalize/1"


def load_normalize_stats(path: str | Path) -> dict[str, Any]:
    """Read statistics written by
    [`ermrl.agents.save_normalize_stats`][ermrl.agents.save_normalize_stats].

    Raises:
        ValueError: the file is not such a JSON document.
    """
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not a JSON file ({err})") from err
    if not isinstance(data, dict) or data.get("format") != STATS_FORMAT:
        raise ValueError(f"{path}: not ermrl normalization statistics ({STATS_FORMAT})")
    return data
