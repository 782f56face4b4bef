"""Procedural, world-anchored, non-periodic face textures and their mip-mapped atlas.

Every face gets its own seeded texture: multi-octave colour noise, thresholded-noise blobs, random shapes and
glyphs, and target markers on the room faces; textures are shaded per face orientation and packed with their
pyrDown levels into one atlas (``build_geometry``), so detections are stable across views. Faces of "plain" boxes
(the walls of the home scene) get a near-uniform light colour with only faint low-contrast noise instead.
"""

from __future__ import annotations

import colorsys
import math

import cv2
import numpy as np

from fullview.synth.geometry import SceneGeometry, face_frame, face_normal


TEXEL_AT_2048 = 0.0075  # texel size (m) used for width-2048 renders (scaled by 2048 / width)
MIP_LEVELS = 7  # texture pyramid levels (level l is 2**l times coarser)
ATLAS_PAD = 2  # replicated border around every atlas tile (texels)
MARKER_RADIUS = 0.07  # marker radius (m)
# Smooth colour noise octaves: (cell size m, relative amplitude).
NOISE_OCTAVES = ((1.2, 0.22), (0.4, 0.18), (0.13, 0.16), (0.045, 0.14), (0.016, 0.10))
# Thresholded-noise blob layers: noise cell size (m).
BLOB_CELLS = (0.25, 0.08, 0.03)
# Random shape bands: (typical size m, fraction of the face area covered by the band).
SHAPE_BANDS = ((0.45, 0.12), (0.22, 0.15), (0.11, 0.15), (0.055, 0.12), (0.028, 0.08))
GOLDEN_HUE_STEP = 0.381966  # hue increment between consecutive faces (golden-ratio spread)
# Faint colour noise of plain faces: (cell size m, relative amplitude); far below SIFT's contrast threshold.
PLAIN_OCTAVES = ((1.0, 0.02), (0.15, 0.008))
LIGHT_DIR = np.array([0.35, -1.0, 0.55]) / np.linalg.norm([0.35, -1.0, 0.55])  # towards the light


def texel_for_width(width: int) -> float:
    return float(np.clip(TEXEL_AT_2048 * 2048.0 / width, 0.003, 0.06))


def _hsv_bgr(h: float, s: float, v: float) -> np.ndarray:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, s, v)
    return np.array([b, g, r]) * 255.0


