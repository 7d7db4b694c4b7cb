"""``cosim render``: PNG previews of chosen ticks (no display needed).

- ``contact_<agent>_t<tick>.png``: one row per camera of the agent: RGB with the labelled 3D boxes
  projected onto it, depth, semantic classes, instance ids. A box is drawn (its 12 edges, in its
  class's ``BOX_COLOURS``) when its track id appears in the camera's instance image, so what is drawn is what
  the camera sees; without an instance image every box in front of the camera is drawn. The
  agent's own box is never drawn. Projection: ``/tf`` gives map <- optical frame, the camera's
  ``calibration`` gives K and the lens D (``cosim.geometry.project_to_image``; through a distorting
  lens each edge is drawn as a curve of short pieces); pixel (col, row) covers u in [col, col + 1),
  v in [row, row + 1) (docs/episode_format.md 3.6).

  The sheet is built with numpy and PIL, not as a matplotlib figure (which spent about 2 s a sheet
  resampling full-resolution images and drawing axes): every panel is ``PANEL_IN * dpi`` pixels wide
  (320 at the default 80 dpi, so four panels span the 16 in of the former figure), its height from
  the camera's aspect ratio. RGB and coloured depth are shrunk by area means (PIL's box filter);
  semantic and instance ids are picked at each panel pixel's centre (nearest) before they are
  coloured, so those panels hold exact label colours. Depth is coloured through :data:`DEPTH_CMAP`
  as a 256-entry table (the colours matplotlib gives) over :func:`depth_limits`, white where there
  is no return, with a colour bar of its far, middle and near metres beside each depth panel. Boxes
  are drawn after the RGB image is shrunk, with their full-resolution edges scaled to the panel, 1 px
  thick per 320 px of panel width (:func:`camera_with_boxes` draws the same edges on the full image):
  drawn before, an edge about 1 px wide in the sheet would be averaged with its surroundings into a
  faint smear. Titles, camera names and colour-bar values use PIL's default font, sized in points at
  ``dpi``.
- ``bev_t<tick>.png``: top view of the map frame (matplotlib, Agg backend): the static layout (roads,
  buildings... from the ``world.json`` attachment), every agent, every labelled box, and every agent's
  LiDAR points moved into ``map`` through ``/tf`` (coloured by semantic class when the cloud has a
  ``class_id`` field, else by height).

Pictures are palette-quantised PNGs (256 colours, median cut) so they stay small enough for documentation.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cosim.classes import SEMANTIC_CLASSES, SEMANTIC_COLOURS
from cosim.errors import CosimError
from cosim.geometry import has_distortion, project_to_image, undistort
from cosim.io.reader import Episode, Tick
from cosim.io.validate_boxes import instance_ids

log = logging.getLogger(__name__)

AGENT_STYLE = {"vehicle": ("o", "#1f77b4"), "rsu": ("s", "#d4a000"), "drone": ("^", "#d62728")}
MAX_BEV_POINTS = 60_000  # per plot, subsampled evenly
DEPTH_MAX_M = 120.0
#: Depth colours: bright near, dark far, lightness monotonic (turbo_r, dark red near and dark blue far, made a
#: drone's nadir view of ground 40-60 m away dark at both ends). No return (the sky) is white.
DEPTH_CMAP = "viridis_r"
NEAR_M = 0.1  # [m] box edges are cut where they pass behind this optical z
#: Box outline colours on camera images: bright, so they stand out on roads, sky and at night.
BOX_COLOURS: dict[str, tuple[int, int, int]] = {
    "car": (255, 215, 0),
    "van": (255, 128, 0),
    "truck": (255, 0, 255),
    "bus": (0, 255, 255),
    "motorcycle": (0, 255, 0),
    "bicycle": (255, 48, 48),
    "drone": (255, 255, 255),
    "pedestrian": (255, 0, 128),
    "static_obstacle": (255, 160, 64),
}
#: Corner order of a box: bit 0 = +x (front), bit 1 = +y (left), bit 2 = +z (top), in the box's body frame.
_CORNER_SIGNS = np.array([[(i & 1) * 2 - 1, (i >> 1 & 1) * 2 - 1, (i >> 2 & 1) * 2 - 1] for i in range(8)], float)
#: The 12 edges of a box as corner index pairs.
BOX_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]])
#: Straight pieces each box edge is drawn with through a distorting lens (its image is a curve).
LENS_EDGE_PIECES = 16


def semantic_palette(class_table: dict[str, Any] | None = None) -> np.ndarray:
    """(256, 3) uint8 colour per semantic id, from the episode's class table (or cosim.classes)."""
    pal = np.zeros((256, 3), np.uint8)
    entries = (class_table or {}).get("semantic_classes") or [
        {"id": i, "colour": SEMANTIC_COLOURS[n]} for i, n in enumerate(SEMANTIC_CLASSES)
    ]
    for e in entries:
        if 0 <= int(e["id"]) < 256:
            pal[int(e["id"])] = e["colour"]
    return pal


