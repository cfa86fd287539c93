"""Deterministic procedural textures and the texture atlas the renderer samples.

Every generator takes a ``numpy.random.Generator`` and returns a BGR uint8 image; the same generator state gives the
same bytes. The designs aim at what local-feature matchers (SIFT) and template detectors meet indoors: posters with
shapes and text, notice boards, signs with unique numbers, brick, tiles, wood, plaster. Repetition (the same design
on several walls) is controlled by the caller, which is how perceptual aliasing is made on purpose.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)
_SYLLABLES = ("ka", "lo", "mi", "ne", "ru", "sa", "to", "vi", "de", "po", "lan", "mer", "ost", "ix", "ber", "qu",
              "ta", "zen", "or", "el", "fa", "gri", "mon", "tek")


# ----------------------------------------------------------------------------------------------- the atlas

@dataclass(frozen=True, eq=False)
class TextureAtlas:
    """All mip levels of all textures packed in flat arrays, for the numba kernel.

    ``texels`` (N, 3) uint8 BGR, ``alpha`` (N,) uint8; ``levels`` (T, L, 3) int64 = (offset, height, width) of
    level l of texture t (unused levels repeat the last one); ``n_levels`` (T,) int64.
    """

    texels: np.ndarray
    alpha: np.ndarray
    levels: np.ndarray
    n_levels: np.ndarray
    sizes: np.ndarray  # (T, 2) height, width of level 0


class TextureStore:
    """Collects textures (deduplicated by identity of the caller's key) and packs them into a TextureAtlas."""

    def __init__(self) -> None:
        self._images: list[np.ndarray] = []
        self._alphas: list[np.ndarray | None] = []
        self._keys: dict = {}

    def __len__(self) -> int:
        return len(self._images)

    def add(self, image: np.ndarray, alpha: np.ndarray | None = None, key=None) -> int:
        """Register a BGR uint8 texture (optional uint8 alpha mask, 255 = opaque); returns its index."""
        if key is not None and key in self._keys:
            return self._keys[key]
        image = np.ascontiguousarray(image)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"a texture must be BGR uint8 (H, W, 3), got {image.dtype} {image.shape}")
        if image.shape[0] < 1 or image.shape[1] < 1:
            raise ValueError("a texture must not be empty")
        if alpha is not None:
            alpha = np.ascontiguousarray(alpha, dtype=np.uint8)
            if alpha.shape != image.shape[:2]:
                raise ValueError(f"alpha shape {alpha.shape} does not match texture {image.shape[:2]}")
        self._images.append(image)
        self._alphas.append(alpha)
        index = len(self._images) - 1
        if key is not None:
            self._keys[key] = index
        return index

    def image(self, index: int) -> np.ndarray:
        return self._images[index]

    def build(self, min_size: int = 2) -> TextureAtlas:
        pyramids = []
        for image, alpha in zip(self._images, self._alphas):
            levels = [(image, alpha if alpha is not None else np.full(image.shape[:2], 255, np.uint8))]
            while min(levels[-1][0].shape[:2]) >= 2 * min_size:
                img, alp = levels[-1]
                levels.append((cv2.pyrDown(img), cv2.pyrDown(alp)))
            pyramids.append(levels)
        max_levels = max((len(p) for p in pyramids), default=1)
        total = sum(lv[0].shape[0] * lv[0].shape[1] for p in pyramids for lv in p)
        texels = np.empty((max(total, 1), 3), np.uint8)
        alpha = np.empty(max(total, 1), np.uint8)
        table = np.zeros((max(len(pyramids), 1), max_levels, 3), np.int64)
        n_levels = np.ones(max(len(pyramids), 1), np.int64)
        sizes = np.zeros((max(len(pyramids), 1), 2), np.int64)
        offset = 0
        for t, levels in enumerate(pyramids):
            n_levels[t] = len(levels)
            sizes[t] = levels[0][0].shape[:2]
            for lvl in range(max_levels):
                img, alp = levels[min(lvl, len(levels) - 1)]
                h, w = img.shape[:2]
                if lvl < len(levels):
                    texels[offset:offset + h * w] = img.reshape(-1, 3)
                    alpha[offset:offset + h * w] = alp.reshape(-1)
                    table[t, lvl] = (offset, h, w)
                    offset += h * w
                else:
                    table[t, lvl] = table[t, len(levels) - 1]
        return TextureAtlas(texels=texels, alpha=alpha, levels=table, n_levels=n_levels, sizes=sizes)


