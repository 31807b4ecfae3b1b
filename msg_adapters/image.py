"""sensor_msgs/Image <-> numpy without cv_bridge. Reading is duck-typed on the message fields (height, width,
encoding, step, is_bigendian, data), so rclpy and rosbags messages both work; it honours row padding (`step`)
and returns a zero-copy view of the message's bytes for rgb8. Writing uses the fast bytes path."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import Image

from msg_adapters.header import copy_header

DEFAULT_MAX_PIXELS = 4096 * 4096
# encoding -> (bytes per pixel, channel order giving RGB; None: copy the single grey channel three times)
ENCODINGS: dict[str, tuple[int, tuple[int, ...] | None]] = {
    "rgb8": (3, (0, 1, 2)),
    "bgr8": (3, (2, 1, 0)),
    "rgba8": (4, (0, 1, 2)),
    "bgra8": (4, (2, 1, 0)),
    "mono8": (1, None),
}


class ImageConversionError(ValueError):
    """An Image message that cannot be turned into an RGB array; the message says which field is wrong."""


def _check_layout(msg, max_pixels: int) -> int:
    """Validate the message's fields against each other; return its bytes per pixel."""
    if msg.encoding not in ENCODINGS:
        raise ImageConversionError(f"unsupported image encoding '{msg.encoding}'; supported: {', '.join(ENCODINGS)}")
    if int(msg.is_bigendian) not in (0, 1):
        raise ImageConversionError(f"is_bigendian must be 0 or 1, got {msg.is_bigendian}")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise ImageConversionError(f"empty image: {width} x {height} px")
    if height * width > max_pixels:
        raise ImageConversionError(f"image {width} x {height} = {height * width} px exceeds the limit of "
                                   f"{max_pixels} px")
    channels = ENCODINGS[msg.encoding][0]
    if step < width * channels:
        raise ImageConversionError(f"step {step} bytes is shorter than a {msg.encoding} row: width {width} x "
                                   f"{channels} bytes = {width * channels}")
    if len(msg.data) != step * height:
        raise ImageConversionError(f"data is {len(msg.data)} bytes; step {step} x height {height} needs "
                                   f"{step * height}")
    return channels


def image_to_rgb(msg, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """(H, W, 3) uint8 RGB from an Image in rgb8, bgr8, rgba8, bgra8 or mono8; a read-only view of msg.data for
    rgb8, a new array otherwise. ImageConversionError for any other encoding or inconsistent fields."""
    channels = _check_layout(msg, max_pixels)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    rows = np.frombuffer(msg.data, np.uint8).reshape(height, step)
    pixels = rows[:, :width * channels].reshape(height, width, channels)
    order = ENCODINGS[msg.encoding][1]
    if order is None:
        return np.repeat(pixels, 3, axis=2)
    if order == (0, 1, 2) and channels == 3:
        pixels.flags.writeable = False
        return pixels
    return np.ascontiguousarray(pixels[..., list(order)])


def rgb_to_image(image: np.ndarray, header=None) -> Image:
    """An Image from (H, W, 3) uint8 RGB (rgb8) or (H, W) uint8 grey (mono8), with a copy of `header`."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ValueError(f"expected (H, W, 3) or (H, W) uint8, got {image.shape} {image.dtype}")
    msg = Image(height=image.shape[0], width=image.shape[1], encoding="rgb8" if image.ndim == 3 else "mono8",
                is_bigendian=0, step=image.shape[1] * (3 if image.ndim == 3 else 1))
    if header is not None:
        msg.header = copy_header(header)
    msg.data = image.tobytes()  # the bytes setter is ~100x faster than assigning an array
    return msg