def _noise_field(rng: np.random.Generator, size_uv: np.ndarray, shape: tuple[int, int], texel: float,
                 cell: float, channels: int) -> np.ndarray | None:
    """World-anchored smooth noise (bicubic on a grid of ``cell`` metres); None if finer than the texels."""
    gu, gv = int(math.ceil(size_uv[0] / cell)) + 4, int(math.ceil(size_uv[1] / cell)) + 4
    grid = rng.standard_normal((gv, gu, channels)).astype(np.float32)
    if cell < 2.5 * texel:
        return None
    nv, nu = shape
    mx = np.arange(nu, dtype=np.float32) * np.float32(texel / cell) + np.float32(1.5)
    my = np.arange(nv, dtype=np.float32) * np.float32(texel / cell) + np.float32(1.5)
    map_x = np.ascontiguousarray(np.broadcast_to(mx[None, :], (nv, nu)))
    map_y = np.ascontiguousarray(np.broadcast_to(my[:, None], (nv, nu)))
    out = cv2.remap(grid, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return out.reshape(nv, nu, channels)


def _face_texture(rng: np.random.Generator, size_uv: np.ndarray, texel: float, shade: float, hue: float,
                  markers_uv: np.ndarray) -> np.ndarray:
    """(n_v, n_u, 3) uint8 BGR texture of one face; texel (a, b) sits at (u, v) = (a, b) * texel."""
    nu, nv = (int(math.ceil(s / texel)) + 1 for s in size_uv)
    base = _hsv_bgr(hue + rng.uniform(-0.04, 0.04), rng.uniform(0.2, 0.55), rng.uniform(0.45, 0.8))
    palette = [_hsv_bgr(hue + rng.uniform(-0.25, 0.25), rng.uniform(0.25, 0.85), rng.uniform(0.1, 1.0))
               for _ in range(3)]
    palette += [_hsv_bgr(rng.uniform(), rng.uniform(0.25, 0.85), rng.uniform(0.1, 1.0)) for _ in range(2)]
    img = np.empty((nv, nu, 3), np.float32)
    img[:] = base
    for cell, amp in NOISE_OCTAVES:
        n = _noise_field(rng, size_uv, (nv, nu), texel, cell, 3)
        if n is not None:
            img *= 1.0 + amp * (0.8 * n[..., :1] + 0.35 * n)
    for cell in BLOB_CELLS:
        thr = rng.uniform(0.4, 1.1)
        colour = palette[int(rng.integers(len(palette)))] * rng.uniform(0.7, 1.2)
        n = _noise_field(rng, size_uv, (nv, nu), texel, cell, 1)
        if n is not None:
            alpha = np.clip(0.5 + (n - thr) * np.float32(cell / (2.0 * texel)), 0.0, 1.0)
            img += alpha * (colour.astype(np.float32) - img)
    img8 = np.clip(img, 0, 255).astype(np.uint8)
    _draw_shapes(img8, rng, size_uv, texel, palette)
    for uv in markers_uv:
        _draw_marker(img8, uv / texel, MARKER_RADIUS / texel)
    return np.clip(img8.astype(np.float32) * shade, 0, 255).astype(np.uint8)


def _plain_texture(rng: np.random.Generator, size_uv: np.ndarray, texel: float, shade: float,
                   markers_uv: np.ndarray) -> np.ndarray:
    """(n_v, n_u, 3) uint8 BGR texture of a plain (painted) face: light, unsaturated, faint noise, markers."""
    nu, nv = (int(math.ceil(s / texel)) + 1 for s in size_uv)
    img = np.empty((nv, nu, 3), np.float32)
    img[:] = _hsv_bgr(rng.uniform(), rng.uniform(0.03, 0.15), rng.uniform(0.7, 0.9))
    for cell, amp in PLAIN_OCTAVES:
        n = _noise_field(rng, size_uv, (nv, nu), texel, cell, 1)
        if n is not None:
            img *= 1.0 + amp * n
    img8 = np.clip(img, 0, 255).astype(np.uint8)
    for uv in markers_uv:
        _draw_marker(img8, uv / texel, MARKER_RADIUS / texel)
    return np.clip(img8.astype(np.float32) * shade, 0, 255).astype(np.uint8)


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, size_uv: np.ndarray, texel: float,
                 palette: list[np.ndarray]) -> None:
    """Random circles, rings, ellipses, polygons, lines and glyphs, coarse to fine (in place)."""
    area = float(size_uv[0] * size_uv[1])
    glyphs = "ABCDEFGHJKLMNPRSTUVWXYZ0123456789#&%@"
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_COMPLEX)
    sh = 4
    one = float(1 << sh) / texel  # metres -> fixed-point texel units
    for size, cover in SHAPE_BANDS:
        n = int(rng.poisson(cover * area / size ** 2))
        cu = rng.uniform(0, size_uv[0], n) * one
        cv = rng.uniform(0, size_uv[1], n) * one
        sz = size * rng.uniform(0.6, 1.5, n) * one
        kind = rng.integers(0, 7, n)
        ang = rng.uniform(0, 360, n)
        aspect = rng.uniform(0.25, 1.0, n)
        use_grey = rng.random(n) < 0.35
        grey = rng.uniform(0, 255, n)
        pal = rng.integers(0, len(palette), n)
        jitter = rng.normal(0, 15, (n, 3))
        verts = rng.uniform(-0.5, 0.5, (n, 3, 2))
        glyph = rng.integers(0, len(glyphs), (n, 2))
        font = rng.integers(0, len(fonts), n)
        if size * 0.6 < 2.0 * texel:  # too fine for this texel size (parameters drawn anyway)
            continue
        colours = np.where(use_grey[:, None], grey[:, None], np.array(palette)[pal] + jitter)
        colours = np.clip(colours, 0, 255)
        for i in range(n):
            _draw_one(img, int(kind[i]), float(cu[i]), float(cv[i]), float(sz[i]), float(ang[i]),
                      float(aspect[i]), tuple(colours[i].tolist()), verts[i], sh,
                      glyphs[glyph[i, 0]] + glyphs[glyph[i, 1]], fonts[font[i]])


