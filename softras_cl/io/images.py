"""Image files in and out, in linear RGB.

All shading and losses in softras-cl work in linear RGB; files hold sRGB-encoded values,
decoded and encoded with softras_cl.srgb's transfer functions (to_linear, to_srgb). Alpha is
never encoded: it is stored and returned linear.

- `read_image(path)`: (H, W, 3) or (H, W, 4) float64, linear RGB (+ alpha as stored, in [0, 1]).
  8-bit and 16-bit files; greyscale becomes 3 equal channels (grey + alpha: RGBA); palette
  images are expanded. 16-bit PNGs are decoded with pypng (Pillow reduces 16-bit colour PNGs to
  8 bits); everything else with Pillow. Embedded ICC profiles are ignored (files are taken as
  sRGB); JPEG EXIF orientation is applied.
- `write_image(path, image, bits=8)`: one (H, W, 3), (H, W, 4) or (H, W) linear image, clipped
  to [0, 1], sRGB-encoded, rounded to 8 bits (any format Pillow writes, chosen by the
  extension) or 16 bits (PNG only).
- `image_format(path)`: the format write_image picks from the extension, or an InputError
  saying what is expected (a folder, no or an unknown extension): a command checks its output
  path with it before the work.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softras_cl.errors import InputError
from softras_cl.io.outputs import atomic_path
from softras_cl.srgb import to_linear, to_srgb

__all__ = ["read_image", "write_image", "image_format", "COMMON_SUFFIXES"]

# the extensions write_image is mostly used with (it writes any format Pillow writes)
COMMON_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# zlib level of the 8-bit PNGs written (Pillow's default is 6): the same pixels, 3-4x faster to
# write, files about 10% larger; figures use it too (PNG_OPTIONS, matplotlib's savefig)
PNG_COMPRESSION = 1
PNG_OPTIONS = dict(pil_kwargs={"compress_level": PNG_COMPRESSION})


# ---------------------------------------------------------------------------------------------
# Reading

def _png_bit_depth(path: Path) -> int | None:
    """Bit depth from a PNG's IHDR chunk, or None if the file is not a PNG."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return head[24]


def _read_png16(path: Path) -> tuple[np.ndarray, float]:
    """16-bit PNG -> (H, W, C) uint16 with C in {1, 2, 3, 4}, and its maximum value."""
    import png  # pypng

    with open(path, "rb") as f:
        width, height, rows, info = png.Reader(file=f).asDirect()
        data = np.vstack([np.asarray(row, dtype=np.uint16) for row in rows])
    data = data.reshape(height, width, info["planes"])
    return data, float(2 ** info["bitdepth"] - 1)


def pil_to_array(img) -> tuple[np.ndarray, float]:
    """A PIL image -> ((H, W, C) integer array with C in {1, 2, 3, 4}, maximum value).

    Channels: 1 grey, 2 grey + alpha, 3 RGB, 4 RGBA. Palette, bilevel, CMYK, YCbCr, ... images
    are converted to RGB or RGBA (RGBA when the image has an alpha band or transparency).
    Also used by softras_cl.io.meshes for texture images loaded by trimesh.
    """
    mode = img.mode
    if mode.startswith("I;16"):
        return np.asarray(img).astype(np.uint16)[..., None], 65535.0
    if mode == "I":
        a = np.asarray(img)
        if a.size and (a.min() < 0 or a.max() > 65535):
            raise ValueError(f"32-bit integer image with values outside [0, 65535] "
                             f"(min {a.min()}, max {a.max()}) is not supported")
        return a.astype(np.uint16)[..., None], 65535.0
    if mode == "F":
        raise ValueError("floating-point images (Pillow mode 'F') are not supported")
    if mode not in ("L", "LA", "RGB", "RGBA"):
        has_alpha = "A" in img.getbands() or "a" in img.getbands() or "transparency" in img.info
        img = img.convert("RGBA" if has_alpha else "RGB")
    elif mode == "L" and "transparency" in img.info:
        img = img.convert("LA")
    elif mode == "RGB" and "transparency" in img.info:
        img = img.convert("RGBA")
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[..., None]
    return a, 255.0


