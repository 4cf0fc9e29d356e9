"""Reading image files that may be hostile: a header claiming 20000 x 20000
pixels, a truncated file, a folder or a FIFO where an image should be.

:func:`read_image` checks the file and the size its header claims before
anything is decoded, so a 50-byte PNG cannot make a calibration allocate
gigabytes or decode for minutes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["read_image", "MAX_IMAGE_PIXELS"]

# 50 Mpx: above every camera FluoGuide calibrates (a 4K frame is 8.3 Mpx)
MAX_IMAGE_PIXELS = 50_000_000


def _header_size(path):
    """(width, height) from the file's header, or None when PIL cannot tell.

    Pillow refuses to open a header claiming more than twice its own limit
    (``DecompressionBombError``, 179 Mpx) and warns above it (89 Mpx); both
    are above :data:`MAX_IMAGE_PIXELS`, so the first is a size too large (its
    pixel count read from Pillow's message) and the second is not said (the
    image is refused here, in one line). Refused images had been left to
    OpenCV, which decoded them and printed libpng's errors.
    """
    import re
    import warnings

    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - matplotlib brings Pillow
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:  # lazy: reads the header only
                return im.size
    except Image.DecompressionBombError as exc:
        m = re.search(r"\((\d+) pixels\)", str(exc))
        return (int(m.group(1)) if m else 2 * Image.MAX_IMAGE_PIXELS + 1, 1)
    except Exception:  # PIL does not know every format cv2 reads; cv2 decides below
        return None


def read_image(path, field=None, max_pixels=MAX_IMAGE_PIXELS, flags=None):
    """The image at ``path`` as an array (OpenCV's ``IMREAD_UNCHANGED`` by default).

    ``.npy`` files are read with numpy (no pickles). Refused with a
    FluoInputError naming the file: not a regular file, more than
    ``max_pixels`` pixels claimed, undecodable, empty.
    """
    path = Path(path)
    if not path.is_file():
        raise FluoInputError("image not found" if not path.exists() else "not a regular file",
                             file=path, field=field)
    if path.suffix.lower() == ".npy":
        try:
            head = np.load(path, mmap_mode="r", allow_pickle=False)
            if head.size > max_pixels * 4:
                raise FluoInputError(f"image too large (more than {max_pixels} pixels)",
                                     file=path, field=field, value=head.shape)
            img = np.array(head)
        except (OSError, ValueError, EOFError) as exc:
            raise FluoInputError(f"cannot read ({str(exc)[:120]})", file=path, field=field) from None
    else:
        import cv2

        size = _header_size(path)
        if size is not None and size[0] * size[1] > max_pixels:
            raise FluoInputError(f"image too large (more than {max_pixels} pixels)", file=path,
                                 field=field, value=size)
        from fluoguide.library_errors import native_stderr_quiet

        with native_stderr_quiet():     # libpng/libjpeg/libtiff print their own errors
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED if flags is None else flags)
        if img is None:
            raise FluoInputError("cannot read image (corrupt or not an image file)", file=path,
                                 field=field)
    if img.size == 0 or img.ndim not in (2, 3):
        raise FluoInputError("not a 2D image", file=path, field=field, value=img.shape)
    if np.issubdtype(img.dtype, np.floating) and not np.all(np.isfinite(img)):
        raise FluoInputError("image has NaN or inf pixels", file=path, field=field)
    if not (np.issubdtype(img.dtype, np.number) and not np.issubdtype(img.dtype, np.complexfloating)):
        raise FluoInputError("image must hold real numbers", file=path, field=field,
                             value=str(img.dtype))
    return img
