"""Template libraries on disk (one sub-folder of exemplars per class) and detectors built from configuration."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from semloc_core.detection.config import build_detector
from semloc_core.io.detector_models import DetectorModelError, load_template_library
from tests.detection.synthetic import make_object, paste, textured_background


def _library(tmp_path):
    library = tmp_path / "library"
    clock = make_object("clock", 100)
    machine = make_object("machine", 100)
    (library / "clock" / "masks").mkdir(parents=True)
    (library / "machine").mkdir(parents=True)
    (library / "empty").mkdir()
    cv2.imwrite(str(library / "clock" / "front_el10.png"), clock)
    cv2.imwrite(str(library / "clock" / "front_el35.png"), clock)
    cv2.imwrite(str(library / "clock" / "masks" / "front_el35.png"), np.full(clock.shape[:2], 255, np.uint8))
    alpha = np.dstack([machine, np.full(machine.shape[:2], 255, np.uint8)])
    alpha[:10, :, 3] = 0
    cv2.imwrite(str(library / "machine" / "a_el35.png"), alpha)
    masks = tmp_path / "library_masks" / "clock"          # the simulator's sibling-folder layout
    masks.mkdir(parents=True)
    sibling = np.zeros(clock.shape[:2], np.uint8)
    sibling[20:80, 20:80] = 255
    cv2.imwrite(str(masks / "front_el10.png"), sibling)
    return library


def test_library_reads_classes_masks_and_patterns(tmp_path):
    library = load_template_library(_library(tmp_path))
    assert list(library) == ["clock", "machine"]          # the empty folder is skipped
    front10, front35 = library["clock"]
    assert front10.mask.sum() == 60 * 60                  # from library_masks/clock/
    assert front35.mask.all()                             # from clock/masks/
    machine = library["machine"][0]
    assert machine.image.shape[2] == 3 and not machine.mask[:10].any() and machine.mask[10:].all()   # alpha
    only35 = load_template_library(tmp_path / "library", "*_el35.png")
    assert [e.path.endswith("_el35.png") for e in only35["clock"]] == [True]
    with pytest.raises(DetectorModelError, match="matching"):
        load_template_library(tmp_path / "library", "*.nothing")
    with pytest.raises(DetectorModelError, match="not a folder"):
        load_template_library(tmp_path / "missing")


@pytest.mark.parametrize("kind, threads", [("templates", None), ("templates", 2), ("multiview", None)])
def test_detector_from_a_yaml_file_finds_the_objects(tmp_path, kind, threads):
    _library(tmp_path)
    config = tmp_path / "detector.yaml"
    settings = {"kind": kind, "templates": "library", "files": "*_el35.png"}
    if kind == "templates":
        settings["color_space"] = "hsv"
    if threads is not None:
        settings["threads"] = threads
    config.write_text(yaml.safe_dump(settings))
    detector = build_detector(config)
    assert detector.classes == ("clock", "machine")
    if kind == "templates":
        assert detector.threads == (threads or 1)
    scene = textured_background(240, 320, seed=9)
    centres = {"clock": (80, 120), "machine": (230, 120)}
    for name, centre in centres.items():
        paste(scene, make_object(name, 100), centre, 90)
    heatmaps = detector.heatmaps(scene)
    for k, name in enumerate(detector.classes):
        r, q = np.unravel_index(np.argmax(heatmaps[k]), heatmaps[k].shape)
        u = (q + 0.5) * scene.shape[1] / heatmaps.shape[2] - 0.5
        v = (r + 0.5) * scene.shape[0] / heatmaps.shape[1] - 0.5
        assert np.hypot(u - centres[name][0], v - centres[name][1]) < 16, name
