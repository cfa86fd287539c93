"""Simulated worlds: textured analytic primitives, objects with exact geometry, and the packed arrays the renderer reads.

A world is built once with a :class:`WorldBuilder` (walls, floors, tables, objects) and is immutable afterwards.
Coordinates follow docs/conventions.md: world z up, metres.

Primitive local frames (see ``_raycast``): a quad is given by its top-left corner and two edge vectors ``right`` and
``down`` as seen from its front; frustums, discs and domes by a centre and a local z axis (``axis``) plus the
direction of their texture's centre (``front``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semloc_core.io.semantic_map import SemanticMap
from semloc_core.sim import _raycast
from semloc_core.sim.textures import TextureAtlas, TextureStore

# Corner order of every bounding box: bit 0 = x, bit 1 = y, bit 2 = z.
_UNIT_CORNERS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float)


@dataclass(frozen=True)
class Material:
    """How a surface takes light: ``ambient + diffuse * max(0, n.l)``, times ``back`` on its inner side."""

    ambient: float = 0.55
    diffuse: float = 0.5
    back: float = 0.6


MATTE = Material()
GLOSSY = Material(0.5, 0.65, 0.6)
EMISSIVE = Material(1.0, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class SimObject:
    """One object instance of a named class, with its exact geometry.

    ``index`` is its row in the world's semantic map; ``position`` the centre of its axis-aligned bounding box,
    ``size`` that box's extents (x, y, z); ``hull_points`` (K, 3) points of its outline whose projection spans its
    image silhouette (used for analytic ground-truth boxes); ``primitives`` the indices of its primitives.
    """

    index: int
    class_name: str
    position: np.ndarray
    size: np.ndarray
    yaw: float
    hull_points: np.ndarray
    primitives: np.ndarray
    appearance: str = ""
    level: int = 0


@dataclass(frozen=True, eq=False)
class World:
    """An immutable scene: packed primitive arrays, the texture atlas, the objects and the map bounds."""

    name: str
    kind: np.ndarray
    flags: np.ndarray
    R_world_local: np.ndarray
    origin_world: np.ndarray
    shape: np.ndarray
    texture: np.ndarray
    tex_scale: np.ndarray
    texel_density: np.ndarray
    material: np.ndarray
    object_id: np.ndarray
    billboard: np.ndarray
    bbox_world: np.ndarray
    atlas: TextureAtlas
    objects: tuple[SimObject, ...]
    class_names: tuple[str, ...]
    bounds: np.ndarray
    free_space: tuple[np.ndarray, ...] = ()
    metadata: dict = field(default_factory=dict)

    @property
    def n_primitives(self) -> int:
        return int(self.kind.shape[0])

    def semantic_map(self) -> SemanticMap:
        """Ground-truth object map (class, centre, axis-aligned size) in the project's map format."""
        objects = [{"class": o.class_name, "position": o.position.tolist(), "size": o.size.tolist(), "score": 1.0}
                   for o in self.objects]
        return SemanticMap.from_objects(objects, bounds=self.bounds, free_space=self.free_space or None,
                                        class_names=self.class_names)

