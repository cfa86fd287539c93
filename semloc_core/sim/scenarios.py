"""The four scenarios of the thesis: ``tabletop`` (ch. 4.8, 5), ``hall`` (ch. 4.5), ``route`` (ch. 3) and
``aliased`` (ch. 3.6.4). ``make_scenario(name, seed=..., frames=..., trajectory=..., **options)`` builds one.

Each builder returns a :class:`~semloc_core.sim.scenario.Scenario` (a Dataset whose frames render on demand).
Options are keyword arguments listed per scenario in docs/sim.md; unknown options are rejected.
"""

from __future__ import annotations

import inspect
import re
from dataclasses import replace

import numpy as np

from semloc_core.camera import CameraRig, EquirectangularCamera, PinholeCamera, forward_extrinsic
from semloc_core.geometry import invert_transform, level_frame_of_camera
from semloc_core.io.trajectory import level_real_trajectory
from semloc_core.sim import objects as objs
from semloc_core.sim import textures as tx
from semloc_core.sim.decor import (
    Decal,
    DecorLibrary,
    build_room_shell,
    build_wall,
    inward_walls,
    outward_walls,
    plan_wall,
)
from semloc_core.sim.effects import Realism
from semloc_core.sim.renderer import Lighting
from semloc_core.sim.scenario import ExemplarSettings, LoopSettings, OdometryNoise, Scenario
from semloc_core.sim.trajectories import (
    orbit_trajectory,
    resample_polyline,
    robot_poses,
    round_corners,
)
from semloc_core.sim.world import WorldBuilder

KINECT_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def _check_frames(frames, default: int) -> int:
    frames = default if frames is None else int(frames)
    if frames < 1:
        raise ValueError(f"frames must be at least 1, got {frames}")
    return frames


def _stamps(frames: int, dt: float) -> np.ndarray:
    return np.round(np.arange(frames) * dt * 1e9).astype(np.int64)


