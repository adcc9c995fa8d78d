"""Image encodings the pipeline reads (pipeline.messages.image_to_gray): mono8, rgb8, bgr8, mono16 (high byte),
yuv422 (UYVY) and yuv422_yuy2 (YUYV), each with padded rows, and buffers of the wrong size rejected with the
reason."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from fixego_ros.pipeline.messages import ENCODINGS, ImageError, image_to_gray

H, W = 6, 8
RNG = np.random.default_rng(7)
Y = RNG.integers(0, 256, (H, W), dtype=np.uint8)


def image(encoding: str, pixels: np.ndarray, pad: int = 0, big: bool = False) -> SimpleNamespace:
    """An Image-like message whose rows are ``pixels`` (H, W*bpp bytes) plus ``pad`` bytes of junk."""
    rows = pixels.reshape(H, -1)
    data = np.concatenate([rows, np.full((H, pad), 0xAB, np.uint8)], axis=1)
    return SimpleNamespace(encoding=encoding, height=H, width=W, step=rows.shape[1] + pad, data=data.tobytes(),
                           is_bigendian=big)


def packed(encoding: str) -> np.ndarray:
    """The bytes of an image whose grey (luma) is Y, in ``encoding``."""
    if encoding == 'mono8':
        return Y
    if encoding in ('rgb8', 'bgr8'):
        return np.repeat(Y[:, :, None], 3, axis=2)          # grey colour: every channel Y
    u, v = RNG.integers(0, 256, (H, W // 2), dtype=np.uint8), RNG.integers(0, 256, (H, W // 2), dtype=np.uint8)
    out = np.zeros((H, W // 2, 4), np.uint8)
    if encoding == 'yuv422':                                 # U Y0 V Y1
        out[..., 0], out[..., 1], out[..., 2], out[..., 3] = u, Y[:, 0::2], v, Y[:, 1::2]
    else:                                                    # Y0 U Y1 V
        out[..., 0], out[..., 1], out[..., 2], out[..., 3] = Y[:, 0::2], u, Y[:, 1::2], v
    return out


@pytest.mark.parametrize('encoding', ['mono8', 'rgb8', 'bgr8', 'yuv422', 'yuv422_yuy2'])
@pytest.mark.parametrize('pad', [0, 5])
def test_eight_bit_encodings_give_the_luma_with_and_without_row_padding(encoding, pad):
    gray = image_to_gray(image(encoding, packed(encoding), pad))
    assert gray.dtype == np.uint8 and gray.shape == (H, W)
    np.testing.assert_array_equal(gray, Y)


def test_yuv_variants_are_not_confused():
    """UYVY read as YUYV gives the chroma bytes, not the luma: the two names are distinct layouts."""
    assert not np.array_equal(image_to_gray(image('yuv422_yuy2', packed('yuv422'))), Y)


@pytest.mark.parametrize('big', [False, True])
@pytest.mark.parametrize('pad', [0, 3])
def test_mono16_keeps_the_high_byte(big, pad):
    v16 = (Y.astype(np.uint16) << 8) | RNG.integers(0, 256, (H, W), dtype=np.uint16)
    raw = v16.astype('>u2' if big else '<u2').view(np.uint8).reshape(H, 2 * W)
    gray = image_to_gray(image('mono16', raw, pad, big))
    np.testing.assert_array_equal(gray, (v16 >> 8).astype(np.uint8))
    np.testing.assert_array_equal(gray, Y)


@pytest.mark.parametrize('encoding', sorted(ENCODINGS))
def test_wrong_size_buffer_is_rejected_with_the_reason(encoding):
    bpp = ENCODINGS[encoding][0]
    msg = image(encoding, np.zeros((H, W * bpp), np.uint8))
    msg.data = msg.data[:-1]
    with pytest.raises(ImageError, match=rf'{H * W * bpp - 1} bytes of data, {W}x{H} {encoding} with step '
                                         rf'{W * bpp} needs {H * W * bpp}'):
        image_to_gray(msg)
    msg = image(encoding, np.zeros((H, W * bpp), np.uint8))
    msg.step = W * bpp - 1
    with pytest.raises(ImageError, match=rf'step {W * bpp - 1} bytes is less than width {W} x {bpp} bytes per pixel'):
        image_to_gray(msg)


def test_odd_width_yuv_and_unknown_encodings_are_rejected():
    msg = SimpleNamespace(encoding='yuv422', height=2, width=3, step=6, data=bytes(12))
    with pytest.raises(ImageError, match='even width'):
        image_to_gray(msg)
    msg = SimpleNamespace(encoding='bayer_rggb8', height=2, width=2, step=2, data=bytes(4))
    with pytest.raises(ImageError, match="unsupported encoding 'bayer_rggb8'") as e:
        image_to_gray(msg)
    assert e.value.kind == 'encoding' and 'yuv422_yuy2' in str(e.value)
