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
        kinds = ("plaster", "brick", "wood", "tiles", "concrete", "plaster")
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


@dataclass(frozen=True)
class WallPlan:
    start: tuple[float, float]
    end: tuple[float, float]
    height: float
    material: int
    material_tile: tuple[float, float]
    decals: tuple[Decal, ...]


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
    return WallPlan((float(start[0]), float(start[1])), (float(end[0]), float(end[1])), height, material,
                    tuple(material_tile), tuple(decals))


def build_wall(b: WorldBuilder, plan: WallPlan, z_floor: float = 0.0, extra: tuple[Decal, ...] = ()) -> None:
    """Add a planned wall (base quad, skirting, decals) standing on ``z_floor``."""
    start = np.asarray(plan.start, float)
    end = np.asarray(plan.end, float)
    length = float(np.linalg.norm(end - start))
    direction = (end - start) / length
    repeat = (max(length / plan.material_tile[0], 1e-3), max(plan.height / plan.material_tile[1], 1e-3))
    b.wall(start, end, z_floor, z_floor + plan.height, plan.material, repeat=repeat)
    for k, decal in enumerate(plan.decals + tuple(extra)):
        p0 = start + direction * decal.s0
        p1 = start + direction * decal.s1
        b.wall(p0, p1, z_floor + decal.z0, z_floor + decal.z1, decal.texture, offset=0.01 + 0.001 * (k % 3),
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