def _orthonormal_frame(axis, front) -> np.ndarray:
    """Rotation whose z column is ``axis`` and whose x column is ``front`` made orthogonal to it."""
    z = np.asarray(axis, float)
    z = z / np.linalg.norm(z)
    x = np.asarray(front, float) - np.dot(front, z) * z
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.cross(z, [1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


class WorldBuilder:
    """Accumulates primitives and objects; :meth:`build` packs them into a :class:`World`."""

    def __init__(self, name: str, class_names: tuple[str, ...] = ()) -> None:
        self.name = name
        self.textures = TextureStore()
        self.class_names = tuple(class_names)
        self._prims: list[dict] = []
        self._objects: list[dict] = []
        self._current_object: int = -1
        self.metadata: dict = {}

    # ------------------------------------------------------------------ objects

    def begin_object(self, class_name: str, appearance: str = "", level: int = 0) -> int:
        """Primitives added until :meth:`end_object` belong to a new object of ``class_name``."""
        if self._current_object >= 0:
            raise RuntimeError("begin_object called twice without end_object")
        if class_name not in self.class_names:
            self.class_names = self.class_names + (class_name,)
        self._objects.append({"class": class_name, "prims": [], "hull": [], "yaw": 0.0, "appearance": appearance,
                              "level": level})
        self._current_object = len(self._objects) - 1
        return self._current_object

    def add_hull_points(self, points) -> None:
        self._objects[self._current_object]["hull"].append(np.asarray(points, float).reshape(-1, 3))

    def end_object(self, yaw: float = 0.0) -> int:
        index = self._current_object
        if index < 0:
            raise RuntimeError("end_object without begin_object")
        obj = self._objects[index]
        if not obj["prims"]:
            raise ValueError(f"object {index} ({obj['class']}) has no primitives")
        obj["yaw"] = float(yaw)
        self._current_object = -1
        return index

    # ------------------------------------------------------------------ primitives

    def _add(self, kind, R, origin, shape, texture, tex_scale, density, material, flags, local_box,
             billboard=False, bbox_world=None) -> int:
        shape6 = np.zeros(6)
        shape6[: len(shape)] = shape
        lo, hi = np.asarray(local_box[0], float), np.asarray(local_box[1], float)
        corners_local = lo + _UNIT_CORNERS * (hi - lo)
        corners = corners_local @ np.asarray(R).T + np.asarray(origin, float) if bbox_world is None else bbox_world
        prim = {
            "kind": kind, "flags": flags, "R": np.asarray(R, float), "origin": np.asarray(origin, float),
            "shape": shape6, "texture": int(texture), "tex_scale": np.asarray(tex_scale, float),
            "density": float(density), "material": np.array([material.ambient, material.diffuse, material.back]),
            "object": self._current_object, "billboard": billboard, "bbox": corners,
        }
        self._prims.append(prim)
        index = len(self._prims) - 1
        if self._current_object >= 0:
            self._objects[self._current_object]["prims"].append(index)
        return index

    def quad(self, corner, right, down, texture: int, repeat=(1.0, 1.0), two_sided: bool = True,
             material: Material = MATTE, alpha: bool = False) -> int:
        """A rectangle from its top-left ``corner`` along ``right`` and ``down`` (as seen from its front)."""
        right = np.asarray(right, float)
        down = np.asarray(down, float)
        sx, sy = np.linalg.norm(right), np.linalg.norm(down)
        if sx <= 0 or sy <= 0:
            raise ValueError("a quad needs two non-zero edges")
        x = right / sx
        y = down / sy
        if abs(np.dot(x, y)) > 1e-6:
            raise ValueError("quad edges must be perpendicular")
        R = np.stack([x, y, np.cross(x, y)], axis=1)
        h, w = self.textures.image(texture).shape[:2]
        density = max(w * repeat[0] / sx, h * repeat[1] / sy)
        flags = (_raycast.FLAG_TWO_SIDED if two_sided else 0) | (_raycast.FLAG_ALPHA if alpha else 0)
        if repeat[0] != 1.0 or repeat[1] != 1.0:
            flags |= _raycast.FLAG_REPEAT
        index = self._add(_raycast.QUAD, R, corner, (sx, sy), texture, repeat, density, material, flags,
                          ((0, 0, 0), (sx, sy, 0)))
        if self._current_object >= 0:
            c = np.asarray(corner, float)
            self.add_hull_points([c, c + right, c + down, c + right + down])
        return index

    def wall(self, start_xy, end_xy, z_bottom: float, z_top: float, texture: int, repeat=(1.0, 1.0),
             offset: float = 0.0, material: Material = MATTE) -> int:
        """A vertical quad from ``start_xy`` to ``end_xy``, front facing left of the start->end direction.

        ``offset`` moves it along its front normal (decals sit a few millimetres in front of their wall).
        """
        start = np.asarray(start_xy, float)
        end = np.asarray(end_xy, float)
        direction = end - start
        normal_left = np.array([-direction[1], direction[0]]) / np.linalg.norm(direction)
        start = start + offset * normal_left
        end = end + offset * normal_left
        # Seen from the left side, the wall's texture runs from ``end`` (viewer's left) to ``start``.
        corner = np.array([end[0], end[1], z_top])
        right = np.array([-direction[0], -direction[1], 0.0])
        down = np.array([0.0, 0.0, -(z_top - z_bottom)])
        return self.quad(corner, right, down, texture, repeat, two_sided=True, material=material)

    def horizontal(self, x0, y0, x1, y1, z: float, texture: int, repeat=(1.0, 1.0), facing_up: bool = True,
                   material: Material = MATTE) -> int:
        """A horizontal rectangle [x0, x1] x [y0, y1] at height z (floor, table top, ceiling)."""
        if facing_up:
            corner = np.array([x0, y1, z])
            return self.quad(corner, [x1 - x0, 0, 0], [0, -(y1 - y0), 0], texture, repeat, material=material)
        corner = np.array([x0, y0, z])
        return self.quad(corner, [x1 - x0, 0, 0], [0, y1 - y0, 0], texture, repeat, material=material)

    def frustum(self, base_centre, axis, r_bottom: float, r_top: float, height: float, texture: int,
                front=(1.0, 0.0, 0.0), phi_range=(-np.pi, np.pi), repeat=(1.0, 1.0), material: Material = MATTE,
                hull_samples: int = 96) -> int:
        R = _orthonormal_frame(axis, front)
        r_max = max(r_bottom, r_top)
        h, w = self.textures.image(texture).shape[:2]
        circumference = 2 * np.pi * max(0.5 * (r_bottom + r_top), 1e-3)
        density = max(w * repeat[0] / circumference, h * repeat[1] / height)
        flags = _raycast.FLAG_TWO_SIDED | (_raycast.FLAG_REPEAT if repeat != (1.0, 1.0) else 0)
        index = self._add(_raycast.FRUSTUM, R, base_centre, (r_bottom, r_top, height, phi_range[0], phi_range[1]),
                          texture, repeat, density, material, flags,
                          ((-r_max, -r_max, 0), (r_max, r_max, height)))
        if self._current_object >= 0:
            phi = np.linspace(phi_range[0], phi_range[1], hull_samples)
            rims = []
            for r, z in ((r_bottom, 0.0), (r_top, height)):
                rims.append(np.stack([r * np.cos(phi), r * np.sin(phi), np.full_like(phi, z)], axis=1))
            self.add_hull_points(np.concatenate(rims) @ R.T + np.asarray(base_centre, float))
        return index

    def disc(self, centre, normal, r_out: float, texture: int, r_in: float = 0.0, front=(1.0, 0.0, 0.0),
             phi_range=(-np.pi, np.pi), material: Material = MATTE, hull_samples: int = 96) -> int:
        R = _orthonormal_frame(normal, front)
        h, w = self.textures.image(texture).shape[:2]
        density = max(w, h) / (2 * r_out)
        index = self._add(_raycast.DISC, R, centre, (r_out, r_in, phi_range[0], phi_range[1]), texture, (1.0, 1.0),
                          density, material, _raycast.FLAG_TWO_SIDED, ((-r_out, -r_out, 0), (r_out, r_out, 0)))
        if self._current_object >= 0:
            phi = np.linspace(phi_range[0], phi_range[1], hull_samples)
            pts = [np.stack([r_out * np.cos(phi), r_out * np.sin(phi), np.zeros_like(phi)], axis=1)]
            if r_in > 0 or phi_range != (-np.pi, np.pi):
                pts.append(np.stack([r_in * np.cos(phi), r_in * np.sin(phi), np.zeros_like(phi)], axis=1))
            self.add_hull_points(np.concatenate(pts) @ R.T + np.asarray(centre, float))
        return index

    def dome(self, centre, axis, a: float, b: float, c: float, texture: int, z_cut: float = 0.0,
             front=(1.0, 0.0, 0.0), material: Material = MATTE, hull_samples: int = 48) -> int:
        """The part ``z >= z_cut`` of an ellipsoid with semi-axes a, b, c (a cap's crown, a lamp shade)."""
        R = _orthonormal_frame(axis, front)
        h, w = self.textures.image(texture).shape[:2]
        density = max(w / (2 * np.pi * max(a, b)), h / (c - z_cut))
        index = self._add(_raycast.DOME, R, centre, (a, b, c, z_cut), texture, (1.0, 1.0), density, material,
                          _raycast.FLAG_TWO_SIDED, ((-a, -b, z_cut), (a, b, c)))
        if self._current_object >= 0:
            phi = np.linspace(-np.pi, np.pi, hull_samples)
            zs = np.linspace(z_cut, c, hull_samples // 2)
            P, Z = np.meshgrid(phi, zs)
            rho = np.sqrt(np.clip(1 - (Z / c) ** 2, 0, 1))
            pts = np.stack([a * rho * np.cos(P), b * rho * np.sin(P), Z], axis=-1).reshape(-1, 3)
            self.add_hull_points(pts @ R.T + np.asarray(centre, float))
        return index

    def box(self, centre, size, yaw: float, textures, material: Material = MATTE, repeat=None) -> list[int]:
        """An upright box; ``textures`` = one index or six (front +x, left +y, back -x, right -y, top, bottom)."""
        if isinstance(textures, (int, np.integer)):
            textures = [int(textures)] * 6
        sx, sy, sz = (float(v) for v in size)
        c = np.asarray(centre, float)
        Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        ex, ey, ez = Rz[:, 0], Rz[:, 1], Rz[:, 2]
        hx, hy, hz = sx / 2, sy / 2, sz / 2
        repeat = repeat or [(1.0, 1.0)] * 6
        faces = [
            # (top-left corner, right, down) seen from outside each face
            (c + hx * ex - hy * ey + hz * ez, sy * ey, -sz * ez),   # front (+x)
            (c + hx * ex + hy * ey + hz * ez, -sx * ex, -sz * ez),  # left (+y)
            (c - hx * ex + hy * ey + hz * ez, -sy * ey, -sz * ez),  # back (-x)
            (c - hx * ex - hy * ey + hz * ez, sx * ex, -sz * ez),   # right (-y)
            (c - hx * ex + hy * ey + hz * ez, sx * ex, -sy * ey),   # top, seen from above: right +x, down -y
            (c - hx * ex - hy * ey - hz * ez, sx * ex, sy * ey),    # bottom
        ]
        indices = []
        for (corner, right, down), tex, rep in zip(faces, textures, repeat):
            indices.append(self.quad(corner, right, down, tex, rep, two_sided=False, material=material))
        return indices

    def billboard(self, centre, width: float, height: float, texture: int, material: Material = MATTE) -> int:
        """An upright textured quad (with alpha) that turns about world z to face the camera at every frame."""
        half = 0.5 * width
        c = np.asarray(centre, float)
        bbox = c + (_UNIT_CORNERS - 0.5) * np.array([2 * half, 2 * half, height])
        R = np.eye(3)
        h, w = self.textures.image(texture).shape[:2]
        density = max(w / width, h / height)
        index = self._add(_raycast.QUAD, R, c, (width, height), texture, (1.0, 1.0), density, material,
                          _raycast.FLAG_TWO_SIDED | _raycast.FLAG_ALPHA, ((0, 0, 0), (width, height, 0)),
                          billboard=True, bbox_world=bbox)
        if self._current_object >= 0:
            self.add_hull_points(bbox)
        return index

    # ------------------------------------------------------------------ build

    def build(self, bounds, free_space=()) -> World:
        if self._current_object >= 0:
            raise RuntimeError("build called inside an unfinished object")
        if not self._prims:
            raise ValueError("a world needs at least one primitive")
        prim_object = np.array([p["object"] for p in self._prims], np.int32)
        objects = []
        for i, obj in enumerate(self._objects):
            hull = np.concatenate(obj["hull"]) if obj["hull"] else np.concatenate(
                [self._prims[p]["bbox"] for p in obj["prims"]])
            lo, hi = hull.min(0), hull.max(0)
            objects.append(SimObject(index=i, class_name=obj["class"], position=0.5 * (lo + hi), size=hi - lo,
                                     yaw=obj["yaw"], hull_points=hull, primitives=np.array(obj["prims"], np.int64),
                                     appearance=obj["appearance"], level=obj["level"]))
        return World(
            name=self.name,
            kind=np.array([p["kind"] for p in self._prims], np.int32),
            flags=np.array([p["flags"] for p in self._prims], np.int32),
            R_world_local=np.stack([p["R"] for p in self._prims]),
            origin_world=np.stack([p["origin"] for p in self._prims]),
            shape=np.stack([p["shape"] for p in self._prims]),
            texture=np.array([p["texture"] for p in self._prims], np.int64),
            tex_scale=np.stack([p["tex_scale"] for p in self._prims]),
            texel_density=np.array([p["density"] for p in self._prims]),
            material=np.stack([p["material"] for p in self._prims]),
            object_id=prim_object,
            billboard=np.array([p["billboard"] for p in self._prims], bool),
            bbox_world=np.stack([p["bbox"] for p in self._prims]),
            atlas=self.textures.build(),
            objects=tuple(objects),
            class_names=self.class_names,
            bounds=np.asarray(bounds, float),
            free_space=tuple(np.asarray(p, float) for p in free_space),
            metadata=dict(self.metadata),
        )
