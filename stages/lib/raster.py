"""A small RGB raster over a map window, written as PNG with the standard library (no matplotlib here).

``MapRaster``: x east, y north, ``resolution_m`` metres per pixel; metres to
pixels, an even-odd scanline polygon fill, and ``write_png``. The
evaluation's figures and ``bench/plot_frame.py`` draw on it.
"""

from __future__ import annotations

import math
import struct
import zlib
from pathlib import Path

import numpy as np


class MapRaster:
    """An RGB image (``rgb``, white) over the map window [x_min, x_max] × [y_min, y_max]."""

    def __init__(self, x_min_m: float, y_min_m: float, x_max_m: float, y_max_m: float, resolution_m: float) -> None:
        self.x0, self.y1, self.res = x_min_m, y_max_m, resolution_m
        self.width = max(int(math.ceil((x_max_m - x_min_m) / resolution_m)), 1)
        self.height = max(int(math.ceil((y_max_m - y_min_m) / resolution_m)), 1)
        self.rgb = np.full((self.height, self.width, 3), 255, dtype=np.uint8)

    def to_px(self, points_m) -> np.ndarray:
        """(n, 2) map points in metres → (n, 2) pixel coordinates (column, row), rows downwards."""
        p = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
        return np.column_stack([(p[:, 0] - self.x0) / self.res, (self.y1 - p[:, 1]) / self.res])

    def fill_polygon(self, points_m, colour) -> None:
        """Even-odd scanline fill of a polygon (n, 2) in metres."""
        px = self.to_px(points_m)
        a, b = px, np.roll(px, -1, axis=0)
        for row in range(max(0, int(px[:, 1].min())), min(self.height, int(px[:, 1].max()) + 1)):
            yc = row + 0.5
            straddle = (a[:, 1] > yc) != (b[:, 1] > yc)
            if not straddle.any():
                continue
            aa, bb = a[straddle], b[straddle]
            xs = np.sort(aa[:, 0] + (yc - aa[:, 1]) * (bb[:, 0] - aa[:, 0]) / (bb[:, 1] - aa[:, 1]))
            for x_start, x_end in zip(xs[0::2], xs[1::2]):
                c0, c1 = max(0, int(math.ceil(x_start - 0.5))), min(self.width, int(math.floor(x_end - 0.5)) + 1)
                if c1 > c0:
                    self.rgb[row, c0:c1] = colour

    def write_png(self, path: Path) -> None:
        write_png(path, self.rgb)


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An 8-bit RGB PNG (filter 0 on every row)."""
    height, width, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[row].tobytes() for row in range(height))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
