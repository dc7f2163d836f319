"""Image files → uint8 RGB: conversions with notes, and one clear line naming the file for every unusable file.

Every file is written by the test (Pillow, OpenCV, or raw bytes), then read back with components.core.images.
"""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from components.core.images import ImageError, group_by_size, iter_images, list_images, read_image
from components.core.seeding import rng


def rgb(h: int = 40, w: int = 40, seed: int = 0) -> np.ndarray:
    return rng(seed, "test", "image").integers(0, 256, (h, w, 3), dtype=np.uint8)


def png_bytes(width: int, height: int) -> bytes:
    """A PNG whose header says width × height (8-bit RGB) with an empty image stream."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")


def test_plain_rgb_png_is_read_exactly_without_note(tmp_path):
    a = rgb()
    Image.fromarray(a).save(tmp_path / "a.png")
    image, note = read_image(tmp_path / "a.png")
    assert image.dtype == np.uint8 and note is None
    np.testing.assert_array_equal(image, a)


def test_jpeg_is_read_as_rgb(tmp_path):
    a = np.zeros((40, 40, 3), np.uint8)
    a[:, :, 0] = 200  # pure red survives JPEG within a few levels
    Image.fromarray(a).save(tmp_path / "a.jpg", quality=95)
    image, note = read_image(tmp_path / "a.jpg")
    assert image.shape == (40, 40, 3) and note is None
    assert abs(int(image[..., 0].mean()) - 200) < 4 and image[..., 1:].mean() < 4


def test_grayscale_becomes_three_equal_channels(tmp_path):
    g = rgb()[..., 0]
    Image.fromarray(g, mode="L").save(tmp_path / "g.png")
    image, note = read_image(tmp_path / "g.png")
    assert "grayscale → RGB" in note
    for c in range(3):
        np.testing.assert_array_equal(image[..., c], g)


def test_black_and_white_becomes_rgb(tmp_path):
    Image.fromarray(rgb()[..., 0] > 127).convert("1").save(tmp_path / "b.png")
    image, note = read_image(tmp_path / "b.png")
    assert "black-and-white" in note and set(np.unique(image)) <= {0, 255}


@pytest.mark.parametrize("mode", ["RGBA", "LA"])
def test_alpha_is_dropped(tmp_path, mode):
    a = rgb()
    alpha = rgb(seed=1)[..., 0]
    if mode == "RGBA":
        Image.fromarray(np.dstack([a, alpha]), mode="RGBA").save(tmp_path / "x.png")
        expected = a
    else:
        Image.fromarray(np.dstack([a[..., 0], alpha]), mode="LA").save(tmp_path / "x.png")
        expected = np.repeat(a[..., :1], 3, axis=2)
    image, note = read_image(tmp_path / "x.png")
    assert f"alpha channel dropped ({mode} → RGB)" in note
    np.testing.assert_array_equal(image, expected)  # colour kept as is, not blended


def test_palette_images_with_and_without_transparency(tmp_path):
    palette = [0, 0, 0, 255, 0, 0, 0, 255, 0] + [0] * (3 * 253)
    index = (rgb()[..., 0] % 3).astype(np.uint8)
    expected = np.array(palette[:9], np.uint8).reshape(3, 3)[index]
    p = Image.fromarray(index, mode="P")
    p.putpalette(palette)
    p.save(tmp_path / "p.png")
    image, note = read_image(tmp_path / "p.png")
    assert note == "palette image expanded to RGB"
    np.testing.assert_array_equal(image, expected)
    p.save(tmp_path / "pt.png", transparency=0)
    image, note = read_image(tmp_path / "pt.png")
    assert "alpha channel dropped (P → RGB)" in note
    np.testing.assert_array_equal(image, expected)


def test_sixteen_bit_images_are_scaled_to_eight_bits(tmp_path):
    g16 = rng(2, "test", "16").integers(0, 65536, (40, 40), dtype=np.uint16)
    g16[0, :3] = [0, 257 * 100, 65535]
    cv2.imwrite(str(tmp_path / "g16.png"), g16)
    image, note = read_image(tmp_path / "g16.png")
    assert "16-bit grayscale scaled to 8 bits" in note
    np.testing.assert_array_equal(image[..., 0], np.rint(g16 * (255 / 65535)).astype(np.uint8))
    assert image[0, :3, 0].tolist() == [0, 100, 255]
    c16 = rng(3, "test", "16").integers(0, 65536, (40, 40, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "c16.png"), c16[..., ::-1])  # OpenCV writes BGR
    image, note = read_image(tmp_path / "c16.png")
    assert "16-bit RGB reduced to 8 bits" in note
    assert np.abs(image.astype(int) - c16 / 257).max() <= 1.0


def test_floating_point_pixels_are_refused(tmp_path):
    Image.fromarray(np.full((40, 40), 0.5, np.float32)).save(tmp_path / "f.tif")
    with pytest.raises(ImageError, match=r"f\.tif: floating-point pixels \(mode F\) are not supported"):
        read_image(tmp_path / "f.tif")


def test_exif_orientation_is_applied(tmp_path):
    a = np.zeros((40, 60, 3), np.uint8)
    a[:, :30] = 255  # left half white
    exif = Image.Exif()
    exif[0x0112] = 6  # stored rotated: display = rotate 90° clockwise
    Image.fromarray(a).save(tmp_path / "r.jpg", exif=exif, quality=95)
    image, note = read_image(tmp_path / "r.jpg")
    assert image.shape == (60, 40, 3) and "EXIF orientation" in note
    assert image[:30].mean() > 200 and image[30:].mean() < 50  # the white half is now on top


def test_animated_images_give_their_first_frame(tmp_path):
    frames = [Image.fromarray(np.full((40, 40, 3), v, np.uint8)) for v in (10, 240)]
    frames[0].save(tmp_path / "a.gif", save_all=True, append_images=frames[1:])
    image, note = read_image(tmp_path / "a.gif")
    assert "first of 2 frames" in note and image.max() < 50


def test_odd_sizes_are_read_with_a_note(tmp_path):
    Image.fromarray(rgb(40, 90)).save(tmp_path / "wide.png")
    image, note = read_image(tmp_path / "wide.png")
    assert image.shape == (40, 90, 3) and "not square (90×40 pixels)" in note
    Image.fromarray(rgb(8, 5)).save(tmp_path / "tiny.png")
    image, note = read_image(tmp_path / "tiny.png")
    assert image.shape == (8, 5, 3) and note == "very small (5×8 pixels)"
    Image.fromarray(rgb(1, 1)).save(tmp_path / "one.png")
    assert read_image(tmp_path / "one.png")[0].shape == (1, 1, 3)
    Image.fromarray(rgb(10, 2000)).save(tmp_path / "strip.png")  # wide, not small: it is the height that is short
    image, note = read_image(tmp_path / "strip.png")
    assert note == "only 10 pixels high (2000×10 pixels): the backbone stretches it to its square input"
    Image.fromarray(rgb(300, 20)).save(tmp_path / "pole.png")
    assert read_image(tmp_path / "pole.png")[1].startswith("only 20 pixels wide (20×300 pixels)")


def _truncated(path: Path, fmt: str) -> None:
    Image.fromarray(rgb(64, 64)).save(path, format=fmt)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


BAD_FILES = {
    "missing.png": (None, "no such file"),
    "folder.png": ("dir", "is a folder, not an image file"),
    "empty.png": (b"", r"empty file \(0 bytes\)"),
    "text.png": (b"hello, not an image\n", "not an image file, or a format Pillow cannot read"),
    "zero.png": (png_bytes(0, 10), r"zero-size PNG image \(0×10 pixels\)"),
    "header.png": (b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, "damaged PNG file"),
    "truncated.png": ("PNG", r"unreadable image \(image file is truncated"),
    "truncated.jpg": ("JPEG", r"unreadable image \(image file is truncated"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_unusable_files_raise_one_line_naming_the_file(tmp_path, name):
    content, reason = BAD_FILES[name]
    path = tmp_path / name
    if content == "dir":
        path.mkdir()
    elif content in ("PNG", "JPEG"):
        _truncated(path, content)
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(ImageError) as info:
        read_image(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    assert re.search(reason, message), message


def test_list_images_sorts_naturally_and_skips_non_images(tmp_path):
    for name in ["frame_10.png", "frame_2.PNG", "frame_1.jpg", ".hidden.png", "notes.txt", "Frame_3.jpeg"]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "frame_0.png").write_bytes(b"x")
    listed = [p.name for p in list_images(tmp_path)]
    assert listed == ["frame_1.jpg", "frame_2.PNG", "Frame_3.jpeg", "frame_10.png"]
    # files named explicitly are kept whatever they are, in the order given, next to folders
    expected = [tmp_path / "notes.txt", tmp_path / "sub" / "frame_0.png"]
    assert list_images([tmp_path / "notes.txt", tmp_path / "sub"]) == expected
    assert list_images(tmp_path / "nope.png") == [tmp_path / "nope.png"]
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "a.txt").write_bytes(b"x")
    with pytest.raises(ImageError, match=r"empty: no image files in this folder"):
        list_images([tmp_path / "sub", tmp_path / "empty"])


def test_iter_images_goes_on_past_bad_files(tmp_path):
    Image.fromarray(rgb()).save(tmp_path / "1.png")
    (tmp_path / "2.png").write_bytes(b"")
    Image.fromarray(rgb()[..., 0], mode="L").save(tmp_path / "3.png")
    items = list(iter_images(tmp_path))
    assert [i.path.name for i in items] == ["1.png", "2.png", "3.png"]
    assert [i.ok for i in items] == [True, False, True]
    assert items[1].image is None and "empty file" in str(items[1].error)
    assert items[0].note is None and "grayscale" in items[2].note and items[2].image.shape == (40, 40, 3)


def test_group_by_size_stacks_equal_sizes_and_keeps_positions():
    images = [rgb(40, 40, 0), rgb(30, 50, 1), rgb(40, 40, 2), rgb(30, 50, 3), rgb(8, 8, 4)]
    groups = group_by_size(images)
    assert [idx for idx, _ in groups] == [[0, 2], [1, 3], [4]]
    for idx, batch in groups:
        np.testing.assert_array_equal(batch, np.stack([images[i] for i in idx]))
    with pytest.raises(ValueError, match=r"images\[1\] must be a uint8 \(H, W, 3\) RGB array"):
        group_by_size([rgb(), rgb()[..., 0]])
