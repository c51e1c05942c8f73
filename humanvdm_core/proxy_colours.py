"""The clothed proxy's colours: the photo on the side it shows, a guess from it on the side it does not.

Step 8 of :func:`humanvdm_core.clothed_proxy.build_clothed_proxy`'s contract; one texture,
``[front | back]`` side by side:

* front: the photo, its silhouette band (:data:`BAND_PX` px) eroded and refilled from inside, blurred
  there (:func:`refill_band`), so no background colour smears onto the edge and the edge's rows do not run
  out as streaks over the rim a side view sees; in the head's band, where the photo shows hair there (the
  temples), the hair's colour instead of the skin inside it (:func:`hair_in_band`);
* back (the unseen side, :func:`unseen_side_colours`): each back pixel takes, for its body part (the
  part of the farthest body surface there; outside the body, the nearest part), the median colour of
  that part's visible pixels at the same height (:func:`row_medians`, :data:`PRINT_BAND`; a row where
  little of the part shows, a shirt between crossed forearms, takes a neighbour's): garments
  keep their colours from top to bottom, but a print, logo, tie or held object narrower than half the
  part is not carried over, nor a wider print on the torso a few rows tall whose colour does not recur
  (:func:`without_print_runs`; stripes recur and stay); arms and legs take their medians per side of
  the body (what one hand holds stays off the other arm); where the torso or the legs are both the
  nearest and the farthest surface, the torso and the legs take one median per row, so the garment's
  own hem decides, not the body's waist line; a torso row of the neckline (from the base of the neck
  to :data:`NECKLINE_DEPTH` below the shoulders' top) that shows clothing beside skin of the face's
  colour (:func:`face_colour`, :data:`NECKLINE_SHARE`: a collar, a V-neck) takes the clothing's median
  only, since a top covers more of the back than of the front; skin of the face's colour within
  :data:`ARM_SKIN_REACH` of the fitted arms and hands (a forearm held before the torso, wider in the
  photo than the fitted one) is theirs, no source of the torso's colours (nor of those it shares with the
  legs), so crossed arms leave no band of skin on the back; hands keep their own colour; the back of
  each foot is its shoe, the colour of the foot's lowest rows in the photo (:func:`shoes`); a thick
  region outside the body (a held object, a hat, a coat's flare) takes its own median per row, not the
  nearest part's; "the same height" is the height in the world for the torso and the legs: seen from
  above, the unseen side lies lower than the seen one along each ray, so its hem, belt or waistline comes
  from the photo's rows that show that height (``source_rows``);
* the head's back (part ``head`` behind what the photo shows as the head; behind a collar or a
  shoulder the neck takes the clothing's colour) is the hair colour sampled at the top of the head in
  the photo, a forehead showing there left out (:func:`hair_colour`), so no face appears on the back;
  long hair seen beside the neck (:func:`hair_curtain`, where hair and clothes can be told apart:
  :func:`distinct_hair_curtain`) takes it too; when the photo shows the person's back, the unseen side
  is the front and the head there takes the head's own median colour (no face is invented); when it
  shows the person in profile, the far side of the head is the near side mirrored: the photo's own
  colours there.
"""

from __future__ import annotations

import cv2
import numpy as np

from humanvdm_core.body.parts import PARTS
from humanvdm_core.image_fill import nearest_fill

