"""Rooms, corridors and wall decoration shared by the scenarios.

A :class:`DecorLibrary` holds a fixed set of designs (posters, adverts, doors, notice boards) generated from one
seed; walls draw their decals from it. ``unique_fraction`` sets how many decals get a fresh design instead of a
library one: low values repeat designs across the building (perceptual aliasing), high values make every place
distinct. A :class:`WallPlan` is the décor of one wall computed once, so two floors can share it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semloc_core.sim import textures as tx
from semloc_core.sim.world import EMISSIVE, MATTE, WorldBuilder


_KINDS = ("poster", "advert", "door", "notice_board", "window")
_SMALL = ("switch", "outlet", "radiator", "exit", "extinguisher", "pipe", "rail")


def _small_texture(kind: str, rng: np.random.Generator) -> np.ndarray:
    import cv2

    if kind == "switch":
        image = np.full((48, 32, 3), 235, np.uint8)
        cv2.rectangle(image, (2, 2), (29, 45), (150, 150, 150), 2)
        cv2.rectangle(image, (11, 12), (20, 35), (200, 200, 200), -1)
        cv2.line(image, (11, 24), (20, 24), (120, 120, 120), 1)
        return image
    if kind == "outlet":
        image = np.full((40, 40, 3), 230, np.uint8)
        cv2.rectangle(image, (2, 2), (37, 37), (140, 140, 140), 2)
        for x in (14, 26):
            cv2.rectangle(image, (x - 2, 13), (x + 2, 25), (40, 40, 40), -1)
        return image
    if kind == "radiator":
        image = np.full((96, 192, 3), 225, np.uint8)
        for x in range(4, 192, 10):
            cv2.rectangle(image, (x, 6), (x + 5, 89), (190, 190, 195), -1)
            cv2.line(image, (x + 6, 6), (x + 6, 89), (120, 120, 125), 1)
        cv2.rectangle(image, (0, 0), (191, 95), (150, 150, 150), 2)
        return image
    if kind == "exit":
        image = np.full((48, 128, 3), (60, 150, 30), np.uint8)
        cv2.putText(image, "EXIT", (18, 36), cv2.FONT_HERSHEY_DUPLEX, 1.2, (255, 255, 255), 2, cv2.LINE_AA)
        cv2.arrowedLine(image, (96, 24), (122, 24), (255, 255, 255), 3, tipLength=0.4)
        return image
    if kind == "extinguisher":
        image = np.full((128, 128, 3), (30, 30, 190), np.uint8)
        cv2.rectangle(image, (44, 40), (84, 90), (235, 235, 235), -1)
        cv2.putText(image, "CO2", (48, 72), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (20, 20, 20), 1, cv2.LINE_AA)
        cv2.line(image, (0, 10), (128, 10), (20, 20, 20), 4)
        return image
    if kind == "pipe":
        image = np.full((16, 64, 3), 200, np.uint8)
        image[:, ::16] = 120
        return image
    image = np.full((8, 64, 3), 70, np.uint8)  # rail
    image[::4] = 50
    return image



@dataclass
class DecorLibrary:
    seed: int
    builder: WorldBuilder
    n_posters: int = 24
    n_adverts: int = 8
    n_doors: int = 4
    n_boards: int = 6
    n_materials: int = 6
    _cache: dict = field(default_factory=dict)

    def _texture(self, kind: str, index: int, make) -> int:
        key = (kind, index)
        if key not in self._cache:
            self._cache[key] = self.builder.textures.add(make())
        return self._cache[key]

    def material(self, index: int) -> int:
        kinds = ("plaster", "brick", "wood", "tiles", "concrete", "brick")
        kind = kinds[index % len(kinds)]
        design_rng = np.random.default_rng([self.seed, 11, index])
        return self._texture("material", index, lambda: tx.MATERIALS[kind](design_rng))

    def design(self, kind: str, index: int) -> int:
        makers = {"poster": tx.poster, "advert": tx.advert, "door": tx.door, "notice_board": tx.notice_board,
                  "window": tx.window}
        design_rng = np.random.default_rng([self.seed, 13, _KINDS.index(kind), index])
        return self._texture(kind, index, lambda: makers[kind](design_rng))

    def fresh(self, kind: str, rng: np.random.Generator) -> int:
        makers = {"poster": tx.poster, "advert": tx.advert, "notice_board": tx.notice_board, "window": tx.window}
        return self.builder.textures.add(makers[kind](rng))

    def small(self, kind: str) -> int:
        """Small wall fixtures shared by the whole building: switch, outlet, radiator, exit sign, extinguisher,
        pipe, rail."""
        key = ("small", kind)
        if key not in self._cache:
            rng = np.random.default_rng([self.seed, 19, _SMALL.index(kind)])
            self._cache[key] = self.builder.textures.add(_small_texture(kind, rng))
        return self._cache[key]

    def sign(self, text: str, colours=None) -> int:
        key = ("sign", text, colours)
        if key not in self._cache:
            rng = np.random.default_rng([self.seed, 17, len(self._cache)])
            self._cache[key] = self.builder.textures.add(tx.sign(rng, text, colours=colours))
        return self._cache[key]


@dataclass(frozen=True)
class Decal:
    """One item on a wall: ``s0..s1`` metres along the wall, ``z0..z1`` above the floor, a texture index."""

    s0: float
    s1: float
    z0: float
    z1: float
    texture: int
    emissive: bool = False
    label: str = ""
    solid: str = ""  # "" = flat decal; "extinguisher" or "pipe" = a 3-D fixture in front of the wall


@dataclass(frozen=True)
class WallPlan:
    start: tuple[float, float]
    end: tuple[float, float]
    height: float
    material: int
    material_tile: tuple[float, float]
    decals: tuple[Decal, ...]
    dado: int | None = None  # texture of the lower band (wainscot), None for none
    dado_height: float = 1.0
    rail: int | None = None  # texture of the rail strip on top of the dado


def plan_wall(library: DecorLibrary, rng: np.random.Generator, start, end, height: float, material: int,
              unique_fraction: float = 0.3, density: float = 0.7, room_number: int | None = None,
              material_tile=(2.0, 1.5)) -> WallPlan:
    """Choose the décor of one wall (front facing left of start->end)."""
    start = np.asarray(start, float)
    end = np.asarray(end, float)
    length = float(np.linalg.norm(end - start))
    decals = []
    s = float(rng.uniform(0.2, 1.0))
    number = room_number
    while s < length - 0.6:
        if rng.random() > density:
            s += float(rng.uniform(0.6, 1.6))
            continue
        kind = rng.choice(["poster", "poster", "door", "notice_board", "advert", "window"])
        unique = rng.random() < unique_fraction
        if kind == "door":
            width, z0, z1 = 1.0, 0.0, min(2.1, height - 0.2)
            texture = library.design("door", int(rng.integers(library.n_doors)))
        elif kind == "poster":
            width = float(rng.uniform(0.5, 0.8))
            z0 = float(rng.uniform(1.0, 1.3))
            z1 = z0 + width * 1.45
            texture = library.fresh("poster", rng) if unique else library.design(
                "poster", int(rng.integers(library.n_posters)))
        elif kind == "notice_board":
            width, z0 = float(rng.uniform(1.0, 1.6)), 0.95
            z1 = z0 + width * 0.66
            texture = library.fresh("notice_board", rng) if unique else library.design(
                "notice_board", int(rng.integers(library.n_boards)))
        elif kind == "advert":
            width, z0 = float(rng.uniform(1.4, 2.0)), 1.1
            z1 = z0 + width * 0.5
            texture = library.fresh("advert", rng) if unique else library.design(
                "advert", int(rng.integers(library.n_adverts)))
        else:
            width, z0 = float(rng.uniform(1.2, 1.8)), 1.0
            z1 = min(z0 + width * 0.66, height - 0.2)
            texture = library.design("window", int(rng.integers(4)))
        if s + width > length - 0.2:
            break
        z1 = min(z1, height - 0.05)
        decals.append(Decal(s, s + width, z0, z1, texture, emissive=(kind == "window")))
        if kind == "door" and number is not None:
            sign_w = 0.36
            if s + width + 0.1 + sign_w < length:
                decals.append(Decal(s + width + 0.1, s + width + 0.1 + sign_w, 1.5, 1.5 + sign_w * 0.375,
                                    library.sign(str(number)), label=f"room:{number}"))
            number += 1
        s += width + float(rng.uniform(0.3, 1.5))
    decals += _small_items(library, rng, decals, length, height)
    dado = rail = None
    if rng.random() < 0.6:
        dado = library.material(int(rng.integers(library.n_materials)))
        rail = library.small("rail")
    return WallPlan((float(start[0]), float(start[1])), (float(end[0]), float(end[1])), height, material,
                    tuple(material_tile), tuple(decals), dado=dado, rail=rail)


def _small_items(library: DecorLibrary, rng: np.random.Generator, decals: list[Decal], length: float,
                 height: float) -> list[Decal]:
    """Switches by doors, outlets, radiators under windows, exit signs, extinguishers and a pipe under the
    ceiling: the clutter of a real corridor (and corners for a feature detector)."""
    items: list[Decal] = []
    occupied = [(d.s0, d.s1) for d in decals]

    def free(s0, s1):
        return 0.05 < s0 and s1 < length - 0.05 and all(s1 < a - 0.05 or s0 > b + 0.05 for a, b in occupied)

    for d in list(decals):
        if d.z0 == 0.0 and d.z1 >= 1.8:  # a door
            if free(d.s1 + 0.1, d.s1 + 0.18):
                items.append(Decal(d.s1 + 0.1, d.s1 + 0.18, 1.05, 1.17, library.small("switch")))
            if rng.random() < 0.3 and d.z1 + 0.3 < height:
                items.append(Decal(d.s0 + 0.25, d.s0 + 0.75, d.z1 + 0.08, d.z1 + 0.27, library.small("exit"),
                                   emissive=True))
        if d.emissive and d.label == "" and d.z0 >= 0.9 and rng.random() < 0.7:  # under a window
            items.append(Decal(d.s0 + 0.1, d.s1 - 0.1, 0.15, min(0.75, d.z0 - 0.1), library.small("radiator")))
    s = float(rng.uniform(0.5, 2.5))
    while s < length - 0.5:
        if free(s, s + 0.1):
            items.append(Decal(s, s + 0.1, 0.25, 0.35, library.small("outlet")))
            occupied.append((s, s + 0.1))
        s += float(rng.uniform(2.5, 5.0))
    if rng.random() < 0.35:
        s = float(rng.uniform(0.3, max(length - 0.6, 0.31)))
        if free(s, s + 0.2):
            items.append(Decal(s, s + 0.2, 0.35, 0.95, library.small("extinguisher"), solid="extinguisher"))
    if rng.random() < 0.5 and length > 2:
        z = height - float(rng.uniform(0.15, 0.3))
        items.append(Decal(0.0, length, z, z + 0.1, library.small("pipe"), solid="pipe"))
    return items


def build_wall(b: WorldBuilder, plan: WallPlan, z_floor: float = 0.0, extra: tuple[Decal, ...] = ()) -> None:
    """Add a planned wall (base quad, skirting, decals) standing on ``z_floor``."""
    start = np.asarray(plan.start, float)
    end = np.asarray(plan.end, float)
    length = float(np.linalg.norm(end - start))
    direction = (end - start) / length
    repeat = (max(length / plan.material_tile[0], 1e-3), max(plan.height / plan.material_tile[1], 1e-3))
    b.wall(start, end, z_floor, z_floor + plan.height, plan.material, repeat=repeat)
    if plan.dado is not None:
        b.wall(start, end, z_floor, z_floor + plan.dado_height, plan.dado,
               repeat=(max(length / plan.material_tile[0], 1e-3), plan.dado_height / plan.material_tile[1]),
               offset=0.004)
        if plan.rail is not None:
            b.wall(start, end, z_floor + plan.dado_height - 0.03, z_floor + plan.dado_height + 0.03, plan.rail,
                   repeat=(max(length, 1e-3), 1.0), offset=0.007)
    normal = np.array([-direction[1], direction[0], 0.0])
    for k, decal in enumerate(plan.decals + tuple(extra)):
        p0 = start + direction * decal.s0
        p1 = start + direction * decal.s1
        if decal.solid == "extinguisher":
            radius = 0.5 * (decal.s1 - decal.s0) * 0.6
            centre = 0.5 * (p0 + p1)
            base = np.array([centre[0], centre[1], z_floor + decal.z0]) + normal * (radius + 0.03)
            b.frustum(base, (0, 0, 1), radius, radius, decal.z1 - decal.z0, decal.texture, front=normal)
            b.dome(base + [0, 0, decal.z1 - decal.z0], (0, 0, 1), radius, radius, radius * 0.8, decal.texture,
                   front=normal)
            continue
        if decal.solid == "pipe":
            radius = 0.5 * (decal.z1 - decal.z0)
            base = np.array([p0[0], p0[1], z_floor + decal.z0 + radius]) + normal * (radius + 0.02)
            b.frustum(base, (direction[0], direction[1], 0.0), radius, radius, decal.s1 - decal.s0, decal.texture,
                      front=normal, repeat=((decal.s1 - decal.s0) / 0.5, 1.0))
            continue
        b.wall(p0, p1, z_floor + decal.z0, z_floor + decal.z1, decal.texture, offset=0.012 + 0.001 * (k % 3),
               material=EMISSIVE if decal.emissive else MATTE)


def build_room_shell(b: WorldBuilder, x0, y0, x1, y1, height, floor_tex, ceiling_tex, floor_tile=1.0,
                     ceiling_tile=1.2, z_floor: float = 0.0) -> None:
    """Floor and ceiling of a rectangular area."""
    b.horizontal(x0, y0, x1, y1, z_floor, floor_tex, repeat=((x1 - x0) / floor_tile, (y1 - y0) / floor_tile))
    b.horizontal(x0, y0, x1, y1, z_floor + height, ceiling_tex,
                 repeat=((x1 - x0) / ceiling_tile, (y1 - y0) / ceiling_tile), facing_up=False)


def inward_walls(x0, y0, x1, y1) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """The four walls of a rectangle, each facing inwards (counter-clockwise order)."""
    return [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]


def outward_walls(x0, y0, x1, y1) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """The four walls of a solid block, each facing outwards (clockwise order)."""
    return [((x1, y0), (x0, y0)), ((x0, y0), (x0, y1)), ((x0, y1), (x1, y1)), ((x1, y1), (x1, y0))]