def _handheld_body(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T_world_body = np.stack([level_frame_of_camera(T) for T in T_world_cam])
    return T_world_body, invert_transform(T_world_body) @ T_world_cam


def _realism(realism, **overrides) -> Realism:
    if realism is False:
        return Realism.off()
    if isinstance(realism, Realism):
        return realism
    if realism is None or realism is True:
        return replace(Realism(), **overrides)
    if isinstance(realism, dict):
        return replace(Realism(), **{**overrides, **realism})
    raise TypeError("realism must be a Realism, a dict of its fields, True/None (defaults) or False (off)")


# ----------------------------------------------------------------------------------------------- tabletop

def _place_on_table(rng, classes: list[str], centre, axes, half, margin: float = 0.05, layouts: int = 50,
                    attempts: int = 300):
    """Rejection-sample object footprints inside the table rectangle, apart from each other (big ones first;
    a whole new layout is drawn when one object finds no room)."""
    order = sorted(range(len(classes)), key=lambda k: -objs.TABLETOP_FOOTPRINT.get(classes[k], 0.1))
    for _ in range(layouts):
        placed: dict[int, tuple[str, np.ndarray, float]] = {}
        for k in order:
            class_name = classes[k]
            r = objs.TABLETOP_FOOTPRINT.get(class_name, 0.1)
            for _ in range(attempts):
                local = rng.uniform(-1, 1, 2) * np.maximum(half - margin - r, 0.02)
                xy = centre + axes @ local
                if all(np.linalg.norm(xy - p) > r + q + 0.02 for _, p, q in placed.values()):
                    placed[k] = (class_name, xy, r)
                    break
            else:
                break
        if len(placed) == len(classes):
            return [placed[k] for k in range(len(classes))]
    raise ValueError(f"could not place {len(classes)} objects on a {2 * half[0]:.2f} x {2 * half[1]:.2f} m table")


def tabletop(seed: int = 0, frames: int | None = None, trajectory=None, *, crops: dict | None = None,
             clutter_crops: dict | None = None, instances: dict | None = None, clutter: int = 3,
             table_size=None, variation: float = 0.6, camera=None, realism=None, room_size: float = 9.0,
             fps: float = 30.0, odometry_noise: OdometryNoise | None = None,
             design_seed: int | None = None) -> Scenario:
    """A table with bowls, caps, cereal boxes, mugs and soda cans, seen by a hand-held camera walking around it.

    ``trajectory``: (N, 4, 4) poses of a real hand-held recording in its own frame (e.g. an RGB-D Scenes v2 pose
    file read with ``io.trajectory.read_rgbd_scenes_poses``); it is levelled and placed around the table
    (``io.trajectory.level_real_trajectory``) and the table is sized to the area the camera looked at. Without it a
    walking orbit is generated. ``crops`` {class: BGR} are real exemplar crops for the object appearances;
    ``clutter_crops`` {name: BGR} other objects to scatter as distractors. ``instances`` {class: count}.
    ``design_seed`` (default ``seed``): draws each class's design (generated artwork, proportions); another scene
    with the same design seed shows the same objects elsewhere, as a detector's calibration scene should.
    """
    rng = np.random.default_rng([seed, 1])
    design_seed = seed if design_seed is None else int(design_seed)
    classes = list(objs.TABLETOP_CLASSES)
    surface_z = 0.75
    if trajectory is not None:
        T_ref = np.asarray(trajectory, float)
        if T_ref.ndim != 3 or T_ref.shape[1:] != (4, 4):
            raise ValueError(f"trajectory must be (N, 4, 4) poses, got {T_ref.shape}")
        frames = _check_frames(frames, len(T_ref))
        if frames > len(T_ref):
            raise ValueError(f"the trajectory has {len(T_ref)} poses, {frames} frames asked")
        T_world_cam, table = level_real_trajectory(T_ref, surface_z)
        T_world_cam = T_world_cam[:frames]
        centre = table["centre"]
        axes = table["axes"]
        half = np.clip(table["half_extent"] + 0.15, [0.5, 0.35], [1.0, 0.7])
        # The table must not swallow the camera: shrink it until every camera centre is outside.
        cam_local = (T_world_cam[:, :2, 3] - centre) @ axes
        inside = np.all(np.abs(cam_local) < half + 0.15, axis=1)
        while inside.any() and half.min() > 0.3:
            half = half * 0.95
            inside = np.all(np.abs(cam_local) < half + 0.15, axis=1)
    else:
        frames = _check_frames(frames, 900)
        half = (np.asarray(table_size, float) / 2 if table_size is not None
                else np.array([rng.uniform(0.6, 0.95), rng.uniform(0.4, 0.6)]))
        centre = np.zeros(2)
        angle = rng.uniform(0, np.pi)
        axes = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        radius = float(np.linalg.norm(half)) + 0.55
        T_world_cam = orbit_trajectory(rng, frames, fps, centre, surface_z, radius=radius)
    if instances is None:
        counts = {c: int(rng.integers(1, 3)) for c in classes}
        for c in rng.choice(classes, 2, replace=False):
            counts[str(c)] += 1
    else:
        unknown = set(instances) - set(classes)
        if unknown:
            raise ValueError(f"unknown tabletop classes {sorted(unknown)}; known: {classes}")
        counts = {c: int(instances.get(c, 0)) for c in classes}
    while True:
        order = [c for c in classes for _ in range(counts[c])]
        rng.shuffle(order)
        try:
            placed = _place_on_table(rng, order, centre, axes, half)
            break
        except ValueError:
            # Too many for this table: drop an instance of the most repeated class (never the last of a class).
            most = max(classes, key=lambda c: counts[c])
            if counts[most] <= 1:
                raise
            counts[most] -= 1

    b = WorldBuilder("tabletop", tuple(c for c in classes if counts[c] > 0))
    library = DecorLibrary(seed * 1000 + 7, b)
    cam_xy = T_world_cam[:, :2, 3]
    extent = max(room_size / 2, float(np.abs(cam_xy - centre).max()) + 1.5)
    x0, y0, x1, y1 = centre[0] - extent, centre[1] - extent, centre[0] + extent, centre[1] + extent
    height = 2.8
    floor_t = b.textures.add(tx.carpet(rng) if rng.random() < 0.5 else tx.tiles(rng, count=2))
    ceiling_t = b.textures.add(tx.ceiling_panels(rng))
    build_room_shell(b, x0, y0, x1, y1, height, floor_t, ceiling_t, floor_tile=1.2)
    for k, (p0, p1) in enumerate(inward_walls(x0, y0, x1, y1)):
        plan = plan_wall(library, rng, p0, p1, height, library.material(int(rng.integers(6))), unique_fraction=0.8,
                         density=0.8, room_number=100 + 10 * k)
        build_wall(b, plan)
    # The table: top slab and four legs.
    wood = b.textures.add(tx.wood_panel(rng))
    legs = b.textures.add(tx.concrete(rng, 32, 32))
    corners = [centre + axes @ (half * np.array(s)) for s in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    yaw = float(np.arctan2(axes[1, 0], axes[0, 0]))
    b.box((centre[0], centre[1], surface_z - 0.02), (2 * half[0], 2 * half[1], 0.04), yaw, wood)
    for c in corners:
        inner = c - (c - centre) / np.linalg.norm(c - centre) * 0.08
        b.frustum((inner[0], inner[1], 0.0), (0, 0, 1), 0.03, 0.03, surface_z - 0.04, legs)
    crops = crops or {}
    for class_name, xy, _ in placed:
        v = objs.Variation.sample(rng, variation)
        object_yaw = float(rng.uniform(-np.pi, np.pi))
        design_rng = np.random.default_rng([design_seed, 2, classes.index(class_name)])
        objs.TABLETOP_BUILDERS[class_name](b, xy, surface_z, object_yaw, design_rng, crop=crops.get(class_name), v=v)
    # Distractors: other objects on the table (not in the map).
    names = sorted(clutter_crops) if clutter_crops else []
    taken = [(xy, r) for _, xy, r in placed]
    for k in range(int(clutter)):
        for _ in range(200):
            xy = centre + axes @ (rng.uniform(-1, 1, 2) * (half - 0.1))
            if all(np.linalg.norm(xy - p) > r + 0.09 for p, r in taken):
                break
        else:
            continue
        taken.append((xy, 0.06))
        crop = clutter_crops[names[int(rng.integers(len(names)))]] if names else None
        objs.build_clutter(b, xy, surface_z, rng, crop=crop, height=float(rng.uniform(0.1, 0.18)))
    free = [np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])]
    world = b.build(bounds=[[x0, y0], [x1, y1]], free_space=free)

    if camera is None:
        camera = PinholeCamera(640, 480, KINECT_K)
    T_world_body, T_body_cam = _handheld_body(T_world_cam)
    exemplar_builders = {c: (lambda bb, c=c: objs.TABLETOP_BUILDERS[c](
        bb, (0.0, 0.0), 0.0, 0.0, np.random.default_rng([design_seed, 2, classes.index(c)]), crop=crops.get(c)))
        for c in classes}
    return Scenario(
        "tabletop", world, camera, T_world_body, T_body_cam, _stamps(frames, 1.0 / fps), seed,
        options={"trajectory": "real" if trajectory is not None else "orbit", "instances": counts,
                 "clutter": clutter, "variation": variation, "real_crops": sorted(crops)},
        realism=_realism(realism), loop=LoopSettings(0.4, 0.8, np.radians(40.0)),
        odometry_noise=odometry_noise or OdometryNoise(), exemplar_settings=ExemplarSettings(),
        exemplar_builders=exemplar_builders, lighting=Lighting((0.3, 0.2, 0.93)),
        metadata={"table": {"centre": centre, "axes": axes, "half_extent": half, "surface_z": surface_z}})


