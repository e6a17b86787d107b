"""Photos in, object masks out: loading any ordinary image safely and finding the object in it.

The mask comes from the alpha channel when the image has one, from a user's mask file when given,
and otherwise from automatic foreground segmentation: a plain-background threshold when the image
border is uniform (studio shots), else OpenCV GrabCut seeded from the border and a centre prior.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAX_SIDE = 8192  # px; larger photos are rejected before decoding (a 20000 x 20000 PNG is 1.6 GB as RGBA)
WORK_SIDE = 512  # px; segmentation runs at most at this size, then the mask is scaled back


@dataclass
class Photo:
    """A decoded photo.

    Attributes:
        rgb: [H, W, 3] float32 in [0, 1].
        alpha: [H, W] float32 in [0, 1], or None when the file has no alpha channel.
        path: where it came from.
    """

    rgb: np.ndarray  # [H, W, 3]
    alpha: np.ndarray | None  # [H, W]
    path: Path


def load_photo(path: str | Path) -> Photo:
    """Read a PNG or JPEG (RGB, RGBA, greyscale, palette, CMYK; 8 or 16 bit); bad files are clear errors."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"input image not found: {path}")
    # PIL's own decompression-bomb guard is replaced by the MAX_SIDE check, which reads only the header.
    guard, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
    try:
        with Image.open(path) as im:
            Image.MAX_IMAGE_PIXELS = guard
            w, h = im.size
            if max(w, h) > MAX_SIDE:
                raise ValueError(
                    f"{path} is {w} x {h} px; the largest side allowed is {MAX_SIDE} px. Resize the photo "
                    "first."
                )
            im.load()
            im = _to_plain_mode(im, path)
            mode = im.mode
            arr = np.asarray(im)
    except UnidentifiedImageError as err:
        raise ValueError(f"{path} is not an image PIL can read (expected PNG or JPEG)") from err
    except (OSError, SyntaxError) as err:  # truncated or corrupt data
        raise ValueError(
            f"{path} could not be decoded ({err}); the file may be truncated or corrupt"
        ) from err
    finally:
        Image.MAX_IMAGE_PIXELS = guard
    if arr.dtype == np.uint16 or mode.startswith("I;16") or mode == "I":
        img = arr.astype(np.float32) / 65535.0
    elif arr.dtype == np.uint8:
        img = arr.astype(np.float32) / 255.0
    elif arr.dtype == bool:
        img = arr.astype(np.float32)
    else:
        img = arr.astype(np.float32)
        img = img / max(float(img.max()), 1.0)
    alpha = None
    if img.ndim == 2:  # greyscale
        rgb = np.repeat(img[..., None], 3, -1)
    elif img.shape[-1] == 2:  # greyscale + alpha
        rgb, alpha = np.repeat(img[..., :1], 3, -1), img[..., 1]
    elif img.shape[-1] == 4:
        rgb, alpha = img[..., :3], img[..., 3]
    else:
        rgb = img[..., :3]
    if min(rgb.shape[:2]) < 8:
        raise ValueError(
            f"{path} is only {rgb.shape[1]} x {rgb.shape[0]} px; need at least 8 px on each side"
        )
    return Photo(
        np.ascontiguousarray(rgb, np.float32),
        None if alpha is None else np.ascontiguousarray(alpha, np.float32),
        path,
    )


# Modes whose channels are not (grey | RGB) [+ alpha]: converted to RGB(A) before reading the array.
# Read raw, CMYK's K channel looked like alpha, a palette image's indices like grey levels.
_TO_RGB = {"CMYK", "YCbCr", "HSV", "RGBX"}
_PREMULTIPLIED = {"RGBa": "RGBA", "La": "LA"}


def _to_plain_mode(im, path: Path):
    """The image in a mode ``load_photo`` reads channel by channel: 1, L, LA, I, I;16*, F, RGB, RGBA."""
    if im.mode == "CMYK":
        return _cmyk_to_rgb(im)
    if im.mode in _TO_RGB:
        return im.convert("RGB")
    if im.mode in _PREMULTIPLIED:
        return im.convert(_PREMULTIPLIED[im.mode])
    if im.mode in ("P", "PA"):  # palette: transparency may sit in the palette or in a tRNS chunk
        return im.convert("RGBA" if im.mode == "PA" or "transparency" in im.info else "RGB")
    if im.mode not in ("1", "L", "LA", "I", "F", "RGB", "RGBA") and not im.mode.startswith("I;16"):
        raise ValueError(
            f"{path} has pixel mode {im.mode!r}, which physgm cannot read; "
            "save it as an RGB or RGBA PNG or JPEG"
        )
    return im


def _cmyk_to_rgb(im):
    """CMYK -> sRGB through the embedded ICC profile when there is one, else PIL's plain formula.

    Print CMYK files (the usual source) carry a profile, and only it says what the inks look like;
    the plain R = (1 - C)(1 - K) formula is not colour-managed, but keeps a white background white.
    """
    icc = im.info.get("icc_profile")
    if icc:
        import io

        from PIL import ImageCms

        try:
            source = ImageCms.ImageCmsProfile(io.BytesIO(icc))
            return ImageCms.profileToProfile(im, source, ImageCms.createProfile("sRGB"), outputMode="RGB")
        except (ImageCms.PyCMSError, OSError, ValueError):
            pass  # an unreadable or mismatched profile: fall back to the plain conversion
    return im.convert("RGB")


