"""PNG bytes and colour maps, without Pillow or matplotlib: what the pictures (``graphslam.viz``)
and the service's heatmaps (``graphslam.service``) write."""

from __future__ import annotations

from typing import Mapping

import numpy as np
from numpy.typing import NDArray

PNG_COMPRESS_LEVEL = 1  # zlib level 1: much faster than 6 on these pictures, files ~25 % bigger

# colour maps sampled at 0, 1/8, ..., 1 (matplotlib's viridis and magma, reversed for densities)
VIRIDIS = np.array([[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
                    [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]], float)
MAGMA_R = np.array([[252, 253, 191], [254, 202, 141], [253, 150, 104], [241, 96, 93], [205, 64, 113],
                    [158, 47, 127], [114, 31, 129], [68, 15, 118], [0, 0, 4]], float)
# matplotlib's RdYlGn reversed: green small (errors), red large
RDYLGN_R = np.array([[0, 104, 55], [45, 161, 85], [135, 203, 103], [205, 234, 131], [255, 254, 190],
                     [254, 210, 127], [248, 140, 81], [221, 61, 45], [165, 0, 38]], float)


def colour_map(values: NDArray, lo: float, hi: float, table: NDArray = VIRIDIS) -> NDArray[np.uint8]:
    """RGB (..., 3) of ``values`` on the colour map ``table`` from ``lo`` to ``hi`` (clipped)."""
    u = np.clip((np.asarray(values, float) - lo) / max(hi - lo, 1e-12), 0.0, 1.0) * (len(table) - 1)
    k = np.minimum(u.astype(int), len(table) - 2)
    f = (u - k)[..., None]
    return np.round(table[k] * (1 - f) + table[k + 1] * f).astype(np.uint8)


def png_bytes(rgb: NDArray[np.uint8], level: int = PNG_COMPRESS_LEVEL, text: Mapping[str, str] | None = None) -> bytes:
    """An 8-bit RGB PNG of ``rgb`` (H, W, 3), every row with filter type 0 (none); ``text``: one
    tEXt chunk per item (what Pillow reads back as ``Image.text``).

    Pillow's encoder tries its adaptive row filters and costs several plain zlib passes on these
    mostly white pictures for about the same size:
    the format is simple enough to write directly (PNG spec: signature, IHDR, IDAT, IEND).
    """
    import struct
    import zlib

    h, w = rgb.shape[:2]
    rows = np.empty((h, 1 + 3 * w), np.uint8)
    rows[:, 0] = 0  # filter type: none
    rows[:, 1:] = np.ascontiguousarray(rgb[..., :3], np.uint8).reshape(h, 3 * w)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8 bits, colour type 2 (RGB), no interlace
    def note(k: str, v: str) -> bytes:
        try:
            return chunk(b"tEXt", k.encode("ascii") + b"\0" + v.encode("latin-1"))
        except UnicodeEncodeError:  # (a BSSID, a frame name) beyond Latin-1: the UTF-8 text chunk
            return chunk(b"iTXt", k.encode("ascii") + b"\0\0\0\0\0" + v.encode("utf-8"))

    notes = b"".join(note(k, v) for k, v in (text or {}).items())
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + notes + chunk(b"IDAT", zlib.compress(rows.tobytes(), level))
            + chunk(b"IEND", b""))