BAND_PX = 4  # silhouette band (input-view pixels) eroded and refilled from inside ...
BAND_BLUR = 3.0  # ... and blurred there (Gaussian sigma, input-view pixels)
PRINT_BAND = 0.02  # rows each side whose colours a row of the unseen side takes the median of, fraction of the frame
ROW_MIN_SHARE = 0.25  # ... a row whose window shows less than this share of the part's median window takes a neighbour's
HAIR_DISTANCE = 0.25  # RGB distance within which a pixel counts as the hair's colour
SKIN_CHROMA = 0.035  # chromaticity distance (rgb / sum) within which a pixel counts as the face's skin ...
SKIN_BRIGHTNESS = (0.45, 1.6)  # ... at a brightness between these multiples of the face's
SKIN_CR = (135, 180)  # any_skin: the YCrCb Cr range of skin of any tone (8 bits) ...
SKIN_CB = (80, 135)  # ... and its Cb range
MIN_SKIN_PX = 32  # hands_skin: the skin pixels needed to take a colour from them
ARM_SKIN_REACH = 0.03  # skin within this fraction of the frame of the fitted arms and hands is theirs (see below)
NECKLINE_SHARE = 0.25  # a torso row with at least this share of non-skin pixels is clothed at the back ...
NECKLINE_DEPTH = 0.15  # ... from the neck's base to this fraction of the person's height below the shoulders' top
SHOE_ROWS = 0.3  # the lowest share of a foot's rows in the photo that shows its shoe (toe box, sole)
PAIRED = ("arms", "legs")  # parts whose unseen side is coloured per side of the body
BY_HEIGHT = ("torso", "legs")  # parts whose unseen side takes the photo's colours at its own world height
LOOSE_OWN_MIN = 0.005  # a region outside the body covering this share of the mask keeps its own colours at the back ...
LOOSE_OWN_OPEN = 0.015  # ... once thinner parts than this fraction of the frame are cut off (a sliver of background)
PRINT_RUN = (0.03, 0.1)  # rows (fraction of the person's height) a print wider than half the garment spans ...
PRINT_STEP = 0.12  # ... its colour this far (RGB) from the garment's running median ...
PRINT_WINDOW = 0.1  # ... over this fraction of the person's height each side ...
PRINT_SAME = 0.08  # ... the garment above and below it this close to each other, and its colour not recurring
HAIR_BAND = 0.2  # the top this fraction of the head's projected height is sampled for the hair colour ...
FACE_ROWS = (0.55, 0.75)  # ... less what has the colour of the face's skin (these rows of the head, its middle fifth) ...
HAIR_SHARE = 0.2  # ... when at least this share of the band is left
HAIR_UPPER = 0.4  # else the head above this fraction of its projected height (down from its top) is searched