def _draw_one(img: np.ndarray, kind: int, x: float, y: float, s: float, ang: float, aspect: float,
              colour: tuple, verts: np.ndarray, sh: int, text: str, font: int) -> None:
    aa = cv2.LINE_AA
    c = (int(x), int(y))
    unit = float(1 << sh)
    if kind == 0:
        cv2.circle(img, c, int(s / 2), colour, -1, aa, sh)
    elif kind == 1:
        cv2.circle(img, c, int(s / 2), colour, max(1, int(s / unit / 8)), aa, sh)
    elif kind == 2:
        cv2.ellipse(img, c, (int(s / 2), int(s * aspect / 2)), ang, 0, 360, colour, -1, aa, sh)
    elif kind == 3:
        a = math.radians(ang)
        ca, sa = math.cos(a), math.sin(a)
        hw, hh = s / 2, s * aspect / 2
        pts = [(x + ca * dx - sa * dy, y + sa * dx + ca * dy) for dx, dy in ((-hw, -hh), (hw, -hh), (hw, hh), (-hw, hh))]
        cv2.fillConvexPoly(img, np.array(pts, np.int32), colour, aa, sh)
    elif kind == 4:
        pts = np.array([x, y]) + verts * s * 1.4
        cv2.fillConvexPoly(img, pts.astype(np.int32), colour, aa, sh)
    elif kind == 5:
        a = math.radians(ang)
        dx, dy = math.cos(a) * s / 2, math.sin(a) * s / 2
        cv2.line(img, (int(x - dx), int(y - dy)), (int(x + dx), int(y + dy)), colour,
                 max(1, int(s * aspect / unit / 5)), aa, sh)
    else:
        scale = s / unit / 30.0
        org = (int((x - s / 2) / unit), int((y + s / 4) / unit))
        cv2.putText(img, text, org, font, scale, colour, max(1, int(scale * 2)), aa)


def _draw_marker(img: np.ndarray, centre: np.ndarray, radius: float) -> None:
    """Quadrant target (black/white) whose centre is the exact marker point (texel units)."""
    sh = 4
    c = (int(round(centre[0] * 16)), int(round(centre[1] * 16)))
    r = int(round(radius * 16))
    aa = cv2.LINE_AA
    cv2.circle(img, c, int(r * 1.15), (0, 0, 0), -1, aa, sh)
    cv2.circle(img, c, r, (255, 255, 255), -1, aa, sh)
    cv2.ellipse(img, c, (r, r), 0, 0, 90, (0, 0, 0), -1, aa, sh)
    cv2.ellipse(img, c, (r, r), 0, 180, 270, (0, 0, 0), -1, aa, sh)


def _face_shade(face: int) -> float:
    """Constant Lambert-like shading factor of a face (view independent, differs between orientations)."""
    n = face_normal(face, room=face < 6)
    return float(0.55 + 0.45 * max(0.0, float(n @ LIGHT_DIR)))


