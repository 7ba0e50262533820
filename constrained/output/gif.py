"""Frames to a GIF quickly: one palette for the whole animation, frames mapped through a table.

A median-cut quantization per frame (Pillow's ``quantize``) costs ~35 ms for a 640 × 600
frame, most of an animation's writing time. Here the palette is chosen once, from a few
frames drawn first (``palette_from``), and every frame is mapped to it by a lookup table over
the 15-bit colours (``PaletteMap``: 32768 entries, the nearest palette colour of each), a few
milliseconds of NumPy per frame; Pillow then only writes the indexed frames.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from ..run.trajectory import file_mode

#: Colours of the GIF palette (one index is left for Pillow's transparency handling).
PALETTE_COLOURS = 255


def palette_from(frames: list[np.ndarray], exact: int = 96) -> np.ndarray:
    """(K, 3) uint8: a palette for the given (H, W, 3) uint8 frames together — their ``exact``
    most frequent colours as they are (the background, the lines' own colours), then a median
    cut of the other pixels (anti-aliased edges, blends)."""
    from PIL import Image

    sample = np.concatenate([np.asarray(f, dtype=np.uint8).reshape(-1, 3) for f in frames], axis=0)
    word = (sample[:, 0].astype(np.uint32) << 16) | (sample[:, 1].astype(np.uint32) << 8) | sample[:, 2]
    colours, counts = np.unique(word, return_counts=True)
    top = colours[np.argsort(counts)[::-1][:exact]]
    palette = np.stack([(top >> 16) & 255, (top >> 8) & 255, top & 255], axis=1).astype(np.uint8)
    rest = sample[~np.isin(word, top)]
    if len(rest) and len(palette) < PALETTE_COLOURS:
        image = Image.fromarray(np.ascontiguousarray(rest.reshape(1, -1, 3)))
        cut = image.quantize(colors=PALETTE_COLOURS - len(palette), dither=Image.Dither.NONE)
        used = len(cut.getcolors(PALETTE_COLOURS + 1) or ())
        palette = np.vstack([palette, np.asarray(cut.getpalette()[: 3 * used], np.uint8).reshape(-1, 3)])
    return palette


class PaletteMap:
    """Maps (H, W, 3) uint8 frames to palette indices: each 15-bit colour to its nearest
    palette entry (squared RGB distance), precomputed once."""

    def __init__(self, palette: np.ndarray):
        self.palette = np.asarray(palette, dtype=np.uint8).reshape(-1, 3)
        levels = (np.arange(32) * 8 + 4).astype(np.float32)  # the centre of each 5-bit bin
        r, g, b = np.meshgrid(levels, levels, levels, indexing="ij")
        bins = np.stack([r.ravel(), g.ravel(), b.ravel()], axis=1)
        pal = self.palette.astype(np.float32)
        table = np.empty(len(bins), dtype=np.uint8)
        for start in range(0, len(bins), 4096):  # bounded memory: 4096 × K distances at a time
            chunk = bins[start:start + 4096]
            d = ((chunk[:, None, :] - pal[None, :, :]) ** 2).sum(axis=2)
            table[start:start + 4096] = np.argmin(d, axis=1)
        # exact palette colours map to themselves (the background, the lines' own colours); where
        # two share a 15-bit bin the first (most frequent, palette_from's order) wins: written last
        codes = self._code(self.palette[None, :, :])[0]
        table[codes[::-1]] = np.arange(len(self.palette), dtype=np.uint8)[::-1]
        self.table = table

    @staticmethod
    def _code(rgb: np.ndarray) -> np.ndarray:
        rgb = rgb.astype(np.uint16)
        return ((rgb[..., 0] >> 3) << 10) | ((rgb[..., 1] >> 3) << 5) | (rgb[..., 2] >> 3)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) uint8 palette indices of an (H, W, 3) uint8 frame, or of an (H, W, 4) RGBA one
        (read as one 32-bit word per pixel: a third of the work)."""
        if rgb.ndim == 3 and rgb.shape[-1] == 4 and rgb.dtype == np.uint8 and rgb.flags.c_contiguous:
            word = rgb.view("<u4")[..., 0]  # R in the lowest byte
            code = ((word >> 3) & 31) << 10 | ((word >> 11) & 31) << 5 | ((word >> 19) & 31)
            return self.table[code]
        return self.table[self._code(rgb)]


def write_gif(path: Path, frames: list[np.ndarray], palette: np.ndarray, frame_ms: int) -> None:
    """Write indexed ``frames`` ((H, W) uint8) with ``palette`` as a looping GIF, atomically
    (a temporary file beside ``path``, then renamed)."""
    from PIL import Image

    flat = np.zeros(768, dtype=np.uint8)
    flat[: palette.size] = palette.ravel()
    images = []
    for indices in frames:
        indices = np.ascontiguousarray(indices, dtype=np.uint8)
        image = Image.frombytes("P", (indices.shape[1], indices.shape[0]), indices.tobytes())
        image.putpalette(flat.tolist())
        images.append(image)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=int(frame_ms),
                       loop=0, optimize=False)
        os.chmod(tmp, file_mode())  # mkstemp makes 0600; give the mode open() would
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and str(exc.filename or "") != str(path):  # name the user's file
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise
