"""A small map renderer on Pillow, for the pictures a command writes as it runs (survey.png,
radio_map.png, track.png, positions.png) and the service's heatmaps (``graphslam.io.heatmap``:
here in io, below both the service and viz, so that both draw with it).

Why not matplotlib: importing it and drawing the 5-walk paper survey cost more than "a few
percent" of a survey; Pillow imports several times faster and
draws a walk as one C call; faint WiFi edges are rasterised with numpy
(``Panel.faint_segments``: sample points along every segment, count them per pixel,
blend), and the PNG is written directly (``png_bytes``).

Layout: a ``Picture`` (the PNG: white, exact pixel size, title lines, legend column) holds
``Panel``s (a plot box in metres at equal scale, with a frame, metre ticks, a light grid
and a scale bar). Panel drawing happens on the panel's own image, so it is clipped to the
box; ``Picture.save`` pastes the panels and writes the PNG atomically.
"""

from __future__ import annotations

import functools
import importlib.util
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.errors import InputError
from graphslam.io.atomic import atomic_open
# re-exported: the pictures' colour maps and PNG writer
from graphslam.io.floor_plan import FloorPlan
from graphslam.io.png import MAGMA_R, PNG_COMPRESS_LEVEL, RDYLGN_R, VIRIDIS, colour_map, png_bytes  # noqa: F401

Colour = tuple[int, int, int]
BLACK: Colour = (0, 0, 0)
GREY: Colour = (120, 120, 120)
GRID: Colour = (232, 232, 232)


@functools.lru_cache(maxsize=16)
def font(size: int) -> Any:
    """DejaVu Sans (shipped with matplotlib, found without importing it: the figures' font, with
    the glyphs Pillow's own font lacks, e.g. ² and γ); else Pillow's own font."""
    from PIL import ImageFont

    spec = importlib.util.find_spec("matplotlib")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        path = Path(folder) / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf"
        if path.exists():
            try:
                return ImageFont.truetype(str(path), size)
            except OSError:  # pragma: no cover - Pillow without FreeType
                break
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # pragma: no cover - Pillow < 10.1 or no FreeType
        return ImageFont.load_default()


def nice_step(span: float, n: float, *, at_most: bool = False) -> float:
    """1, 2 or 5 times a power of ten: the smallest at least ``span / n`` (``at_most``: the
    largest at most ``span / n``)."""
    if not (span > 0 and math.isfinite(span)):
        return 1.0
    target = span / n
    p = 10.0 ** math.floor(math.log10(target))
    if at_most:
        return max(m * p for m in (1.0, 2.0, 5.0) if m * p <= target * 1.001)
    return min(m * p for m in (1.0, 2.0, 5.0, 10.0) if m * p >= target * 0.999)


@dataclass
class LegendEntry:
    text: str
    colour: Colour = BLACK
    kind: str = "line"  # line | dashed | point | ring | cross | star | diamond | square | box | text
    width: int = 3