# ----------------------------------------------------------------------------------------------- helpers

def random_colour(rng: np.random.Generator, saturation=(0.3, 0.9), value=(0.3, 0.95)) -> tuple[int, int, int]:
    """A BGR colour from a random hue with saturation and value in the given ranges."""
    hsv = np.uint8([[[rng.integers(0, 180), int(255 * rng.uniform(*saturation)), int(255 * rng.uniform(*value))]]])
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def value_noise(rng: np.random.Generator, height: int, width: int, octaves: int = 4, base_cells: int = 4,
                persistence: float = 0.5) -> np.ndarray:
    """Fractal value noise in [0, 1], float32 (H, W): smooth random grids upsampled and summed over octaves."""
    total = np.zeros((height, width), np.float32)
    amplitude = 1.0
    norm = 0.0
    cells = base_cells
    for _ in range(octaves):
        grid = rng.random((cells + 1, cells + 1)).astype(np.float32)
        total += amplitude * cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        norm += amplitude
        amplitude *= persistence
        cells *= 2
    return np.clip(total / norm, 0.0, 1.0)


def random_word(rng: np.random.Generator, syllables: tuple[int, int] = (1, 3)) -> str:
    return "".join(_SYLLABLES[i] for i in rng.integers(0, len(_SYLLABLES), rng.integers(syllables[0],
                                                                                         syllables[1] + 1)))


def put_text_fit(image: np.ndarray, text: str, box: tuple[int, int, int, int], colour, font: int = 0,
                 thickness: int = 2) -> None:
    """Draw ``text`` scaled to fit the box (x, y, w, h)."""
    x, y, w, h = box
    (tw, th), base = cv2.getTextSize(text, font, 1.0, thickness)
    scale = min(w / max(tw, 1), h / max(th + base, 1))
    if scale <= 0.05:
        return
    (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    org = (int(x + (w - tw) / 2), int(y + (h + th) / 2 - base / 2))
    cv2.putText(image, text, org, font, scale, colour, max(1, int(round(thickness))), cv2.LINE_AA)


def hue_shift(image: np.ndarray, degrees: float, saturation_gain: float = 1.0) -> np.ndarray:
    """Rotate the hue of a BGR image (OpenCV hue unit = 2 degrees); white/grey pixels stay put."""
    if abs(degrees) < 1e-9 and saturation_gain == 1.0:
        return image.copy()
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV).astype(np.int32)
    hsv[..., 0] = (hsv[..., 0] + int(round(degrees / 2.0))) % 180
    hsv[..., 1] = np.clip(hsv[..., 1] * saturation_gain, 0, 255)
    return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2BGR)