# ----------------------------------------------------------------------------------------------- hall

def _segment_clear(a, b, obstacles: np.ndarray, radii: np.ndarray) -> bool:
    if len(obstacles) == 0:
        return True
    d = b - a
    length2 = float(d @ d)
    s = np.clip(((obstacles - a) @ d) / max(length2, 1e-12), 0, 1)
    closest = a + s[:, None] * d
    return bool(np.all(np.linalg.norm(obstacles - closest, axis=1) > radii))


def _tour(rng, anchors_fn, obstacles, radii, length_needed: float, start=None) -> np.ndarray:
    """Waypoints visiting random free points, each leg clear of obstacles, until the path is long enough."""
    points = [anchors_fn() if start is None else np.asarray(start, float)]
    total = 0.0
    guard = 0
    while total < length_needed:
        guard += 1
        if guard > 100000:
            raise RuntimeError("could not plan a long enough collision-free tour")
        candidate = anchors_fn()
        step = float(np.linalg.norm(candidate - points[-1]))
        if step < 6.0 or not _segment_clear(points[-1], candidate, obstacles, radii):
            continue
        points.append(candidate)
        total += step
    return np.asarray(points)


def hall(seed: int = 0, frames: int | None = None, trajectory=None, *, size=(88.0, 41.0), counts: dict | None = None,
         camera="panorama", spacing: float = 2.0, speed: float = 1.0, realism=None,
         odometry_noise: OdometryNoise | None = None, variation: float = 0.3) -> Scenario:
    """An open station hall (~88 x 41 m) with clocks, trash cans, payphones and ticket machines (thesis §4.5).

    A ground robot carries a 1024x256 equirectangular panorama (``camera="panorama"``), a five-camera ring
    (``"rig"``) or a forward 640x480 pinhole (``"pinhole"``) at 1.5 m and drives a tour of random places about
    ``spacing`` metres between frames; places are revisited from other directions. ``trajectory`` may be given as
    planar waypoints (M, 2) to follow instead.
    """
    rng = np.random.default_rng([seed, 3])
    frames = _check_frames(frames, 400)
    L, Wd = (float(v) for v in size)
    if L < 20 or Wd < 15:
        raise ValueError("the hall must be at least 20 x 15 m")
    x0, y0, x1, y1 = -L / 2, -Wd / 2, L / 2, Wd / 2
    counts = {"clock": 4, "trashcan": 8, "payphone": 5, "ticket_machine": 6, **(counts or {})}
    unknown = set(counts) - set(objs.HALL_CLASSES)
    if unknown:
        raise ValueError(f"unknown hall classes {sorted(unknown)}; known: {list(objs.HALL_CLASSES)}")
    b = WorldBuilder("hall", tuple(c for c in objs.HALL_CLASSES if counts.get(c, 0) > 0))
    library = DecorLibrary(seed * 1000 + 31, b, n_posters=16, n_adverts=10)
    height = 29.0
    floor_t = b.textures.add(tx.tiles(rng, 256, 256, count=2, colour=(170, 180, 190)))
    ceiling_t = b.textures.add(tx.ceiling_panels(rng))
    build_room_shell(b, x0, y0, x1, y1, height, floor_t, ceiling_t, floor_tile=1.6, ceiling_tile=4.0)
    stone = library.material(4)
    lower = 5.0
    for k, (p0, p1) in enumerate(inward_walls(x0, y0, x1, y1)):
        p0, p1 = np.asarray(p0), np.asarray(p1)
        length = float(np.linalg.norm(p1 - p0))
        direction = (p1 - p0) / length
        # Upper wall: stone with tall windows; lower band: shop fronts, adverts and doors.
        b.wall(p0, p1, lower, height, stone, repeat=(length / 3.0, (height - lower) / 3.0))
        window_t = library.design("window", k % 4)
        s = 3.0
        while s + 4.0 < length:
            b.wall(p0 + direction * s, p0 + direction * (s + 4.0), 11.0, 19.0, window_t, offset=0.02)
            s += 9.0
        s = float(rng.uniform(0.5, 2.0))
        b.wall(p0, p1, 0.0, lower, library.material(2 + (k % 2)), repeat=(length / 2.0, lower / 1.5))
        while s < length - 2.0:
            kind = rng.choice(["shop", "advert", "door", "gap"], p=[0.3, 0.35, 0.15, 0.2])
            width = {"shop": 6.0, "advert": 2.4, "door": 2.0, "gap": 2.0}[str(kind)]
            if s + width > length - 0.5:
                break
            if kind != "gap":
                if kind == "shop":
                    texture, z1 = b.textures.add(tx.shop_front(rng)), 3.2
                elif kind == "advert":
                    texture, z1 = library.fresh("advert", rng), 2.6
                else:
                    texture, z1 = library.design("door", int(rng.integers(4))), 2.6
                z0 = 0.0 if kind != "advert" else 1.2
                b.wall(p0 + direction * s, p0 + direction * (s + width), z0, z1 if kind != "advert" else 2.4,
                       texture, offset=0.02)
            s += width + float(rng.uniform(0.5, 3.0))
    # Fixtures: payphones and ticket machines against walls; trash cans and clocks in the open.
    obstacles: list[np.ndarray] = []
    radii: list[float] = []

    def wall_spot(clearance: float):
        side = int(rng.integers(4))
        if side in (0, 2):
            x = float(rng.uniform(x0 + 4, x1 - 4))
            y = y0 + clearance if side == 0 else y1 - clearance
            yaw = np.pi / 2 if side == 0 else -np.pi / 2
        else:
            y = float(rng.uniform(y0 + 4, y1 - 4))
            x = x1 - clearance if side == 1 else x0 + clearance
            yaw = np.pi if side == 1 else 0.0
        return np.array([x, y]), yaw, side

    def free_spot(margin: float):
        for _ in range(1000):
            p = rng.uniform([x0 + margin, y0 + margin], [x1 - margin, y1 - margin])
            if all(np.linalg.norm(p - o) > r + 3.0 for o, r in zip(obstacles, radii)):
                return p
        raise RuntimeError("hall too crowded")

    class_rng = {c: np.random.default_rng([seed, 4, k]) for k, c in enumerate(objs.HALL_CLASSES)}
    placed_walls: list[tuple[np.ndarray, int]] = []

    def take_wall_spot(width: float, clearance: float):
        for _ in range(1000):
            p, yaw, side = wall_spot(clearance)
            if all(np.linalg.norm(p - q) > width + 2.0 for q, _ in placed_walls):
                placed_walls.append((p, side))
                return p, yaw
        raise RuntimeError("no free wall space left")

    remaining = counts.get("ticket_machine", 0)
    while remaining > 0:
        group = min(remaining, int(rng.integers(2, 4)))
        p, yaw = take_wall_spot(group * 0.8, 0.3)
        along = np.array([-np.sin(yaw), np.cos(yaw)])
        for g in range(group):
            q = p + along * (g - (group - 1) / 2) * 0.85
            objs.build_ticket_machine(b, q, 0.0, yaw, class_rng["ticket_machine"],
                                      objs.Variation.sample(rng, variation * 0.3))
        obstacles.append(p)
        radii.append(0.5 * group + 1.0)
        remaining -= group
    for _ in range(counts.get("payphone", 0)):
        p, yaw = take_wall_spot(0.7, 0.25)
        objs.build_payphone(b, p, 0.0, yaw, class_rng["payphone"], objs.Variation.sample(rng, variation))
        obstacles.append(p)
        radii.append(1.2)
    for _ in range(counts.get("clock", 0)):
        p = free_spot(8.0)
        objs.build_clock(b, p, 0.0, float(rng.uniform(-np.pi, np.pi)), class_rng["clock"],
                         objs.Variation.sample(rng, variation))
        obstacles.append(p)
        radii.append(1.2)
    for _ in range(counts.get("trashcan", 0)):
        p = free_spot(3.0)
        objs.build_trashcan(b, p, 0.0, float(rng.uniform(-np.pi, np.pi)), class_rng["trashcan"],
                            objs.Variation.sample(rng, variation))
        obstacles.append(p)
        radii.append(1.2)
    # Benches and an information kiosk: occluders that are not in the map.
    bench_t = b.textures.add(tx.wood_panel(rng))
    for _ in range(6):
        p = free_spot(6.0)
        b.box((p[0], p[1], 0.45), (0.6, 3.0, 0.9), float(rng.choice([0.0, np.pi / 2])), bench_t)
        obstacles.append(p)
        radii.append(2.5)
    p = free_spot(10.0)
    kiosk = b.textures.add(tx.shop_front(rng, 384, 512))
    b.box((p[0], p[1], 1.5), (3.0, 3.0, 3.0), float(rng.uniform(0, np.pi)), kiosk)
    obstacles.append(p)
    radii.append(3.5)
    free = [np.array([[x0 + 1, y0 + 1], [x1 - 1, y0 + 1], [x1 - 1, y1 - 1], [x0 + 1, y1 - 1]])]
    world = b.build(bounds=[[x0, y0], [x1, y1]], free_space=free)

    # The robot's tour.
    obstacle_xy = np.asarray(obstacles)
    obstacle_r = np.asarray(radii)
    if trajectory is not None:
        waypoints = np.asarray(trajectory, float)
        if waypoints.ndim != 2 or waypoints.shape[1] != 2 or len(waypoints) < 2:
            raise ValueError("a hall trajectory is planar waypoints (M, 2)")
    else:
        def anchor():
            for _ in range(1000):
                p = rng.uniform([x0 + 4, y0 + 4], [x1 - 4, y1 - 4])
                if np.all(np.linalg.norm(obstacle_xy - p, axis=1) > obstacle_r):
                    return p
            raise RuntimeError("no free anchor")

        # Rounding sharp turns shortens a tour a lot: plan twice the length, extend if still short.
        needed = spacing * frames + 20
        waypoints = _tour(rng, anchor, obstacle_xy, obstacle_r, 2 * needed)
        while np.sum(np.linalg.norm(np.diff(round_corners(waypoints, 2.5), axis=0), axis=1)) < needed:
            waypoints = np.concatenate([waypoints, _tour(rng, anchor, obstacle_xy, obstacle_r, needed,
                                                         start=waypoints[-1])[1:]])
    path = round_corners(waypoints, 2.5)
    xy, heading = resample_polyline(path, spacing, frames)
    T_world_body = robot_poses(xy, heading, rng, yaw_jitter_deg=2.0, lateral_jitter=0.3)
    cam = _robot_camera(camera, 1.5)
    return Scenario(
        "hall", world, cam, T_world_body, None if isinstance(cam, CameraRig) else
        np.repeat(cam.T_body_cam[None], frames, axis=0), _stamps(frames, spacing / speed), seed,
        options={"size": [L, Wd], "counts": counts, "camera": camera if isinstance(camera, str) else "custom",
                 "spacing": spacing},
        realism=_realism(realism, exposure_time=1.0 / 30.0, illumination_period=600.0),
        loop=LoopSettings(4.0, 8.0, None if not isinstance(cam, PinholeCamera) else np.radians(45)),
        odometry_noise=odometry_noise or OdometryNoise(),
        exemplar_settings=ExemplarSettings(elevation_deg=5.0, multiview_elevations_deg=(0.0, 15.0)),
        exemplar_builders={c: (lambda bb, c=c: objs.HALL_BUILDERS[c](
            bb, (0.0, 0.0), 0.0, 0.0, np.random.default_rng([seed, 4, objs.HALL_CLASSES.index(c)])))
            for c in objs.HALL_CLASSES},
        lighting=Lighting((0.2, -0.3, 0.93)))


