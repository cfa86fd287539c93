"""Object models with exact geometry: the five tabletop classes, the four hall fixtures, and clutter.

Each ``build_*`` function adds one object to a :class:`~semloc_core.sim.world.WorldBuilder` standing on a surface at
height ``z`` (its footprint centred on ``xy``, its front turned to ``yaw``), and returns the object's index.
Appearances come from real exemplar crops when given (``crops[class] = BGR image``, e.g. the RGB-D Object Dataset
crops in the data folder's rgbd_object_exemplars) and are generated otherwise; ``variation`` in [0, 1] scales the
intra-class differences between instances (hue, scale, proportions, crop window).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from semloc_core.sim import textures as tx
from semloc_core.sim.world import EMISSIVE, GLOSSY, Material, WorldBuilder

TABLETOP_CLASSES = ("bowl", "cap", "cereal_box", "coffee_mug", "soda_can")
HALL_CLASSES = ("clock", "trashcan", "payphone", "ticket_machine")


@dataclass(frozen=True)
class Variation:
    """One instance's deviation from its class's canonical appearance."""

    hue_deg: float = 0.0
    scale: float = 1.0
    aspect: float = 1.0  # height / width multiplier
    window_shift: float = 0.0  # fraction of the crop the texture window moves by
    flip: bool = False  # mirror the artwork (never sampled: mirrored print is not a real variation)

    @classmethod
    def sample(cls, rng: np.random.Generator, amount: float) -> "Variation":
        if amount <= 0:
            return cls()
        return cls(hue_deg=float(rng.uniform(-40, 40) * amount), scale=float(1 + rng.uniform(-0.12, 0.12) * amount),
                   aspect=float(1 + rng.uniform(-0.1, 0.1) * amount),
                   window_shift=float(rng.uniform(-0.06, 0.06) * amount))


def _window(image: np.ndarray, rows, cols, shift: float = 0.0) -> np.ndarray:
    """Sub-image by fractional row and column ranges, shifted horizontally by ``shift`` of the width."""
    h, w = image.shape[:2]
    c0 = int(np.clip(cols[0] + shift, 0, 1) * w)
    c1 = int(np.clip(cols[1] + shift, 0, 1) * w)
    r0, r1 = int(rows[0] * h), int(rows[1] * h)
    if c1 - c0 < 2 or r1 - r0 < 2:
        return image
    return np.ascontiguousarray(image[r0:r1, c0:c1])


def _wrap_label(image: np.ndarray, blend: float = 0.15) -> np.ndarray:
    """A label to wrap 360 degrees: the artwork printed twice (front and back, as on real cans and mugs), its
    left and right edges cross-faded so the seams do not show, one copy centred on the texture."""
    a = image.astype(np.float32)
    width = a.shape[1]
    k = max(1, int(blend * width))
    w = np.linspace(0.0, 1.0, k, dtype=np.float32)[None, :, None]
    seamless = a[:, : width - k].copy()
    seamless[:, :k] = w * a[:, :k] + (1 - w) * a[:, width - k:]
    doubled = np.hstack([seamless, seamless])
    # The artwork's centre (column width/2 of the first copy) goes to the texture's centre (column width - k).
    centred = np.roll(doubled, (width - k) - width // 2, axis=1)
    return np.ascontiguousarray(np.clip(centred + 0.5, 0, 255).astype(np.uint8))


def _finish(image: np.ndarray, v: Variation) -> np.ndarray:
    image = tx.hue_shift(image, v.hue_deg)
    return cv2.flip(image, 1) if v.flip else image


def _solid(colour, size=(32, 32)) -> np.ndarray:
    image = np.empty((size[0], size[1], 3), np.uint8)
    image[:] = np.clip(np.asarray(colour), 0, 255)
    return image


def _mean_colour(image: np.ndarray) -> np.ndarray:
    return image.reshape(-1, 3).mean(axis=0)


# ----------------------------------------------------------------------------------------------- generated looks

def _generated_can_label(rng) -> np.ndarray:
    base = tx.random_colour(rng, (0.6, 1.0), (0.35, 0.8))
    image = _solid(base, (160, 320))
    ys = np.arange(320)
    wave = (80 + 18 * np.sin(ys / 320 * 4 * np.pi)).astype(np.int32)
    for x, y in zip(ys, wave):
        cv2.line(image, (int(x), int(y)), (int(x), int(y) + 16), (245, 245, 245), 1)
    cv2.circle(image, (160, 60), 28, tx.random_colour(rng), -1, cv2.LINE_AA)
    tx.put_text_fit(image, tx.random_word(rng, (1, 2)).upper(), (90, 110, 140, 36), (250, 250, 250),
                    cv2.FONT_HERSHEY_DUPLEX, 2)
    return image


def _generated_mug(rng) -> np.ndarray:
    base = tx.random_colour(rng, (0.5, 0.9), (0.3, 0.8))
    image = _solid(base, (128, 256))
    cv2.rectangle(image, (90, 30), (166, 96), (240, 240, 240), -1)
    tx.put_text_fit(image, tx.random_word(rng, (1, 2)), (94, 40, 68, 40), base, cv2.FONT_HERSHEY_COMPLEX, 2)
    return image


def _generated_bowl(rng) -> tuple[np.ndarray, np.ndarray]:
    outer = _solid(tx.random_colour(rng, (0.4, 0.9), (0.3, 0.7)), (64, 256))
    for k in range(8):
        cv2.circle(outer, (16 + 32 * k, 32), 9, tx.random_colour(rng), -1, cv2.LINE_AA)
    cv2.line(outer, (0, 6), (256, 6), (230, 230, 230), 3)
    inner = _solid(tx.random_colour(rng, (0.1, 0.5), (0.6, 0.9)), (64, 256))
    return outer, inner


def _generated_cereal(rng) -> dict[str, np.ndarray]:
    front = tx.poster(rng, 280, 200)
    cv2.circle(front, (100, 150), 50, (200, 220, 235), -1, cv2.LINE_AA)
    for _ in range(12):
        cv2.circle(front, (int(rng.integers(65, 135)), int(rng.integers(120, 175))), 7, (60, 120, 180), -1)
    side = tx.notice_board(rng, 280, 80)
    return {"front": front, "back": tx.hue_shift(front, 30), "side": side,
            "top": _solid(_mean_colour(front), (40, 140))}


def _generated_cap(rng) -> tuple[np.ndarray, np.ndarray]:
    colour = tx.random_colour(rng, (0.5, 1.0), (0.3, 0.8))
    crown = _solid(colour, (96, 256))
    for x in range(0, 256, 32):
        cv2.line(crown, (x, 0), (x, 96), (30, 30, 30), 1)
    cv2.circle(crown, (128, 50), 18, (245, 245, 245), -1, cv2.LINE_AA)
    tx.put_text_fit(crown, tx.random_word(rng, (1, 1))[:2].upper(), (114, 38, 28, 24), colour,
                    cv2.FONT_HERSHEY_DUPLEX, 2)
    brim = _solid(np.asarray(colour) * 0.8, (64, 64))
    return crown, brim


# ----------------------------------------------------------------------------------------------- tabletop classes

def build_soda_can(b: WorldBuilder, xy, z: float, yaw: float, rng, crop=None, v: Variation = Variation()) -> int:
    radius = 0.033 * v.scale
    height = 0.122 * v.scale * v.aspect
    if crop is not None:
        label = _window(crop, (0.12, 0.82), (0.18, 0.82), v.window_shift)
    else:
        label = _generated_can_label(rng)
    label = _finish(_wrap_label(label) if crop is not None else label, v)
    side = b.textures.add(label)
    top = b.textures.add(_solid((185, 185, 190)))
    front = (np.cos(yaw), np.sin(yaw), 0.0)
    index = b.begin_object("soda_can")
    b.frustum((xy[0], xy[1], z), (0, 0, 1), radius, radius, height, side, front=front, material=GLOSSY)
    b.disc((xy[0], xy[1], z + height), (0, 0, 1), radius, top, front=front, material=GLOSSY)
    b.end_object(yaw)
    return index


def build_coffee_mug(b: WorldBuilder, xy, z: float, yaw: float, rng, crop=None, v: Variation = Variation()) -> int:
    radius = 0.042 * v.scale
    height = 0.105 * v.scale * v.aspect
    if crop is not None:
        body = _window(crop, (0.12, 0.78), (0.12, 0.82), v.window_shift)
        body = _wrap_label(body)
    else:
        body = _generated_mug(rng)
    body = _finish(body, v)
    side = b.textures.add(body)
    glaze = b.textures.add(_solid(np.minimum(_mean_colour(body) * 1.2 + 30, 255)))
    coffee = b.textures.add(_solid((20, 40, 60)))
    c, s = np.cos(yaw), np.sin(yaw)
    front = np.array([c, s, 0.0])
    lateral = np.array([-s, c, 0.0])  # the handle sits on the object's left
    base = np.array([xy[0], xy[1], z])
    index = b.begin_object("coffee_mug")
    b.frustum(base, (0, 0, 1), radius, radius, height, side, front=front, material=GLOSSY)
    b.disc(base + [0, 0, height - 0.012], (0, 0, 1), radius, coffee, front=front)
    b.disc(base + [0, 0, height], (0, 0, 1), radius, glaze, r_in=radius - 0.004, front=front, material=GLOSSY)
    handle_centre = base + lateral * radius + [0, 0, 0.5 * height]
    b.disc(handle_centre, front, 0.032 * v.scale, glaze, r_in=0.021 * v.scale, front=lateral,
           phi_range=(-np.pi / 2, np.pi / 2), material=GLOSSY)
    b.frustum(handle_centre - front * 0.007, front, 0.027 * v.scale, 0.027 * v.scale, 0.014, glaze, front=lateral,
              phi_range=(-np.pi / 2, np.pi / 2), material=GLOSSY)
    b.end_object(yaw)
    return index


def build_bowl(b: WorldBuilder, xy, z: float, yaw: float, rng, crop=None, v: Variation = Variation()) -> int:
    r_top = 0.085 * v.scale
    r_bottom = 0.045 * v.scale
    height = 0.065 * v.scale * v.aspect
    if crop is not None:
        outer = _wrap_label(_window(crop, (0.5, 0.88), (0.12, 0.88), v.window_shift))
        inner = _wrap_label(_window(crop, (0.12, 0.42), (0.2, 0.8), v.window_shift))
    else:
        outer, inner = _generated_bowl(rng)
    outer_t = b.textures.add(_finish(outer, v))
    inner_t = b.textures.add(_finish(inner, v))
    bottom_t = b.textures.add(_solid(_mean_colour(_finish(inner, v))))
    base = np.array([xy[0], xy[1], z])
    front = (np.cos(yaw), np.sin(yaw), 0.0)
    index = b.begin_object("bowl")
    b.frustum(base, (0, 0, 1), r_bottom, r_top, height, outer_t, front=front, material=Material(0.55, 0.5, 1.0))
    # The inside is a second, slightly smaller shell: seen only through the opening.
    b.frustum(base + [0, 0, 0.004], (0, 0, 1), r_bottom - 0.003, r_top - 0.003, height - 0.004, inner_t, front=front,
              material=Material(0.5, 0.45, 1.0))
    b.disc(base + [0, 0, 0.005], (0, 0, 1), r_bottom - 0.003, bottom_t, front=front)
    b.end_object(yaw)
    return index


def build_cereal_box(b: WorldBuilder, xy, z: float, yaw: float, rng, crop=None, v: Variation = Variation()) -> int:
    width = 0.19 * v.scale
    depth = 0.07 * v.scale
    height = 0.28 * v.scale * v.aspect
    if crop is not None:
        front = _window(crop, (0.02, 0.84), (0.06, 0.76), v.window_shift * 0.5)
        side = _window(crop, (0.02, 0.84), (0.76, 0.96))
        faces = {"front": front, "back": tx.hue_shift(front, 25), "side": side,
                 "top": _solid(_mean_colour(front), (40, 140))}
    else:
        faces = _generated_cereal(rng)
    t = {k: b.textures.add(_finish(img, v)) for k, img in faces.items()}
    index = b.begin_object("cereal_box")
    # Box frame: +x is the front; the wide face (width) faces front.
    b.box((xy[0], xy[1], z + height / 2), (depth, width, height), yaw,
          [t["front"], t["side"], t["back"], t["side"], t["top"], t["top"]])
    b.end_object(yaw)
    return index


def build_cap(b: WorldBuilder, xy, z: float, yaw: float, rng, crop=None, v: Variation = Variation()) -> int:
    a = 0.095 * v.scale
    c = 0.08 * v.scale * v.aspect
    if crop is not None:
        crown = _wrap_label(_window(crop, (0.08, 0.62), (0.3, 0.92), v.window_shift))
        brim = _window(crop, (0.6, 0.9), (0.05, 0.45))
    else:
        crown, brim = _generated_cap(rng)
    crown_t = b.textures.add(_finish(crown, v))
    brim_t = b.textures.add(_finish(brim, v))
    centre = np.array([xy[0], xy[1], z])
    front = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    index = b.begin_object("cap")
    b.dome(centre + [0, 0, 0.004], (0, 0, 1), a, a * 1.1, c, crown_t, z_cut=0.0, front=front)
    # The brim: a flat crescent sticking out in front.
    b.disc(centre + front * 0.03 + [0, 0, 0.008], (0, 0, 1), a * 1.45, brim_t, r_in=a * 0.95,
           front=front, phi_range=(-0.9, 0.9))
    b.end_object(yaw)
    return index


TABLETOP_BUILDERS = {"bowl": build_bowl, "cap": build_cap, "cereal_box": build_cereal_box,
                     "coffee_mug": build_coffee_mug, "soda_can": build_soda_can}
# Footprint radius (m) used to keep instances apart on the table.
TABLETOP_FOOTPRINT = {"bowl": 0.1, "cap": 0.17, "cereal_box": 0.11, "coffee_mug": 0.075, "soda_can": 0.045}


# ----------------------------------------------------------------------------------------------- hall fixtures

def _clock_face(rng) -> np.ndarray:
    size = 256
    image = _solid((235, 238, 240), (size, size))
    centre = (size // 2, size // 2)
    cv2.circle(image, centre, size // 2 - 4, (40, 40, 40), 6, cv2.LINE_AA)
    for k in range(60):
        angle = 2 * np.pi * k / 60
        r0 = size // 2 - (28 if k % 5 == 0 else 16)
        r1 = size // 2 - 10
        p0 = (int(centre[0] + r0 * np.sin(angle)), int(centre[1] - r0 * np.cos(angle)))
        p1 = (int(centre[0] + r1 * np.sin(angle)), int(centre[1] - r1 * np.cos(angle)))
        cv2.line(image, p0, p1, (20, 20, 20), 4 if k % 5 == 0 else 1, cv2.LINE_AA)
    hours, minutes = rng.uniform(0, 12), rng.uniform(0, 60)
    for value, length, width in ((hours / 12, 60, 7), (minutes / 60, 95, 4)):
        angle = 2 * np.pi * value
        tip = (int(centre[0] + length * np.sin(angle)), int(centre[1] - length * np.cos(angle)))
        cv2.line(image, centre, tip, (15, 15, 15), width, cv2.LINE_AA)
    cv2.circle(image, centre, 6, (30, 30, 160), -1, cv2.LINE_AA)
    return image


def build_clock(b: WorldBuilder, xy, z: float, yaw: float, rng, v: Variation = Variation(), pole: bool = True) -> int:
    """A double-faced station clock on a pole (the pole is not part of the object)."""
    radius = 0.4 * v.scale
    depth = 0.14
    centre_z = z + 3.2
    face = b.textures.add(_clock_face(rng))
    rim = b.textures.add(_finish(_solid((40, 90, 40) if rng.random() < 0.5 else (30, 30, 30), (16, 64)), v))
    metal = b.textures.add(tx.concrete(rng, 64, 64))
    front = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    centre = np.array([xy[0], xy[1], centre_z])
    up = np.array([0.0, 0.0, 1.0])
    if pole:
        b.frustum((xy[0], xy[1], z), (0, 0, 1), 0.06, 0.05, centre_z - radius - z, metal)
    index = b.begin_object("clock")
    b.frustum(centre - front * depth / 2, front, radius, radius, depth, rim, front=up, material=GLOSSY)
    b.disc(centre + front * depth / 2, front, radius * 0.97, face, front=up, material=EMISSIVE)
    b.disc(centre - front * depth / 2, -front, radius * 0.97, face, front=up, material=EMISSIVE)
    b.end_object(yaw)
    return index


def build_trashcan(b: WorldBuilder, xy, z: float, yaw: float, rng, v: Variation = Variation()) -> int:
    r_bottom = 0.24 * v.scale
    r_top = 0.28 * v.scale
    height = 0.95 * v.scale * v.aspect
    body = _solid((40, 70, 40), (128, 512))
    for x in range(0, 512, 16):
        cv2.line(body, (x, 0), (x, 128), (25, 45, 25), 4)
    cv2.rectangle(body, (200, 30), (312, 80), (235, 235, 235), -1)
    tx.put_text_fit(body, "TRASH", (204, 36, 104, 38), (30, 60, 30), cv2.FONT_HERSHEY_DUPLEX, 2)
    cv2.line(body, (0, 8), (512, 8), (150, 150, 150), 6)
    side = b.textures.add(_finish(body, v))
    lid = b.textures.add(_solid((120, 120, 120)))
    inside = b.textures.add(_solid((15, 15, 15)))
    base = np.array([xy[0], xy[1], z])
    front = (np.cos(yaw), np.sin(yaw), 0.0)
    index = b.begin_object("trashcan")
    b.frustum(base, (0, 0, 1), r_bottom, r_top, height, side, front=front, material=Material(0.55, 0.5, 0.3))
    b.disc(base + [0, 0, height], (0, 0, 1), r_top, lid, r_in=r_top * 0.55, front=front, material=GLOSSY)
    b.disc(base + [0, 0, height - 0.25], (0, 0, 1), r_top * 0.6, inside, front=front)
    b.end_object(yaw)
    return index


def _payphone_front(rng) -> np.ndarray:
    image = _solid((150, 150, 155), (360, 240))
    cv2.rectangle(image, (0, 0), (240, 60), (160, 80, 20), -1)
    tx.put_text_fit(image, "PHONE", (20, 8, 200, 44), (250, 250, 250), cv2.FONT_HERSHEY_DUPLEX, 3)
    cv2.rectangle(image, (30, 80), (110, 300), (30, 30, 30), -1)  # handset
    cv2.rectangle(image, (40, 90), (100, 290), (60, 60, 60), -1)
    for r in range(4):
        for c in range(3):
            x, y = 140 + c * 28, 110 + r * 34
            cv2.rectangle(image, (x, y), (x + 20, y + 24), (220, 220, 220), -1)
            cv2.putText(image, "123456789*0#"[r * 3 + c], (x + 4, y + 19), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                        (20, 20, 20), 2)
    cv2.rectangle(image, (140, 260), (220, 280), (20, 20, 20), -1)
    return image


def build_payphone(b: WorldBuilder, xy, z: float, yaw: float, rng, v: Variation = Variation()) -> int:
    width, depth, height = 0.6 * v.scale, 0.35, 0.85 * v.scale
    front_t = b.textures.add(_finish(_payphone_front(rng), v))
    body_t = b.textures.add(_finish(_solid((140, 140, 145)), v))
    metal = b.textures.add(_solid((90, 90, 95)))
    front = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    index = b.begin_object("payphone")
    b.box((xy[0], xy[1], z + 1.05 + height / 2), (depth, width, height), yaw,
          [front_t, body_t, body_t, body_t, body_t, body_t], material=GLOSSY)
    b.box((xy[0] - 0.05 * front[0], xy[1] - 0.05 * front[1], z + 0.525), (0.12, 0.12, 1.05), yaw, metal)
    b.end_object(yaw)
    return index


def _ticket_front(rng, width=256, height=576) -> np.ndarray:
    image = _solid((190, 110, 40), (height, width))
    cv2.rectangle(image, (0, 0), (width, 70), (40, 40, 180), -1)
    tx.put_text_fit(image, "TICKETS", (14, 10, width - 28, 50), (255, 255, 255), cv2.FONT_HERSHEY_DUPLEX, 3)
    cv2.rectangle(image, (30, 100), (width - 30, 260), (40, 30, 20), -1)  # screen
    cv2.rectangle(image, (40, 110), (width - 40, 250), (120, 60, 10), -1)
    for k in range(4):
        tx.put_text_fit(image, tx.random_word(rng, (2, 3)), (50, 120 + 30 * k, width - 100, 22), (240, 240, 240),
                        cv2.FONT_HERSHEY_SIMPLEX, 1)
    for r in range(3):
        for c in range(4):
            x, y = 36 + c * 48, 290 + r * 40
            cv2.rectangle(image, (x, y), (x + 36, y + 28), (230, 230, 230), -1)
    cv2.rectangle(image, (60, 440), (width - 60, 470), (20, 20, 20), -1)  # ticket slot
    cv2.circle(image, (width // 2, 520), 20, (30, 200, 240), -1)
    return image


def build_ticket_machine(b: WorldBuilder, xy, z: float, yaw: float, rng, v: Variation = Variation()) -> int:
    width, depth, height = 0.75 * v.scale, 0.5, 1.8 * v.aspect
    front_t = b.textures.add(_finish(_ticket_front(rng), v))
    body_t = b.textures.add(_finish(_solid((170, 100, 40)), v))
    index = b.begin_object("ticket_machine")
    b.box((xy[0], xy[1], z + height / 2), (depth, width, height), yaw,
          [front_t, body_t, body_t, body_t, body_t, body_t], material=GLOSSY)
    b.end_object(yaw)
    return index


HALL_BUILDERS = {"clock": build_clock, "trashcan": build_trashcan, "payphone": build_payphone,
                 "ticket_machine": build_ticket_machine}


# ----------------------------------------------------------------------------------------------- clutter

def crop_alpha(crop: np.ndarray, threshold: float = 45.0) -> np.ndarray:
    """Object mask (uint8 0/255) of a crop on a plain turntable background: pixels far in colour from the border's
    median, cleaned up, largest blob with its holes filled. The whole crop when nothing stands out."""
    border = np.concatenate([crop[0], crop[-1], crop[:, 0], crop[:, -1]]).astype(np.float32)
    background = np.median(border, axis=0)
    distance = np.linalg.norm(crop.astype(np.float32) - background, axis=2)
    mask = (distance > threshold).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count <= 1:
        return np.full(crop.shape[:2], 255, np.uint8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    blob = (labels == largest).astype(np.uint8)
    if blob.sum() < 0.05 * blob.size:
        return np.full(crop.shape[:2], 255, np.uint8)
    # Fill holes: flood the outside from the border; what is not outside is object.
    padded = cv2.copyMakeBorder(blob, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    flood = padded.copy()
    cv2.floodFill(flood, None, (0, 0), 1)
    outside = (flood == 1) & (padded == 0)
    return (~outside[1:-1, 1:-1] * 255).astype(np.uint8)


def build_clutter(b: WorldBuilder, xy, z: float, rng, crop=None, height: float = 0.12) -> int:
    """A non-class object: a real crop as an upright billboard when given, else a small generated box.

    Returns the primitive index (clutter is not in the semantic map; it occludes and distracts).
    """
    if crop is not None:
        alpha = crop_alpha(crop)
        ys, xs = np.nonzero(alpha)
        crop, alpha = crop[ys.min():ys.max() + 1, xs.min():xs.max() + 1], alpha[ys.min():ys.max() + 1,
                                                                               xs.min():xs.max() + 1]
        h, w = crop.shape[:2]
        width = height * w / h
        texture = b.textures.add(np.ascontiguousarray(crop), alpha=np.ascontiguousarray(alpha))
        return b.billboard((xy[0], xy[1], z + height / 2), width, height, texture)
    size = rng.uniform(0.05, 0.14, 3)
    texture = b.textures.add(tx.poster(rng, 96, 64))
    return b.box((xy[0], xy[1], z + size[2] / 2), size, float(rng.uniform(0, np.pi)), texture)[0]
