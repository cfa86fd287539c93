"""Real exemplar crops (``rgbd_object_exemplars`` in the data folder, docs/datasets.md): one RGB crop per class of
the RGB-D Object Dataset, named ``<class>_1_1_1_crop.png``. The simulator textures its tabletop objects with them
when present."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

# The tabletop classes' file-name prefixes in the RGB-D Object Dataset.
TABLETOP_PREFIX = {"bowl": "bowl", "cap": "cap", "cereal_box": "cereal-box", "coffee_mug": "coffee-mug",
                   "soda_can": "soda_can"}


def shared_data_dir() -> Path | None:
    """The data folder (docs/datasets.md): ``$SEMLOC_SHARED_DATA``, else ``shared/data`` beside the checkout, if it
    exists."""
    env = os.environ.get("SEMLOC_SHARED_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2].parent / "shared" / "data")
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    return None


def default_exemplar_dir() -> Path | None:
    base = shared_data_dir()
    if base is None:
        return None
    path = base / "rgbd_object_exemplars"
    return path if path.is_dir() else None


def load_exemplar_crops(folder) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(tabletop class -> crop, other class -> crop), BGR uint8, from a folder of ``<class>_*.png`` crops."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"exemplar folder {folder} does not exist")
    by_prefix: dict[str, np.ndarray] = {}
    for path in sorted(folder.glob("*_crop.png")):
        prefix = path.name[: -len("_1_1_1_crop.png")] if path.name.endswith("_1_1_1_crop.png") else path.stem
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is not None and prefix not in by_prefix:
            by_prefix[prefix] = image
    tabletop = {c: by_prefix[p] for c, p in TABLETOP_PREFIX.items() if p in by_prefix}
    others = {p: img for p, img in by_prefix.items() if p not in TABLETOP_PREFIX.values()}
    return tabletop, others