def _robot_camera(camera, height: float):
    if isinstance(camera, (PinholeCamera, EquirectangularCamera, CameraRig)):
        return camera
    if camera == "panorama":
        return EquirectangularCamera(1024, 256, forward_extrinsic(height))
    if isinstance(camera, str) and camera.startswith("panorama:"):
        # "panorama:WxH": e.g. 4096x1024, 0.09 degrees a pixel, near the thesis's Ladybug 3 (§4.5: ~5400 px around),
        # at which the station's objects are as many pixels tall as the template detector needs.
        match = re.fullmatch(r"panorama:(\d+)x(\d+)", camera)
        if match is None or int(match[1]) < 64 or int(match[2]) < 16:
            raise ValueError(f"a panorama is 'panorama:WIDTHxHEIGHT' (at least 64x16), got {camera!r}")
        return EquirectangularCamera(int(match[1]), int(match[2]), forward_extrinsic(height))
    if camera == "rig":
        return CameraRig.ring(5, 512, 384, 76.0, height_m=height)
    if camera == "pinhole":
        return PinholeCamera.from_fov(640, 480, 60.0, T_body_cam=forward_extrinsic(height))
    raise ValueError(f"camera must be 'panorama', 'panorama:WxH', 'rig', 'pinhole' or a camera model, got {camera!r}")


