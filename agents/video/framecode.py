"""The machine-readable code stamped into synthetic frames (a frame counter and the
capture time, readable from the pixels after encoding and decoding: what latency is
measured by) and the seven-segment digits drawn over pictures.
"""

from __future__ import annotations

import zlib
from typing import Final, NamedTuple, TypeAlias

import numpy as np
import numpy.typing as npt

RGB: TypeAlias = npt.NDArray[np.uint8]


#: Bits per row of the machine-readable code stamped at the top of synthetic frames.
CODE_BITS: Final = 48


class FrameCode(NamedTuple):
    """What :func:`read_frame_code` recovers from a frame's top rows."""

    counter: int  # frames drawn by the source since it was created
    ts_ms: int  # Unix time, milliseconds, when the frame was drawn


def code_layout(width: int) -> tuple[int, int]:
    """(block size, left margin) of the code rows for a frame ``width`` pixels wide."""
    block = width // CODE_BITS
    if block < 4:
        raise ValueError(f"frames must be at least {4 * CODE_BITS} pixels wide for the code")
    return block, (width - block * CODE_BITS) // 2


def _code_check(counter: int, ts_ms: int) -> int:
    return zlib.crc32(counter.to_bytes(4, "big") + ts_ms.to_bytes(6, "big")) & 0xFFFF


def stamp_frame_code(img: RGB, counter: int, ts_ms: int) -> None:
    """Draw ``counter`` and ``ts_ms`` as two rows of black/white blocks at the top of
    ``img`` (H x W x 3, uint8, modified in place).

    Row 0: 32-bit counter then a 16-bit check (CRC-32 of counter and timestamp); row 1:
    48-bit Unix milliseconds. Blocks are ``W // 48`` pixels square, MSB first, centred:
    big enough to survive lossy video coding, so a test or a browser can recover the
    exact numbers (and so the capture-to-display latency) from a decoded frame.
    """
    block, x0 = code_layout(img.shape[1])
    counter &= 0xFFFF_FFFF
    ts_ms &= 0xFFFF_FFFF_FFFF
    rows = ((counter << 16) | _code_check(counter, ts_ms), ts_ms)
    for r, value in enumerate(rows):
        bits = (value >> np.arange(CODE_BITS - 1, -1, -1)) & 1
        # One row of per-block values, widened to pixels and stacked to block height.
        line = np.repeat(bits.astype(np.uint8) * 255, block)
        img[r * block : (r + 1) * block, x0 : x0 + block * CODE_BITS] = line[None, :, None]


def read_frame_code(img: RGB) -> FrameCode | None:
    """Recover the code :func:`stamp_frame_code` drew, or None when the check fails (not
    a synthetic frame, or too damaged). Samples the middle half of each block."""
    block, x0 = code_layout(img.shape[1])
    lo, hi = block // 4, block - block // 4
    values = []
    for r in range(2):
        band = img[r * block + lo : r * block + hi, x0 : x0 + block * CODE_BITS].astype(np.int32)
        if band.shape[0] == 0:
            return None
        # mean over rows and channels, then per block over its middle columns
        cols = band.mean(axis=(0, 2)).reshape(CODE_BITS, block)[:, lo:hi].mean(axis=1)
        value = 0
        for bit in cols > 127:
            value = (value << 1) | int(bit)
        values.append(value)
    counter, check = values[0] >> 16, values[0] & 0xFFFF
    if _code_check(counter, values[1]) != check:
        return None
    return FrameCode(counter, values[1])


# Seven-segment font: segments a (top), b (top right), c (bottom right), d (bottom),
# e (bottom left), f (top left), g (middle).
_SEGMENTS: Final[dict[str, str]] = {
    "0": "abcdef",
    "1": "bc",
    "2": "abged",
    "3": "abgcd",
    "4": "fgbc",
    "5": "afgcd",
    "6": "afgedc",
    "7": "abc",
    "8": "abcdefg",
    "9": "abcdfg",
    "-": "g",
    " ": "",
}


def draw_text(img: RGB, text: str, x: int, y: int, height: int, color: tuple[int, ...]) -> int:
    """Draw ``text`` (digits, space, '-', ':', '.') in a seven-segment font with its top
    left corner at (x, y); returns the x after the last character. Characters that fall
    outside ``img`` are clipped by numpy slicing."""
    w, t = height // 2, max(2, height // 8)
    mid = height // 2 - t // 2
    rgb = np.asarray(color, dtype=np.uint8)
    for ch in text:
        if ch in ":.":
            dot_rows = (height // 3, 2 * height // 3) if ch == ":" else (height - t,)
            for dy in dot_rows:
                img[y + dy : y + dy + t, x : x + t] = rgb
            x += t * 3
            continue
        boxes = {
            "a": (0, t, 0, w),
            "d": (height - t, height, 0, w),
            "g": (mid, mid + t, 0, w),
            "f": (0, height // 2, 0, t),
            "e": (height // 2, height, 0, t),
            "b": (0, height // 2, w - t, w),
            "c": (height // 2, height, w - t, w),
        }
        for seg in _SEGMENTS.get(ch, ""):
            r0, r1, c0, c1 = boxes[seg]
            img[y + r0 : y + r1, x + c0 : x + c1] = rgb
        x += w + t * 2
    return x