def add_grain(rng: np.random.Generator, image: np.ndarray, amount: float = 8.0) -> np.ndarray:
    noise = rng.normal(0.0, amount, image.shape[:2]).astype(np.float32)
    return np.clip(image.astype(np.float32) + noise[..., None], 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------- wall materials

def _scuffs(rng, image: np.ndarray, count: int) -> None:
    """Marks, scuffs and small stains: what makes a real painted wall findable by a feature detector."""
    height, width = image.shape[:2]
    for _ in range(count):
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        tone = float(rng.uniform(0.55, 0.9))
        colour = tuple(float(c) * tone for c in image[y, x])
        kind = rng.integers(0, 3)
        if kind == 0:
            cv2.circle(image, (x, y), int(rng.integers(1, 5)), colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.line(image, (x, y), (x + int(rng.integers(-25, 25)), y + int(rng.integers(-6, 6))), colour,
                     int(rng.integers(1, 3)), cv2.LINE_AA)
        else:
            cv2.ellipse(image, (x, y), (int(rng.integers(3, 12)), int(rng.integers(2, 6))),
                        float(rng.uniform(0, 180)), 0, 360, colour, -1, cv2.LINE_AA)


def plaster(rng, height=512, width=512, colour=None) -> np.ndarray:
    """Painted plaster: a flat colour with low-frequency mottling and a few scuffs and marks."""
    colour = np.array(colour if colour is not None else random_colour(rng, (0.05, 0.3), (0.6, 0.9)), np.float32)
    mottle = value_noise(rng, height, width, octaves=5, base_cells=3)
    image = np.clip(colour[None, None, :] * (0.88 + 0.24 * mottle[..., None]), 0, 255).astype(np.uint8)
    _scuffs(rng, image, int(rng.integers(25, 60)))
    return add_grain(rng, image, 3.0)


def brick(rng, height=512, width=512) -> np.ndarray:
    """Running-bond brick with per-brick colour, mortar joints and surface noise."""
    mortar = np.array(random_colour(rng, (0.0, 0.15), (0.6, 0.8)), np.float32)
    base = np.array(random_colour(rng, (0.4, 0.8), (0.35, 0.6)), np.float32)
    image = np.empty((height, width, 3), np.float32)
    image[:] = mortar
    rows = 16
    cols = 8
    bh = height / rows
    bw = width / cols
    for r in range(rows):
        shift = (bw / 2) if r % 2 else 0.0
        for c in range(-1, cols + 1):
            x0 = int(round(c * bw + shift)) + 2
            x1 = int(round((c + 1) * bw + shift)) - 2
            y0 = int(round(r * bh)) + 2
            y1 = int(round((r + 1) * bh)) - 2
            tone = base * rng.uniform(0.75, 1.2)
            image[max(y0, 0):max(y1, 0), max(x0, 0):max(min(x1, width), 0)] = tone
    image *= (0.85 + 0.3 * value_noise(rng, height, width, 4, 8))[..., None]
    return add_grain(rng, np.clip(image, 0, 255).astype(np.uint8), 6.0)


def wood_panel(rng, height=512, width=512) -> np.ndarray:
    """Vertical wood planks with grain streaks."""
    base = np.array(random_colour(rng, (0.4, 0.7), (0.35, 0.7)), np.float32)
    base = np.array([base[0] * 0.4, base[1] * 0.7, base[2]], np.float32)
    grain = value_noise(rng, height, width // 8 + 1, 5, 6)
    grain = cv2.resize(grain, (width, height), interpolation=cv2.INTER_LINEAR)
    streak = 0.5 + 0.5 * np.sin(np.linspace(0, 40, width)[None, :] + 6 * grain)
    image = base[None, None, :] * (0.75 + 0.35 * streak[..., None])
    planks = 6
    for knot in range(int(rng.integers(4, 10))):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        cv2.ellipse(image, centre, (int(rng.integers(3, 8)), int(rng.integers(8, 20))), 0, 0, 360,
                    tuple(float(c) * 0.55 for c in base), -1, cv2.LINE_AA)
    for p in range(1, planks):
        x = int(p * width / planks)
        image[:, max(x - 1, 0):x + 1] *= 0.45
    return add_grain(rng, np.clip(image, 0, 255).astype(np.uint8), 4.0)


def tiles(rng, height=512, width=512, count=4, colour=None) -> np.ndarray:
    """Square tiles with grout lines and per-tile tone and speckle (floors, lower walls)."""
    colour = np.array(colour if colour is not None else random_colour(rng, (0.0, 0.35), (0.45, 0.85)), np.float32)
    image = np.empty((height, width, 3), np.float32)
    image[:] = colour * 0.55
    th = height / count
    tw = width / count
    for r in range(count):
        for c in range(count):
            tone = colour * rng.uniform(0.85, 1.1)
            image[int(r * th) + 3:int((r + 1) * th) - 2, int(c * tw) + 3:int((c + 1) * tw) - 2] = tone
    speckle = value_noise(rng, height, width, 3, 32)
    image *= (0.9 + 0.2 * speckle)[..., None]
    image = np.clip(image, 0, 255).astype(np.uint8)
    _scuffs(rng, image, int(rng.integers(20, 50)))
    return add_grain(rng, image, 5.0)


def concrete(rng, height=512, width=512) -> np.ndarray:
    """Fair-faced concrete: formwork panel seams, tie holes in a grid, stains."""
    grey = rng.uniform(120, 185)
    n = value_noise(rng, height, width, 6, 4)
    image = np.stack([grey * (0.8 + 0.35 * n)] * 3, axis=-1) * np.array([1.0, 1.0, rng.uniform(0.95, 1.08)])
    for _ in range(rng.integers(2, 6)):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        axes = (int(rng.integers(10, 60)), int(rng.integers(5, 40)))
        cv2.ellipse(image, centre, axes, float(rng.uniform(0, 180)), 0, 360, tuple([grey * 0.8] * 3), -1)
    image = cv2.GaussianBlur(image, (0, 0), 1.2)
    seam = tuple([grey * 0.7] * 3)
    cv2.line(image, (0, height // 2), (width, height // 2), seam, 2)
    cv2.line(image, (width // 2, 0), (width // 2, height), seam, 2)
    for y in (height // 4, 3 * height // 4):
        for x in (width // 8, 3 * width // 8, 5 * width // 8, 7 * width // 8):
            cv2.circle(image, (x, y), 5, tuple([grey * 0.45] * 3), -1, cv2.LINE_AA)
    image = np.clip(image, 0, 255).astype(np.uint8)
    _scuffs(rng, image, int(rng.integers(15, 40)))
    return add_grain(rng, image, 6.0)


def ceiling_panels(rng, height=256, width=256) -> np.ndarray:
    """Acoustic ceiling tiles: fissured surface, grid bars, a light panel and a vent."""
    image = np.full((height, width, 3), rng.uniform(200, 235), np.float32)
    image *= (0.9 + 0.12 * value_noise(rng, height, width, 3, 32))[..., None]
    for _ in range(120):
        x, y = int(rng.integers(4, width - 4)), int(rng.integers(4, height - 4))
        cv2.line(image, (x, y), (x + int(rng.integers(-4, 5)), y + int(rng.integers(-4, 5))), (150, 150, 150), 1)
    cv2.rectangle(image, (0, 0), (width - 1, height - 1), (140, 140, 140), 3)
    cv2.rectangle(image, (width // 4, height // 3), (3 * width // 4, 2 * height // 3), (250, 250, 255), -1)
    for k in range(1, 8):
        x = width // 4 + k * (width // 2) // 8
        cv2.line(image, (x, height // 3), (x, 2 * height // 3), (215, 215, 220), 1)
    return np.clip(image, 0, 255).astype(np.uint8)


def carpet(rng, height=256, width=256) -> np.ndarray:
    colour = np.array(random_colour(rng, (0.2, 0.6), (0.25, 0.5)), np.float32)
    n = value_noise(rng, height, width, 3, 32)
    image = colour * (0.7 + 0.5 * n)[..., None]
    return add_grain(rng, np.clip(image, 0, 255).astype(np.uint8), 14.0)


MATERIALS = {"plaster": plaster, "brick": brick, "wood": wood_panel, "tiles": tiles, "concrete": concrete}


# ----------------------------------------------------------------------------------------------- décor

def poster(rng, height=384, width=256) -> np.ndarray:
    """A poster: gradient background, shapes, a picture block and lines of text - rich in corners and blobs."""
    c0 = np.array(random_colour(rng), np.float32)
    c1 = np.array(random_colour(rng), np.float32)
    ramp = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None, None]
    image = (c0 * (1 - ramp) + c1 * ramp) * np.ones((1, width, 1), np.float32)
    image = np.clip(image, 0, 255).astype(np.uint8)
    # A "photo": smooth noise colour field with a few blobs.
    py0, py1 = int(height * rng.uniform(0.08, 0.2)), int(height * rng.uniform(0.5, 0.65))
    px0, px1 = int(width * 0.08), int(width * 0.92)
    field = value_noise(rng, py1 - py0, px1 - px0, 4, 3)
    tint = np.array(random_colour(rng), np.float32)
    tint2 = np.array(random_colour(rng), np.float32)
    image[py0:py1, px0:px1] = np.clip(tint * field[..., None] + tint2 * (1 - field[..., None]), 0, 255)
    for _ in range(rng.integers(4, 10)):
        colour = random_colour(rng)
        kind = rng.integers(0, 4)
        cx, cy = int(rng.integers(px0, px1)), int(rng.integers(py0, py1))
        size = int(rng.integers(6, max(8, width // 5)))
        if kind == 0:
            cv2.circle(image, (cx, cy), size, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(image, (cx - size, cy - size // 2), (cx + size, cy + size // 2), colour, -1)
        elif kind == 2:
            pts = rng.integers(-size, size, (int(rng.integers(3, 6)), 2)) + np.array([cx, cy])
            cv2.fillPoly(image, [pts.astype(np.int32)], colour, cv2.LINE_AA)
        else:
            cv2.line(image, (cx - size, cy), (cx + size, cy + int(rng.integers(-size, size))), colour, 3,
                     cv2.LINE_AA)
    # Title and body text.
    font = _FONTS[int(rng.integers(0, len(_FONTS)))]
    text_colour = random_colour(rng, (0.0, 0.4), (0.0, 0.25)) if rng.random() < 0.5 else (245, 245, 245)
    put_text_fit(image, random_word(rng, (2, 4)).upper(), (int(width * 0.05), int(height * 0.68), int(width * 0.9),
                                                           int(height * 0.1)), text_colour, font, 2)
    y = int(height * 0.8)
    while y < height - 12:
        put_text_fit(image, " ".join(random_word(rng) for _ in range(3)),
                     (int(width * 0.08), y, int(width * rng.uniform(0.5, 0.84)), 12), text_colour, font, 1)
        y += 16
    cv2.rectangle(image, (0, 0), (width - 1, height - 1), (30, 30, 30), 2)
    return image


def notice_board(rng, height=256, width=384) -> np.ndarray:
    """Cork board with pinned sheets of text - dense texture, distinct per instance."""
    cork = np.array([60, 110, 170], np.float32) * rng.uniform(0.85, 1.1)
    image = cork * (0.75 + 0.4 * value_noise(rng, height, width, 3, 48))[..., None]
    image = np.clip(image, 0, 255).astype(np.uint8)
    for _ in range(rng.integers(4, 9)):
        w = int(rng.integers(width // 7, width // 3))
        h = int(rng.integers(height // 5, height // 2))
        x = int(rng.integers(0, width - w))
        y = int(rng.integers(0, height - h))
        paper = (245, 245, 240) if rng.random() < 0.6 else random_colour(rng, (0.2, 0.5), (0.85, 1.0))
        cv2.rectangle(image, (x, y), (x + w, y + h), paper, -1)
        ty = y + 8
        while ty < y + h - 6:
            put_text_fit(image, random_word(rng, (2, 4)), (x + 4, ty, int(w * rng.uniform(0.4, 0.9)), 7),
                         (40, 40, 40), cv2.FONT_HERSHEY_PLAIN, 1)
            ty += 10
        cv2.circle(image, (x + w // 2, y + 4), 3, random_colour(rng), -1)
    cv2.rectangle(image, (0, 0), (width - 1, height - 1), (40, 60, 90), 6)
    return image


def sign(rng, text: str, height=96, width=256, colours=None) -> np.ndarray:
    """A flat sign with a number or name; the text makes the place unique unless it is repeated on purpose."""
    background, foreground = colours if colours is not None else (random_colour(rng, (0.5, 0.9), (0.3, 0.7)),
                                                                   (245, 245, 245))
    image = np.empty((height, width, 3), np.uint8)
    image[:] = background
    cv2.rectangle(image, (4, 4), (width - 5, height - 5), foreground, 2)
    put_text_fit(image, text, (12, 10, width - 24, height - 20), foreground, cv2.FONT_HERSHEY_DUPLEX, 3)
    return image


def door(rng, height=512, width=224) -> np.ndarray:
    colour = np.array(random_colour(rng, (0.2, 0.6), (0.3, 0.7)), np.float32)
    image = colour * (0.9 + 0.15 * value_noise(rng, height, width, 3, 4))[..., None]
    image = np.clip(image, 0, 255).astype(np.uint8)
    cv2.rectangle(image, (0, 0), (width - 1, height - 1), (50, 50, 50), 6)
    cv2.rectangle(image, (width // 5, height // 10), (4 * width // 5, height // 3), (200, 210, 220), -1)
    cv2.rectangle(image, (width // 5, height // 10), (4 * width // 5, height // 3), (60, 60, 60), 3)
    cv2.circle(image, (int(width * 0.82), height // 2), 8, (180, 180, 190), -1)
    cv2.rectangle(image, (int(width * 0.72), height // 2 - 3), (int(width * 0.82), height // 2 + 3), (170, 170, 180),
                  -1)
    return image


def window(rng, height=256, width=384) -> np.ndarray:
    """A window with frame bars and a blurred 'outside' behind the glass."""
    outside = value_noise(rng, height, width, 4, 3)
    sky = np.array([235, 200, 150], np.float32)
    ground = np.array(random_colour(rng, (0.3, 0.6), (0.3, 0.6)), np.float32)
    image = sky * (1 - outside[..., None]) + ground * outside[..., None]
    image = np.clip(image, 0, 255).astype(np.uint8)
    frame = (225, 225, 225)
    cv2.rectangle(image, (0, 0), (width - 1, height - 1), frame, 10)
    for k in range(1, 3):
        cv2.line(image, (k * width // 3, 0), (k * width // 3, height), frame, 6)
    cv2.line(image, (0, height // 2), (width, height // 2), frame, 6)
    return image


def shop_front(rng, height=384, width=768) -> np.ndarray:
    """A shop or kiosk front: lettered fascia, display windows with goods, a door."""
    image = np.empty((height, width, 3), np.uint8)
    fascia = random_colour(rng, (0.5, 1.0), (0.3, 0.8))
    image[:] = (60, 60, 60)
    cv2.rectangle(image, (0, 0), (width, height // 5), fascia, -1)
    put_text_fit(image, random_word(rng, (2, 4)).upper(), (20, 8, width - 40, height // 5 - 16), (250, 250, 250),
                 _FONTS[int(rng.integers(0, 4))], 3)
    glass = window(rng, height - height // 5 - 10, width * 2 // 3)
    for _ in range(rng.integers(6, 14)):
        x = int(rng.integers(10, glass.shape[1] - 40))
        y = int(rng.integers(glass.shape[0] // 2, glass.shape[0] - 30))
        cv2.rectangle(glass, (x, y), (x + int(rng.integers(15, 40)), y + int(rng.integers(15, 40))),
                      random_colour(rng), -1)
    image[height // 5 + 5:height // 5 + 5 + glass.shape[0], 5:5 + glass.shape[1]] = glass
    d = door(rng, height - height // 5 - 10, width // 3 - 15)
    image[height // 5 + 5:height // 5 + 5 + d.shape[0], width - d.shape[1] - 5:width - 5] = d
    return image


def advert(rng, height=256, width=512) -> np.ndarray:
    """A wide advertising panel (a poster rotated into landscape with a bold strip)."""
    image = poster(rng, width, height)
    image = cv2.rotate(image, cv2.ROTATE_90_CLOCKWISE)
    cv2.rectangle(image, (0, height - 40), (width, height), random_colour(rng, (0.6, 1.0), (0.5, 0.9)), -1)
    put_text_fit(image, random_word(rng, (2, 3)).upper(), (10, height - 36, width // 2, 32), (255, 255, 255),
                 cv2.FONT_HERSHEY_DUPLEX, 2)
    return image