# ----------------------------------------------------------------------------------------------- buildings

class _Building:
    """A grid of solid blocks separated by corridors; corridor centre lines meet at nodes (i, j)."""

    def __init__(self, nx: int, ny: int, block=(14.0, 10.0), corridor: float = 3.0) -> None:
        self.nx, self.ny = nx, ny
        self.block = block
        self.corridor = corridor
        self.pitch = (block[0] + corridor, block[1] + corridor)

    def node(self, i: int, j: int) -> np.ndarray:
        return np.array([i * self.pitch[0], j * self.pitch[1]])

    @property
    def outer(self):
        h = self.corridor / 2
        return -h, -h, self.nx * self.pitch[0] + h, self.ny * self.pitch[1] + h

    def blocks(self):
        h = self.corridor / 2
        for i in range(self.nx):
            for j in range(self.ny):
                yield i, j, (i * self.pitch[0] + h, j * self.pitch[1] + h, (i + 1) * self.pitch[0] - h,
                             (j + 1) * self.pitch[1] - h)

    def neighbours(self, node):
        i, j = node
        out = []
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            if 0 <= i + di <= self.nx and 0 <= j + dj <= self.ny:
                out.append((i + di, j + dj))
        return out

    def free_space(self) -> list[np.ndarray]:
        """Corridor rectangles (along rows and columns)."""
        x0, y0, x1, y1 = self.outer
        h = self.corridor / 2
        rects = []
        for j in range(self.ny + 1):
            y = j * self.pitch[1]
            rects.append(np.array([[x0, y - h], [x1, y - h], [x1, y + h], [x0, y + h]]))
        for i in range(self.nx + 1):
            x = i * self.pitch[0]
            rects.append(np.array([[x - h, y0], [x + h, y0], [x + h, y1], [x - h, y1]]))
        return rects


