"""Image I/O in linear RGB: sRGB decoding/encoding, 8- and 16-bit round trips, errors."""
import numpy as np
import pytest
from PIL import Image

from softras_cl.io.images import read_image, write_image
from softras_cl.srgb import to_linear, to_srgb


def srgb_formula(x):
    """IEC 61966-2-1 encoding, written out independently of colour-science."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.abs(x) ** (1 / 2.4) - 0.055)


def test_srgb_known_values():
    assert to_linear(0.5) == pytest.approx(0.214041140, abs=1e-9)
    assert to_srgb(0.214041140482) == pytest.approx(0.5, abs=1e-9)
    np.testing.assert_allclose(to_linear([0.0, 0.04045, 1.0]), [0.0, 0.04045 / 12.92, 1.0],
                               atol=1e-8)
    np.testing.assert_allclose(to_srgb([0.0, 0.0031308, 1.0]), [0.0, 0.04045, 1.0], atol=1e-6)
    x = np.random.default_rng(0).random((4, 5, 3))
    np.testing.assert_allclose(to_srgb(x), srgb_formula(x), atol=1e-12)
    np.testing.assert_allclose(to_srgb(to_linear(x)), x, atol=1e-12)
    assert to_linear(np.zeros((2, 3), np.float32)).dtype == np.float64


def test_curves_equal_colour_science_bit_for_bit():
    colour = pytest.importorskip("colour")
    x = np.concatenate([np.linspace(-0.5, 1.5, 20001), np.arange(256) / 255.0,
                        [0.0031308, 0.04045, 0.0404499, -1e-9, 0.0]])
    np.testing.assert_array_equal(to_srgb(x), colour.cctf_encoding(x, function="sRGB"))
    np.testing.assert_array_equal(to_linear(x), colour.cctf_decoding(x, function="sRGB"))


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("shape", [(6, 9, 3), (6, 9, 4), (6, 9)])
def test_round_trip_within_quantisation(tmp_path, bits, shape):
    rng = np.random.default_rng(1)
    a = rng.random(shape)
    path = tmp_path / "x.png"
    write_image(path, a, bits=bits)
    assert path.read_bytes()[24] == bits                          # PNG IHDR bit depth
    b = read_image(path)
    assert b.dtype == np.float64
    grey = a.ndim == 2
    assert b.shape == (shape[0], shape[1], 3 if grey else shape[2])
    if grey:
        a = np.repeat(a[..., None], 3, axis=-1)
        assert (b[..., 0] == b[..., 1]).all() and (b[..., 0] == b[..., 2]).all()
    step = 1.0 / (2 ** bits - 1)
    err = np.abs(to_srgb(b[..., :3]) - to_srgb(a[..., :3])).max()
    assert err <= 0.5 * step + 1e-9                             # quantisation in sRGB space
    if shape[-1] == 4:                                          # alpha stored linear
        assert np.abs(b[..., 3] - a[..., 3]).max() <= 0.5 * step + 1e-9


def test_written_bytes_are_srgb(tmp_path):
    a = np.array([[[to_linear(128 / 255), 0.0, 1.0], [0.5, 0.01, 0.9]]])
    write_image(tmp_path / "x.png", a)
    stored = np.asarray(Image.open(tmp_path / "x.png"))
    np.testing.assert_array_equal(stored, np.round(srgb_formula(a) * 255).astype(np.uint8))
    assert stored[0, 0, 0] == 128


def test_read_decodes_8bit_files(tmp_path):
    rgb = np.array([[[128, 0, 255], [10, 200, 64]]], np.uint8)
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    np.testing.assert_allclose(read_image(tmp_path / "rgb.png"), to_linear(rgb / 255.0),
                               atol=1e-12)
    assert read_image(tmp_path / "rgb.png")[0, 0, 0] == pytest.approx(0.2158605, abs=1e-6)
    grey = np.array([[0, 128, 255]], np.uint8)
    Image.fromarray(grey).save(tmp_path / "grey.png")
    g = read_image(tmp_path / "grey.png")
    assert g.shape == (1, 3, 3)
    np.testing.assert_allclose(g, np.repeat(to_linear(grey / 255.0)[..., None], 3, -1))
    la = Image.fromarray(np.stack([grey, np.array([[255, 51, 0]], np.uint8)], -1), mode="LA")
    la.save(tmp_path / "la.png")
    g = read_image(tmp_path / "la.png")
    assert g.shape == (1, 3, 4)
    np.testing.assert_allclose(g[..., 3], [[1.0, 0.2, 0.0]])    # alpha not decoded
    pal = Image.fromarray(rgb).convert("P")
    pal.save(tmp_path / "pal.png")
    assert read_image(tmp_path / "pal.png").shape == (1, 2, 3)


def test_read_16bit_files(tmp_path):
    grey16 = np.array([[0, 32768, 65535]], np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")                   # Pillow: I;16
    g = read_image(tmp_path / "g16.png")
    np.testing.assert_allclose(g[..., 0], to_linear(grey16 / 65535.0), atol=1e-12)
    a = np.random.default_rng(2).random((3, 4, 3))
    write_image(tmp_path / "c16.png", a, bits=16)
    b = read_image(tmp_path / "c16.png")
    # finer than 8 bits could give: the file really keeps 16 bits
    assert np.abs(to_srgb(b) - to_srgb(a)).max() < 1e-4


def test_write_clips(tmp_path):
    write_image(tmp_path / "x.png", np.array([[[-1.0, 2.0, 0.5]]]))
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "x.png"))[0, 0], [0, 255, 188])


def test_jpeg(tmp_path):
    a = np.full((8, 8, 3), 0.2)
    write_image(tmp_path / "x.jpg", a)
    np.testing.assert_allclose(read_image(tmp_path / "x.jpg"), a, atol=0.01)


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.png"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "junk.png").write_bytes(b"not an image at all")
    with pytest.raises(ValueError, match="cannot read image .*junk.png"):
        read_image(tmp_path / "junk.png")
    (tmp_path / "trunc.png").write_bytes((b"\x89PNG\r\n\x1a\n" + b"\0\0\0\rIHDR"
                                          + b"\0\0\0\4\0\0\0\4\x10\2\0\0\0"))
    with pytest.raises(ValueError, match="trunc.png"):
        read_image(tmp_path / "trunc.png")


@pytest.mark.parametrize("image, match", [
    (np.zeros((2, 4, 4, 3)), "one image"),
    (np.zeros((4, 4, 2)), r"shape \(H, W, 3\)"),
    (np.zeros(5), r"shape \(H, W, 3\)"),
    (np.zeros((0, 4, 3)), "empty"),
    (np.full((2, 2, 3), np.nan), "non-finite"),
    (np.array([["a"]]), "numeric"),
])
def test_write_shape_errors(tmp_path, image, match):
    with pytest.raises(ValueError, match=match):
        write_image(tmp_path / "x.png", image)


def test_write_errors(tmp_path):
    img = np.zeros((2, 2, 4))
    with pytest.raises(ValueError, match="bits"):
        write_image(tmp_path / "x.png", img, bits=12)
    with pytest.raises(ValueError, match="PNG only"):
        write_image(tmp_path / "x.tif", img, bits=16)
    with pytest.raises(ValueError, match="JPEG cannot store alpha"):
        write_image(tmp_path / "x.jpg", img)
    with pytest.raises(ValueError, match="x.unknownext"):
        write_image(tmp_path / "x.unknownext", img)


def _zlib_level_field(path) -> int:
    """FLEVEL (0 fastest .. 3 best) of the zlib stream in a PNG's first IDAT chunk."""
    data = path.read_bytes()
    start = data.index(b"IDAT") + 4
    return data[start + 1] >> 6


