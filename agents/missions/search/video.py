"""The thermal camera as video: :class:`ThermalVideo`, the search mission's
:class:`~agents.missions.search.thermal.ThermalFeed` in false colour with its
detections, a source for :mod:`agents.video` (the agent's ``video`` section with
``"source": "thermal"``)."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import TypeAlias

import av
import numpy as np
import numpy.typing as npt

from agents.missions.search.thermal import Blob, ThermalFeed, colour_range, false_colour
from agents.video.framecode import draw_text

RGB: TypeAlias = npt.NDArray[np.uint8]


class ThermalVideo:
    """The agent's thermal camera as video: each frame of its
    :class:`~agents.missions.search.thermal.ThermalFeed` in an ironbow palette, upscaled
    to ``width`` x ``height``, with a box and the confidence over each detection (green from
    ``box_confidence``), and at the bottom the palette's temperature range.

    It shares the feed with the search mission (one camera, each frame captured and
    analysed once) and is paced by it. ``close()`` only forgets the position in the
    feed: the camera belongs to the agent, which closes it on shutdown.
    """

    def __init__(
        self,
        feed: ThermalFeed,
        *,
        width: int = 640,
        height: int = 480,
        box_confidence: float = 0.6,
    ) -> None:
        if width % 2 or height % 2 or not (64 <= width <= 1920 and 64 <= height <= 1080):
            raise ValueError("thermal video width and height must be even, 64..1920x1080")
        self.feed = feed
        self.width, self.height = width, height
        self.box_confidence = box_confidence
        self._seq = 0

    async def frame(self) -> av.VideoFrame:
        """The next thermal frame, drawn (in a worker thread)."""
        thermal = await self.feed.frame(newer_than=self._seq)
        self._seq = thermal.seq
        img = await asyncio.to_thread(self.render, thermal.celsius, thermal.blobs)
        return av.VideoFrame.from_ndarray(img, format="rgb24")

    def render(self, celsius: npt.NDArray[np.float32], blobs: Sequence[Blob] = ()) -> RGB:
        """One picture (H x W x 3 RGB) of a frame in degrees Celsius and its blobs."""
        img = false_colour(
            celsius,
            blobs,
            width=self.width,
            height=self.height,
            box_confidence=self.box_confidence,
        )
        sy, sx = self.height / celsius.shape[0], self.width / celsius.shape[1]
        digit_h = max(14, self.height // 28)
        for blob in blobs:
            r0, c0, _, _ = blob.box
            colour = (0, 255, 0) if blob.confidence >= self.box_confidence else (255, 220, 0)
            y = max(0, int(r0 * sy) - digit_h - 8)
            draw_text(img, f"{blob.confidence:.2f}", int(c0 * sx), y, digit_h, colour)
        # The palette's range: the temperatures of its two ends, in degC.
        low, high = colour_range(celsius)
        band = img[self.height - digit_h - 8 :]
        np.right_shift(band, 1, out=band)  # darken behind the digits
        y = self.height - digit_h - 4
        draw_text(img, f"{low:.1f}", 6, y, digit_h, (255, 255, 255))
        text = f"{high:.1f}"
        x = self.width - 6 - len(text) * (digit_h // 2 + 2 * max(2, digit_h // 8))
        draw_text(img, text, x, y, digit_h, (255, 255, 255))
        return img

    async def close(self) -> None:
        self._seq = 0