def _build_atlas(textures: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Shelf-pack every face texture and its pyrDown levels into one atlas."""
    tiles = []
    for f, tex in enumerate(textures):
        lvl = tex
        for level in range(MIP_LEVELS):
            tiles.append((level, f, lvl))
            if min(lvl.shape[:2]) >= 2:
                lvl = cv2.pyrDown(lvl)  # level-l texel k sits at level-0 texel k * 2**l
            else:
                lvl = cv2.resize(lvl, ((lvl.shape[1] + 1) // 2, (lvl.shape[0] + 1) // 2), interpolation=cv2.INTER_AREA)
    order = sorted(range(len(tiles)), key=lambda i: (-tiles[i][2].shape[0], i))
    atlas_w = max(4096, max(t[2].shape[1] for t in tiles) + 2 * ATLAS_PAD)
    offset = np.zeros((MIP_LEVELS, len(textures), 2), np.float32)
    placed = []
    x = y = shelf_h = 0
    for i in order:
        level, f, img = tiles[i]
        h, w = img.shape[0] + 2 * ATLAS_PAD, img.shape[1] + 2 * ATLAS_PAD
        if x + w > atlas_w:
            x, y, shelf_h = 0, y + shelf_h, 0
        placed.append((x, y, img))
        offset[level, f] = (x + ATLAS_PAD, y + ATLAS_PAD)
        x += w
        shelf_h = max(shelf_h, h)
    atlas = np.zeros((y + shelf_h, atlas_w, 3), np.uint8)
    for x0, y0, img in placed:
        padded = cv2.copyMakeBorder(img, ATLAS_PAD, ATLAS_PAD, ATLAS_PAD, ATLAS_PAD, cv2.BORDER_REPLICATE)
        atlas[y0:y0 + padded.shape[0], x0:x0 + padded.shape[1]] = padded
    if atlas.shape[0] >= 32767 or atlas.shape[1] >= 32767:
        raise ValueError(f"texture atlas too large ({atlas.shape[:2]}); texel too small")
    return atlas, offset


def build_geometry(boxes: np.ndarray, *, texel: float, seed: np.random.SeedSequence | int,
                   markers: np.ndarray | None = None, marker_names: list[str] | None = None,
                   marker_faces: list[int] | None = None, plain_boxes: tuple[int, ...] = ()) -> SceneGeometry:
    """Procedural textures (one per face, seeded) and their mip-mapped atlas for ``boxes``; the faces of the
    boxes in ``plain_boxes`` get plain textures (see ``_plain_texture``)."""
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or np.any(boxes[:, 1] <= boxes[:, 0]):
        raise ValueError(f"boxes must be (K, 2, 3) with min < max, got shape {boxes.shape}")
    markers = np.zeros((0, 3)) if markers is None else np.asarray(markers, dtype=np.float64)
    marker_faces = marker_faces or []
    seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    # children derived without SeedSequence.spawn (which mutates seq): same seed -> same textures
    hue0 = np.random.default_rng(np.random.SeedSequence(seq.entropy, spawn_key=seq.spawn_key + (1 << 20,))).uniform()
    textures = []
    for face in range(6 * len(boxes)):
        child = np.random.SeedSequence(seq.entropy, spawn_key=seq.spawn_key + (face,))
        _, uax, vax, _, uv0, size = face_frame(boxes, face)
        on_face = [m for m, f in zip(markers, marker_faces) if f == face]
        muv = np.array([[m[uax], m[vax]] for m in on_face]).reshape(-1, 2) - uv0
        hue = hue0 + GOLDEN_HUE_STEP * face  # neighbouring face indices get well separated hues
        if face // 6 in plain_boxes:
            textures.append(_plain_texture(np.random.default_rng(child), size, texel, _face_shade(face), muv))
        else:
            textures.append(_face_texture(np.random.default_rng(child), size, texel, _face_shade(face), hue, muv))
    atlas, offset = _build_atlas(textures)
    return SceneGeometry(boxes=boxes, texel=texel, atlas=atlas, tile_offset=offset,
                         markers=markers, marker_names=list(marker_names or []))
