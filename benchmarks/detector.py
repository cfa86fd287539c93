"""Benchmark: the §4.3 soft detector (HOGE x HQC templates) on 640x480 frames, against the direct equations.

    .venv/bin/python benchmarks/detector.py [--frames 60] [--reference-frames 3]

Workload: 5 exemplar templates (each matched together with its mirror image, §4.5.1, so 10 correlations per level)
x 3 pyramid levels, 8-pixel blocks, 8 orientations + epsilon bin, 64 colours. The reference
(tests/detection/reference.py) computes the same equations the straightforward way: each oriented filter applied
on its own, per-pixel squaring and block sums, nearest-palette colours by distance, and the correlation of eq. 4.3
as an explicit sum over template blocks. Both run in this process on the same frames; the heatmaps must agree to
1e-4. Also timed, for context: heatline projection, the multi-view (eq. 5.1) detector and OpenCV's HOG people
detector made soft.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.bearing import BearingGrid  # noqa: E402
from semloc_core.camera import PinholeCamera  # noqa: E402
from semloc_core.detection.boxes import BoxHeatmapDetector, HogPeopleDetector, ScoreSquash  # noqa: E402
from semloc_core.detection.features import FeatureParams  # noqa: E402
from semloc_core.detection.heatlines import HeatlineProjector  # noqa: E402
from semloc_core.detection.multiview import MultiViewDetector, OrientationParams, build_view_template  # noqa: E402
from semloc_core.detection.templates import MatchParams, TemplateDetector, build_templates  # noqa: E402
from tests.detection.reference import heatmaps_reference  # noqa: E402
from tests.detection.synthetic import make_object, paste, textured_background  # noqa: E402

KINDS = ("clock", "machine", "can", "arrow", "clock")


def _frames(count: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(count):
        scene = textured_background(480, 640, seed=seed + i)
        for kind in ("clock", "machine", "can", "arrow"):
            centre = (int(rng.integers(60, 580)), int(rng.integers(60, 420)))
            paste(scene, make_object(kind, 120), centre, int(rng.integers(50, 150)))
        frames.append(scene)
    return frames


def _timed(function, *args) -> tuple[float, object]:
    start = time.perf_counter()
    result = function(*args)
    return time.perf_counter() - start, result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60, help="frames timed for the fast detector")
    parser.add_argument("--reference-frames", type=int, default=3, help="frames run through the reference")
    parser.add_argument("--color-space", choices=["rgb", "hsv"], default="rgb",
                        help="HQC colour model (rgb: the thesis's 64-colour cube; hsv: the evaluated variant)")
    parser.add_argument("--cell", type=int, default=8, help="block size in pixels")
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.75, 0.5], help="pyramid scales")
    parser.add_argument("--template-cells", type=int, default=9, help="blocks along a template's longer side")
    args = parser.parse_args()

    params = FeatureParams(cell=args.cell, color_space=args.color_space)
    match = MatchParams(tuple(args.scales))
    templates = []
    for index, kind in enumerate(KINDS):
        # The fifth exemplar is a second clock drawn at another size: a class may hold several exemplars.
        exemplar = make_object(kind, 110 + 15 * index)
        templates += build_templates(exemplar, f"{kind}{index}", params, args.template_cells, mirror=True)
    detector = TemplateDetector(templates, params, match)
    frames = _frames(max(args.frames, args.reference_frames))
    detector.heatmaps(frames[0])   # plans the FFTs for this image size (once per stream)

    fast_times = []
    for frame in frames[:args.frames]:
        elapsed, _ = _timed(detector.heatmaps, frame)
        fast_times.append(elapsed)

    reference_times, differences = [], []
    for frame in frames[:args.reference_frames]:
        elapsed, slow = _timed(heatmaps_reference, frame, list(detector.templates), params, match.scales)
        reference_times.append(elapsed)
        differences.append(float(np.abs(detector.heatmaps(frame) - slow).max()))

    no_mirror = TemplateDetector([t for t in templates if not t.mirrored], params, match)
    no_mirror.heatmaps(frames[0])
    no_mirror_times = [_timed(no_mirror.heatmaps, frame)[0] for frame in frames[:args.frames]]

    camera = PinholeCamera.from_fov(640, 480, 60.0)
    projector = HeatlineProjector(camera, detector.classes, BearingGrid())
    heatmaps = detector.heatmaps(frames[0])
    projector.project(heatmaps)
    heatline_times = [_timed(projector.project, heatmaps)[0] for _ in range(200)]

    orientation = OrientationParams()
    views = [build_view_template(make_object(kind, 120), kind, orientation) for kind in KINDS]
    multiview = MultiViewDetector(views, orientation)
    multiview_times = [_timed(multiview.heatmaps, frame)[0] for frame in frames[:10]]

    hog = BoxHeatmapDetector(HogPeopleDetector(), ScoreSquash(), cell=4)
    hog_times = [_timed(hog.heatmaps, frame)[0] for frame in frames[:5]]

    fast_ms = 1e3 * statistics.median(fast_times)
    reference_ms = 1e3 * statistics.median(reference_times)
    print(f"soft template detector, 640x480, 5 exemplar templates (+ mirrors) x {len(args.scales)} scales "
          f"{args.scales}, {args.cell}-px blocks, {args.template_cells}-block templates, {args.color_space} colours")
    print(f"  fast      : median {fast_ms:7.1f} ms/frame = {1e3 / fast_ms:6.1f} frames/s "
          f"(p90 {1e3 * np.percentile(fast_times, 90):.1f} ms, {len(fast_times)} frames)")
    print(f"  reference : median {reference_ms:7.1f} ms/frame = {1e3 / reference_ms:6.2f} frames/s "
          f"({len(reference_times)} frames)")
    print(f"  speed-up  : {reference_ms / fast_ms:.0f}x;  max |fast - reference| = {max(differences):.2e} "
          f"(limit 1e-4: {'OK' if max(differences) <= 1e-4 else 'FAIL'})")
    print(f"  without mirrors (5 correlations per level): median {1e3 * statistics.median(no_mirror_times):.1f} "
          f"ms/frame = {1 / statistics.median(no_mirror_times):.1f} frames/s")
    print(f"heatline projection (5 classes, 60x80 heatmap -> 360 bins): median "
          f"{1e6 * statistics.median(heatline_times):.0f} us")
    print(f"multi-view eq. 5.1 detector, 5 views x 3 scales: median {1e3 * statistics.median(multiview_times):.1f} "
          f"ms/frame")
    print(f"OpenCV HOG people detector made soft (every window scored): median "
          f"{1e3 * statistics.median(hog_times):.1f} ms/frame")
    return 0 if max(differences) <= 1e-4 else 1


if __name__ == "__main__":
    sys.exit(main())