def colourise_semantic(ids: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """Class ids (H, W) -> RGB (H, W, 3) uint8."""
    return palette[np.clip(ids.astype(np.int64), 0, 255)]


def colourise_instance(ids: np.ndarray) -> np.ndarray:
    """Instance ids (H, W) -> RGB (H, W, 3) uint8: a fixed bright colour per id, black for 0 (no actor)."""
    ids = np.asarray(ids)
    if ids.dtype.kind not in "iub":
        ids = ids.astype(np.uint64)
    # Knuth's multiplicative hash (neighbours differ), low 24 bits: they depend only on the id's low 32 bits
    h = (ids.astype(np.uint32) * np.uint32(2654435761)) & np.uint32(0xFFFFFF)
    rgb = h.astype("<u4").view(np.uint8).reshape(*h.shape, 4)[..., 2::-1] // 2 + 96  # 96..223: never black/white
    rgb[ids == 0] = 0
    return rgb


def box_corners(centers_m: np.ndarray, sizes_m: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Corners (N, 8, 3) [m, map] of boxes: centres (N, 3), sizes (N, 3) = l, w, h, rotations (N, 4) x, y, z, w."""
    from cosim.io.decode import quat_to_matrix

    if len(centers_m) == 0:
        return np.zeros((0, 8, 3))
    rot = np.stack([quat_to_matrix(q) for q in rotations])
    local = _CORNER_SIGNS[None] * (np.asarray(sizes_m, float)[:, None, :] / 2)
    return np.einsum("nij,nkj->nki", rot, local) + np.asarray(centers_m, float)[:, None, :]


def project_box_edges(corners_map: np.ndarray, map_from_optical: np.ndarray, K: np.ndarray, D: Any = None,
                      size_px: tuple[int, int] | None = None) -> np.ndarray:
    """Pixel end points (N, E, 2, 2) [u, v] of the pieces of every box edge (BOX_EDGES), NaN where none.

    An edge crossing the plane optical z = NEAR_M is cut there, so boxes around or beside the camera
    draw only their visible part. ``map_from_optical`` is the 4x4 ``/tf`` chain map <- optical; points
    go through the calibration's ``K`` and lens ``D`` (``cosim.geometry.project_to_image``). On a
    pinhole E = 12, one straight piece per edge; through a distorting lens an edge's image is curved,
    so each edge is cut into :data:`LENS_EDGE_PIECES` pieces (E = 12 x pieces, edge by edge), and with
    ``size_px`` = (width, height) pieces outside the field the image sees are NaN (the lens polynomial
    folds far-off rays back into the picture).
    """
    pieces = LENS_EDGE_PIECES if has_distortion(D) else 1
    if len(corners_map) == 0:
        return np.zeros((0, len(BOX_EDGES) * pieces, 2, 2))
    inv = np.linalg.inv(map_from_optical)
    p = corners_map @ inv[:3, :3].T + inv[:3, 3]  # (N, 8, 3) optical: x right, y down, z forward
    a, b = p[:, BOX_EDGES[:, 0]], p[:, BOX_EDGES[:, 1]]  # (N, 12, 3)
    za, zb = a[..., 2:3], b[..., 2:3]
    dz = zb - za
    t = (NEAR_M - za) / np.where(dz == 0, 1.0, dz)
    cut = a + t * (b - a)  # where the edge meets z = NEAR_M (used only for edges that cross it)
    ends = np.stack([np.where(za < NEAR_M, cut, a), np.where(zb < NEAR_M, cut, b)], axis=2)  # (N, 12, 2, 3)
    ends[(za < NEAR_M)[..., 0] & (zb < NEAR_M)[..., 0]] = np.nan
    f = np.linspace(0.0, 1.0, pieces + 1)[None, None, :, None]
    pts = ends[:, :, :1] + f * (ends[:, :, 1:] - ends[:, :, :1])  # (N, 12, pieces + 1, 3)
    pts[:, :, 0], pts[:, :, -1] = ends[:, :, 0], ends[:, :, 1]
    uv, _ = project_to_image(pts.reshape(-1, 3), K, D)
    if pieces > 1 and size_px is not None:
        r = np.hypot(*(pts[..., :2] / pts[..., 2:3]).reshape(-1, 2).T)
        uv[~(r <= _lens_field_radius(K, D, *size_px))] = np.nan
    uv = uv.reshape(*pts.shape[:3], 2)
    return np.stack([uv[:, :, :-1], uv[:, :, 1:]], axis=3).reshape(len(p), -1, 2, 2)


def _lens_field_radius(K: np.ndarray, D: Any, width: int, height: int) -> float:
    """The largest normalised radius (x / z, y / z) of a ray a distorted image of ``width`` x ``height`` sees,
    with a margin of 10 % so that edges leaving the picture are still drawn to its border."""
    corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]])
    xy_d = (corners - K[:2, 2]) / np.diag(K)[:2]
    return 1.1 * float(np.hypot(*undistort(xy_d, np.asarray(D, np.float64)).T).max())


def _clip_segment(p0: np.ndarray, p1: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Liang-Barsky: the part of p0-p1 inside [0, w) x [0, h), or None."""
    d = p1 - p0
    t0, t1 = 0.0, 1.0
    for pk, qk in ((-d[0], p0[0]), (d[0], w - 1e-6 - p0[0]), (-d[1], p0[1]), (d[1], h - 1e-6 - p0[1])):
        if pk == 0:
            if qk < 0:
                return None
            continue
        r = qk / pk
        if pk < 0:
            t0 = max(t0, r)
        else:
            t1 = min(t1, r)
        if t0 > t1:
            return None
    return p0 + t0 * d, p0 + t1 * d


def draw_segments(rgb: np.ndarray, segments: np.ndarray, colours: np.ndarray, thickness_px: int = 1) -> np.ndarray:
    """A copy of ``rgb`` (H, W, 3) uint8 with line segments (M, 2, 2) [u, v] drawn in ``colours`` (M, 3).

    Every pixel whose square the segment passes through (sampled at least twice per pixel) is painted,
    widened to a ``thickness_px`` square; NaN segments are skipped.
    """
    out = rgb.copy()
    h, w = out.shape[:2]
    lo = -((thickness_px - 1) // 2)
    d_col, d_row = (o.ravel() for o in np.meshgrid(np.arange(lo, lo + thickness_px), np.arange(lo, lo + thickness_px)))
    for seg, colour in zip(segments, colours, strict=True):
        if not np.isfinite(seg).all():
            continue
        clipped = _clip_segment(seg[0], seg[1], w, h)
        if clipped is None:
            continue
        p0, p1 = clipped
        n = int(np.ceil(2 * np.abs(p1 - p0).max())) + 1
        t = np.linspace(0.0, 1.0, n)[:, None]
        px = np.floor(p0 + t * (p1 - p0)).astype(np.int64)
        cols = (px[:, 0, None] + d_col[None, :]).ravel()
        rows = (px[:, 1, None] + d_row[None, :]).ravel()
        keep = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
        out[rows[keep], cols[keep]] = colour
    return out


def _box_segments(ep: Episode, tick: Tick, agent: str, camera: str, width: int,
                  height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The labelled boxes the camera sees (module docstring) as pixel segments (M, 2, 2) [u, v] on its
    ``width`` x ``height`` image (NaN where none) and their colours (M, 3); None when there is nothing to draw."""
    needed = ("/labels/objects", "/tf", f"/{agent}/{camera}/calibration")
    if not all(t in tick for t in needed):
        return None
    labels = tick.labels
    keep = np.array([aid != agent for aid in labels.agent_ids], bool)
    inst_topic = f"/{agent}/{camera}/instance"
    if inst_topic in tick:
        keep &= np.isin(labels.track_ids, instance_ids(tick[inst_topic].array)[0])  # the tracks it sees
    if not keep.any():
        return None
    frame = tick.image(agent, camera).frame_id
    try:
        map_from_optical = tick.transforms.to_root(frame)
    except CosimError as exc:
        log.warning("tick %d: %s; no boxes on %s %s", tick.index, exc, agent, camera)
        return None
    calib = tick.calibration(agent, camera)
    if calib.distorted and calib.distortion_model != "plumb_bob":
        log.warning("tick %d: %s %s has lens model %r; no boxes drawn", tick.index, agent, camera,
                    calib.distortion_model)
        return None
    corners = box_corners(labels.centers_m[keep], labels.sizes_m[keep], labels.rotations[keep])
    edges = project_box_edges(corners, map_from_optical, calib.K, calib.D if calib.distorted else None,
                              (width, height))  # (N, E, 2, 2)
    colours = np.array([BOX_COLOURS.get(labels.classes[i], (255, 255, 255)) for i in np.flatnonzero(keep)])
    return edges.reshape(-1, 2, 2), np.repeat(colours, edges.shape[1], axis=0)


def _rgb(img: np.ndarray) -> np.ndarray:
    return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., :3]


def camera_with_boxes(ep: Episode, tick: Tick, agent: str, camera: str) -> np.ndarray:
    """The camera's RGB image (H, W, 3) uint8 with the labelled boxes it sees drawn (module docstring)."""
    rgb = _rgb(tick.image(agent, camera).array)
    boxes = _box_segments(ep, tick, agent, camera, rgb.shape[1], rgb.shape[0])
    if boxes is None:
        return rgb
    return draw_segments(rgb, *boxes, _box_thickness(rgb.shape[1]))


def _box_thickness(width_px: int) -> int:
    """Box edge thickness [px] on an image ``width_px`` wide: about 1 px per 320 px (1 px in a default sheet)."""
    return max(1, round(width_px / 320))


def depth_limits(depth_m: np.ndarray) -> tuple[float, float]:
    """The depth range [m] a contact sheet's colours span: the image's own nearest to farthest return (1st and
    99th percentile; far capped at ``DEPTH_MAX_M``), so a drone's narrow range of ground depths uses the whole
    colour map instead of its dark end."""
    d = depth_m[np.isfinite(depth_m) & (depth_m > 0)]
    if d.size == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(d, [1, 99]))
    hi = min(hi, DEPTH_MAX_M)
    lo = min(lo, hi - 1.0)
    return max(0.0, lo), max(hi, 1.0)


@functools.cache
def depth_lut() -> np.ndarray:
    """(257, 3) uint8: the 256 colours of :data:`DEPTH_CMAP` (as matplotlib turns it into bytes), then white."""
    import matplotlib

    lut = matplotlib.colormaps[DEPTH_CMAP].resampled(256)(np.arange(256), bytes=True)[:, :3]
    return np.concatenate([lut, [[255, 255, 255]]]).astype(np.uint8)


def colourise_depth(depth_m: np.ndarray, limits: tuple[float, float]) -> np.ndarray:
    """Depth (H, W) [m] -> RGB (H, W, 3) uint8 through :data:`DEPTH_CMAP` from ``limits`` = (near, far) [m],
    values outside clamped to its ends, as matplotlib maps them (``Normalize`` then 256 entries); white where the
    depth is NaN (no return)."""
    lo, hi = limits
    t = np.asarray(depth_m, np.float32) - np.float32(lo)
    t *= np.float32(256.0 / (hi - lo) if hi > lo else 0.0)
    np.clip(t, 0, 255, out=t)
    np.nan_to_num(t, copy=False, nan=256)
    return np.take(depth_lut(), t.astype(np.uint16), axis=0)


def _save_image(im: Any, path: Path, optimize: bool = True) -> Path:
    """Write a PIL image as a palette-quantised PNG (at most 256 colours); ``optimize``: smallest file (zlib level
    9 and more tries: a few % smaller, four times the encoding time), else zlib's default level."""
    from PIL import Image

    q = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    q.save(path, **({"optimize": True} if optimize else {"compress_level": 6}))
    return path


def _save(fig: Any, path: Path, dpi: int) -> Path:
    """Write a matplotlib figure as a palette-quantised PNG (at most 256 colours)."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    buf.seek(0)
    with Image.open(buf) as im:
        return _save_image(im, path)


# ------------------------------------------------------------------------------------------ contact sheets

#: Width of one contact-sheet panel [in]; x ``dpi`` = pixels (4 panels: the 16 in of the former matplotlib figure).
PANEL_IN = 4.0
#: The panels of a camera row: topic kind and column title.
SHEET_COLUMNS = (("image", "RGB + 3D boxes"), ("depth", "depth [m]"), ("semantic", "semantic"),
                 ("instance", "instance"))


@functools.cache
def _font(size_px: int) -> Any:
    from PIL import ImageFont

    return ImageFont.load_default(size=size_px)


def area_resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """RGB (H, W, 3) uint8 resized to ``width`` x ``height``, each output pixel the mean of the input area it
    covers (PIL's box filter), so thin details fade instead of flickering in and out."""
    from PIL import Image

    h, w = rgb.shape[:2]
    if (h, w) == (height, width):
        return rgb
    im = Image.fromarray(np.ascontiguousarray(rgb))
    if w % width == 0 and h % height == 0:  # whole blocks (1280 x 720 into 320 x 180): the same, twice as fast
        return np.asarray(im.reduce((w // width, h // height)))
    return np.asarray(im.resize((width, height), Image.Resampling.BOX))


def nearest_resize(labels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Label image (H, W) resized to ``width`` x ``height`` by picking the input pixel under each output
    pixel's centre: values stay exact labels (no averaging)."""
    h, w = labels.shape[:2]
    rows = np.minimum(((np.arange(height) + 0.5) * (h / height)).astype(np.intp), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * (w / width)).astype(np.intp), w - 1)
    return labels[rows[:, None], cols[None, :]]


def _label_ids(img: Any) -> np.ndarray:
    return img.array if img.array.ndim == 2 else img.array[..., 0]


def _depth_label(metres: float) -> str:
    return f"{metres:.0f} m" if metres >= 10 else f"{metres:.1f} m"


def contact_sheet_image(
    ep: Episode, tick: Tick, agent: str, dpi: int = 80
) -> tuple[Any, dict[tuple[str, str], tuple[int, int, int, int]]] | None:
    """One agent's cameras at one tick as an RGB PIL image (None: no camera), and where its pieces are:
    (camera, kind) -> (x0, y0, x1, y1) pixel box (end exclusive) for kind in ``image``, ``depth``,
    ``semantic``, ``instance`` (:data:`SHEET_COLUMNS`) and ``depth_bar`` (that row's colour bar).

    Built with numpy and PIL, no matplotlib figure (see the module docstring): every panel is
    ``round(PANEL_IN * dpi)`` px wide, its height from the camera's aspect ratio.
    """
    from PIL import Image, ImageDraw

    cams = [c for c in ep.cameras(agent) if f"/{agent}/{c}/image" in tick]
    if not cams:
        return None
    palette = semantic_palette(ep.class_table)
    pw = max(16, round(PANEL_IN * dpi))

    def pt(points: float) -> int:  # a font size [pt] in pixels at this dpi
        return max(6, round(points * dpi / 72))

    f_title, f_label, f_small = _font(pt(11)), _font(pt(10)), _font(pt(8))

    def height(font: Any) -> int:
        _, top, _, bottom = font.getbbox("Ag")
        return bottom - top

    margin, gap = max(4, round(0.1 * dpi)), max(6, round(0.15 * dpi))
    bar_w, bar_gap = max(4, round(0.1 * dpi)), max(2, round(0.05 * dpi))
    label_w = max(f_small.getbbox(s)[2] for s in ("888 m", "8.8 m"))
    xs = [margin + height(f_label) + bar_gap]
    xs.append(xs[0] + pw + gap)
    x_bar = xs[1] + pw + bar_gap
    xs.append(x_bar + bar_w + bar_gap + label_w + gap)
    xs.append(xs[2] + pw + gap)
    width = xs[3] + pw + margin

    rows = []  # (camera, panel height, y)
    y = margin + height(f_title) + gap + height(f_label) + bar_gap
    for cam in cams:
        h, w = tick.image(agent, cam).array.shape[:2]
        ph = max(1, round(pw * h / max(w, 1)))
        rows.append((cam, ph, y))
        y += ph + gap
    sheet = np.full((y - gap + margin, width, 3), 255, np.uint8)
    boxes: dict[tuple[str, str], tuple[int, int, int, int]] = {}
    missing: list[tuple[int, int, int]] = []
    bars: list[tuple[int, int, float, float]] = []  # y, height, near, far
    lut = depth_lut()
    for cam, ph, y in rows:
        for x, (kind, _) in zip(xs, SHEET_COLUMNS, strict=True):
            boxes[cam, kind] = (x, y, x + pw, y + ph)
            topic = f"/{agent}/{cam}/{kind}"
            if topic not in tick:
                missing.append((x, y, ph))
                continue
            if kind == "image":
                raw = tick.image(agent, cam).array
                panel = area_resize(_rgb(raw), pw, ph)
                segments = _box_segments(ep, tick, agent, cam, raw.shape[1], raw.shape[0])
                if segments is not None:  # drawn after downsampling: a crisp edge in its exact colour
                    scale = np.array([pw / raw.shape[1], ph / raw.shape[0]])
                    panel = draw_segments(panel, segments[0] * scale, segments[1], _box_thickness(pw))
            elif kind == "depth":
                d = tick[topic].depth_m
                lim = depth_limits(d)
                panel = area_resize(colourise_depth(d, lim), pw, ph)
                bars.append((y, ph, *lim))
                boxes[cam, "depth_bar"] = (x_bar, y, x_bar + bar_w, y + ph)
                ramp = np.linspace(255, 0, ph).round().astype(np.intp)  # far (dark) at the top, as matplotlib does
                sheet[y : y + ph, x_bar : x_bar + bar_w] = lut[ramp][:, None, :]
            elif kind == "semantic":
                panel = colourise_semantic(nearest_resize(_label_ids(tick[topic]), pw, ph), palette)
            else:
                panel = colourise_instance(nearest_resize(_label_ids(tick[topic]), pw, ph))
            sheet[y : y + ph, x : x + pw] = panel

    im = Image.fromarray(sheet)
    draw = ImageDraw.Draw(im)

    def text(x: float, y: float, s: str, font: Any, align: str = "left") -> None:
        """``s`` with its top (of the font's "Ag") at ``y``, starting at / centred on / ending at ``x``."""
        left, _, right, _ = font.getbbox(s)
        dx = {"left": -left, "centre": -(left + right) / 2, "right": -right}[align]
        draw.text((round(x + dx), y - font.getbbox("Ag")[1]), s, fill=(0, 0, 0), font=font)

    text(width / 2, margin, f"{ep.scenario}  {agent}  tick {tick.index} (t = {tick.t_ns / 1e9:.1f} s)", f_title,
         "centre")
    y_titles = margin + height(f_title) + gap
    for x, (_, title) in zip(xs, SHEET_COLUMNS, strict=True):
        text(x + pw / 2, y_titles, title, f_label, "centre")
    for x, y, ph in missing:
        text(x + pw / 2, y + (ph - height(f_label)) / 2, "not recorded", f_label, "centre")
    for (_, ph, y), x in ((r, x) for r in rows for x in xs):
        draw.rectangle((x - 1, y - 1, x + pw, y + ph), outline=(0, 0, 0))
    for y, ph, near, far in bars:
        draw.rectangle((x_bar - 1, y - 1, x_bar + bar_w, y + ph), outline=(0, 0, 0))
        text(x_bar + bar_w + bar_gap, y, _depth_label(far), f_small)
        if ph >= 4 * height(f_small):  # room for the middle value too
            text(x_bar + bar_w + bar_gap, y + (ph - height(f_small)) / 2, _depth_label((near + far) / 2), f_small)
        text(x_bar + bar_w + bar_gap, y + ph - height(f_small), _depth_label(near), f_small)
    for cam, ph, y in rows:  # the camera's name along the left of its row, read bottom to top
        left, _, right, _ = f_label.getbbox(cam)
        tag = Image.new("RGB", (right - left, height(f_label)), (255, 255, 255))
        ImageDraw.Draw(tag).text((-left, -f_label.getbbox("Ag")[1]), cam, fill=(0, 0, 0), font=f_label)
        tag = tag.rotate(90, expand=True)
        if tag.height > ph:  # a name longer than the row is tall: its start (at the bottom) is kept
            tag = tag.crop((0, tag.height - ph, tag.width, tag.height))
        im.paste(tag, (margin, y + (ph - tag.height) // 2))
    return im, boxes


def contact_sheet(ep: Episode, tick: Tick, agent: str, path: Path, dpi: int = 80) -> Path | None:
    """One agent's cameras at one tick: RGB with boxes | depth | semantic | instance per row (None: no camera),
    written to ``path`` (:func:`contact_sheet_image`)."""
    built = contact_sheet_image(ep, tick, agent, dpi)
    return None if built is None else _save_image(built[0], path, optimize=False)


def _box_corners_xy(center: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    half = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1], [1, 1]]) * (size[:2] / 2)
    return center[:2] + half @ np.array([[c, s], [-s, c]])


def bev_points(ep: Episode, tick: Tick) -> tuple[np.ndarray, np.ndarray | None]:
    """All agents' LiDAR points in map (N, 3) and their class ids (N,) (None when a cloud has none)."""
    xyz_all, cls_all = [], []
    have_cls = True
    tree = tick.transforms if "/tf" in tick else None
    for agent in ep.agents:
        topic = f"/{agent}/lidar"
        if topic not in tick or tree is None:
            continue
        pc = tick[topic]
        if len(pc) == 0:
            continue
        try:
            m = tree.to_root(pc.frame_id)
        except CosimError as exc:
            log.warning("tick %d: %s; %s not drawn", tick.index, exc, topic)
            continue
        xyz_all.append(pc.xyz @ m[:3, :3].T + m[:3, 3])
        if "class_id" in pc.fields:
            cls_all.append(np.asarray(pc.points["class_id"], np.int64))
        else:
            have_cls = False
    if not xyz_all:
        return np.zeros((0, 3)), None
    return np.concatenate(xyz_all), (np.concatenate(cls_all) if have_cls and cls_all else None)


#: Static layout classes drawn under the BEV (terrain would cover everything), in drawing order.
LAYOUT_CLASSES = ("vegetation", "sidewalk", "road", "lane_marking", "building", "pole", "street_light", "rsu")


def layout_polygons(ep: Episode) -> list[tuple[str, np.ndarray]]:
    """Footprints (K, 2) [m, map] of the static layout from the ``world.json`` attachment, by class."""
    import json

    if "world.json" not in ep.attachments:
        return []
    try:
        prisms = json.loads(ep.attachment("world.json")).get("prisms") or []
        out = [(str(p[0]), np.asarray(p[1], dtype=np.float64)) for p in prisms if p[0] in LAYOUT_CLASSES]
    except (ValueError, TypeError, KeyError, IndexError, CosimError) as exc:
        log.warning("world.json not drawn: %s", exc)
        return []
    order = {c: i for i, c in enumerate(LAYOUT_CLASSES)}
    return sorted((o for o in out if o[1].ndim == 2 and len(o[1]) >= 3), key=lambda o: order[o[0]])


#: [pt] where an agent's name starts, right of and above its marker
LABEL_OFFSET_PT = (5.0, 5.0)
#: a light box behind each agent's name: readable over LiDAR points and link lines
_NAME_BACKGROUND = {"boxstyle": "square,pad=0.1", "facecolor": "white", "edgecolor": "none", "alpha": 0.6}


def place_agent_labels(ax: Any, labels: Sequence[tuple[str, float, float]], fontsize: float,
                       zorder: float = 6) -> list[Any]:
    """Name each agent: ``labels`` are (text, x, y) in data coordinates [m, map]. Each name starts at
    :data:`LABEL_OFFSET_PT` from its point; one whose box would overlap a name already placed (agents within a
    few metres of each other at the plot's scale) moves up a line at a time, with a thin leader to its point:
    co-located agents get a readable stack of names, not one smudge. Call it once the axes' limits and layout
    are final (it measures the names as they will be drawn); returns the annotations, in ``labels`` order."""
    renderer = ax.figure.canvas.get_renderer()
    ax.apply_aspect()
    line_pt = 1.25 * fontsize
    placed, out = [], []
    for text, x, y in labels:
        dx, dy = LABEL_OFFSET_PT
        style = {"fontsize": fontsize, "zorder": zorder, "annotation_clip": True, "bbox": _NAME_BACKGROUND}
        ann = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), **style)
        box = _name_box(ann, renderer)
        for _ in range(len(labels)):
            if not any(box.overlaps(b) for b in placed):
                break
            dy += line_pt
            ann.xyann = (dx, dy)
            box = _name_box(ann, renderer)
        if dy > LABEL_OFFSET_PT[1]:  # moved up: drawn again with a leader to its point
            ann.remove()
            ann = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), **style,
                              arrowprops={"arrowstyle": "-", "lw": 0.7, "color": "0.2", "shrinkA": 0, "shrinkB": 2})
        placed.append(box)
        out.append(ann)
    return out


def _name_box(ann: Any, renderer: Any) -> Any:
    """Display box of an annotation's text alone (its own box also holds its leader), where it will be drawn."""
    from matplotlib.text import Text

    ann.update_positions(renderer)
    return Text.get_window_extent(ann, renderer)


def bev_plot(
    ep: Episode, tick: Tick, path: Path, dpi: int = 80, layout: list[tuple[str, np.ndarray]] | None = None,
    window_m: tuple[float, float, float] | None = None,
) -> Path:
    """Top view of one tick (see the module docstring); ``layout`` from :func:`layout_polygons`;
    ``window_m`` (centre x, y, half width [m]) zooms onto a square of the map instead of fitting the data."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection
    from matplotlib.lines import Line2D

    palette = semantic_palette(ep.class_table)
    fig, ax = plt.subplots(figsize=(10, 10))
    if layout:
        colours = np.array([SEMANTIC_COLOURS.get(c, (200, 200, 200)) for c, _ in layout]) / 255.0
        ax.add_collection(
            PolyCollection([p for _, p in layout], facecolors=colours, edgecolors="none", alpha=0.35, zorder=0)
        )
    xyz, cls = bev_points(ep, tick)
    if len(xyz):
        step = max(1, len(xyz) // MAX_BEV_POINTS)
        p = xyz[::step]
        dot = float(np.clip(20_000 / len(p), 0.3, 4.0))  # [pt^2] bigger dots for sparse clouds
        if cls is not None:
            colours = palette[np.clip(cls[::step], 0, 255)] / 255.0
            ax.scatter(p[:, 0], p[:, 1], s=dot, c=colours, linewidths=0, rasterized=True)
        else:
            ax.scatter(p[:, 0], p[:, 1], s=dot, c=p[:, 2], cmap="viridis", linewidths=0, rasterized=True)
    extent = [xyz[:, :2]]
    names: list[tuple[str, float, float]] = []  # agent id, map x, y [m]: named once the layout is final
    if "/labels/objects" in tick:
        labels = tick.labels
        segments, colours, widths = [], [], []  # one collection for every box (one draw call, not two per box)
        for center, size, yaw, name in zip(
            labels.centers_m, labels.sizes_m, labels.yaws_rad, labels.classes, strict=True
        ):
            colour = np.array(SEMANTIC_COLOURS.get(name, (0, 0, 0))) / 255.0
            corners = _box_corners_xy(center, size, yaw)
            segments += [corners, np.array([center[:2], (corners[0] + corners[1]) / 2])]  # outline, heading
            colours += [colour, colour]
            widths += [1.2, 0.8]
        if segments:
            ax.add_collection(LineCollection(segments, colors=np.array(colours), linewidths=widths, zorder=2))
        extent.append(labels.centers_m[:, :2])
        by_kind: dict[str, list[tuple[float, float]]] = {}
        for a in labels.agents:
            x, y = a["position_m"][0], a["position_m"][1]
            by_kind.setdefault(a.get("kind", "vehicle"), []).append((x, y))
            names.append((a["agent_id"], x, y))
        for kind, xy in by_kind.items():
            marker, colour = AGENT_STYLE.get(kind, ("x", "k"))
            pos = np.array(xy, float)
            ax.scatter(pos[:, 0], pos[:, 1], marker=marker, s=60, c=colour, edgecolors="k", zorder=5)
            extent.append(pos)
    if window_m is not None:
        ax.set_xlim(window_m[0] - window_m[2], window_m[0] + window_m[2])
        ax.set_ylim(window_m[1] - window_m[2], window_m[1] + window_m[2])
    elif len(e := np.concatenate(extent)):
        lo, hi = np.percentile(e, 1, axis=0) - 20, np.percentile(e, 99, axis=0) + 20
        centre, half = (lo + hi) / 2, max(hi - lo) / 2
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal")
    ax.set_xlabel("map x (east) [m]")
    ax.set_ylabel("map y (north) [m]")
    handles = [Line2D([], [], marker=m, color=c, ls="", label=k) for k, (m, c) in AGENT_STYLE.items()]
    ax.legend(handles=handles, loc="upper right", fontsize=8)
    n_boxes = len(tick.labels) if "/labels/objects" in tick else 0
    ax.set_title(
        f"{ep.scenario}  tick {tick.index} (t = {tick.t_ns / 1e9:.1f} s): {n_boxes} boxes, {len(xyz)} LiDAR points"
    )
    ax.grid(alpha=0.3)
    fig.tight_layout()
    place_agent_labels(ax, names, fontsize=8)
    out = _save(fig, path, dpi)
    plt.close(fig)
    return out


def render_episode(
    ep: Episode, out_dir: Path, ticks: Sequence[int], agents: Sequence[str] | None = None, dpi: int = 80
) -> list[Path]:
    """Contact sheets of ``agents`` (default all with cameras) and a BEV plot for each tick; returns the files."""
    import matplotlib

    matplotlib.use("Agg")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    agents = list(agents) if agents else ep.agents
    written: list[Path] = []
    layout = layout_polygons(ep)
    wanted = ["/tf", "/labels/objects", *[f"/{a}/lidar" for a in ep.agents]]
    for a in agents:
        kinds = ("image", "depth", "semantic", "instance", "calibration")
        wanted += [f"/{a}/{c}/{k}" for c in ep.cameras(a) for k in kinds]
    wanted = [t for t in wanted if t in ep.topics]
    for k in ticks:
        tick = ep.tick(k, topics=wanted)
        for a in agents:
            sheet = contact_sheet(ep, tick, a, out_dir / f"contact_{a}_t{k:04d}.png", dpi)
            if sheet is not None:
                written.append(sheet)
        written.append(bev_plot(ep, tick, out_dir / f"bev_t{k:04d}.png", dpi, layout))
    return written