def inside_band(person: np.ndarray, band_px: int = BAND_PX) -> np.ndarray:
    """(H, W bool): ``person`` less its silhouette band, ``band_px`` pixels deep (an elliptical erosion)."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1, 2 * band_px + 1))
    return cv2.erode(person.astype(np.uint8), kernel).astype(bool)


def refill_band(rgb: np.ndarray, mask: np.ndarray, band_px: int = BAND_PX, band_blur: float = BAND_BLUR) -> np.ndarray:
    """``rgb`` with the mask's silhouette band (``band_px``) and everything outside replaced by the
    nearest pixel further inside, so edge pixels never mix in the background, and then blurred (a Gaussian
    of ``band_blur`` px) there: each row's colour at the edge, which a side view sees stretched over the
    proxy's rim, blends with its neighbours' instead of running out as a streak."""
    person = mask > 0.5
    inner = inside_band(person, band_px)
    if inner.sum() < 64:
        inner = person
    out = nearest_fill(rgb, inner)
    # the band seen from the side stretches over the sheets' steep rim: blurred, its rows blend instead of
    # running out as streaks of the edge's colours
    return np.where((~inner)[..., None], cv2.GaussianBlur(out, (0, 0), band_blur), out)


def hair_in_band(front: np.ndarray, photo: np.ndarray, mask: np.ndarray, head: np.ndarray, hair: np.ndarray,
                 band_px: int = BAND_PX, band_blur: float = BAND_BLUR) -> np.ndarray:
    """``front`` (the photo with its silhouette band refilled, :func:`refill_band`) where the photo shows
    hair in the head's band: the hair's colour ``hair`` there, not the face's skin refilled from inside. At
    the temples the hair seen from the front is a strip a few pixels wide along the head's outline; the
    band's refill replaced it with the forehead's and the cheeks' skin, which a side view then saw
    stretched over the side of the head up to the ears. A band pixel of the ``head`` (H, W bool) is hair
    where most of the band's pixels within ``band_px`` of it that lie a pixel or more inside the outline
    (the outline's own pixels mix in the background) are within :data:`HAIR_DISTANCE` of ``hair``; along
    the band it blends to ``hair`` over ``band_blur`` px. Outside the head's band ``front`` is returned unchanged."""
    person = mask > 0.5
    band = person & ~inside_band(person, band_px) & head
    if not band.any():
        return front
    probe = band & cv2.erode(person.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    near = probe & (np.linalg.norm(photo - np.asarray(hair, np.float32)[None, None], axis=2) < HAIR_DISTANCE)
    window = (2 * band_px + 1, 2 * band_px + 1)
    share = cv2.boxFilter(near.astype(np.float32), -1, window, normalize=False) / np.maximum(
        cv2.boxFilter(probe.astype(np.float32), -1, window, normalize=False), 1.0)
    hairy = cv2.GaussianBlur((band & (share >= 0.5)).astype(np.float32), (0, 0), band_blur)
    weight = hairy / np.maximum(cv2.GaussianBlur(band.astype(np.float32), (0, 0), band_blur), 1e-6) * band
    return front * (1.0 - weight[..., None]) + np.asarray(hair, np.float32)[None, None] * weight[..., None]


def median_colour(pixels: np.ndarray) -> np.ndarray:
    """(C,) the median colour of ``pixels`` (N, C) as a colour they have: the mean of the pixels whose
    brightness (channel mean) lies in the middle fifth of theirs. A per-channel median mixes the
    channels of different pixels (half a light shirt and half dark jeans give a skin tone)."""
    order = np.argsort(pixels.mean(axis=1), kind="stable")
    n = len(order)
    lo, hi = int(0.4 * n), max(int(0.4 * n) + 1, int(np.ceil(0.6 * n)))
    return pixels[order[lo:hi]].mean(axis=0)


def skin_like(image: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of about the colour ``skin`` (3,) -- chromaticity within :data:`SKIN_CHROMA`,
    brightness within :data:`SKIN_BRIGHTNESS` of it, so a shadowed neck still counts."""
    total = image.sum(axis=2, keepdims=True) + 1e-3
    ref = np.asarray(skin, np.float32)
    chroma = np.linalg.norm(image / total - ref / (ref.sum() + 1e-3), axis=2)
    ratio = image.mean(axis=2) / max(float(ref.mean()), 1e-3)
    return (chroma < SKIN_CHROMA) & (ratio > SKIN_BRIGHTNESS[0]) & (ratio < SKIN_BRIGHTNESS[1])


def any_skin(image: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of ``image`` (RGB float in [0, 1]) whose chroma lies in the range of human skin
    of any tone (:data:`SKIN_CR`, :data:`SKIN_CB` in YCrCb, 8 bits), for a photo that shows no face to
    take the skin's colour from."""
    ycc = cv2.cvtColor((np.clip(image, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2YCrCb)
    cr, cb = ycc[..., 1], ycc[..., 2]
    return (cr >= SKIN_CR[0]) & (cr <= SKIN_CR[1]) & (cb >= SKIN_CB[0]) & (cb <= SKIN_CB[1])


def row_medians(image: np.ndarray, select: np.ndarray, band: int, prefer: np.ndarray | None = None,
                share: float = NECKLINE_SHARE, prefer_rows: tuple[int, int] | None = None,
                min_share: float = ROW_MIN_SHARE) -> np.ndarray:
    """(H, C): per image row, the median colour (:func:`median_colour`) of the ``select``ed pixels within
    ``band`` rows of it (rows with none, or with fewer than ``min_share`` of the median row's -- the few
    pixels of a shirt that crossed forearms leave, a badge or a shadow -- take the nearest row that has
    enough); with ``prefer`` (a subset of ``select``) and in the rows ``prefer_rows`` (start, stop; all
    without), only of those where they are at least ``share`` of the row's."""
    h = image.shape[0]
    out = np.full((h, image.shape[2]), np.nan, np.float32)
    counts = select.sum(axis=1)
    preferred = prefer.sum(axis=1) if prefer is not None else None
    windows = np.convolve(counts, np.ones(2 * band + 1), mode="same")  # selected pixels within band rows of each
    floor = min_share * np.median(windows[windows > 0]) if (windows > 0).any() else 0.0
    for y in range(h):
        y0, y1 = max(0, y - band), min(h, y + band + 1)
        n = windows[y]
        if n == 0 or n < floor:
            continue
        if (preferred is not None and (prefer_rows is None or prefer_rows[0] <= y < prefer_rows[1])
                and preferred[y0:y1].sum() >= max(1, share * n)):
            out[y] = median_colour(image[y0:y1][prefer[y0:y1]])
        else:
            out[y] = median_colour(image[y0:y1][select[y0:y1]])
    have = np.nonzero(np.isfinite(out[:, 0]))[0]
    if len(have) == 0:
        return np.zeros_like(out)
    nearest = have[np.clip(np.searchsorted(have, np.arange(h)), 0, len(have) - 1)]
    before = have[np.clip(np.searchsorted(have, np.arange(h)) - 1, 0, len(have) - 1)]
    pick = np.where(np.abs(before - np.arange(h)) < np.abs(nearest - np.arange(h)), before, nearest)
    return out[pick]


def without_print_runs(per_row: np.ndarray, shown: np.ndarray, height: int, band: int) -> np.ndarray:
    """``per_row`` (H, C) with each run of rows that looks like a print wider than half the part replaced by
    the colours around it: a run :data:`PRINT_RUN` (min, max) of ``height`` tall whose colour stands more
    than :data:`PRINT_STEP` from the garment's running median (over :data:`PRINT_WINDOW` of ``height`` each
    side), the garment above and below it (``band`` rows beyond it: the medians' window smooths the run
    into them) within :data:`PRINT_SAME` of each other, and whose colour fewer other rows of the part have
    than half its own (a striped shirt's stripes recur and stay; the few rows of a transition between
    two garments do not count). ``shown``: (H,) bool, the rows the part is seen in."""
    rows = np.nonzero(shown)[0]
    if len(rows) < 3 or height <= 0:
        return per_row
    out = per_row.copy()
    y0 = int(rows.min())
    c = per_row[y0:int(rows.max()) + 1]
    n = len(c)
    w = max(1, int(PRINT_WINDOW * height))
    ref = np.stack([np.median(c[max(0, i - w):i + w + 1], axis=0) for i in range(n)])
    off = np.append(np.linalg.norm(c - ref, axis=1) > PRINT_STEP, False)
    off[0] = False  # a run at the top has no garment above it
    starts = np.nonzero(off[1:] & ~off[:-1])[0] + 1
    ends = np.nonzero(off[:-1] & ~off[1:])[0] + 1
    for start, end in zip(starts, ends, strict=True):
        a, b = start - band, end + band
        if not PRINT_RUN[0] * height <= end - start <= PRINT_RUN[1] * height or a < 1 or b >= n:
            continue
        above, below = c[a - 1], c[b]
        if np.linalg.norm(above - below) > PRINT_SAME:
            continue
        colour = np.median(c[start:end], axis=0)
        elsewhere = np.ones(n, bool)
        elsewhere[a:b] = False
        if (np.linalg.norm(c[elsewhere] - colour, axis=1) <= PRINT_SAME).sum() >= max(3, (end - start) // 2):
            continue
        t = ((np.arange(a, b) - a + 0.5) / (b - a))[:, None]
        out[y0 + a:y0 + b] = (1 - t) * above + t * below
    return out


def unseen_side_colours(photo: np.ndarray, mask: np.ndarray, front_part: np.ndarray, back_part: np.ndarray,
                        head_colour: np.ndarray | None, front_side: np.ndarray | None = None,
                        back_side: np.ndarray | None = None, skin_colour: np.ndarray | None = None,
                        loose: np.ndarray | None = None, profile: bool = False,
                        source_rows: np.ndarray | None = None, back_face: np.ndarray | None = None,
                        face_skin: np.ndarray | None = None, hair_curtain: bool = True) -> np.ndarray:
    """The colour of the unseen side per input-view pixel (contract step 8, "back"): per body part, the
    median colour of that part's visible pixels at the same height (:data:`PRINT_BAND` of the frame):
    garments keep their colours from top to bottom, while prints, logos, ties, buttons and held
    objects narrower than half the part are not carried over (on the torso, nor a wider print a few
    rows tall: :func:`without_print_runs`); with ``skin_colour`` the skin within :data:`ARM_SKIN_REACH` of
    the fitted arms and hands (an arm held before the torso, wider in the photo than the fitted one) is
    no source of the torso's colours, nor of the torso's and the legs' shared ones (below), unless that
    leaves less than half of what they show; with ``front_side`` / ``back_side`` (the body's side per
    pixel, +1 left, -1 right) each arm and leg takes the medians of its own side; the torso and the legs
    share one median per row where both the nearest and the farthest surface are one of them (the
    garment's hem, not the body's waist, divides them); hands keep their own colour, each foot takes its
    shoe's (:func:`shoes`),
    the head takes ``head_colour`` (behind a collar or a shoulder the neck takes the clothing's colour).
    With ``skin_colour`` (the face's), a torso row of the neckline (from the torso's top, the base of the
    neck, to :data:`NECKLINE_DEPTH` of the person's height below the shoulders' top, the highest arm
    pixel) that shows clothing beside skin (a collar, a V-neck, a low or open neckline) takes the
    clothing's colour only: a top covers more of the back than of the front, up to the neck. With
    ``loose`` (the mask's pixels outside the body), each of its connected regions at least
    :data:`LOOSE_OWN_OPEN` of the frame thick and :data:`LOOSE_OWN_MIN` of the mask large (a held object,
    a hat, a coat's or a skirt's flare) takes its own median per row, not the nearest body part's, and
    is left out of the parts' medians: a box held beside the jeans is not jeans at the back. With
    ``profile`` (the photo shows the person from the side) the far side of the head is its near side
    mirrored, and the camera's rays cross the head's midplane, so one pixel shows both: wherever the head
    is both the nearest and the farthest surface it keeps the photo's own colours (the other cheek, ear
    and hair), not ``head_colour`` over half a face. With ``source_rows`` (H, W float: per pixel the row at
    which the photo shows the world height of the unseen side's point there,
    :func:`humanvdm_core.clothed_proxy.unseen_rows`) the torso's and the legs' colours (a hem, a belt, a
    waistline) and long hair come from that row (fractional: the two nearest blended), not the pixel's
    own; the arms, the hands, the head and what lies outside the body keep their own rows. With
    ``back_face`` (H, W float in [0, 1]: how much the farthest surface is the face, the head's front, as
    where a person turned from the camera shows the far cheek) and ``face_skin`` (the face's skin colour;
    for a photo from behind, :func:`hands_skin`), the head there blends from ``head_colour`` to it. ``hair_curtain`` False (a photo from behind: the hair it shows hangs on its own side)
    paints no hair curtain on the unseen side."""
    size = photo.shape[0]
    band = max(1, int(PRINT_BAND * size))
    person = mask > 0.5
    clothed = ~skin_like(photo, skin_colour) if skin_colour is not None else None
    # ... in the neckline's rows: from the torso's top (the base of the neck: a row there that shows a collar
    # beside the neck is the collar at the back, one that shows only the neck stays skin; or the shoulders'
    # top, the highest arm pixel, if higher) down NECKLINE_DEPTH of the person's height below the shoulders'
    # top (below it a hem's rows keep their plain median)
    arm_rows = np.nonzero((person & (front_part == PARTS.index("arms"))).any(axis=1))[0]
    rows = np.nonzero(person.any(axis=1))[0]
    height = int(rows.max() - rows.min() + 1) if len(rows) else 0
    top = int(arm_rows.min()) if len(arm_rows) else 0
    torso_rows = np.nonzero((person & (front_part == PARTS.index("torso"))).any(axis=1))[0]
    start = min(top, int(torso_rows.min())) if len(torso_rows) else top
    neckline = (start, top + int(NECKLINE_DEPTH * height)) if len(rows) else None
    out = nearest_fill(photo, person).astype(np.float32)
    # the back of the neck behind a collar or a shoulder is the clothing's, not the hair's: the head's
    # colour goes only behind what the photo shows as the head
    head = PARTS.index("head")
    back_part = np.where((back_part == head) & np.isin(front_part, [PARTS.index("torso"), PARTS.index("arms")]),
                         front_part, back_part)
    # what lies outside the body (a held object, a hat, a coat's or a skirt's flare) takes its own colours at
    # the back, not those of the body part nearest to it (per thick connected region, its median per row),
    # and is no source of the parts' colours
    regions = []
    if loose is not None:
        k = max(3, int(LOOSE_OWN_OPEN * size) | 1)
        thick = cv2.morphologyEx((loose & person).astype(np.uint8), cv2.MORPH_OPEN,
                                 cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
        n, labels, stats, _ = cv2.connectedComponentsWithStats(thick, connectivity=8)
        regions = [labels == i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= LOOSE_OWN_MIN * person.sum()]
    kept_apart = np.logical_or.reduce(regions) if regions else np.zeros_like(person)

    # the photo's skin within ARM_SKIN_REACH of the fitted arms and hands is theirs where the fitted arm is
    # thinner than the photo's (crossed forearms, hands clasped before the torso): no source of the trunk's
    # colours (its back would show a band of the arms' skin), unless that leaves the trunk less than half
    # of what it shows (a bare chest)
    arm_skin = np.zeros_like(person)
    if skin_colour is not None:
        skin = person & skin_like(photo, skin_colour)
        limbs = person & np.isin(front_part, [PARTS.index("arms"), PARTS.index("hands")])
        near = cv2.distanceTransform((~limbs).astype(np.uint8), cv2.DIST_L2, 5) <= ARM_SKIN_REACH * size
        arm_skin = skin & near & (front_part != PARTS.index("head"))

    def at_rows(per_row: np.ndarray, where: np.ndarray, by_height: bool) -> np.ndarray:
        """``per_row`` (H, C) at the pixels ``where``: of each one's ``source_rows`` row if ``by_height``
        (the torso and the legs), else of its own row."""
        ys, xs = np.nonzero(where)
        if source_rows is None or not by_height:
            return per_row[ys]
        r = np.clip(source_rows[ys, xs], 0, size - 1)
        lo = np.floor(r).astype(np.int64)
        t = (r - lo)[:, None].astype(np.float32)
        return per_row[lo] * (1 - t) + per_row[np.minimum(lo + 1, size - 1)] * t

    def shown(select: np.ndarray) -> np.ndarray:
        rest = select & ~kept_apart
        return rest if rest.sum() >= 4 else select

    def trunk_shown(select: np.ndarray) -> np.ndarray:
        rest = shown(select)
        own = rest & ~arm_skin
        return own if own.sum() >= 0.5 * rest.sum() and own.sum() >= 4 else rest

    for p in range(len(PARTS)):
        want = back_part == p
        source = (trunk_shown if PARTS[p] == "torso" else shown)(person & (front_part == p))
        if not want.any() or source.sum() < 4:
            continue
        if PARTS[p] == "head" and head_colour is not None:
            if back_face is not None and face_skin is not None:  # the far cheek of a person turned away
                w = back_face[want][:, None]
                out[want] = (1.0 - w) * np.asarray(head_colour, np.float32) + w * np.asarray(face_skin, np.float32)
            else:
                out[want] = head_colour
        elif PARTS[p] == "hands":
            out[want] = nearest_fill(photo, source)[want]  # skin keeps its own colour
        else:
            prefer = source & clothed if clothed is not None and PARTS[p] == "torso" else None
            per_row = row_medians(photo, source, band, prefer, prefer_rows=neckline)
            if PARTS[p] == "torso":
                per_row = without_print_runs(per_row, source.any(axis=1), height, band)
            out[want] = at_rows(per_row, want, PARTS[p] in BY_HEIGHT)
            if PARTS[p] in PAIRED and front_side is not None and back_side is not None:
                # each arm (leg) from its own visible pixels: what one hand holds stays off the other arm
                for side in (-1, 1):
                    own, own_source = want & (back_side == side), source & (front_side == side)
                    if own.any() and own_source.sum() >= 4:
                        per_row = row_medians(photo, own_source, band)
                        out[own] = at_rows(per_row, own, PARTS[p] in BY_HEIGHT)
    shoes(photo, out, shown(person & (front_part == PARTS.index("feet"))), back_part == PARTS.index("feet"),
          front_side, back_side)
    # where the torso or the legs are the farthest surface and the nearest one too (or an arm or a hand
    # held before them), the garments' own hem (a shirt over the hips, a dress over the thighs) decides,
    # not the body's waist line: one median per row over the torso and the legs together
    trunk = [PARTS.index("torso"), PARTS.index("legs")]
    source = trunk_shown(person & np.isin(front_part, trunk))
    same = np.isin(front_part, trunk + [PARTS.index("arms"), PARTS.index("hands")]) & np.isin(back_part, trunk)
    if source.sum() >= 4 and same.any():
        per_row = row_medians(photo, source, band, source & clothed if clothed is not None else None,
                              prefer_rows=neckline)
        per_row = without_print_runs(per_row, source.any(axis=1), height, band)
        out[same] = at_rows(per_row, same, True)  # the torso and the legs
    for region in regions:
        per_row = row_medians(photo, region, band)
        out[region] = at_rows(per_row, region, False)  # outside the body: its own rows
    if head_colour is not None and hair_curtain:
        hair = distinct_hair_curtain(photo, mask, front_part, np.asarray(head_colour, np.float32))
        if source_rows is not None:  # long hair hangs as far down the back as the photo shows it at the sides
            r = np.clip(np.rint(source_rows), 0, size - 1).astype(np.int64)
            hair = hair[r, np.arange(photo.shape[1])[None, :]]
        out[hair & (back_part != PARTS.index("hands"))] = head_colour
    if profile:
        mirrored = person & (front_part == head) & (back_part == head)
        out[mirrored] = photo[mirrored]
    return out


def shoes(photo: np.ndarray, out: np.ndarray, shown: np.ndarray, want: np.ndarray,
          front_side: np.ndarray | None, back_side: np.ndarray | None) -> None:
    """Colour ``out`` at ``want`` (the unseen side of the feet) with each foot's shoe: the median colour of
    the lowest :data:`SHOE_ROWS` of the foot's rows that the photo shows (``shown``), where a shoe's toe
    box or sole is, not of the pixel's own row (a pump's instep skin would give a bare heel; a sock, a
    boot or a bare foot is the same colour there). Per side of the body with ``front_side`` /
    ``back_side`` (+1 left, -1 right), else one for both feet."""
    sides = (-1, 1) if front_side is not None and back_side is not None else (None,)
    for side in sides:
        src = shown if side is None else shown & (front_side == side)
        dst = want if side is None else want & (back_side == side)
        if src.sum() < 4 or not dst.any():
            continue
        ys = np.nonzero(src)[0]
        low = src & (np.arange(src.shape[0])[:, None] >= ys.max() - SHOE_ROWS * (ys.max() - ys.min()))
        out[dst] = median_colour(photo[low])


def face_colour(photo: np.ndarray, mask: np.ndarray, front_part: np.ndarray,
                hair: np.ndarray | None) -> np.ndarray | None:
    """The face's skin colour: the median colour (:func:`median_colour`) of the head's pixels in the
    photo that are not of about the ``hair`` colour (:data:`HAIR_DISTANCE`); None without a hair colour
    or with fewer than 32 such pixels (a photo from behind, a tiny head)."""
    if hair is None:
        return None
    head = (mask > 0.5) & (front_part == PARTS.index("head"))
    face = head & (np.linalg.norm(photo - np.asarray(hair, np.float32)[None, None], axis=2) > HAIR_DISTANCE)
    return median_colour(photo[face]) if face.sum() >= 32 else None


def hands_skin(photo: np.ndarray, mask: np.ndarray, front_part: np.ndarray) -> np.ndarray | None:
    """The skin colour of a photo that shows no face (taken from behind): the median colour of the hands'
    pixels in the chroma range of skin (:func:`any_skin`), else of the arms' (bare arms); None with fewer
    than :data:`MIN_SKIN_PX` of them (gloves, sleeves, hands out of view)."""
    person, skin = mask > 0.5, any_skin(photo)
    for part in ("hands", "arms"):
        shown = person & skin & (front_part == PARTS.index(part))
        if shown.sum() >= MIN_SKIN_PX:
            return median_colour(photo[shown])
    return None


def hair_curtain(photo: np.ndarray, mask: np.ndarray, front_part: np.ndarray, hair: np.ndarray) -> np.ndarray:
    """Where long hair hangs on the unseen side: the photo's pixels of about the hair's colour
    (:data:`HAIR_DISTANCE`) connected to the top of the head, and, per column of their span, everything
    from the top down to the lowest of them nearby (hair seen beside the neck hangs behind it too; that
    lowest row averaged over the same span of columns, so its lower edge slopes up where the locks end),
    at most down to the middle of the person's height. Used only where the torso's clothes differ from
    the hair's colour by more than :data:`HAIR_DISTANCE` (else hair and clothes cannot be told apart)."""
    person = mask > 0.5
    rows = np.nonzero(person.any(axis=1))[0]
    if len(rows) == 0:
        return np.zeros_like(person)
    top, bottom = int(rows.min()), int(rows.max()) + 1
    near = person & (np.linalg.norm(photo - hair[None, None], axis=2) < HAIR_DISTANCE)
    n, labels = cv2.connectedComponents(near.astype(np.uint8), connectivity=8)
    head = person & (front_part == PARTS.index("head"))
    band = np.zeros_like(person)
    band[top:top + max(2, (bottom - top) // 30)] = True
    seeds = np.unique(labels[near & band & cv2.dilate(head.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)])
    region = np.isin(labels, seeds[seeds > 0])
    if not region.any():
        return np.zeros_like(person)
    lowest = np.where(region.any(axis=0), region.shape[0] - 1 - np.argmax(region[::-1], axis=0), -1)
    cols = np.nonzero(lowest >= 0)[0]
    span = max(3, (cols.max() - cols.min()) // 3) | 1
    lowest = cv2.dilate(lowest.astype(np.float32)[None], np.ones((1, span), np.uint8))[0]
    inside = lowest[cols.min():cols.max() + 1]  # averaged over the same span: a slope, not a wall, where it rises
    lowest[cols.min():cols.max() + 1] = cv2.blur(inside[None], (span, 1), borderType=cv2.BORDER_REPLICATE)[0]
    lowest = np.minimum(lowest, top + 0.5 * (bottom - top))
    lowest[: cols.min()] = -1
    lowest[cols.max() + 1:] = -1
    yy = np.arange(person.shape[0])[:, None]
    return person & (yy <= lowest[None, :])


def distinct_hair_curtain(photo: np.ndarray, mask: np.ndarray, front_part: np.ndarray, hair: np.ndarray) -> np.ndarray:
    """:func:`hair_curtain` where hair can be told from the clothes under it: the torso's median colour
    lies more than :data:`HAIR_DISTANCE` from ``hair`` (else, or with fewer than 16 torso pixels, none).
    The one rule for both the unseen side's hair colour and its volume (:func:`hang_hair`)."""
    torso = (mask > 0.5) & (front_part == PARTS.index("torso"))
    if torso.sum() < 16 or np.linalg.norm(np.median(photo[torso], axis=0) - hair) <= HAIR_DISTANCE:
        return np.zeros(mask.shape, bool)
    return hair_curtain(photo, mask, front_part, hair)


def hair_colour(image: np.ndarray, mask: np.ndarray, head_px: np.ndarray) -> np.ndarray | None:
    """The hair's colour: the person's pixels in the top :data:`HAIR_BAND` of the head's projected box
    (``head_px``: projected head vertices) less those of the face's skin colour (the median of the head's
    :data:`FACE_ROWS`, middle fifth; a forehead under hair drawn back), their median colour
    (:func:`median_colour`) when at least :data:`HAIR_SHARE` of the band is
    left; else the same over the head above :data:`HAIR_UPPER` of its box (hands resting on the head
    fill the band with skin); else the band's per-channel median (a bald head, hair of the skin's
    colour); None when the band holds no person."""
    if len(head_px) == 0:
        return None
    h, w = mask.shape
    x0, x1 = np.clip(np.percentile(head_px[:, 0], [10, 90]).astype(int), 0, w - 1)
    y_lo, y_hi = np.clip(np.percentile(head_px[:, 1], [0, 100]).astype(int), 0, h - 1)
    cols = mask[:, x0:x1 + 1] > 0.5
    rows_with_person = np.nonzero(cols.any(axis=1))[0]
    if rows_with_person.size == 0:
        return None
    top = int(rows_with_person.min())  # the top of the head in the photo (hair included)
    bottom = top + max(2, int(HAIR_BAND * max(y_hi - min(top, y_lo), 1)))
    band = mask[top:bottom, x0:x1 + 1] > 0.5
    if band.sum() < 4:
        return None
    pixels = image[top:bottom, x0:x1 + 1][band]
    # the forehead showing in the band (hair drawn back, a high hairline) is not hair
    fy0, fy1 = (int(y_lo + f * (y_hi - y_lo)) for f in FACE_ROWS)
    cx, half = (x0 + x1) // 2, max(1, (x1 - x0) // 5)
    face = image[fy0:fy1, cx - half:cx + half + 1][mask[fy0:fy1, cx - half:cx + half + 1] > 0.5]
    if len(face) >= 16:
        upper = max(bottom, int(y_lo + HAIR_UPPER * (y_hi - y_lo)))
        for rows in (slice(top, bottom), slice(top, upper)):
            seen = image[rows, x0:x1 + 1][mask[rows, x0:x1 + 1] > 0.5]
            hair = ~skin_like(seen[None], median_colour(face))[0]
            if hair.sum() >= max(4, HAIR_SHARE * len(seen)):
                return median_colour(seen[hair])
    return np.median(pixels, axis=0)