def load_mask(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """A user's mask image (white = object) as bool [H, W], resized to ``shape`` if needed."""
    import cv2

    photo = load_photo(path)
    grey = photo.rgb.mean(-1) if photo.alpha is None else photo.alpha
    if grey.shape != shape:
        grey = cv2.resize(grey, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return grey > 0.5


def _clean(mask: np.ndarray) -> np.ndarray:
    """Largest connected component with its holes filled."""
    import cv2

    m = mask.astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if count <= 1:
        return np.zeros_like(mask, bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    m = (labels == largest).astype(np.uint8)
    # Fill holes: flood the background from the border; what it does not reach is inside.
    flood = np.pad(1 - m, 1, constant_values=1)
    ff_mask = np.zeros((flood.shape[0] + 2, flood.shape[1] + 2), np.uint8)
    cv2.floodFill(flood, ff_mask, (0, 0), 2)
    return (flood[1:-1, 1:-1] != 2) | m.astype(bool)


def segment_foreground(rgb: np.ndarray, border: int | None = None) -> np.ndarray:
    """Object mask [H, W] bool of a photo without alpha.

    Args:
        rgb: [H, W, 3] float in [0, 1].
        border: width in pixels of the image frame assumed to be background (default 4 % of the side).
    """
    import cv2

    h, w = rgb.shape[:2]
    scale = min(1.0, WORK_SIDE / max(h, w))
    small = (
        cv2.resize(rgb, (max(8, round(w * scale)), max(8, round(h * scale))), interpolation=cv2.INTER_AREA)
        if scale < 1
        else rgb
    )
    sh, sw = small.shape[:2]
    b = border or max(2, round(0.04 * max(sh, sw)))
    frame = np.concatenate(
        [
            small[:b].reshape(-1, 3),
            small[-b:].reshape(-1, 3),
            small[:, :b].reshape(-1, 3),
            small[:, -b:].reshape(-1, 3),
        ]
    )
    bg_colour, bg_spread = np.median(frame, 0), np.percentile(np.abs(frame - np.median(frame, 0)).max(-1), 95)
    if bg_spread < 0.04:  # plain studio background: a colour distance threshold is exact enough
        mask = np.abs(small - bg_colour).max(-1) > max(0.08, 3 * bg_spread)
    else:
        img8 = (small * 255).astype(np.uint8)
        gc = np.full((sh, sw), cv2.GC_PR_BGD, np.uint8)
        gc[:b], gc[-b:], gc[:, :b], gc[:, -b:] = cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD
        # Centre prior: the middle of the frame is probably the object.
        cy, cx, ry, rx = sh // 2, sw // 2, max(1, sh // 8), max(1, sw // 8)
        gc[cy - ry : cy + ry, cx - rx : cx + rx] = cv2.GC_PR_FGD
        bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        # GrabCut starts its colour models by k-means on OpenCV's global random generator, which
        # every call advances: the same photo segmented again in one process came out with 4,727 or
        # 11,561 object pixels instead of 4,771. Seed 0 is the generator's state in a fresh process.
        cv2.setRNGSeed(0)
        cv2.grabCut(cv2.cvtColor(img8, cv2.COLOR_RGB2BGR), gc, None, bgd, fgd, 6, cv2.GC_INIT_WITH_MASK)
        mask = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    mask = _clean(
        cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool)
    )
    if scale < 1:
        mask = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    return mask


def object_mask(
    photo: Photo, mask_path: str | Path | None = None, min_fraction: float = 0.002
) -> tuple[np.ndarray, str]:
    """The object mask and where it came from ("mask file", "alpha", "segmentation").

    Raises:
        ValueError: the mask is empty or tiny: no object was found.
    """
    h, w = photo.rgb.shape[:2]
    if mask_path is not None:
        mask, source = load_mask(mask_path, (h, w)), "mask file"
    elif photo.alpha is not None and (photo.alpha < 0.5).any():
        mask, source = photo.alpha > 0.5, "alpha"
    else:
        mask, source = segment_foreground(photo.rgb), "segmentation"
    if mask.mean() < min_fraction:
        raise ValueError(
            f"no object found in {photo.path} (mask from {source} covers {100 * mask.mean():.2f} % of the "
            "image). Give a mask with mask=path.png, use a PNG with an alpha channel, or crop the photo "
            "around the object."
        )
    return mask, source


def frame_object(
    rgb: np.ndarray,  # [H, W, 3]
    mask: np.ndarray,  # [H, W] bool
    size: int,
    fill: float,
    matte: np.ndarray | None = None,  # [H, W] coverage in [0, 1] (a photo's alpha); None: the mask
) -> tuple[np.ndarray, np.ndarray]:  # [size, size, 3], [size, size] float in [0, 1]
    """Crop a square around the object (``mask``'s bounding box) so it spans ``fill`` of the side,
    resized to ``size``: the colour composited over white with ``matte``, and the matte.

    With a photo's alpha as the matte, translucent parts (jelly, glass) keep the look of the
    training renders, which are their RGBA composited over white, and soft edges stay soft.
    """
    import cv2

    ys, xs = np.nonzero(mask)
    cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
    half = max(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1) / (2 * fill)
    x0, y0 = cx - half, cy - half
    # Affine map from the crop square to the output grid; outside the photo is white background.
    m = np.array(
        [[size / (2 * half), 0, -x0 * size / (2 * half)], [0, size / (2 * half), -y0 * size / (2 * half)]],
        np.float32,
    )
    cover = (mask if matte is None else matte).astype(np.float32)
    comp = rgb * cover[..., None] + (1 - cover[..., None])
    out_rgb = cv2.warpAffine(
        comp.astype(np.float32), m, (size, size), flags=cv2.INTER_AREA, borderValue=(1, 1, 1)
    )
    out_cover = cv2.warpAffine(cover, m, (size, size), flags=cv2.INTER_LINEAR, borderValue=0)
    return np.clip(out_rgb, 0, 1), np.clip(out_cover, 0, 1)