def _to_linear_rgb(data: np.ndarray, maxval: float) -> np.ndarray:
    """(H, W, C) integers, C in {1, 2, 3, 4}, sRGB -> (H, W, 3|4) float64 linear (+ alpha)."""
    levels = np.arange(int(maxval) + 1) / maxval
    # each stored level decoded once and looked up: the same values as decoding every pixel
    # (to_linear is elementwise), without a power per pixel of a many-megapixel photo
    decoded = to_linear(levels)
    grey = data.shape[-1] in (1, 2)                   # grey (+ alpha) -> RGB (+ alpha)
    rgb = decoded[np.repeat(data[..., :1], 3, axis=-1) if grey else data[..., :3]]
    if data.shape[-1] in (2, 4):
        return np.concatenate([rgb, levels[data[..., -1:]]], axis=-1)
    return rgb


def _image_file(path) -> Path:
    """``path`` as a Path when it is a regular file (or a link to one), without opening it (a
    FIFO would block): FileNotFoundError when nothing is there, InputError saying what it is
    when it is a folder, a FIFO, a device or a socket."""
    import stat

    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"image file not found: {path}") from None
    except OSError as e:
        raise InputError(f"cannot read image {path}: {e.strerror or e}") from None
    if stat.S_ISDIR(mode):
        raise InputError(f"{path} is a directory, not an image file")
    if not stat.S_ISREG(mode):
        kind = ("a FIFO" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                else "a socket" if stat.S_ISSOCK(mode) else "a special file")
        raise InputError(f"{path} is not a regular file ({kind}); give an image file")
    return path


def _decode(path) -> tuple[np.ndarray, float]:
    """An image file, upright by its EXIF orientation -> ((H, W, C) stored integers with C in
    {1, 2, 3, 4}, their maximum value). FileNotFoundError for a missing file, InputError for a
    folder or another file that is not a regular one (_image_file), ValueError naming it for one
    that cannot be decoded or is empty."""
    path = _image_file(path)
    try:
        if _png_bit_depth(path) == 16:
            data, maxval = _read_png16(path)
        else:
            from PIL import Image, ImageOps

            with Image.open(path) as img:
                img.load()
                img = ImageOps.exif_transpose(img)
                data, maxval = pil_to_array(img)
    except Exception as e:   # Pillow and pypng raise many kinds (OSError, SyntaxError, ...)
        raise ValueError(f"cannot read image {path}: {type(e).__name__}: {e}") from e
    if data.shape[0] == 0 or data.shape[1] == 0:
        raise ValueError(f"cannot read image {path}: it is empty ({data.shape[1]}x{data.shape[0]})")
    return data, maxval


def _to_rgb8(data: np.ndarray, maxval: float) -> np.ndarray:
    """(H, W, C) stored integers, C in {1, 2, 3, 4} -> (H, W, 3) uint8 sRGB values (grey
    repeated, alpha dropped, 16-bit values rounded to 8 bits)."""
    rgb = np.repeat(data[..., :1], 3, axis=-1) if data.shape[-1] in (1, 2) else data[..., :3]
    if maxval == 255.0:
        return np.ascontiguousarray(rgb, dtype=np.uint8)
    return np.round(rgb * (255.0 / maxval)).astype(np.uint8)


def read_image(path) -> np.ndarray:
    """Read an image file as linear RGB.

    Returns (H, W, 3) float64 linear RGB, or (H, W, 4) when the file has alpha (or a
    transparency entry); alpha is returned as stored, scaled to [0, 1], not decoded.
    Raises FileNotFoundError for a missing file and ValueError (naming the path) for a file
    that cannot be decoded.
    """
    return _to_linear_rgb(*_decode(path))


def read_rgb8(path) -> np.ndarray:
    """An image file as (H, W, 3) uint8 RGB (sRGB values undecoded, alpha dropped, 16-bit files
    rounded to 8 bits), turned upright by its EXIF orientation as read_image does, so points
    found on it match the fitted image: what the detectors and video frames take.
    FileNotFoundError for a missing file, ValueError naming it for an unreadable one."""
    return _to_rgb8(*_decode(path))


@dataclass(frozen=True)
class Photo:
    """A photo file decoded once (upright by its EXIF orientation, alpha dropped): ``rgb8`` (H, W,
    3) uint8 sRGB values, as read_rgb8 gives them (what the detectors take), and ``linear`` (H, W,
    3) float64 linear RGB, as read_image gives them (what the fits take)."""
    path: Path
    rgb8: np.ndarray
    linear: np.ndarray


