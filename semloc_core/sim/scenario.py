"""A simulated recording: world + camera + trajectory, rendered frame by frame on demand, with exact ground truth.

:class:`Scenario` is a :class:`semloc_core.io.dataset.Dataset`, so anything that reads a dataset from disk reads a
scenario in memory the same way; :meth:`Scenario.write` stores it in the on-disk layout (docs/datasets.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semloc_core.camera import CameraRig, EquirectangularCamera, PinholeCamera
from semloc_core.eval.loops import loop_ground_truth
from semloc_core.geometry import invert_transform, wrap_angle
from semloc_core.io.dataset import (
    Dataset,
    Odometry,
    ViewExemplar,
    VisibleObject,
    increment_to_twist,
    relative_increments,
    write_dataset,
)
from semloc_core.sim.effects import NoiseBank, Realism, finish_image, illumination_schedule, vignette_map
from semloc_core.sim.renderer import Lighting, Renderer, RenderOutput
from semloc_core.sim.world import World, WorldBuilder


MAX_BLUR_PX = 30.0


@dataclass(frozen=True)
class OdometryNoise:
    """Odometry error model: relative (multiplicative) and absolute (additive) Gaussian noise per component."""

    v_rel: float = 0.05
    v_abs: float = 0.01  # m/s
    omega_rel: float = 0.05
    omega_abs: float = 0.005  # rad/s

    @classmethod
    def none(cls) -> "OdometryNoise":
        return cls(0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class LoopSettings:
    """Loop ground-truth thresholds: ``distance`` (m) for true loops, ``soft_distance`` for ignored pairs,
    ``max_angle`` (rad, None = any direction) between viewing directions for limited fields of view."""

    distance: float = 2.0
    soft_distance: float = 4.0
    max_angle: float | None = None


@dataclass(frozen=True)
class ExemplarSettings:
    """How exemplars are rendered: single-view elevation, multi-view azimuths x elevations, image size (px)."""

    elevation_deg: float = 20.0
    multiview_azimuths: int = 12
    multiview_elevations_deg: tuple[float, ...] = (10.0, 35.0)
    size_px: int = 160
    background: tuple[int, int, int] = (255, 255, 255)


@dataclass
class _FrameCache:
    index: int = -1
    outputs: list = field(default_factory=list)


def odometry_from_poses(poses2d: np.ndarray, stamps_ns: np.ndarray, noise: OdometryNoise,
                        rng: np.random.Generator) -> Odometry:
    """Noisy odometry from ground-truth planar poses: exact SE(2) twists between frames, then the noise model."""
    inc = relative_increments(poses2d)
    twist = increment_to_twist(inc)
    dt = np.zeros(len(poses2d))
    dt[1:] = np.diff(np.asarray(stamps_ns, np.int64)) / 1e9
    safe = np.where(dt > 0, dt, 1.0)
    v = np.where(dt > 0, twist[:, 0] / safe, 0.0)
    vl = np.where(dt > 0, twist[:, 1] / safe, 0.0)
    w = np.where(dt > 0, twist[:, 2] / safe, 0.0)
    n = len(poses2d)
    e = rng.standard_normal((n, 6))
    moving = dt > 0
    v = v * (1 + noise.v_rel * e[:, 0]) + noise.v_abs * e[:, 1] * moving
    vl = vl * (1 + noise.v_rel * e[:, 2]) + noise.v_abs * e[:, 3] * moving
    w = w * (1 + noise.omega_rel * e[:, 4]) + noise.omega_abs * e[:, 5] * moving
    return Odometry(v, vl, w, dt)


def _interpolate_pose(Ta: np.ndarray, Tb: np.ndarray, alpha: float) -> np.ndarray:
    """Pose a fraction ``alpha`` of the way from Ta to Tb (rotation about the relative axis, linear translation)."""
    R_rel = Ta[:3, :3].T @ Tb[:3, :3]
    angle = np.arccos(np.clip((np.trace(R_rel) - 1) / 2, -1.0, 1.0))
    T = np.eye(4)
    if angle < 1e-9:
        T[:3, :3] = Ta[:3, :3]
    else:
        axis = np.array([R_rel[2, 1] - R_rel[1, 2], R_rel[0, 2] - R_rel[2, 0], R_rel[1, 0] - R_rel[0, 1]])
        norm = np.linalg.norm(axis)
        if norm < 1e-9:  # a half turn: no unique shortest path, keep the start attitude
            T[:3, :3] = Ta[:3, :3]
        else:
            axis /= norm
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            a = alpha * angle
            T[:3, :3] = Ta[:3, :3] @ (np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K)
    T[:3, 3] = (1 - alpha) * Ta[:3, 3] + alpha * Tb[:3, 3]
    return T


class Scenario(Dataset):
    """A simulated dataset whose frames render on demand (see the module docstring)."""

    def __init__(self, name: str, world: World, camera, T_world_body: np.ndarray, T_body_cam: np.ndarray | None,
                 stamps_ns: np.ndarray, seed: int, options: dict | None = None, realism: Realism | None = None,
                 loop: LoopSettings = LoopSettings(), odometry_noise: OdometryNoise = OdometryNoise(),
                 exemplar_settings: ExemplarSettings = ExemplarSettings(), exemplar_builders: dict | None = None,
                 lighting: Lighting = Lighting(), metadata: dict | None = None) -> None:
        self.world = world
        self.seed = int(seed)
        self.options = dict(options or {})
        self.realism = (realism or Realism()).validate()
        self.loop_settings = loop
        self.exemplar_settings = exemplar_settings
        self._exemplar_builders = exemplar_builders or {}
        self.base_lighting = lighting
        self.renderer = Renderer(world)
        self._cache = _FrameCache()
        rig = isinstance(camera, CameraRig)
        stamps_ns = np.asarray(stamps_ns, np.int64)
        super().__init__(name=name, n_frames=len(T_world_body), camera=camera, stamps_ns=stamps_ns,
                         T_world_body=T_world_body, T_body_cam=None if rig else T_body_cam,
                         semantic_map=world.semantic_map(), image_source=self._image,
                         visible_source=self._visible, metadata=metadata)
        poses2d = self.poses2d
        self.odometry = odometry_from_poses(poses2d, stamps_ns, odometry_noise,
                                            np.random.default_rng([self.seed, 77]))
        self.odometry_noise = odometry_noise
        T_cam = self.T_world_cam
        self.loop_gt, self.loop_gt_soft = loop_ground_truth(T_cam[:, :3, 3], T_cam[:, :3, 2], loop.distance,
                                                            loop.soft_distance, loop.max_angle)
        self._lights = illumination_schedule(self.realism, stamps_ns / 1e9, self.seed)
        self._vignettes: dict[int, np.ndarray | None] = {}
        self._noise_banks: dict = {}
        self._flow_cache: dict = {}

    # ------------------------------------------------------------------ cameras and poses

    @property
    def cameras(self) -> tuple:
        return self.camera.cameras if isinstance(self.camera, CameraRig) else (self.camera,)

    def camera_pose(self, i: int, k: int = 0) -> np.ndarray:
        """T_world_cam of camera k of the rig (or the camera) at frame i."""
        T_body_cam = self.T_body_cam[i] if self.T_body_cam is not None else self.cameras[k].T_body_cam
        return self.T_world_body[i] @ T_body_cam

    def lighting(self, i: int) -> Lighting:
        light = self._lights[i]
        d = np.asarray(self.base_lighting.direction, float)
        c, s = np.cos(light.light_azimuth), np.sin(light.light_azimuth)
        return Lighting((c * d[0] - s * d[1], s * d[0] + c * d[1], d[2]))

    # ------------------------------------------------------------------ rendering

    def render(self, i: int) -> list[RenderOutput]:
        """The raw renders of frame i (one per camera): linear colour, range and object ids."""
        i = self._index(i)
        if self._cache.index == i:
            return self._cache.outputs
        lighting = self.lighting(i)
        outputs = [self.renderer.render(cam, self.camera_pose(i, k), lighting) for k, cam in enumerate(self.cameras)]
        self._cache = _FrameCache(i, outputs)
        return outputs

    def _noise(self, camera) -> NoiseBank | None:
        if self.realism.noise_sigma <= 0 and self.realism.shot_noise <= 0:
            return None
        key = (camera.height, camera.width)
        if key not in self._noise_banks:
            self._noise_banks[key] = NoiseBank(self.seed, camera.height, camera.width)
        return self._noise_banks[key]

    def _vignette(self, k: int, camera) -> np.ndarray | None:
        if k not in self._vignettes:
            self._vignettes[k] = (vignette_map(camera.height, camera.width, self.realism.vignetting)
                                  if isinstance(camera, PinholeCamera) and self.realism.vignetting > 0 else None)
        return self._vignettes[k]

    def _flows(self, i: int, k: int, camera, output: RenderOutput) -> np.ndarray | None:
        """Image displacement over the exposure, per column band, from the motion between neighbouring frames."""
        r = self.realism
        if not r.motion_blur or r.exposure_time <= 0 or len(self) < 2:
            return None
        half = 0.5 * r.exposure_time
        T_mid = self.camera_pose(i, k)
        ends = []
        jumps = self.metadata.get("jumps", ())
        for j in (i - 1, i + 1):
            # No blur across a teleport (an elevator ride between floors).
            if not 0 <= j < len(self) or max(i, j) in jumps:
                ends.append(T_mid)
                continue
            gap = abs(self.stamps_ns[j] - self.stamps_ns[i]) / 1e9
            alpha = min(half / gap, 1.0) if gap > 0 else 0.0
            ends.append(_interpolate_pose(T_mid, self.camera_pose(j, k), alpha))
        T_start, T_end = ends
        # Column bands: a forward motion blurs the left and right of the image in opposite directions.
        bands = 8 if isinstance(camera, PinholeCamera) else 16
        samples = self._flow_samples(camera, bands)
        ui, vi, rays = samples
        rng_ = output.depth[vi, ui].astype(float)
        rng_ = np.where(np.isfinite(rng_), rng_, 30.0)
        points_world = (rays * rng_[..., None]) @ T_mid[:3, :3].T + T_mid[:3, 3]
        uv = []
        for T in (T_start, T_end):
            pc = (points_world - T[:3, 3]) @ T[:3, :3]
            uv.append(camera.project_cam(pc)[0])
        d = uv[1] - uv[0]
        if isinstance(camera, EquirectangularCamera):
            d[..., 0] = (d[..., 0] + camera.width / 2) % camera.width - camera.width / 2
        flows = np.median(d, axis=(1, 2))
        # A blur longer than this is a modelling failure (a pose jump), not a photograph.
        length = np.linalg.norm(flows, axis=1, keepdims=True)
        return flows * np.minimum(1.0, MAX_BLUR_PX / np.maximum(length, 1e-9))

    def _flow_samples(self, camera, bands: int):
        """Per band, a 4 x 3 grid of sample pixels and their rays (cached per camera)."""
        key = (id(camera), bands)
        if key not in self._flow_cache:
            rows = np.linspace(0.15, 0.85, 4) * (camera.height - 1)
            cols = (np.arange(bands)[:, None] + np.array([0.25, 0.5, 0.75])[None, :]) / bands * (camera.width - 1)
            vv = np.broadcast_to(rows[None, :, None], (bands, 4, 3))
            uu = np.broadcast_to(cols[:, None, :], (bands, 4, 3))
            self._flow_cache[key] = (np.round(uu).astype(int), np.round(vv).astype(int), camera.rays_cam(uu, vv))
        return self._flow_cache[key]

    def _image(self, i: int):
        outputs = self.render(i)
        light = self._lights[i]
        images = []
        for k, (camera, output) in enumerate(zip(self.cameras, outputs)):
            rng = np.random.default_rng([self.seed, i, k, 99])
            flows = self._flows(i, k, camera, output)
            images.append(finish_image(output.colour, light, self.realism, rng, self._vignette(k, camera), flows,
                                       self._noise(camera), wrap=isinstance(camera, EquirectangularCamera)))
        return tuple(images) if isinstance(self.camera, CameraRig) else images[0]

    # ------------------------------------------------------------------ ground truth per frame

    def _visible(self, i: int) -> list[VisibleObject]:
        outputs = self.render(i)
        result = []
        T_body_world = invert_transform(self.T_world_body[i])
        for k, (camera, output) in enumerate(zip(self.cameras, outputs)):
            T_world_cam = self.camera_pose(i, k)
            counts = np.bincount(output.ids[output.ids >= 0].ravel(), minlength=len(self.world.objects))
            for index in np.flatnonzero(counts):
                obj = self.world.objects[index]
                alone = self.renderer.render(camera, T_world_cam, subset=obj.primitives, colour=False)
                mask = alone.ids == index
                visible = output.ids == index
                pixels = int(mask.sum())
                if pixels == 0:
                    continue
                centre_body = T_body_world[:3, :3] @ obj.position + T_body_world[:3, 3]
                cam_body = T_body_world[:3, :3] @ T_world_cam[:3, 3] + T_body_world[:3, 3]
                rel = centre_body - cam_body
                hull_cam = (obj.hull_points - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
                _, inside = camera.project_cam(hull_cam)
                wrap = isinstance(camera, EquirectangularCamera)
                result.append(VisibleObject(
                    object_index=int(index), class_name=obj.class_name, camera=k, box=_mask_box(mask, wrap),
                    visible_box=_mask_box(visible, wrap), pixels=pixels, visible_pixels=int(visible.sum()),
                    occluded_fraction=float(1.0 - visible.sum() / pixels),
                    bearing=float(wrap_angle(np.arctan2(centre_body[1], centre_body[0]))),
                    elevation=float(np.arctan2(rel[2], np.hypot(rel[0], rel[1]))),
                    distance=float(np.linalg.norm(obj.position - T_world_cam[:3, 3])),
                    truncated=bool(not inside.all())))
        return result

    def analytic_box(self, object_index: int, i: int, k: int = 0) -> tuple[float, float, float, float] | None:
        """Bounding box of the projection of an object's outline points (pixel-edge coordinates, unclipped)."""
        camera = self.cameras[k]
        T = self.camera_pose(i, k)
        hull_cam = (self.world.objects[object_index].hull_points - T[:3, 3]) @ T[:3, :3]
        uv, _ = camera.project_cam(hull_cam)
        if np.any(hull_cam[:, 2] <= 0) and isinstance(camera, PinholeCamera):
            return None
        return (float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max()))

    # ------------------------------------------------------------------ exemplars

    def _exemplar_world(self, class_name: str) -> World:
        builder = self._exemplar_builders.get(class_name)
        if builder is None:
            raise KeyError(f"no exemplar model for class {class_name!r}")
        b = WorldBuilder(f"exemplar-{class_name}", (class_name,))
        builder(b)
        return b.build(bounds=[[-1, -1], [1, 1]])

    def _render_view(self, world: World, renderer: Renderer, azimuth: float, elevation: float):
        obj = world.objects[0]
        s = self.exemplar_settings
        radius = 0.5 * float(np.linalg.norm(obj.size))
        fov = np.radians(40.0)
        distance = radius / np.sin(fov / 2) * 1.05
        camera = PinholeCamera.from_fov(s.size_px, s.size_px, np.degrees(fov))
        front = obj.yaw + azimuth
        direction = np.array([np.cos(front) * np.cos(elevation), np.sin(front) * np.cos(elevation), np.sin(elevation)])
        from semloc_core.sim.trajectories import look_at

        T = look_at(obj.position + distance * direction, obj.position)
        out = renderer.render(camera, T, self.base_lighting)
        mask = out.ids == 0
        image = np.where(mask[..., None], np.clip(out.colour + 0.5, 0, 255), np.asarray(s.background, np.float32))
        image = image.astype(np.uint8)
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:
            return None
        pad = 2
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, s.size_px)
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, s.size_px)
        return (np.ascontiguousarray(image[y0:y1, x0:x1]), (mask[y0:y1, x0:x1] * 255).astype(np.uint8), distance)

    def exemplars(self) -> dict[str, list[np.ndarray]]:
        """One rendered exemplar per class (its canonical appearance, front view, on white), BGR."""
        return {c: [views[0].image] for c, views in self._single_views().items()}

    def exemplar_masks(self) -> dict[str, list[np.ndarray]]:
        return {c: [views[0].mask] for c, views in self._single_views().items()}

    def _single_views(self) -> dict[str, list[ViewExemplar]]:
        out = {}
        elevation = np.radians(self.exemplar_settings.elevation_deg)
        for class_name in self.world.class_names:
            world = self._exemplar_world(class_name)
            view = self._render_view(world, Renderer(world), 0.0, elevation)
            if view is not None:
                out[class_name] = [ViewExemplar(class_name, view[0], view[1], 0.0, elevation, view[2])]
        return out

    def multiview_exemplars(self) -> dict[str, list[ViewExemplar]]:
        """Views of each class's canonical object around a view sphere (thesis §5.5.1), with their angles."""
        s = self.exemplar_settings
        out: dict[str, list[ViewExemplar]] = {}
        for class_name in self.world.class_names:
            world = self._exemplar_world(class_name)
            renderer = Renderer(world)
            views = []
            for elevation_deg in s.multiview_elevations_deg:
                for a in range(s.multiview_azimuths):
                    azimuth = float(wrap_angle(2 * np.pi * a / s.multiview_azimuths))
                    view = self._render_view(world, renderer, azimuth, np.radians(elevation_deg))
                    if view is not None:
                        views.append(ViewExemplar(class_name, view[0], view[1], azimuth, np.radians(elevation_deg),
                                                  view[2]))
            out[class_name] = views
        return out

    # ------------------------------------------------------------------ writing

    def write(self, path, progress=None, multiview: bool = True):
        """Write frames and ground truth in the semloc dataset layout (docs/datasets.md)."""
        extra = {"scenario": self.name, "seed": self.seed, "options": self.options,
                 "loop": {"distance": self.loop_settings.distance, "soft_distance": self.loop_settings.soft_distance,
                          "max_angle_deg": None if self.loop_settings.max_angle is None
                          else float(np.degrees(self.loop_settings.max_angle))},
                 "realism": self.realism.__dict__, "odometry_noise": self.odometry_noise.__dict__,
                 "classes": list(self.world.class_names)}
        # A world without object classes (aliased: corridors only) has no views to write.
        views = self.multiview_exemplars() if multiview and self.world.class_names else None
        return write_dataset(self, path, progress=progress, extra=extra, exemplars=self.exemplars(),
                             exemplar_masks=self.exemplar_masks(), multiview=views)


def _mask_box(mask: np.ndarray, wrap: bool = False) -> tuple[float, float, float, float]:
    """Pixel-edge box of a mask. ``wrap`` (panoramas): an object across the left/right seam gets a box starting
    left of column 0 (x_min < -0.5) rather than one spanning the whole width."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return (0.0, 0.0, 0.0, 0.0)
    width = mask.shape[1]
    if wrap and cols[0] == 0 and cols[-1] == width - 1 and len(cols) < width:
        gaps = np.diff(cols)
        g = int(np.argmax(gaps))
        # The object runs from just after the largest gap, across the seam, to just before it.
        return (cols[g + 1] - width - 0.5, rows[0] - 0.5, cols[g] + 0.5, rows[-1] + 0.5)
    return (cols[0] - 0.5, rows[0] - 0.5, cols[-1] + 0.5, rows[-1] + 0.5)
