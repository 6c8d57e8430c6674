"""The target-free stroke measure (eval/metrics.py stroke_descriptor / stroke_distance) on real images: LLFF fern
photos against the four paintings of ../shared/data/styles. Skipped (with a message) when the data is absent.

The cases, per photo and painting:
- photo: the un-stylized scene (what "no stylization" shows);
- sticker: the painting center-cropped and resized to the view (built here with the stylize outputs' own crop,
  not with the metric's);
- painting-like: the painting's strokes laid out by the photo ("texture by numbers": every 8x8 block of the
  photo replaced by the painting block, same size, of closest mean colour): the photo's layout, the painting's
  brushwork, no trained model;
- blurred painting-like: the same, blurred (σ 3 px): layout and palette kept, strokes smeared.
A measure of strokes must put the sticker near the painting, the painting-like image closer than the photo,
and the blurred one behind the sharp one.

Where it does not discriminate (measured): fern against The Starry Night. The fern's fine leaflets already have
the painting's stroke statistics (photo 0.073; painting-like 0.094; blurred 0.065), so on that pair the photo is
as close as anything built from the painting; `evaluate` then marks the metric "not discriminating" through the
un-stylized anchor. The ordering is asserted for the other three paintings, and the exception is recorded by its
own test (it fails if the measure starts separating them, so this note is revisited)."""
import cv2
import numpy as np
import pytest

from _io_helpers import data_root
from tlvg_warp.eval import metrics as M
from tlvg_warp.stylize.outputs import _fit_painting

ROOT = data_root()
pytestmark = pytest.mark.skipif(ROOT is None,
                                reason="../shared/data (or $TLVG_DATA) not found: real-image stroke tests skipped")
PAINTINGS = ("starry_night.jpg", "shipwreck.jpg", "starry_night_over_the_rhone.png", "monet_san_giorgio.jpg")
ORDERED = PAINTINGS[1:]  # see the module doc for starry_night
PHOTOS = 2  # fern images_8 (504x378): enough views for the ordering, quick on a CPU
BLOCK = 8
STICKER_NEAR = 0.3  # the sticker is within this fraction of the photo's distance (measured: 0.05-0.25)


def _read(path):
    a = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return cv2.cvtColor(a, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def texture_by_numbers(photo, painting, block=BLOCK):
    h, w = photo.shape[:2]
    ph, pw = painting.shape[:2]
    p = cv2.resize(painting, (round(pw * h / ph), h), interpolation=cv2.INTER_AREA)
    cands = np.stack([p[y:y + block, x:x + block] for y in range(0, p.shape[0] - block, block // 2)
                      for x in range(0, p.shape[1] - block, block // 2)])  # [K,b,b,3]
    means = cands.mean((1, 2))  # [K,3]
    out = np.empty_like(photo)
    for y in range(0, h, block):
        for x in range(0, w, block):
            t = photo[y:y + block, x:x + block]
            k = int(np.argmin(((means - t.mean((0, 1))) ** 2).sum(1)))
            out[y:y + block, x:x + block] = cands[k][:t.shape[0], :t.shape[1]]
    return out


@pytest.fixture(scope="module")
def distances():
    photos = [_read(p) for p in sorted((ROOT / "scenes" / "fern_llff" / "images_8").glob("*.png"))[:PHOTOS]]
    out = {}
    for name in PAINTINGS:
        painting = _read(ROOT / "styles" / name)
        ref = M.stroke_descriptor(painting)
        rows = {"photo": [], "sticker": [], "painting_like": [], "blurred": [], "oil": []}
        for ph in photos:
            h, w = ph.shape[:2]
            like = texture_by_numbers(ph, painting)
            oil = cv2.xphoto.oilPainting(cv2.cvtColor((ph * 255).astype(np.uint8), cv2.COLOR_RGB2BGR), 7, 1)
            for k, img in (("photo", ph), ("sticker", _fit_painting(painting, h, w)), ("painting_like", like),
                           ("blurred", cv2.GaussianBlur(like, (0, 0), 3.0)),
                           ("oil", cv2.cvtColor(oil, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0)):
                rows[k].append(M.stroke_distance(M.stroke_descriptor(img), ref))
        out[name] = {k: float(np.mean(v)) for k, v in rows.items()}
    return out


@pytest.mark.parametrize("painting", ORDERED)
def test_painting_like_beats_the_photo_and_the_sticker_scores_near_the_painting(distances, painting):
    d = distances[painting]
    assert d["sticker"] < STICKER_NEAR * d["photo"], d
    assert d["painting_like"] < d["photo"], d
    assert d["painting_like"] < d["blurred"], d


def test_fern_against_starry_night_is_the_recorded_exception(distances):
    d = distances["starry_night.jpg"]
    assert d["sticker"] < STICKER_NEAR * d["photo"], d  # the sticker still scores near the painting
    assert d["photo"] <= d["painting_like"], d


def test_the_painting_itself_is_at_zero_and_a_photo_is_not():
    painting = _read(ROOT / "styles" / "starry_night.jpg")
    ref = M.stroke_descriptor(painting)
    assert M.stroke_distance(M.stroke_descriptor(painting), ref) == 0.0
    photo = _read(sorted((ROOT / "scenes" / "fern_llff" / "images_8").glob("*.png"))[0])
    # brightness and contrast do not count (the luminance is standardized): the strokes do
    same = M.stroke_distance(M.stroke_descriptor(0.5 * painting + 0.2), ref)
    assert same < 0.01
    assert M.stroke_distance(M.stroke_descriptor(photo), ref) > 5 * same