def read_photo(path) -> Photo:
    """Decode a photo file once for both the detectors and the fits (see Photo); errors as
    read_image."""
    data, maxval = _decode(path)
    return Photo(Path(path), _to_rgb8(data, maxval), _to_linear_rgb(data, maxval)[..., :3])


# ---------------------------------------------------------------------------------------------
# Writing

def _image_to_write(image) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype == object or not (np.issubdtype(a.dtype, np.floating)
                                 or np.issubdtype(a.dtype, np.integer)
                                 or a.dtype == np.bool_):
        raise ValueError(f"image must be a numeric array, got dtype {a.dtype}")
    if a.ndim == 4:
        raise ValueError(f"write_image writes one image, got shape {a.shape} (a batch?); "
                         "write each image of the batch separately")
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[-1] in (3, 4))):
        raise ValueError(f"image must have shape (H, W, 3), (H, W, 4) or (H, W), got {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"image is empty: shape {a.shape}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"image has {int((~np.isfinite(a)).sum())} non-finite values "
                         "(NaN or inf)")
    return a


def image_format(path, alpha: bool = False, what: str = "image") -> str:
    """The Pillow format (e.g. "PNG") in which write_image writes 8-bit ``path``, from its
    extension. InputError (a ValueError) saying what is expected when ``path`` is a folder, has
    no extension Pillow writes, or is a JPEG for an image with ``alpha``; ``what`` names the
    path in the message (e.g. "--out")."""
    from PIL import Image

    path = Path(path)
    expected = f"expected an image file path ({', '.join(COMMON_SUFFIXES)}, or another format Pillow writes)"
    if path.is_dir():
        raise InputError(f"{what} {path} is a folder: {expected}")
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt not in Image.SAVE:
        reason = f"no image format Pillow writes has the extension {path.suffix!r}" if path.suffix else "no extension"
        raise InputError(f"{what} {path}: {reason}: {expected}")
    if alpha and fmt == "JPEG":
        raise InputError(f"{what} {path}: JPEG cannot store alpha: write an (H, W, 3) image, or use .png")
    return fmt


def write_image(path, image, bits: int = 8) -> None:
    """Write one linear-RGB image, sRGB-encoded.

    image: (H, W, 3) linear RGB, (H, W, 4) linear RGB + alpha, or (H, W) linear grey; values are
    clipped to [0, 1], colour channels encoded with the sRGB curve (alpha stored as is) and
    rounded to `bits` = 8 (any format Pillow writes, chosen by the extension: .png, .jpg, ...)
    or 16 (.png only). The file is replaced atomically (softras_cl.io.outputs.atomic_path).
    """
    path = Path(path)
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    a = _image_to_write(image)
    a = np.clip(a, 0.0, 1.0)
    if a.ndim == 2:
        enc = to_srgb(a)
    else:
        enc = np.concatenate([to_srgb(a[..., :3]), a[..., 3:]], axis=-1)
    suffix = path.suffix.lower()
    if bits == 16:
        if suffix != ".png":
            raise ValueError(f"16-bit images are written as PNG only, got {path}")
        import png  # pypng

        q = np.round(np.clip(enc, 0.0, 1.0) * 65535.0).astype(np.uint16)
        h, w = q.shape[:2]
        channels = 1 if q.ndim == 2 else q.shape[-1]
        writer = png.Writer(width=w, height=h, greyscale=channels == 1, alpha=channels == 4,
                            bitdepth=16)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            writer.write(f, q.reshape(h, w * channels))
        return
    from PIL import Image

    q = np.round(np.clip(enc, 0.0, 1.0) * 255.0).astype(np.uint8)
    fmt = image_format(path, alpha=q.ndim == 3 and q.shape[-1] == 4)
    try:
        with atomic_path(path) as tmp:
            options = {"compress_level": PNG_COMPRESSION} if fmt == "PNG" else {}
            Image.fromarray(q).save(tmp, format=fmt, **options)
    except (KeyError, ValueError) as e:   # Pillow: mode not writable in this format
        raise ValueError(f"cannot write image {path}: {e}") from e