def _plan_building(b: WorldBuilder, building: _Building, library: DecorLibrary, rng, height: float,
                   unique_fraction: float, density: float):
    """Décor of every wall of the building (blocks facing out, outer boundary facing in)."""
    plans = []
    number = 100
    x0, y0, x1, y1 = building.outer
    for p0, p1 in inward_walls(x0, y0, x1, y1):
        plans.append(plan_wall(library, rng, p0, p1, height, library.material(0), unique_fraction, density, number))
        number += 20
    for i, j, (bx0, by0, bx1, by1) in building.blocks():
        material = library.material(int(rng.integers(library.n_materials)))
        for p0, p1 in outward_walls(bx0, by0, bx1, by1):
            plans.append(plan_wall(library, rng, p0, p1, height, material, unique_fraction, density, number))
            number += 20
    return plans


def _itinerary(building: _Building, rng, length_needed: float) -> list[tuple[int, int]]:
    """Designed start (same-direction revisit, opposite-direction revisit, crossings) then a random walk."""
    loop = [(1, 1), (2, 1), (3, 1), (3, 2), (2, 2), (1, 2), (1, 1)]
    if building.nx < 4 or building.ny < 3:
        loop = [(0, 0), (1, 0), (1, 1), (0, 1), (0, 0)]
        crossing = []
    else:
        crossing = [(1, 0), (2, 0), (2, 1), (2, 2), (2, 3)]
    nodes = loop + loop[1:] + loop[::-1][1:] + crossing

    def length(seq):
        return sum(float(np.linalg.norm(building.node(*a) - building.node(*c))) for a, c in zip(seq, seq[1:]))

    while length(nodes) < length_needed:
        here, previous = nodes[-1], nodes[-2]
        options = [n for n in building.neighbours(here) if n != previous]
        straight = (2 * here[0] - previous[0], 2 * here[1] - previous[1])
        if straight in options and rng.random() < 0.5:
            nodes.append(straight)
        else:
            nodes.append(options[int(rng.integers(len(options)))])
    return nodes


def _walk(building: _Building, nodes, spacing: float, frames: int, rng, lane: float = 0.45):
    waypoints = np.array([building.node(*n) for n in nodes], float)
    path = round_corners(waypoints, 1.2)
    xy, heading = resample_polyline(path, spacing, frames)
    # Keep to the right of the corridor's centre line.
    xy = xy + lane * np.stack([np.sin(heading), -np.cos(heading)], axis=1)
    return robot_poses(xy, heading, rng, yaw_jitter_deg=3.0, lateral_jitter=0.15)