def test_png_written_with_fast_compression(tmp_path):
    """8-bit PNGs (images and the report's figures) use zlib level PNG_COMPRESSION = 1 (the
    header's FLEVEL 0: 'fastest'); Pillow's default 6 would be FLEVEL 2."""
    from matplotlib.figure import Figure

    from softras_cl.io.images import PNG_OPTIONS
    from softras_cl.io.outputs import write_figure

    image = np.random.default_rng(0).uniform(size=(64, 80, 3))
    write_image(tmp_path / "a.png", image)
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(tmp_path / "default.png")
    fig = Figure(figsize=(2, 2))
    fig.subplots().imshow(image)
    write_figure(fig, tmp_path / "fig.png", **PNG_OPTIONS)
    assert _zlib_level_field(tmp_path / "default.png") == 2
    assert _zlib_level_field(tmp_path / "a.png") == 0 and _zlib_level_field(tmp_path / "fig.png") == 0


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_read_decodes_every_level_as_to_linear_does_bit_for_bit(tmp_path, bits, channels):
    """read_image decodes through a table of levels: it must give the bits that decoding each
    pixel with to_linear gives, for every level, every channel layout, alpha undecoded."""
    maxval = 2 ** bits - 1
    levels = np.arange(maxval + 1) if bits == 8 else np.r_[0:256, 32000:32256, 65280:65536]
    data = np.stack([np.roll(levels, 17 * c) for c in range(channels)], -1)[None]
    data = data.astype(np.uint8 if bits == 8 else np.uint16)
    path = tmp_path / "levels.png"
    if bits == 8:
        mode = {1: "L", 2: "LA", 3: "RGB", 4: "RGBA"}[channels]
        Image.fromarray(data if channels > 1 else data[..., 0], mode=mode).save(path)
    else:
        import png
        writer = png.Writer(width=data.shape[1], height=1, greyscale=channels < 3,
                            alpha=channels in (2, 4), bitdepth=16)
        with open(path, "wb") as f:
            writer.write(f, data.reshape(1, -1))
    x = data / float(maxval)
    colour = x[..., :1].repeat(3, -1) if channels < 3 else x[..., :3]
    expected = to_linear(colour)
    if channels in (2, 4):
        expected = np.concatenate([expected, x[..., -1:]], -1)
    got = read_image(path)
    assert got.dtype == np.float64 and got.shape == expected.shape
    np.testing.assert_array_equal(got.view(np.int64), expected.view(np.int64))
