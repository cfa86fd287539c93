"""Realism of the simulated worlds, measured the way a loop-closure front end sees them (docs/sim.md).

    .venv/bin/python benchmarks/sim_realism.py [--out docs/img/sim] [--seed 0] [--quick]

* SIFT keypoints per 640x480 ``route`` frame (OpenCV defaults), over the whole route.
* SIFT matches (Lowe ratio 0.8) and RANSAC-verified matches for revisit pairs at the same place versus pairs at
  different places (``route``), and for ``aliased`` pairs: same place on the other floor versus a true revisit.
* Pictures: a gallery of the scenarios, keypoints, match pairs, exemplars; written as JPEG to ``--out``.

Prints the figures and writes them to ``<out>/realism.json``.

A realism study, not a speed benchmark: counts (median, 10th and 90th percentiles, mean over frames or pairs), no
timing and no ratio.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.geometry import wrap_angle  # noqa: E402
from semloc_core.io.exemplars import default_exemplar_dir, load_exemplar_crops  # noqa: E402
from semloc_core.sim import make_scenario  # noqa: E402

SIFT = cv2.SIFT_create()
MATCHER = cv2.BFMatcher(cv2.NORM_L2)


def features(image):
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return SIFT.detectAndCompute(grey, None)


def matches(fa, fb, ratio: float = 0.8):
    """(ratio-test matches, RANSAC inliers among them: fundamental matrix, or a homography when that is
    degenerate)."""
    (ka, da), (kb, db) = fa, fb
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return [], 0
    good = [m for m, n in MATCHER.knnMatch(da, db, k=2) if m.distance < ratio * n.distance]
    if len(good) < 8:
        return good, 0
    pa = np.float32([ka[m.queryIdx].pt for m in good])
    pb = np.float32([kb[m.trainIdx].pt for m in good])
    F, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 3.0, 0.99)
    if F is None or F.shape != (3, 3):
        # Degenerate for a fundamental matrix (e.g. every match on one wall): verify with a homography.
        H, mask = cv2.findHomography(pa, pb, cv2.RANSAC, 3.0)
        if H is None:
            return good, 0
    return good, int(np.count_nonzero(mask))


def pair_sets(scenario, rng, count: int, window: int = 30):
    """Same-place revisit pairs (loop ground truth, > window frames apart) and different-place pairs (> 15 m)."""
    n = len(scenario)
    i, j = np.nonzero(np.tril(scenario.loop_gt, -(window + 1)))
    pick = rng.choice(len(i), min(count, len(i)), replace=False)
    same = list(zip(i[pick], j[pick]))
    xy = scenario.T_world_cam[:, :2, 3]
    different = []
    while len(different) < count:
        a, b = rng.integers(0, n, 2)
        if abs(a - b) > window and np.linalg.norm(xy[a] - xy[b]) > 15.0:
            different.append((max(a, b), min(a, b)))
    return same, different


def draw_pair(a, b, fa, fb, good, title: str):
    canvas = cv2.drawMatches(a, fa[0], b, fb[0], good[:80], None, matchColor=(0, 255, 0),
                             singlePointColor=(0, 0, 255), flags=cv2.DrawMatchesFlags_DEFAULT)
    cv2.putText(canvas, title, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 4, cv2.LINE_AA)
    cv2.putText(canvas, title, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 0), 2, cv2.LINE_AA)
    return canvas


def stats(values) -> dict:
    v = np.asarray(values, float)
    return {"n": int(v.size), "median": float(np.median(v)), "p10": float(np.percentile(v, 10)),
            "p90": float(np.percentile(v, 90)), "mean": float(v.mean())}


def plot_boxes(path: Path, groups: dict[str, list[int]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 3.6), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    ax.boxplot(list(groups.values()), tick_labels=list(groups.keys()), showfliers=True)
    ax.set_yscale("symlog", linthresh=10)
    ax.set_ylabel("RANSAC-verified SIFT matches")
    ax.grid(True, axis="y", alpha=0.3)
    ax.tick_params(axis="x", labelsize=8)
    fig.savefig(path, bbox_inches="tight")


def save(path: Path, image, quality: int = 85) -> None:
    cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, quality])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="docs/img/sim")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="fewer frames and pairs")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    pairs = 15 if args.quick else 40
    step = 40 if args.quick else 10
    report: dict = {"seed": args.seed}
    start = time.perf_counter()

    # --- route: keypoints per frame, same vs different places ------------------------------------------------
    route = make_scenario("route", seed=args.seed, frames=1200)
    counts = [len(features(route.image(i))[0]) for i in range(0, len(route), step)]
    report["route_sift_keypoints"] = stats(counts)
    typical = int(np.argsort(counts)[len(counts) // 2]) * step
    image = route.image(typical)
    keypoints = features(image)[0]
    save(out / "route_sift.jpg", cv2.drawKeypoints(image, keypoints, None, (0, 255, 0),
                                                   cv2.DRAW_MATCHES_FLAGS_DRAW_RICH_KEYPOINTS))
    same, different = pair_sets(route, rng, pairs)
    cache: dict = {}

    def feat(scenario, i):
        key = (id(scenario), i)
        if key not in cache:
            cache[key] = features(scenario.image(i))
        return cache[key]

    results = {}
    boxes: dict[str, list[int]] = {}
    for label, group in (("same_place", same), ("different_place", different)):
        raw, verified = [], []
        for a, b in group:
            good, inliers = matches(feat(route, a), feat(route, b))
            raw.append(len(good))
            verified.append(inliers)
        results[label] = {"ratio_matches": stats(raw), "ransac_inliers": stats(verified)}
        boxes[f"route\n{label.replace('_', ' ')}"] = verified
    report["route_pairs"] = results
    heading = route.poses2d[:, 2]
    a, b = max(same, key=lambda p: -abs(wrap_angle(heading[p[0]] - heading[p[1]])))
    good, inliers = matches(feat(route, a), feat(route, b))
    top = draw_pair(route.image(a), route.image(b), feat(route, a), feat(route, b), good,
                    f"same place, frames {a} / {b}: {len(good)} matches, {inliers} verified")
    a, b = different[0]
    good, inliers = matches(feat(route, a), feat(route, b))
    bottom = draw_pair(route.image(a), route.image(b), feat(route, a), feat(route, b), good,
                       f"different places, frames {a} / {b}: {len(good)} matches, {inliers} verified")
    save(out / "route_pairs.jpg", cv2.resize(np.vstack([top, bottom]), None, fx=0.6, fy=0.6))

    # --- aliased: the other floor vs a true revisit ------------------------------------------------------------
    aliased = make_scenario("aliased", seed=args.seed, frames=600)
    floors = np.asarray(aliased.metadata["floor"])
    cross = np.argwhere(np.tril(aliased.extra_gt["aliased_gt"], -31))
    revisit = np.argwhere(np.tril(aliased.loop_gt, -31))
    chosen_cross = cross[rng.choice(len(cross), min(pairs, len(cross)), replace=False)]
    chosen_revisit = revisit[rng.choice(len(revisit), min(pairs, len(revisit)), replace=False)]
    xy = aliased.T_world_cam[:, :2, 3]
    far = []
    while len(far) < pairs:
        p, q = rng.integers(0, len(aliased), 2)
        if abs(p - q) > 30 and np.linalg.norm(xy[p] - xy[q]) > 15:
            far.append((max(p, q), min(p, q)))
    aliased_results = {}
    for label, group in (("other_floor_same_place", chosen_cross), ("same_floor_revisit", chosen_revisit),
                         ("different_place", far)):
        raw, verified = [], []
        for p, q in group:
            good, inliers = matches(feat(aliased, p), feat(aliased, q))
            raw.append(len(good))
            verified.append(inliers)
        aliased_results[label] = {"ratio_matches": stats(raw), "ransac_inliers": stats(verified)}
        boxes[f"aliased\n{label.replace('_', ' ')}"] = verified
    report["aliased_pairs"] = aliased_results
    p, q = chosen_cross[0]
    good, inliers = matches(feat(aliased, p), feat(aliased, q))
    save(out / "aliased_pair.jpg", cv2.resize(draw_pair(
        aliased.image(p), aliased.image(q), feat(aliased, p), feat(aliased, q), good,
        f"floor {floors[p] + 1} frame {p} / floor {floors[q] + 1} frame {q}: {len(good)} matches, {inliers} verified"),
        None, fx=0.6, fy=0.6))

    plot_boxes(out / "matches.png", boxes)

    # --- gallery ----------------------------------------------------------------------------------------------
    crops_dir = default_exemplar_dir()
    options = {}
    if crops_dir is not None:
        crops, others = load_exemplar_crops(crops_dir)
        options = {"crops": crops, "clutter_crops": others}
    tabletop = make_scenario("tabletop", seed=args.seed, frames=300, **options)
    hall = make_scenario("hall", seed=args.seed, frames=60)
    tiles = [cv2.resize(im, (480, 360)) for im in (tabletop.image(40), tabletop.image(200), route.image(typical),
                                                    aliased.image(int(chosen_cross[0][0])))]
    save(out / "gallery.jpg", np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])]))
    save(out / "hall_panorama.jpg", np.vstack([hall.image(5), hall.image(30)]))
    exemplars = tabletop.exemplars()
    sheet = [cv2.copyMakeBorder(cv2.resize(img[0], (120, int(120 * img[0].shape[0] / img[0].shape[1]))), 0, 0, 4,
                                4, cv2.BORDER_CONSTANT, value=(255, 255, 255)) for img in exemplars.values()]
    height = max(s.shape[0] for s in sheet)
    sheet = [cv2.copyMakeBorder(s, 0, height - s.shape[0], 0, 0, cv2.BORDER_CONSTANT, value=(255, 255, 255))
             for s in sheet]
    save(out / "tabletop_exemplars.jpg", np.hstack(sheet))
    views = hall.multiview_exemplars()["ticket_machine"][:12]
    save(out / "multiview_ticket_machine.jpg", np.hstack([cv2.resize(v.image, (80, 120)) for v in views]))
    report["real_crops"] = crops_dir is not None
    report["seconds"] = time.perf_counter() - start
    (out / "realism.json").write_text(json.dumps(report, indent=1))
    print(json.dumps({k: v for k, v in report.items()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
