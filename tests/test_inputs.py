import numpy as np
import pytest
from PIL import Image

from physgm.inputs import frame_object, load_photo, object_mask, segment_foreground


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def synthetic_photo(h=180, w=240, textured=True, seed=0):
    """An orange, shaded ellipse on a cluttered (textured) or plain grey background, and its true mask."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:h, :w]
    if textured:
        stripes = 0.5 + 0.25 * np.sin(xx / 5.0)[..., None] * np.array([1.0, 0.8, 0.6])
        blocks = rng.uniform(0.2, 0.6, (h // 12 + 1, w // 12 + 1, 3)).repeat(12, 0).repeat(12, 1)[:h, :w]
        bg = 0.5 * stripes + 0.5 * blocks * np.array([0.5, 0.7, 1.0])
    else:
        bg = np.full((h, w, 3), 0.85)
    mask = ((yy - h * 0.55) / (h * 0.3)) ** 2 + ((xx - w * 0.5) / (w * 0.22)) ** 2 < 1
    shade = 0.7 + 0.3 * (1 - (yy - h * 0.3) / h)[..., None]
    obj = np.array([0.95, 0.45, 0.1]) * shade + rng.normal(0, 0.02, (h, w, 3))
    img = np.where(mask[..., None], obj, bg)
    return np.clip(img, 0, 1).astype(np.float32), mask


@pytest.mark.parametrize("textured", [True, False])
def test_segmentation_recovers_known_mask(textured):
    img, truth = synthetic_photo(textured=textured)
    assert iou(segment_foreground(img), truth) >= 0.8


def test_segmentation_is_the_same_every_time_in_one_process():
    """GrabCut seeds its colour models from OpenCV's global generator, which each call advances: the
    shipped cluttered photo came out with 4,771, 4,727 and 11,561 object pixels in three calls."""
    from pathlib import Path

    photo = load_photo(Path(__file__).resolve().parents[1] / "examples" / "wood_toy_cluttered.jpg")
    first, *again = (segment_foreground(photo.rgb) for _ in range(3))
    assert all((m == first).all() for m in again)


def test_load_photo_kinds(tmp_path):
    rgb8 = (np.random.default_rng(0).uniform(0, 1, (20, 30, 3)) * 255).astype(np.uint8)
    Image.fromarray(rgb8).save(tmp_path / "rgb.png")
    Image.fromarray(rgb8).save(tmp_path / "rgb.jpg", quality=95)
    rgba = np.concatenate([rgb8, np.full((20, 30, 1), 255, np.uint8)], -1)
    rgba[:5, :, 3] = 0
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    Image.fromarray(rgb8[..., 0]).save(tmp_path / "grey.png")
    Image.fromarray(rgb8[..., 0].astype(np.uint16) * 257).save(tmp_path / "grey16.png")

    p = load_photo(tmp_path / "rgb.png")
    assert p.rgb.shape == (20, 30, 3) and p.alpha is None and p.rgb.dtype == np.float32
    np.testing.assert_allclose(p.rgb, rgb8 / 255.0, atol=1e-6)
    assert load_photo(tmp_path / "rgb.jpg").rgb.shape == (20, 30, 3)
    a = load_photo(tmp_path / "rgba.png")
    assert a.alpha is not None and a.alpha[:5].max() == 0 and a.alpha[5:].min() == 1
    g = load_photo(tmp_path / "grey.png")
    np.testing.assert_allclose(g.rgb[..., 0], g.rgb[..., 2])
    g16 = load_photo(tmp_path / "grey16.png")
    np.testing.assert_allclose(g16.rgb[..., 0], rgb8[..., 0] / 255.0, atol=1e-4)


def test_bad_photos_give_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_photo(tmp_path / "missing.png")
    (tmp_path / "notes.png").write_text("this is text, not an image")
    with pytest.raises(ValueError, match="not an image"):
        load_photo(tmp_path / "notes.png")
    Image.fromarray(np.zeros((64, 64, 3), np.uint8) + 100).save(tmp_path / "full.png")
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="truncated or corrupt|not an image"):
        load_photo(tmp_path / "cut.png")
    # A 20000 x 20000 PNG is rejected from its header, before 1.6 GB are decoded.
    Image.new("L", (20000, 20000)).save(tmp_path / "huge.png", optimize=False, compress_level=9)
    with pytest.raises(ValueError, match="20000 x 20000.*largest side"):
        load_photo(tmp_path / "huge.png")


def test_alpha_and_mask_file_win_and_empty_mask_fails(tmp_path):
    img, truth = synthetic_photo(textured=True)
    rgba = np.concatenate([img, truth[..., None].astype(np.float32)], -1)
    Image.fromarray((rgba * 255).astype(np.uint8)).save(tmp_path / "obj.png")
    mask, source = object_mask(load_photo(tmp_path / "obj.png"))
    assert source == "alpha" and iou(mask, truth) > 0.99
    Image.fromarray((img * 255).astype(np.uint8)).save(tmp_path / "photo.png")
    Image.fromarray(truth.astype(np.uint8) * 255).save(tmp_path / "mask.png")
    mask, source = object_mask(load_photo(tmp_path / "photo.png"), tmp_path / "mask.png")
    assert source == "mask file" and iou(mask, truth) > 0.99
    Image.fromarray(np.zeros_like(truth, np.uint8)).save(tmp_path / "empty.png")
    with pytest.raises(ValueError, match="no object found"):
        object_mask(load_photo(tmp_path / "photo.png"), tmp_path / "empty.png")


def test_frame_object_centres_and_scales():
    img, truth = synthetic_photo(textured=False)
    rgb, cover = frame_object(img, truth, size=64, fill=0.8)
    assert rgb.shape == (64, 64, 3) and cover.shape == (64, 64)
    mask = cover > 0.5
    ys, xs = np.nonzero(mask)
    assert abs((ys.min() + ys.max()) / 2 - 31.5) <= 1 and abs((xs.min() + xs.max()) / 2 - 31.5) <= 1
    assert max(ys.max() - ys.min(), xs.max() - xs.min()) + 1 == pytest.approx(0.8 * 64, abs=2)
    import cv2

    outside = ~cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.allclose(rgb[outside], 1.0, atol=1e-5)  # white outside the object


def test_a_translucent_photo_is_framed_over_white_like_the_training_renders(tmp_path):
    """An RGBA photo's colour is composited over white with its alpha, as the training views are:
    a black jelly at alpha 0.6 reads as grey 0.4 with coverage 0.6, not as an opaque black block."""
    from PIL import Image

    from physgm.pipeline.prepared_input import prepare_input

    rgba = np.zeros((64, 64, 4), np.uint8)
    rgba[16:48, 16:48, 3] = 153  # alpha 0.6 over a black object
    Image.fromarray(rgba).save(tmp_path / "jelly.png")
    inp = prepare_input(tmp_path / "jelly.png", 32)
    centre = (slice(None), slice(12, 20), slice(12, 20))
    assert inp.info["mask_source"] == "alpha"
    assert np.allclose(inp.images[0][centre].numpy(), 0.4, atol=0.01)
    assert np.allclose(inp.masks[0][centre].numpy(), 0.6, atol=0.01)
    assert np.allclose(inp.classifier_images[0][:, 100:124, 100:124].numpy(), 0.4, atol=0.01)


@pytest.mark.parametrize("profile", [None, "srgb"])
def test_cmyk_jpeg_is_converted_not_read_as_rgba(tmp_path, profile):
    """A CMYK JPEG (print workflows) has 4 channels; the 4th is K, not alpha.

    Read raw, K = 0 on the white background and on the light object looked like alpha 0 everywhere:
    "no object found (mask from alpha covers 0.00 %)". An sRGB profile attached to CMYK data is
    a mismatched profile: the loader falls back to the plain conversion instead of failing.
    """
    img, truth = synthetic_photo(textured=False)
    cmyk = Image.fromarray((img * 255).astype(np.uint8)).convert("CMYK")
    extra = {}
    if profile == "srgb":
        from PIL import ImageCms

        extra["icc_profile"] = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    cmyk.save(tmp_path / "cmyk.jpg", quality=95, **extra)
    with Image.open(tmp_path / "cmyk.jpg") as im:
        assert im.mode == "CMYK" and (profile is None) == ("icc_profile" not in im.info)
    photo = load_photo(tmp_path / "cmyk.jpg")
    assert photo.alpha is None and photo.rgb.shape == img.shape
    assert np.abs(photo.rgb - img).mean() < 0.02  # JPEG loss only: the colours come back
    mask, source = object_mask(photo)
    assert source == "segmentation" and iou(mask, truth) > 0.95


def test_palette_images_read_as_colours_and_their_transparency_as_alpha(tmp_path):
    img, truth = synthetic_photo(textured=False)
    rgb = Image.fromarray((img * 255).astype(np.uint8)).quantize(64)
    rgb.save(tmp_path / "palette.png")
    photo = load_photo(tmp_path / "palette.png")
    assert photo.alpha is None and np.abs(photo.rgb - img).mean() < 0.03  # not palette indices as grey
    rgba = Image.fromarray((np.concatenate([img, truth[..., None]], -1) * 255).astype(np.uint8), "RGBA")
    rgba.quantize(64, method=Image.Quantize.FASTOCTREE).save(tmp_path / "palette_alpha.png")
    with Image.open(tmp_path / "palette_alpha.png") as im:
        assert im.mode == "P" and "transparency" in im.info
    mask, source = object_mask(load_photo(tmp_path / "palette_alpha.png"))
    assert source == "alpha" and iou(mask, truth) > 0.99