class Panel:
    """A plot box at ``box`` (x0, y0, x1, y1 pixels of the picture) showing ``bounds`` (x0, y0, x1,
    y1 metres), widened to the box's aspect so that a metre is as long across as up."""

    def __init__(
        self, box: tuple[int, int, int, int], bounds: Sequence[float], margin: float = 0.04, pad_m: float = 0.5
    ) -> None:
        from PIL import Image, ImageDraw

        self.box = box
        w, h = box[2] - box[0], box[3] - box[1]
        lo = np.array(bounds[:2], float)
        hi = np.array(bounds[2:], float)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            lo, hi = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
        span = float(max(hi - lo)) or 1.0
        half = (hi - lo) / 2.0 + margin * span + pad_m
        centre = (lo + hi) / 2.0
        scale = min(w / (2 * half[0]), h / (2 * half[1]))  # px per metre
        self.scale = scale
        self.lo = centre - np.array([w, h]) / (2 * scale)
        self.hi = centre + np.array([w, h]) / (2 * scale)
        self.image = Image.new("RGB", (w, h), (255, 255, 255))
        self.draw = ImageDraw.Draw(self.image)
        self._grid()

    # ---- coordinates --------------------------------------------------------------------

    def px(self, xy: NDArray) -> NDArray[np.float64]:
        """Metres (N, 2) -> pixel coordinates of the panel image (y down)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        return np.column_stack([(xy[:, 0] - self.lo[0]) * self.scale, (self.hi[1] - xy[:, 1]) * self.scale])

    # ---- layers -------------------------------------------------------------------------

    def raster(self, rgba: NDArray[np.uint8], extent: Sequence[float], smooth: bool = False) -> None:
        """An RGBA image (rows from the top) covering ``extent`` (x0, x1, y0, y1 metres), alpha-blended.
        Only its part inside the panel is resized (a floor plan seen through a small survey's window)."""
        from PIL import Image

        x0, x1, y0, y1 = (float(v) for v in extent)
        rows, cols = rgba.shape[:2]
        # the source columns / rows in view, one pixel of margin
        c0 = max(0, math.floor((self.lo[0] - x0) / (x1 - x0) * cols) - 1)
        c1 = min(cols, math.ceil((self.hi[0] - x0) / (x1 - x0) * cols) + 1)
        r0 = max(0, math.floor((y1 - self.hi[1]) / (y1 - y0) * rows) - 1)
        r1 = min(rows, math.ceil((y1 - self.lo[1]) / (y1 - y0) * rows) + 1)
        if c1 <= c0 or r1 <= r0:
            return  # entirely outside the panel
        sx0, sx1 = x0 + c0 / cols * (x1 - x0), x0 + c1 / cols * (x1 - x0)
        sy0, sy1 = y1 - r1 / rows * (y1 - y0), y1 - r0 / rows * (y1 - y0)
        (a, b), (c, d) = self.px(np.array([[sx0, sy1], [sx1, sy0]]))  # top-left, bottom-right
        w, h = max(1, round(c - a)), max(1, round(d - b))
        if w * h > 64 * self.image.width * self.image.height:
            return  # a source pixel far bigger than the panel (a degenerate image): nothing to show
        im = Image.fromarray(np.ascontiguousarray(rgba[r0:r1, c0:c1]), "RGBA").resize(
            (w, h), Image.BILINEAR if smooth else Image.NEAREST)
        self.image.paste(im, (round(a), round(b)), im)

    def floor_plan(self, plan: FloorPlan, opacity: float = 0.85) -> None:
        """The plan image over x in [0, W], y in [0, H] of the frame drawn (top row at y = H)."""
        from PIL import Image

        try:
            with Image.open(plan.path) as im:
                rgba = np.asarray(im.convert("RGBA")).copy()
        except Exception as e:  # Pillow raises many types for a damaged image
            raise InputError(plan.path, f"cannot read the floor plan image ({e})") from None
        rgba[..., 3] = (rgba[..., 3].astype(float) * opacity).astype(np.uint8)
        self.raster(rgba, (0.0, plan.width_m, 0.0, plan.height_m), smooth=True)

    def faint_segments(self, seg: NDArray, colour: Colour, alpha: float = 0.25, max_samples: int = 3_000_000) -> None:
        """Segments (E, 2, 2) metres, 1 px wide, each covering pixel blended at ``alpha`` (more where
        they pile up). Vectorised: samples every pixel along every segment, no per-segment call."""
        seg = np.asarray(seg, float).reshape(-1, 2, 2)
        if not len(seg):
            return
        p = self.px(seg.reshape(-1, 2)).reshape(-1, 2, 2)
        n = np.ceil(np.abs(p[:, 1] - p[:, 0]).max(axis=1)).astype(np.int64) + 1
        n = np.minimum(n, 4 * max(self.image.size))  # a segment far outside the box: bounded
        if n.sum() > max_samples:  # a huge survey: thin the samples, not the segments
            n = np.maximum(1, (n * (max_samples / n.sum())).astype(np.int64))
        owner = np.repeat(np.arange(len(p)), n)
        start = np.repeat(np.cumsum(n) - n, n)
        t = (np.arange(len(owner)) - start) / np.maximum(n[owner] - 1, 1)
        xy = p[owner, 0] + (p[owner, 1] - p[owner, 0]) * t[:, None]
        w, h = self.image.size
        ij = np.round(xy).astype(np.int64)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        hits = np.bincount(ij[ok, 1] * w + ij[ok, 0], minlength=w * h)
        idx = np.flatnonzero(hits)  # blend only the pixels touched
        cover = 1.0 - (1.0 - alpha) ** np.minimum(hits[idx], 20)
        img = np.array(self.image)  # (h, w, 3) uint8, a copy
        flat = img.reshape(-1, 3)
        v = flat[idx].astype(float)
        flat[idx] = np.round(v + (np.array(colour, float) - v) * cover[:, None]).astype(np.uint8)
        self._replace(img)

    def dots(self, xy: NDArray, colour: Colour, size: int = 2) -> None:
        """Square dots of ``size`` px at ``xy`` (metres), set directly: 100,000 cost milliseconds."""
        w, h = self.image.size
        ij = np.floor(self.px(xy)).astype(np.int64)
        ij = ij[(ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)]
        img = np.array(self.image)
        for dx in range(size):
            for dy in range(size):
                img[np.minimum(ij[:, 1] + dy, h - 1), np.minimum(ij[:, 0] + dx, w - 1)] = colour
        self._replace(img)

    def polylines(self, lines: Sequence[NDArray], colours: Sequence[Colour], width: int = 2) -> None:
        """One polyline per item (metres), in order: later ones on top."""
        for xy, c in zip(lines, colours):
            xy = np.asarray(xy, float).reshape(-1, 2)
            xy = xy[np.isfinite(xy).all(axis=1)]
            if len(xy) > 1:
                self.draw.line(self.px(xy).ravel().tolist(), fill=tuple(c), width=width, joint="curve")

    def dashed(self, xy: NDArray, colour: Colour, width: int = 1, dash_px: float = 6.0) -> None:
        """A polyline drawn as dashes of ``dash_px`` (on and off)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        xy = xy[np.isfinite(xy).all(axis=1)]
        if len(xy) < 2:
            return
        p = self.px(xy)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        if s[-1] <= 0:
            return
        marks = np.arange(0.0, s[-1], dash_px)
        q = np.column_stack([np.interp(marks, s, p[:, 0]), np.interp(marks, s, p[:, 1])])
        for k in range(0, len(q) - 1, 2):
            self.draw.line([tuple(q[k]), tuple(q[k + 1])], fill=tuple(colour), width=width)

    def points(self, xy: NDArray, colours: Colour | Sequence[Colour], radius: float = 2.0, kind: str = "point",
               outline: Colour | None = None) -> None:
        """Markers at ``xy``: ``point`` (disc), ``ring``, ``cross``, ``star``, ``diamond`` or ``square``
        (filled, outlined in ``outline``, default white)."""
        p = self.px(xy)
        one = np.ndim(colours) == 1  # one colour for all, else one per point
        cs = [tuple(int(v) for v in colours)] * len(p) if one else [tuple(int(v) for v in c) for c in colours]
        for (x, y), c in zip(p.tolist(), cs):
            if kind == "cross":
                self.draw.line([(x - radius, y - radius), (x + radius, y + radius)], fill=c, width=2)
                self.draw.line([(x - radius, y + radius), (x + radius, y - radius)], fill=c, width=2)
            elif kind == "star":
                self.draw.polygon(_star(x, y, radius), fill=c, outline=outline or (255, 255, 255))
            elif kind == "ring":
                self.draw.ellipse([x - radius, y - radius, x + radius, y + radius], outline=c, width=2)
            elif kind == "diamond":
                self.draw.polygon([(x, y - radius), (x + radius, y), (x, y + radius), (x - radius, y)], fill=c,
                                  outline=outline or (255, 255, 255))
            elif kind == "square":
                self.draw.rectangle([x - radius, y - radius, x + radius, y + radius], fill=c,
                                    outline=outline or (255, 255, 255))
            else:
                self.draw.ellipse([x - radius, y - radius, x + radius, y + radius], fill=c, outline=outline)

    def scale_bar(self) -> float:
        """A bar of a round length, lower left; returns the length (m)."""
        w, h = self.image.size
        length = nice_step(self.hi[0] - self.lo[0], 5.0, at_most=True)  # a round fifth of the width
        px_len = length * self.scale
        x0, y0 = 14, h - 22
        self.draw.rectangle([x0 - 8, y0 - 20, x0 + px_len + 8, y0 + 10], fill=(255, 255, 255), outline=(160, 160, 160))
        self.draw.line([(x0, y0), (x0 + px_len, y0)], fill=BLACK, width=3)
        for x in (x0, x0 + px_len):
            self.draw.line([(x, y0 - 5), (x, y0 + 5)], fill=BLACK, width=2)
        label = f"{length:g} m" if length >= 1 else f"{length * 100:g} cm"
        f = font(12)
        self.draw.text((x0 + px_len / 2 - f.getlength(label) / 2, y0 - 19), label, fill=BLACK, font=f)
        return length

    # ---- internals ----------------------------------------------------------------------

    def _replace(self, img: NDArray) -> None:
        from PIL import Image, ImageDraw

        self.image = Image.fromarray(img, "RGB")
        self.draw = ImageDraw.Draw(self.image)

    def _grid(self) -> None:
        step = nice_step(float(max(self.hi - self.lo)), 8.0)
        self.ticks = []
        for axis in (0, 1):
            v = math.ceil(self.lo[axis] / step) * step
            while v <= self.hi[axis]:
                self.ticks.append((axis, v))
                v += step
        w, h = self.image.size
        for axis, v in self.ticks:
            if axis == 0:
                x = (v - self.lo[0]) * self.scale
                self.draw.line([(x, 0), (x, h)], fill=GRID, width=1)
            else:
                y = (self.hi[1] - v) * self.scale
                self.draw.line([(0, y), (w, y)], fill=GRID, width=1)


@dataclass
class Picture:
    """The PNG: ``size`` pixels, panels, title lines on top, a legend column on the right."""

    size: tuple[int, int]
    panels: list[Panel] = field(default_factory=list)
    title_lines: list[str] = field(default_factory=list)
    legend: list[LegendEntry] = field(default_factory=list)
    legend_x: int = 0  # left edge of the legend column (0: no legend)
    colourbars: list[tuple[tuple[int, int, int, int], NDArray, float, float, str]] = field(default_factory=list)
    captions: list[tuple[tuple[int, int], str, int]] = field(default_factory=list)
    frame: str = ""  # the frame the panels are drawn in (report.json's name), written as a text chunk
    scale_bars: list[tuple[tuple[int, int], float, float]] = field(default_factory=list)  # outside the panels

    def panel(
        self, box: tuple[int, int, int, int], bounds: Sequence[float], *, tick_labels: bool = True, tight: bool = False
    ) -> Panel:
        """A panel at ``box``; ``tick_labels``: metre labels beside the frame (off: the grid alone);
        ``tight``: ``bounds`` fill the box with no margin (a box of their aspect shows exactly them)."""
        p = Panel(box, bounds, margin=0.0, pad_m=0.0) if tight else Panel(box, bounds)
        if not tick_labels:
            p.ticks = []
        self.panels.append(p)
        return p

    def colourbar(self, box: tuple[int, int, int, int], table: NDArray, lo: float, hi: float, label: str) -> None:
        self.colourbars.append((box, table, lo, hi, label))

    def caption(self, xy: tuple[int, int], text: str, size: int = 12) -> None:
        self.captions.append((xy, text, size))

    def scale_bar(self, panel: Panel, xy: tuple[int, int]) -> float:
        """A scale bar of ``panel``'s metres drawn outside it, its left end at ``xy`` (picture pixels):
        a bar that hides none of the panel. Returns its length (m)."""
        length = nice_step(panel.hi[0] - panel.lo[0], 5.0, at_most=True)
        self.scale_bars.append((xy, length, length * panel.scale))
        return length

    def render(self) -> Any:
        """The picture as a Pillow RGB image."""
        from PIL import Image, ImageDraw

        im = Image.new("RGB", self.size, (255, 255, 255))
        d = ImageDraw.Draw(im)
        f_title, f_tick, f_leg = font(15), font(11), font(12)
        y = 8
        for line in self.title_lines:
            d.text((16, y), line, fill=BLACK, font=f_title)
            y += 20
        for p in self.panels:
            im.paste(p.image, p.box[:2])
            x0, y0, x1, y1 = p.box
            d.rectangle([x0 - 1, y0 - 1, x1, y1], outline=BLACK, width=1)
            for axis, v in p.ticks:
                label = f"{v:g}"
                if axis == 0:
                    x = x0 + (v - p.lo[0]) * p.scale
                    d.line([(x, y1), (x, y1 + 4)], fill=BLACK)
                    d.text((x - f_tick.getlength(label) / 2, y1 + 5), label, fill=BLACK, font=f_tick)
                else:
                    yy = y0 + (p.hi[1] - v) * p.scale
                    d.line([(x0 - 4, yy), (x0, yy)], fill=BLACK)
                    d.text((x0 - 6 - f_tick.getlength(label), yy - 7), label, fill=BLACK, font=f_tick)
        for (x0, y0, x1, y1), table, lo, hi, label in self.colourbars:
            ramp = colour_map(np.linspace(hi, lo, max(2, y1 - y0))[:, None].repeat(x1 - x0, axis=1), lo, hi, table)
            im.paste(Image.fromarray(ramp, "RGB"), (x0, y0))
            d.rectangle([x0, y0, x1, y1], outline=BLACK)
            step = nice_step(hi - lo, 5.0)
            for v in np.arange(math.ceil(lo / step) * step, hi + 1e-9 * step, step):
                yy = y1 - (v - lo) / (hi - lo) * (y1 - y0)
                d.line([(x1, yy), (x1 + 4, yy)], fill=BLACK)
                d.text((x1 + 6, yy - 7), f"{v:g}", fill=BLACK, font=f_tick)
            d.text((x0, y1 + 4), label, fill=BLACK, font=f_tick)
        for (x, yy), text, size in self.captions:
            d.multiline_text((x, yy), text, fill=BLACK, font=font(size), spacing=2)
        for (x, yy), length, px_len in self.scale_bars:
            d.line([(x, yy), (x + px_len, yy)], fill=BLACK, width=3)
            for xx in (x, x + px_len):
                d.line([(xx, yy - 5), (xx, yy + 5)], fill=BLACK, width=2)
            label = f"{length:g} m" if length >= 1 else f"{length * 100:g} cm"
            d.text((x + px_len + 8, yy - 8), label, fill=BLACK, font=f_leg)
        if self.legend and self.legend_x:
            self._legend(d, f_leg)
        return im

    def png(self, text: Mapping[str, str] | None = None) -> bytes:
        """The rendered PNG's bytes; ``text``: tEXt chunks (ASCII keyword -> text), e.g. how the
        picture was drawn. The title and the frame are chunks too (``Title``, ``frame``): what the
        picture says, readable without looking."""
        meta = {"Title": " ".join(self.title_lines)} if self.title_lines else {}
        if self.frame:
            meta["frame"] = self.frame
        return png_bytes(np.asarray(self.render()), text={**meta, **(text or {})})

    def save(self, path: str | Path, text: Mapping[str, str] | None = None) -> Path:
        """Render and write the PNG (``png``) atomically: complete or absent."""
        data = self.png(text)
        with atomic_open(path, "wb") as fh:
            fh.write(data)
        return Path(path)

    def _legend(self, d: Any, f: Any) -> None:
        x, y = self.legend_x, self.panels[0].box[1] if self.panels else 40
        width = self.size[0] - x - 12
        for e in self.legend:
            lines = wrap(e.text, f, width - 40)
            cy = y + 8
            if e.kind in ("line", "dashed"):
                if e.kind == "line":
                    d.line([(x, cy), (x + 28, cy)], fill=e.colour, width=e.width)
                else:
                    for a in range(x, x + 28, 8):
                        d.line([(a, cy), (a + 4, cy)], fill=e.colour, width=e.width)
            elif e.kind == "point":
                d.ellipse([x + 10, cy - 4, x + 18, cy + 4], fill=e.colour)
            elif e.kind == "ring":
                d.ellipse([x + 8, cy - 6, x + 20, cy + 6], outline=e.colour, width=2)
            elif e.kind == "cross":
                d.line([(x + 9, cy - 5), (x + 19, cy + 5)], fill=e.colour, width=2)
                d.line([(x + 9, cy + 5), (x + 19, cy - 5)], fill=e.colour, width=2)
            elif e.kind == "star":
                d.polygon(_star(x + 14, cy, 8), fill=e.colour)
            elif e.kind == "diamond":
                d.polygon([(x + 14, cy - 8), (x + 22, cy), (x + 14, cy + 8), (x + 6, cy)], fill=e.colour)
            elif e.kind == "square":
                d.rectangle([x + 8, cy - 6, x + 20, cy + 6], fill=e.colour)
            elif e.kind == "box":
                d.rectangle([x + 6, cy - 6, x + 22, cy + 6], fill=e.colour, outline=GREY)
            tx = x if e.kind == "text" else x + 36
            for k, line in enumerate(lines):
                d.text((tx, y + 1 + 16 * k), line, fill=BLACK, font=f)
            y += 16 * len(lines) + 5
            if y > self.size[1] - 20:
                d.text((x, y), "... (more in report.json)", fill=GREY, font=f)
                break


def wrap(text: str, f: Any, width_px: float) -> list[str]:
    """``text`` split into lines of at most ``width_px`` (at spaces; newlines kept)."""
    out: list[str] = []
    for para in text.split("\n"):
        line = ""
        for word in para.split(" "):
            cand = f"{line} {word}" if line else word
            if line and f.getlength(cand) > width_px:
                out.append(line)
                line = "   " + word
            else:
                line = cand
        out.append(line)
    return out


def _star(x: float, y: float, r: float) -> list[tuple[float, float]]:
    a = np.pi / 2 + np.arange(10) * np.pi / 5
    rr = np.where(np.arange(10) % 2 == 0, r, r * 0.45)
    return list(zip((x + rr * np.cos(a)).tolist(), (y - rr * np.sin(a)).tolist()))


def bounds_of(*arrays: NDArray | None) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of the finite points of ``arrays`` (each (N, 2)); a unit box if none."""
    pts = [np.asarray(a, float).reshape(-1, 2) for a in arrays if a is not None and len(a)]
    xy = np.concatenate(pts) if pts else np.zeros((0, 2))
    xy = xy[np.isfinite(xy).all(axis=1)]
    if not len(xy):
        return (-1.0, -1.0, 1.0, 1.0)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