def route(seed: int = 0, frames: int | None = None, trajectory=None, *, blocks=(4, 3), camera="pinhole",
          spacing: float = 0.6, speed: float = 1.2, unique_fraction: float = 0.35, decor_density: float = 0.9,
          realism=None, odometry_noise: OdometryNoise | None = None, fixtures: bool = True) -> Scenario:
    """A building of corridors around blocks, walked along a route with revisits (thesis ch. 3, Fig. 3.2).

    The route starts with a loop around two blocks, the same loop again (same-direction revisit), the loop in
    reverse (opposite direction), and a walk through the loop's middle (crossings), then wanders at random until
    ``frames`` frames (default 1200, any number available) ``spacing`` m apart. ``trajectory`` may be a list of grid
    nodes (i, j) to walk instead. ``camera``: "pinhole" (640x480, 60 degrees, default), "panorama" or "rig".
    """
    rng = np.random.default_rng([seed, 5])
    frames = _check_frames(frames, 1200)
    nx, ny = (int(v) for v in blocks)
    if nx < 2 or ny < 2:
        raise ValueError("the route building needs at least 2 x 2 blocks")
    building = _Building(nx, ny)
    b = WorldBuilder("route", ("trashcan", "clock") if fixtures else ())
    library = DecorLibrary(seed * 1000 + 53, b)
    height = 3.0
    x0, y0, x1, y1 = building.outer
    floor_t = b.textures.add(tx.tiles(rng, count=4))
    ceiling_t = b.textures.add(tx.ceiling_panels(rng))
    build_room_shell(b, x0, y0, x1, y1, height, floor_t, ceiling_t, floor_tile=1.2)
    for plan in _plan_building(b, building, library, rng, height, unique_fraction, decor_density):
        build_wall(b, plan)
    if fixtures:
        _corridor_fixtures(b, building, rng, seed, 0.0)
    world = b.build(bounds=[[x0, y0], [x1, y1]], free_space=building.free_space())
    if trajectory is not None:
        nodes = [tuple(int(v) for v in n) for n in trajectory]
    else:
        nodes = _itinerary(building, rng, spacing * frames + 30)
    T_world_body = _walk(building, nodes, spacing, frames, rng)
    cam = _robot_camera(camera, 1.4)
    return Scenario(
        "route", world, cam, T_world_body, None if isinstance(cam, CameraRig) else
        np.repeat(cam.T_body_cam[None], frames, axis=0), _stamps(frames, spacing / speed), seed,
        options={"blocks": [nx, ny], "camera": camera if isinstance(camera, str) else "custom", "spacing": spacing,
                 "unique_fraction": unique_fraction, "nodes": [list(n) for n in nodes]},
        realism=_realism(realism, exposure_time=1.0 / 60.0, illumination_period=300.0),
        loop=LoopSettings(2.5, 5.0, np.radians(45.0) if isinstance(cam, PinholeCamera) else None),
        odometry_noise=odometry_noise or OdometryNoise(),
        exemplar_settings=ExemplarSettings(elevation_deg=5.0, multiview_elevations_deg=(0.0, 15.0)),
        exemplar_builders=_fixture_exemplars(seed), lighting=Lighting((0.3, 0.4, 0.87)))


def _fixture_exemplars(seed: int) -> dict:
    return {"trashcan": lambda bb: objs.build_trashcan(bb, (0.0, 0.0), 0.0, 0.0, np.random.default_rng([seed, 6, 0])),
            "clock": lambda bb: objs.build_clock(bb, (0.0, 0.0), 0.0, 0.0, np.random.default_rng([seed, 6, 1]),
                                                 pole=False)}


def _corridor_fixtures(b: WorldBuilder, building: _Building, rng, seed: int, z: float, count_scale: float = 1.0):
    """Trash cans at some corridor corners and clocks hanging over some corridors."""
    trash_rng = np.random.default_rng([seed, 6, 0])
    clock_rng = np.random.default_rng([seed, 6, 1])
    h = building.corridor / 2
    for i, j, (bx0, by0, bx1, by1) in building.blocks():
        if rng.random() < 0.5 * count_scale:
            corner = np.array([bx0 - 0.4 if rng.random() < 0.5 else bx1 + 0.4,
                               by0 - 0.4 if rng.random() < 0.5 else by1 + 0.4])
            # Keep it in the corridor but off the walking lanes' centre: against the block's corner.
            objs.build_trashcan(b, corner, z, float(rng.uniform(-np.pi, np.pi)), trash_rng, objs.Variation(scale=0.6))
        if rng.random() < 0.35 * count_scale:
            x = float(rng.uniform(bx0 + 2, bx1 - 2))
            y = by0 - h if rng.random() < 0.5 else by1 + h
            clock_z = z - 0.9
            objs.build_clock(b, (x, y), clock_z, 0.0, clock_rng, objs.Variation(scale=0.5), pole=False)


# ----------------------------------------------------------------------------------------------- aliased

def aliased(seed: int = 0, frames: int | None = None, trajectory=None, *, blocks=(3, 2), camera="pinhole",
            spacing: float = 0.6, speed: float = 1.2, floor_height: float = 3.6, distinct_signs: bool = False,
            realism=None, odometry_noise: OdometryNoise | None = None) -> Scenario:
    """Two floors with the same layout and décor (thesis §3.6.4, Fig. 3.8), walked one after the other.

    Floor 2 repeats floor 1 exactly (same designs at the same places) except a floor-number sign at the start and,
    with ``distinct_signs``, its room numbers. The walk: a loop on floor 1, the same loop on floor 2 (an
    elevator in between: same x, y, no planar motion), then back to floor 1. Same-place pairs on different floors
    are not loops (3-D distance); they are listed in ``scenario.aliased_gt``.
    """
    rng = np.random.default_rng([seed, 8])
    frames = _check_frames(frames, 600)
    nx, ny = (int(v) for v in blocks)
    building = _Building(nx, ny, block=(12.0, 9.0))
    b = WorldBuilder("aliased", ())
    library = DecorLibrary(seed * 1000 + 71, b)
    height = 3.0
    x0, y0, x1, y1 = building.outer
    floor_t = b.textures.add(tx.tiles(rng, count=4))
    ceiling_t = b.textures.add(tx.ceiling_panels(rng))
    plans = _plan_building(b, building, library, rng, height, 0.5, 0.9)
    for level in range(2):
        z = level * floor_height
        build_room_shell(b, x0, y0, x1, y1, height, floor_t, ceiling_t, floor_tile=1.2, z_floor=z)
        for k, plan in enumerate(plans):
            extra = ()
            if k == 0:
                sign = library.sign(f"FLOOR {level + 1}", colours=((40, 40, 40), (255, 255, 255)))
                extra = (Decal(1.0, 1.6, 2.0, 2.25, sign),)
            if distinct_signs and level == 1:
                # Room 123 upstairs is room 223: the only difference between the floors.
                plan = replace(plan, decals=tuple(
                    replace(d, texture=library.sign(str(int(d.label[5:]) + 100))) if d.label.startswith("room:")
                    else d for d in plan.decals))
            build_wall(b, plan, z_floor=z, extra=extra)
    world = b.build(bounds=[[x0, y0], [x1, y1]], free_space=building.free_space())

    loop_nodes = [(0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (0, 1), (0, 0)] if nx >= 2 else \
        [(0, 0), (1, 0), (1, 1), (0, 1), (0, 0)]
    if trajectory is not None:
        loop_nodes = [tuple(int(v) for v in n) for n in trajectory]
        if loop_nodes[0] != loop_nodes[-1]:
            raise ValueError("an aliased trajectory is a closed loop of grid nodes (first node = last node)")
    loop_length = sum(float(np.linalg.norm(building.node(*a) - building.node(*c)))
                      for a, c in zip(loop_nodes, loop_nodes[1:]))
    repeats = int(np.ceil((spacing * frames + 10) / loop_length)) + 1
    nodes = loop_nodes + loop_nodes[1:] * (repeats - 1)
    T_world_body = _walk(building, nodes, spacing, frames, rng)
    # The loop starts at an elevator: every lap is driven on the other floor (1, 2, 1, 2, ...).
    floors = (np.floor(np.arange(frames) * spacing / loop_length).astype(int) % 2).tolist()
    T_world_body[:, 2, 3] = np.asarray(floors) * floor_height
    jumps = [i for i in range(1, frames) if floors[i] != floors[i - 1]]
    cam = _robot_camera(camera, 1.4)
    scenario = Scenario(
        "aliased", world, cam, T_world_body, None if isinstance(cam, CameraRig) else
        np.repeat(cam.T_body_cam[None], frames, axis=0), _stamps(frames, spacing / speed), seed,
        options={"blocks": [nx, ny], "camera": camera if isinstance(camera, str) else "custom",
                 "floor_height": floor_height},
        realism=_realism(realism, illumination_period=300.0),
        loop=LoopSettings(2.5, 5.0, np.radians(45.0) if isinstance(cam, PinholeCamera) else None),
        odometry_noise=odometry_noise or OdometryNoise(), exemplar_builders={},
        lighting=Lighting((0.3, 0.4, 0.87)), metadata={"floor": floors, "jumps": jumps})
    # Same place (planar distance), different floor: the confusable pairs.
    xy = scenario.T_world_cam[:, :2, 3]
    floor = np.asarray(floors)
    planar, _ = _planar_pairs(xy, scenario.T_world_cam[:, :3, 2], scenario.loop_settings)
    scenario.extra_gt["aliased_gt"] = planar & (floor[:, None] != floor[None, :])
    return scenario


def _planar_pairs(xy, axes, loop: LoopSettings):
    from semloc_core.eval.loops import loop_ground_truth

    return loop_ground_truth(xy, axes, loop.distance, loop.soft_distance, loop.max_angle)


# ----------------------------------------------------------------------------------------------- registry

SCENARIOS = {"tabletop": tabletop, "hall": hall, "route": route, "aliased": aliased}


def make_scenario(name: str, seed: int = 0, frames: int | None = None, trajectory=None, **options) -> Scenario:
    """Build scenario ``name`` (tabletop, hall, route, aliased); see each builder for its options."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose from {sorted(SCENARIOS)}")
    builder = SCENARIOS[name]
    allowed = set(inspect.signature(builder).parameters) - {"seed", "frames", "trajectory"}
    unknown = set(options) - allowed
    if unknown:
        raise TypeError(f"scenario {name!r} has no option(s) {sorted(unknown)}; options: {sorted(allowed)}")
    return builder(seed=int(seed), frames=frames, trajectory=trajectory, **options)
