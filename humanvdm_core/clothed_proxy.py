"""The clothed proxy: a closed surface of the person as photographed (clothing, hair, hats and held
objects included), built from a body fitted to one photo and the person's mask.

This is the geometry the weight-free ``diffuse`` backend renders its orbit from. The body alone cuts
everything outside it away; the proxy keeps the person's whole silhouette in the input view and gives
it a plausible thickness from the side (in the spirit of Photo Wake-Up, Weng et al., CVPR 2019:
the body's depth carried out to the silhouette, front and back stitched along it).

Contract of :func:`build_clothed_proxy` (all in the input view's camera, OpenCV axes):

1. **Body depth.** The fitted body is rasterised in the input camera at ``grid`` px: its nearest
   (``front``) and farthest (``back``) camera depth per pixel, and per pixel the body part
   (:data:`PARTS`, from the skinning weights) of the nearest and of the farthest surface; and per leg
   (:data:`LEGS`) its own depths and the farthest depth of the body without it, which tell a leg behind
   the other (step 7, layers).
2. **Domain.** The person's mask (``mask > 0.5``, dilated by one grid pixel so the proxy covers the
   whole silhouette) is the proxy's footprint; the vertices on its border move onto the mask's own
   outline (:func:`rim_shift`): in the input view the proxy's silhouette is the mask, without a grid
   pixel around it or the grid's staircase along a nearly vertical edge.
3. **Arms in front.** Where an arm or a hand is the body's nearest surface, it is pulled back to at most
   :data:`ARM_REACH` in front of the nearest surface of the body without its arms (fading out over
   :data:`ARM_NEAR` from that body's silhouette, so an arm reaching out sideways keeps its depth): a
   single photo's arm depth is the fit's least certain, and the proxy fills everything between an arm
   and the body behind it. The arm's far surface moves with it, unless it is the other arm's: behind a
   forearm folded across the other arm lies that arm, which stays where it is rather than being pushed
   out behind the back. Likewise where an arm or a hand is the body's farthest surface (behind the body,
   hidden by it: the far arm of a person seen in profile), it stands at most :data:`ARM_REACH` behind
   the farthest surface of the body without its arms (:func:`arm_reach_limit`), not a fin the arm's
   length deep. An arm whose hand rests on the head (``placed_arms``) keeps its fitted depth wherever it
   is: the contact fixes the hand's depth, and a forearm rising to it from the chest then stands as far
   before the chest and the face as its length demands. A hand's depth is its mean over
   :data:`HAND_SMOOTH` of the grid, and within the hand's outline (the gaps between its fitted fingers
   included) no pixel stands more than :data:`SHARD_STEP` off its neighbours' median (:func:`smooth_hands`):
   the photo does not show the fingers' depth, and the fitted fingers' relief, or a thigh showing between
   the fingers of a hand on the hip, would stand out from the side as shards (:func:`flatten_shards`).
4. **Clothes and shoes.** The body is fitted inside the silhouette, so it is naked: where the torso (the
   feet) is the nearest (farthest) surface, that surface moves ``CLOTHING["torso"]``
   (``CLOTHING["feet"]``) towards (away from) the camera, faded out over :data:`CLOTHING_FEATHER` of
   the grid (:func:`add_clothing`), so a shirt, a sweater or a jacket has some thickness from the side,
   shoes are longer than bare feet, and no ledge forms at the arms, hips, neck or ankles. Where the mask
   stands out beyond the body at both sides in the torso's (the legs') rows (:func:`garment_margins`: a
   puffy jacket, a coat, armour, wide trousers), the torso (the legs) moves that far instead, between
   :data:`GARMENT_NOISE` and :data:`GARMENT_MAX`: a garment is about as thick in front and behind as it
   is wide beyond the body. The feet's outline is cleaned as the hands' is (:func:`flatten_shards`):
   the fitted toes' tips stood out as spikes.
5. **Mid-depth.** Where the body covers the mask, the mid-depth is the body's ``(front + back) / 2``;
   elsewhere (loose clothing, hair, held objects) it is the harmonic extension of it (Laplace
   equation, body pixels fixed, free at the silhouette). With ``legs_hidden`` (the photo shows no
   ankle: a long dress or coat hides the legs, whose fitted depth is then a guess) the mid-depth of
   loose neighbourhoods comes instead, by ``looseness`` (step 6), from the extension of the body
   where it is not loose (the torso the garment hangs from; extended as the horizontal distance in
   front of the camera, :func:`horizontal_reach`, so it hangs plumb, not leaning towards a camera that
   looks down), so a gown hangs centred, not along guessed legs. Without it the same holds in the
   rows of a skirt (:func:`skirt_rows`: one garment wraps both legs, with no gap between legs that
   stand apart, and reaches :data:`SKIRT_MARGIN` beyond them on both sides; shorts and trousers are
   no skirt), feathered over :data:`CLOTHING_FEATHER` of the grid, from the body above the skirt only
   (the shins seen below its hem do not pull it), and not for an arm, a hand or what lies beside one
   in its row.
6. **Half-thickness.** ``T = max(body half-thickness, looseness * INFLATION * r)``: ``r`` is the half-depth
   of a round cross-section through the pixel (:func:`run_halfdepth`: across its row and down its
   column of the mask, the smaller; a run ends where the body part changes, a pixel outside the body
   taking the part of the nearest body pixel in its row (:func:`row_nearest`), so a sleeve touching
   the torso is as thick as the sleeve and a skirt below hanging hands keeps its whole width; beside
   and above the head, the row's alone: a hat, big hair or a bun is round about the vertical, so a
   brim, thin in its column, is as deep as it is wide), in world units at the local depth;
   :data:`INFLATION` makes it a little flatter front to back than wide; ``looseness`` in [0, 1] grows
   with the share of the neighbourhood (:data:`LOOSE_WINDOW`) that the mask covers and the body's trunk (arms and hands
   left out: hands hanging beside a skirt do not make it tight) does not (:data:`LOOSE_RANGE`), so a
   skirt, a gown, a coat or hair gets volume while a torso keeps the body's own thickness; in a
   skirt's rows (step 5) the whole run of the mask is inflated as loose (``r`` from the run without
   the body parts' splits: the legs, the gap between them and hands hanging at its sides included;
   the fitted arms and hands keep their own), so the skirt is one cross-section around both legs,
   not pinched between them or at the hands. ``T = 0`` on the footprint's border, so front and back
   meet there.
7. **Surface.** Front sheet at ``mid - T``, back sheet at ``mid + T`` (a pixel standing more than
   :data:`SPIKE_DEPTH` out of its sheet's 5x5 median takes the median, :func:`remove_spikes`; near the
   border both sheets' depths are averaged over :data:`EDGE_SMOOTH` grid px, fading out
   :data:`EDGE_BAND` px inside, so that an outline seen from an angle is not toothed by the grid's rows,
   :func:`smooth_edge`; where the photo shows long hair, the back sheet behind the head and the neck
   moves back so the hair hangs plumb from the back of the head, :func:`hang_hair`; last, both sheets'
   depths are averaged down each column over :data:`ROW_SMOOTH` px, :func:`smooth_rows`: each row's
   depths come from its own runs, and rows that disagree are ridges and streaks seen from the side), one
   vertex per grid pixel of the footprint back-projected along its ray (the border's through its point on
   the mask's outline, step 2), two triangles per 2x2 block
   (one for a 3-pixel corner); both sheets share positions along the border (border vertices are duplicated, so each sheet has
   its own texture coordinates): geometrically closed. Front faces are wound to face the camera,
   back faces away (outward normals).

   **Layers.** Two sheets hold one stretch of each ray, so a leg behind the other (the far leg of a
   person seen in profile, the trailing leg of a stride) would be joined to the near one by a slab,
   seen from the front as one block from hip to feet. Where a leg starts more than :data:`LAYER_GAP`
   behind the other one's far side (the region closed and opened by :data:`LAYER_KERNEL`, at least
   :data:`LAYER_MIN` of the body's pixels; not in rows where the mask reaches beyond the legs as one
   garment wrapping them, :func:`wrapped_rows`: a skirt, a dress, a coat; not with ``legs_hidden``;
   :func:`leg_layers`), that leg is a layer: the sheets hold what lies before it (their far side is the body's farthest
   without that leg there; no :data:`ARM_REACH` limit there), and the leg gets its own closed two-sheet
   surface from its own depths plus its clothing (:func:`layer_surface`) over where it is hidden,
   reaching two grid pixels into where the sheets hold it, and over what the photo shows of it within
   :data:`LAYER_OWN` of the other leg, with the mask up to :data:`LAYER_FRINGE` beyond its outline
   (there the sheets leave it to the layer and end at the near leg's outline; a bit of the footprint
   the body does not reach then goes with the layer too). A layer's near side stays
   :data:`LAYER_BEHIND` behind the sheets' front where both are: the input view still shows the photo.
8. **Colour** (one texture, ``[front | back]`` side by side, ``size`` x ``2 size``): the photo on the
   front, its silhouette band refilled from inside (the head's keeps the hair the photo shows there,
   where hair and face differ); on the back (the unseen side) per body part and
   row the median colour of what the photo shows of that part, without prints, logos, held objects or
   the skin of arms held before it, hands in their own colour and the head's back in the hair's, where
   its farthest surface is the face (the far cheek of a person turned from the camera: the body's head
   before its ears and below its hairline, :func:`~humanvdm_core.body.parts.face_vertices`) in the
   face's skin, blended over :data:`FACE_SMOOTH` (for a photo from behind, which shows no face: the
   skin of its hands, and no hair curtain over it) (:mod:`humanvdm_core.proxy_colours`). A point of the
   back sheet takes the colours of the photo's row at its own height in the world (:func:`unseen_rows`), not of the row it is seen through: seen from
   above, the back sheet lies lower than the front along each ray. The body parts' map is resized from
   the grid to the texture with smooth borders (:func:`smooth_labels`), so the hairline at the back of
   the neck is not the grid's staircase. With layers, a third panel (``[front | back | layers]``)
   holds the unseen side's colours of the legs they hold, on a layer's near side where the other leg
   hides it; elsewhere (what the photo shows of it, and behind the sheets' front) it takes the photo's.

9. **Skinning.** Every proxy vertex takes the skinning weights of its nearest body vertex (top
   :data:`SKIN_INFLUENCES` joints), so later stages can pose it with the body.

:class:`ClothedProxy` holds the mesh, the per-vertex skinning, which sheet each vertex is on, and
``body_fraction``: the share of the mask the body covers (low = much clothing/hair outside the body).
:meth:`ClothedProxy.save` writes it as one NPZ (schema :data:`SCHEMA`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from humanvdm_core.body.parts import PARTS, face_vertices, vertex_parts, vertex_sides
from humanvdm_core.cameras import Cameras
from humanvdm_core.image_fill import CROSS, harmonic_extension, nearest_fill, outside_of, row_nearest
from humanvdm_core.proxy_colours import (
    HAIR_DISTANCE,
    distinct_hair_curtain,
    face_colour,
    hair_in_band,
    hands_skin,
    refill_band,
    unseen_side_colours,
)
from humanvdm_core.scans import TexturedMesh

SCHEMA = "humanvdm.clothed_proxy"
SCHEMA_VERSION = 1
INFLATION = 0.8  # half-depth / half-width of an inflated cross-section (round would be 1)
LOOSE_WINDOW = 0.08  # the neighbourhood (fraction of the frame) whose share outside the body decides ...
LOOSE_RANGE = (0.15, 0.45)  # ... how much to inflate: none below the first share, fully above the second
HAIR_DEPTH = 0.05  # metres of hair behind the skull where the photo shows long hair (a hair curtain) ...
HAIR_CURTAIN_DEPTH = 0.03  # ... and at least this far behind the body where the curtain hangs ...
HAIR_FADE = 0.1  # ... fading out over this fraction of the grid below the curtain's lowest row
HAIR_BELOW_CHIN = 0.03  # a curtain column reaching this fraction of the grid below the chin hangs beside the face too
SKIN_INFLUENCES = 4
LABEL_SMOOTH = 1.0  # grid px over which the body parts' borders are smoothed for the texture (smooth_labels)
FACE_SMOOTH = 2.0  # grid px over which the border of the face and the hair on the unseen side is blended
ARM_REACH = 0.08  # metres an arm in front of or beside the body may stand out of the body's nearest surface ...
ARM_NEAR = 0.15  # ... fading out over this distance (metres in the image plane) from the body's silhouette
# metres clothes and shoes add to a part's depth, in front and behind (the fitted body is naked) ...
CLOTHING = {"torso": 0.02, "feet": 0.025}
CLOTHING_FEATHER = 0.04  # ... fading into the neighbouring parts over this fraction of the grid
# ... or, for the torso and the legs, as far as the person's mask stands out beyond the body at both sides
# (garment_margins), when that is at least GARMENT_NOISE (a grid pixel) and at most GARMENT_MAX
GARMENT_NOISE = 0.01
GARMENT_MAX = 0.06
SPIKE_DEPTH = 0.04  # metres a sheet's pixel may stand out of its 5x5 neighbourhood's median
EDGE_SMOOTH = 2.0  # grid pixels (Gaussian sigma) over which the sheets' depths are averaged near the border ...
EDGE_BAND = 4.0  # ... fading out over this many grid pixels inside it
HAND_SMOOTH = 0.025  # fraction of the grid over which a hand's depth is averaged ...
SHARD_CLOSE = 0.017  # flatten_shards: gaps narrower than this fraction of the grid (between fingers, toes) are the part's ...
SHARD_STEP = 0.01  # ... and a pixel of it this far (metres) off its 5x5 median takes the median
SKIRT_MARGIN = 0.03  # metres a garment reaches beyond the legs on both sides for its rows to hang like a skirt
SKIRT_MIN_ROWS = 0.05  # rows of a garment wrapping both legs span at least this fraction of the person's height
GRID = 288  # proxy grid resolution (vertices per side of the input view at most)
RIM_SMOOTH = 0.75  # grid pixels (Gaussian sigma) over which the mask's outline is smoothed for the rim ...
RIM_MAX_SHIFT = 1.0  # ... and the farthest (grid pixels) a rim vertex moves onto it
ROW_SMOOTH = 2.0  # grid pixels (Gaussian sigma) over which the sheets' depths are averaged down each column
LEGS = (1, -1)  # the legs' sides (+1 left, -1 right), in the order of body_maps' leg maps
LAYER_GAP = 0.03  # metres of empty ray between a leg and the other one before it for it to be a layer ...
LAYER_MIN = 0.02  # ... over at least this share of the body's pixels
LAYER_KERNEL = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))  # a layer's region: closed, then opened
LAYER_OWN = 4.0  # grid pixels from the other leg within which what the photo shows of a layered leg is the layer's ...
LAYER_FRINGE = 3.0  # ... with the mask up to this many grid pixels beyond its outline
LAYER_BEHIND = 0.002  # metres a layer's near side stays behind the sheets' front where both are


@dataclass
class ClothedProxy:
    """A closed, textured, skinned surface of the person (see the module docstring)."""

    mesh: TexturedMesh  # vertices in the orbit's world, UVs into the [front | back (| layers)] texture
    skin_joints: np.ndarray  # (V, SKIN_INFLUENCES) int32 joint indices of the body model
    skin_weights: np.ndarray  # (V, SKIN_INFLUENCES) float32, rows sum to 1
    front: np.ndarray  # (V,) bool: seen in the input view (the front sheet; a layer where the photo shows it)
    body_fraction: float  # share of the person's mask the body covers

    def vertex_colors(self) -> np.ndarray:
        """(V, 3) float32 colours sampled from the texture at each vertex (nearest texel)."""
        tex = self.mesh.texture
        h, w = tex.shape[:2]
        col = np.clip((self.mesh.uvs[:, 0] * w).astype(np.int64), 0, w - 1)
        row = np.clip(((1.0 - self.mesh.uvs[:, 1]) * h).astype(np.int64), 0, h - 1)
        return tex[row, col].astype(np.float32) / 255.0

    def save(self, path: str | Path) -> None:
        """One NPZ: vertices, faces, uvs, texture, vertex colours, skinning, front flags."""
        from humanvdm_core.io import write_npz

        write_npz(path, {
            "vertices": self.mesh.vertices, "faces": self.mesh.faces, "uvs": self.mesh.uvs,
            "texture": self.mesh.texture, "vertex_colors": self.vertex_colors(),
            "skin_joints": self.skin_joints, "skin_weights": self.skin_weights, "front": self.front,
            "body_fraction": np.float64(self.body_fraction),
        }, schema=SCHEMA, version=SCHEMA_VERSION)


# ----------------------------------------------------------------------------- body maps

def reflected_along_rays(vertices: np.ndarray, camera: Cameras) -> tuple[np.ndarray, float]:
    """``vertices`` (V, 3, world) moved along the rays of ``camera`` (its first) so their depth order
    reverses, and ``c``: a vertex at camera depth z goes to 2c - z, on the same pixel. Rendering the moved
    mesh gives each pixel its farthest surface: depth 2c - (the rendered depth)."""
    w2c = camera.w2c[0]
    cam = vertices @ w2c[:3, :3].T + w2c[:3, 3]
    c = float(cam[:, 2].max()) + 0.1
    z = np.maximum(cam[:, 2], 1e-4)
    cam2 = cam * ((2.0 * c - z) / z)[:, None]
    world = (cam2 - w2c[:3, 3]) @ w2c[:3, :3]
    return world, c


def _face_mode(values: np.ndarray) -> np.ndarray:
    """(F,) the value most of each face's three corners have ((F, 3) int; the first on a three-way tie)."""
    a, b, c = values[:, 0], values[:, 1], values[:, 2]
    return np.where((a == b) | (a == c), a, np.where(b == c, b, a))


def body_maps(vertices: np.ndarray, faces: np.ndarray, parts: np.ndarray, camera: Cameras,
              sides: np.ndarray | None = None, face: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per pixel of ``camera`` (one camera): the body's nearest and farthest depth, its coverage, the
    part of the nearest and of the farthest surface (-1 where empty), from ``sides`` (V,) in
    {-1, 0, 1} their sides (0 where empty or without ``sides``), from ``face`` (V,) bool whether the
    farthest surface is the face (``back_face``; False without ``face``), and the same depths of the body
    without its arms and hands (``trunk_*``: what lies behind an arm held before the body); per leg
    (:data:`LEGS`, stacked) its own nearest and farthest depth and far part (``leg_near`` / ``leg_far`` /
    ``leg_part``), and the farthest depth, part and side of the body without it (``rest_far`` /
    ``rest_part`` / ``rest_side``)."""
    from humanvdm_core.render import render_views

    # one part (and side) per face, drawn flat: codes interpolated across a face between two parts pass
    # through the codes of others (torso -> legs through head and hands: a line of them along the waist)
    face_part = _face_mode(parts[faces])
    face_side = _face_mode(np.asarray(sides)[faces]) if sides is not None else np.zeros(len(faces), np.int64)
    code = np.repeat(((face_part + 0.5) / len(PARTS))[:, None], 3, axis=1).astype(np.float32)
    if sides is not None:
        code[:, 1] = (face_side + 1.5) / 3.0
    code[:, 2] = 0.25 + 0.5 * (_face_mode(np.asarray(face, np.int64)[faces]) if face is not None else 0)
    code = np.repeat(code, 3, axis=0)
    flat = np.arange(3 * len(faces)).reshape(-1, 3)
    corners = np.asarray(vertices)[faces].reshape(-1, 3)
    near = render_views(TexturedMesh(corners, flat, vertex_colors=code), camera, (0.0, 0.0, 0.0), samples=1)
    world, c = reflected_along_rays(np.asarray(corners, np.float64), camera)
    far = render_views(TexturedMesh(world, flat, vertex_colors=code), camera, (0.0, 0.0, 0.0), samples=1)
    w2c = camera.w2c[0]
    z = np.asarray(vertices, np.float64) @ w2c[2, :3] + w2c[2, 3]
    lo, hi = float(z.min()) - 0.01, float(z.max()) + 0.01

    def within(depth: np.ndarray) -> np.ndarray:
        """Where ``depth`` is one the body has (the rasteriser can give a stray pixel metres off)."""
        return (depth >= lo) & (depth <= hi)

    back = np.where(far.depth[0] > 0, 2.0 * c - far.depth[0], 0.0)
    # a pixel is the body's where both passes saw it at a depth the body has (a stray rasterised depth
    # outside the body's range, or the bent triangles of the far pass missing it, is left to the extension)
    covered = (near.depth[0] > 0) & (far.depth[0] > 0) & within(near.depth[0]) & within(back)

    # the body without its arms and hands: what lies behind an arm held in front of the body
    limb = np.isin(parts, [PARTS.index("arms"), PARTS.index("hands")])
    trunk_faces = flat[~limb[faces].all(axis=1)]
    trunk = render_views(TexturedMesh(corners, trunk_faces, vertex_colors=code), camera, (0.0, 0.0, 0.0), samples=1)
    trunk_far = render_views(TexturedMesh(world, trunk_faces, vertex_colors=code), camera, (0.0, 0.0, 0.0), samples=1)

    def part_map(result) -> np.ndarray:
        p = np.floor(result.rgba[0, ..., 0] * len(PARTS)).astype(np.int64)
        return np.where(result.depth[0] > 0, np.clip(p, 0, len(PARTS) - 1), -1)

    def side_map(result) -> np.ndarray:
        if sides is None:
            return np.zeros(result.depth[0].shape, np.int64)
        side = np.clip(np.floor(result.rgba[0, ..., 1] * 3.0).astype(np.int64) - 1, -1, 1)
        return np.where(result.depth[0] > 0, side, 0)

    # the trunk's depths likewise, empty where the rasteriser gave a depth the body does not have (a stray
    # pixel 4 m behind the body once pushed the arm before it as far back: contract step 3)
    trunk_front = np.where(within(trunk.depth[0]), trunk.depth[0], 0.0).astype(np.float64)
    trunk_back = np.where(trunk_far.depth[0] > 0, 2.0 * c - trunk_far.depth[0], 0.0)
    trunk_back = np.where(within(trunk_back), trunk_back, 0.0)

    # each leg (LEGS: left, right) alone, its nearest and farthest depth, and the farthest depth of the body
    # without it (with that surface's part and side): what lies along a ray besides the leg (a leg behind
    # the other, contract step 7); 0 (-1 for a part) where empty
    is_leg = np.isin(face_part, [PARTS.index("legs"), PARTS.index("feet")])
    legs = {"leg_near": [], "leg_far": [], "leg_part": [], "rest_far": [], "rest_part": [], "rest_side": []}
    for side in LEGS:
        own = is_leg & (face_side == side)
        leg_near = render_views(TexturedMesh(corners, flat[own], vertex_colors=code), camera, (0.0, 0.0, 0.0), samples=1)
        leg_far = render_views(TexturedMesh(world, flat[own], vertex_colors=code), camera, (0.0, 0.0, 0.0), samples=1)
        rest = render_views(TexturedMesh(world, flat[~own], vertex_colors=code), camera, (0.0, 0.0, 0.0), samples=1)
        leg_back = np.where(leg_far.depth[0] > 0, 2.0 * c - leg_far.depth[0], 0.0)
        seen = (leg_near.depth[0] > 0) & within(leg_near.depth[0]) & within(leg_back)
        rest_back = np.where(rest.depth[0] > 0, 2.0 * c - rest.depth[0], 0.0)
        rest_seen = (rest.depth[0] > 0) & within(rest_back)
        legs["leg_near"].append(np.where(seen, leg_near.depth[0], 0.0))
        legs["leg_far"].append(np.where(seen, leg_back, 0.0))
        legs["leg_part"].append(np.where(seen, part_map(leg_far), -1))
        legs["rest_far"].append(np.where(rest_seen, rest_back, 0.0))
        legs["rest_part"].append(np.where(rest_seen, part_map(rest), -1))
        legs["rest_side"].append(np.where(rest_seen, side_map(rest), 0))
    return {"front": near.depth[0].astype(np.float64), "back": back, "covered": covered,
            "front_part": part_map(near), "back_part": part_map(far), "front_side": side_map(near),
            "back_side": side_map(far), "back_face": (far.depth[0] > 0) & (far.rgba[0, ..., 2] > 0.5),
            "trunk_front": trunk_front, "trunk_back": trunk_back,
            **{key: np.stack(value).astype(np.float64 if key.endswith(("near", "far")) else np.int64)
               for key, value in legs.items()}}


def grid_faces(index: np.ndarray) -> np.ndarray:
    """(F, 3) triangles over a grid of vertex indices (H, W; -1 where there is none): two per 2x2 block of
    vertices, one for a block with three, wound to face the camera (normals towards -z)."""
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    tris = []
    for t0, t1, t2, cond in (
        (a, c, b, (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)),
        (b, c, d, (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)),
        (a, c, b, (a >= 0) & (b >= 0) & (c >= 0) & (d < 0)),
        (b, c, d, (a < 0) & (b >= 0) & (c >= 0) & (d >= 0)),
        (a, d, b, (a >= 0) & (b >= 0) & (c < 0) & (d >= 0)),
        (a, c, d, (a >= 0) & (b < 0) & (c >= 0) & (d >= 0)),
    ):
        tris.append(np.stack([t0[cond], t1[cond], t2[cond]], axis=1))
    return np.concatenate(tris)


def footprint_border(region: np.ndarray) -> np.ndarray:
    """(H, W bool): the pixels of ``region`` with a 4-neighbour outside it, where a surface's two sheets meet."""
    return region & ~cv2.erode(region.astype(np.uint8), CROSS.astype(np.uint8)).astype(bool)


def layer_surface(near: np.ndarray, far: np.ndarray, zone: np.ndarray, border: np.ndarray, extra: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A closed two-sheet surface of a layer over ``zone`` (H, W bool): mid-depth and half-thickness per
    pixel from its ``near`` / ``far`` depths, ``extra`` metres (clothing) added to both sides, and 0 on
    the zone's ``border`` (:func:`footprint_border`) so its two sheets meet there."""
    return 0.5 * (near + far), np.where(zone & ~border, 0.5 * (far - near) + extra, 0.0)


# ----------------------------------------------------------------------------- thickness

def row_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The horizontal runs of ``mask`` (H, W bool): each run's row, first column and end column
    (exclusive), row by row and left to right."""
    h, w = mask.shape
    padded = np.zeros((h, w + 2), np.int8)
    padded[:, 1:-1] = mask
    diff = np.diff(padded, axis=1)
    rows, starts = np.nonzero(diff == 1)
    _, ends = np.nonzero(diff == -1)  # the same row order as the starts
    return rows, starts, ends


def run_halfdepth(domain: np.ndarray, labels: np.ndarray | None = None,
                  round_about_vertical: np.ndarray | None = None) -> np.ndarray:
    """Per pixel of ``domain``, in pixels: the round cross-section's half-depth ``sqrt(a^2 - (x - c)^2)`` of
    the horizontal run of domain pixels it lies on (centre ``c``, half-length ``a``), and the same along
    its column; the smaller of the two. A skirt's rows are short and its columns long (round from the
    side, not rounded at its hem); an outstretched arm's columns are the short ones. With ``labels``
    (H, W int, e.g. the body part beside each pixel) a row's run also ends where the label changes, so a
    sleeve that touches the torso is as thick as the sleeve, not as the row through both (columns stay
    whole: a skirt's column runs through the hands' rows). Where ``round_about_vertical`` (H, W bool) is
    set the row's value holds alone: what lies there is round about the vertical (a hat's brim, thin in
    its column, is as deep as it is wide)."""

    def along_rows(d: np.ndarray) -> np.ndarray:
        out = np.zeros(d.shape, np.float32)
        for r, x0, x1 in zip(*row_runs(d), strict=True):
            a = 0.5 * (x1 - x0)
            x = np.arange(x0, x1) + 0.5 - 0.5 * (x0 + x1)
            out[r, x0:x1] = np.sqrt(np.maximum(a * a - x * x, 0.0))
        return out

    d = domain.astype(bool)
    rows = along_rows(d)
    if labels is not None:
        for value in np.unique(labels[d]):
            region = d & (labels == value)
            rows[region] = along_rows(region)[region]
    both = np.minimum(rows, along_rows(d.T).T)
    return both if round_about_vertical is None else np.where(round_about_vertical, rows, both)


def despiked(depth: np.ndarray, region: np.ndarray, limit: float) -> np.ndarray:
    """``depth`` (H, W) with every pixel of ``region`` (H, W bool) that stands more than ``limit`` off the
    5x5 median of the region's depths (those beyond it filled from the nearest region pixel) replaced by
    that median."""
    median = cv2.medianBlur(nearest_fill(depth, region).astype(np.float32), 5)
    return np.where(region & (np.abs(depth - median) > limit), median, depth)


def remove_spikes(mid: np.ndarray, half: np.ndarray, domain: np.ndarray, border: np.ndarray,
                  limit: float = SPIKE_DEPTH) -> tuple[np.ndarray, np.ndarray]:
    """The sheets ``mid -/+ half`` with every pixel of the footprint ``domain`` that stands more than
    ``limit`` out of its sheet's 5x5 median replaced by that median (a stray rasterised depth on the
    body's edge, a one-pixel gap between a hand and the body: from the side, a spike), returned as
    ``(mid, half)`` again, ``half`` 0 on ``border`` and never negative."""
    sheets = [despiked(depth, domain, limit) for depth in (mid - half, mid + half)]
    half = np.where(border, 0.0, np.maximum(0.5 * (sheets[1] - sheets[0]), 0.0))
    return 0.5 * (sheets[0] + sheets[1]), half


def weighted_blur(weight: np.ndarray, sigma: float, columns: bool = False) -> Callable[[np.ndarray], np.ndarray]:
    """A function taking ``values`` (H, W) to their Gaussian average (``sigma`` pixels) over ``weight``
    (H, W float: 1 where a value counts, 0 where it does not), normalised by the weight's own average;
    ``columns``: down each column only (a kernel one column wide). The weight's average is computed once."""
    ksize, sigma_x = ((1, 0), 0.1) if columns else ((0, 0), sigma)
    norm = np.maximum(cv2.GaussianBlur(weight, ksize, sigmaX=sigma_x, sigmaY=sigma), 1e-6)

    def blur(values: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur((values * weight).astype(np.float32), ksize, sigmaX=sigma_x, sigmaY=sigma) / norm

    return blur


def smooth_edge(mid: np.ndarray, half: np.ndarray, domain: np.ndarray, border: np.ndarray,
                sigma: float = EDGE_SMOOTH, band: float = EDGE_BAND) -> tuple[np.ndarray, np.ndarray]:
    """``mid`` and ``half`` near the ``border`` of the footprint ``domain``: averaged over the domain with
    a Gaussian of ``sigma`` grid pixels, fully on the border and fading to the pixel's own value ``band``
    grid pixels inside it; ``half`` stays 0 on the border. Each row's run of the grid ends on a pixel
    boundary of its own, so the sheets' depths near the outline jump from row to row; seen from an
    angle, the outline then shows a tooth every row or two."""
    blurred = weighted_blur(domain.astype(np.float32), sigma)
    distance = cv2.distanceTransform((~border).astype(np.uint8), cv2.DIST_L2, 5)
    w = np.clip(1.0 - distance / band, 0.0, 1.0) * domain
    mid = w * blurred(mid) + (1.0 - w) * mid
    half = np.where(border, 0.0, w * blurred(half) + (1.0 - w) * half)
    return mid, half


def hang_hair(mid: np.ndarray, half: np.ndarray, inner: np.ndarray, maps: dict, rgb: np.ndarray,
              mask: np.ndarray, camera: Cameras, hair: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Long hair as geometry on the unseen side (contract step 7). Where the photo shows a hair curtain
    (:func:`distinct_hair_curtain` on the grid of ``camera``): the back of the head in the curtain's columns
    stands :data:`HAIR_DEPTH` further back (hair over the skull); below the head the back sheet
    (``mid + half``) reaches at least that far back, plumb (the same horizontal distance in front of the
    camera, :func:`horizontal_reach`; beyond the head's columns the nearest head column's), and at least
    :data:`HAIR_CURTAIN_DEPTH` behind the body, so the hair fills the hollow of the neck instead of
    clinging to it; so does the hair beside the face below the head's widest row, in the columns where the
    curtain reaches :data:`HAIR_BELOW_CHIN` below the chin (long hair hangs plumb from the ears down, no
    ledge where the head's part ends); below the curtain's lowest row that pull fades out over
    :data:`HAIR_FADE` of the grid (the hair falls onto the back, no ledge). ``inner``: the pixels that may
    move (not the footprint's border). Returns the new ``(mid, half)``; the front sheet does not move."""
    g = mid.shape[0]
    known = maps["front_part"] >= 0
    if not known.any():
        return mid, half
    photo = cv2.resize(rgb.astype(np.float32), (g, g), interpolation=cv2.INTER_AREA)
    person = cv2.resize(mask.astype(np.float32), (g, g), interpolation=cv2.INTER_AREA)
    front_part = nearest_fill(maps["front_part"].astype(np.float32), known).astype(np.int64)
    head = inner & (front_part == PARTS.index("head"))
    if head.sum() < 8:
        return mid, half
    hairy = distinct_hair_curtain(photo, person, front_part, hair) & inner
    curtain = hairy & ~head
    if not curtain.any():
        return mid, half
    reach = horizontal_reach(camera)
    back = mid + half
    cols = np.nonzero(head.any(axis=0))[0]
    skull = np.where(head, back * reach, -np.inf).max(axis=0)[cols]  # the head's back, horizontal distance
    plumb = (np.interp(np.arange(g), cols, skull)[None, :] + HAIR_DEPTH) / reach
    rows = np.arange(g)[:, None]
    last = np.where(curtain.any(axis=0), g - 1 - np.argmax(curtain[::-1], axis=0), -1)[None, :]
    # long hair beside the face (outside the head's body pixels, below its widest row, in columns where the
    # curtain hangs below the chin) hangs with the hair below it, not forward of it: no ledge at the chin
    skull_px = head & (maps["front_part"] == PARTS.index("head"))
    if skull_px.any():
        widest = int(np.argmax(skull_px.sum(axis=1)))
        chin = int(np.nonzero(skull_px.any(axis=1))[0].max())
        long_cols = last >= chin + HAIR_BELOW_CHIN * g
        curtain = curtain | (hairy & head & ~skull_px & (rows > widest) & long_cols)
    below = (rows > last) & (last >= 0) & inner & ~head
    weight = np.where(curtain, 1.0, below * np.clip(1.0 - (rows - last) / (HAIR_FADE * g), 0.0, 1.0))
    target = np.maximum(back + HAIR_CURTAIN_DEPTH, plumb)
    new_back = np.maximum(back, weight * target + (1.0 - weight) * back)
    skull_hair = head & curtain.any(axis=0)[None, :] & (maps["back_part"] == PARTS.index("head"))
    new_back = np.where(skull_hair, back + HAIR_DEPTH, new_back)
    front = mid - half
    return 0.5 * (front + new_back), 0.5 * (new_back - front)


# ----------------------------------------------------------------------------- the proxy

def garment_margins(maps: dict, body: np.ndarray, person: np.ndarray, metres_per_px: float) -> dict[str, float]:
    """How far the person's mask (``person``, grid pixels) stands out beyond the body's silhouette at the
    sides, per part (torso, legs), in metres: in each row, for each run of the mask that shows the part
    as the body's nearest surface (a leg standing apart is a run of its own), the smaller of its left
    and right margin beyond the body pixels there; the median over all of them. The smaller side, so a
    bag or a binder held beside one side does not count; a coat, a puffy jacket, armour or wide trousers
    stand out on both."""
    out = {}
    runs = row_runs(person.astype(bool))
    for part in ("torso", "legs"):
        gaps = []
        shown = body & (maps["front_part"] == PARTS.index(part))
        for y, a, b in zip(*runs, strict=True):
            cols = np.nonzero(shown[y, a:b])[0]
            if len(cols) == 0:
                continue
            left, right = cols.min(), cols.max()
            while left > 0 and body[y, a + left - 1]:
                left -= 1
            while a + right + 1 < b and body[y, a + right + 1]:
                right += 1
            gaps.append(min(left, b - a - 1 - right))
        out[part] = float(np.median(gaps)) * metres_per_px if gaps else 0.0
    return out


def add_clothing(maps: dict, body: np.ndarray, grid: int, clothing: dict[str, float]) -> None:
    """Move the body's nearest surface towards the camera by ``clothing[part]`` metres (:data:`CLOTHING`,
    or a garment's margin, :func:`garment_margins`) where it is that part (the torso: a shirt or a jacket;
    the feet: shoes), and its farthest surface as far away where that is the part, each faded out over
    :data:`CLOTHING_FEATHER` of the ``grid`` (a Gaussian of the part's indicator), so no ledge forms where
    an arm crosses the torso, the torso meets the hips and the neck, or the feet meet the legs. In place
    on ``maps["front"]`` / ``maps["back"]``."""
    k = max(3, int(CLOTHING_FEATHER * grid) | 1)
    for key, sign in (("front", -1.0), ("back", 1.0)):
        margin = np.zeros(body.shape, np.float32)
        for part, metres in clothing.items():
            inside = ((maps[key + "_part"] == PARTS.index(part)) & body).astype(np.float32)
            margin += metres * cv2.GaussianBlur(inside, (k, k), 0)
        maps[key] = maps[key] + sign * margin * body


def arm_reach_limit(trunk_depth: np.ndarray, fx: float) -> tuple[np.ndarray, np.ndarray]:
    """For an arm's depth limit (contract step 3): ``trunk_depth`` (H, W; 0 where empty, the depth of the
    body without its arms) filled out to every pixel from the nearest trunk pixel, and the limit's weight,
    1 on the trunk and fading to 0 at :data:`ARM_NEAR` (metres in the image plane, ``fx`` the focal
    length in pixels) from its silhouette."""
    trunk = trunk_depth > 0
    ref = nearest_fill(trunk_depth, trunk)
    gap_px = cv2.distanceTransform((~trunk).astype(np.uint8), cv2.DIST_L2, 5)
    return ref, np.clip(1.0 - gap_px * ref / fx / ARM_NEAR, 0.0, 1.0)


def smooth_hands(maps: dict, body: np.ndarray, grid: int) -> None:
    """Replace the depth of the hands' nearest (farthest) surface by its mean over the hand's pixels
    within :data:`HAND_SMOOTH` of the ``grid``: a photo does not show its fingers' depth, and the fitted
    fingers' own relief, a few centimetres from pixel to pixel, stands out from the side as shards. Then
    :func:`flatten_shards` over the hands: the gaps between the fitted fingers, where the body behind
    them or a thigh bulging past a hand on the hip shows through. In place on ``maps["front"]`` /
    ``maps["back"]``."""
    k = max(3, int(HAND_SMOOTH * grid) | 1)
    for key in ("front", "back"):
        hand = ((maps[key + "_part"] == PARTS.index("hands")) & body).astype(np.float32)
        if not hand.any():
            continue
        total = cv2.boxFilter(np.where(hand > 0, maps[key], 0.0).astype(np.float32), -1, (k, k), normalize=False)
        count = cv2.boxFilter(hand, -1, (k, k), normalize=False)
        maps[key] = np.where(hand > 0, total / np.maximum(count, 1.0), maps[key])
    flatten_shards(maps, body, PARTS.index("hands"), grid)


def flatten_shards(maps: dict, body: np.ndarray, part: int, grid: int) -> None:
    """Over the outline of the body ``part`` (its pixels of the nearest, or farthest, surface closed over
    :data:`SHARD_CLOSE` of the ``grid``, so the gaps between fitted fingers or toes count), every pixel more
    than :data:`SHARD_STEP` off the region's 5x5 median depth takes the median: from the side, a row of
    such pixels is a blade (a thigh showing between the fingers of a hand on the hip, a toe's tip). A
    slope (a foot pointing at the camera) keeps its depths. In place on ``maps["front"]`` /
    ``maps["back"]``, the back kept behind the front."""
    close = max(3, int(SHARD_CLOSE * grid) | 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (close, close))
    for key in ("front", "back"):
        own = ((maps[key + "_part"] == part) & body).astype(np.uint8)
        if not own.any():
            continue
        region = cv2.morphologyEx(own, cv2.MORPH_CLOSE, kernel).astype(bool) & body
        maps[key] = despiked(maps[key], region, SHARD_STEP)
    maps["back"] = np.where(body, np.maximum(maps["back"], maps["front"]), maps["back"])


def skirt_rows(maps: dict, body: np.ndarray, domain: np.ndarray, metres_per_px: np.ndarray) -> np.ndarray:
    """(H,) bool: rows between the top of the legs and the top of the feet where one garment wraps both
    legs (a skirt or a dress): the body's legs stand more than :data:`SKIRT_MARGIN` apart, the
    footprint (arms and hands left out) has no gap between them (shorts and trousers have one) and
    reaches more than that beyond them on both sides (legs in a stride that the fitted legs miss reach
    beyond them on one side only); with the rows between two such rows and below the last one while
    the footprint, still without a gap, reaches that far on one side (a hem that swings to one side).
    Fewer than :data:`SKIRT_MIN_ROWS` of the person's height in all (where shorts part a little lower
    than the fitted legs) count as none. ``metres_per_px`` (H, W): the grid's pixel size in metres at
    each pixel's depth."""
    legs = body & (maps["front_part"] == PARTS.index("legs"))
    out = np.zeros(domain.shape[0], bool)
    rows = np.nonzero(legs.any(axis=1))[0]
    if len(rows) == 0:
        return out
    feet = np.nonzero((body & (maps["front_part"] == PARTS.index("feet"))).any(axis=1))[0]
    stop = feet.min() if len(feet) else domain.shape[0]
    cover = domain & ~(body & np.isin(maps["front_part"], [PARTS.index("arms"), PARTS.index("hands")]))
    one_side = np.zeros_like(out)
    for r in range(rows.min(), stop):
        lx, cx = np.nonzero(legs[r])[0], np.nonzero(cover[r])[0]
        if len(lx) == 0 or len(cx) == 0:
            continue
        m = float(metres_per_px[r, lx].mean())
        margins = (lx.min() - cx.min()) * m, (cx.max() - lx.max()) * m
        closed = bool(cover[r, lx.min():lx.max() + 1].all())
        apart = (~body[r, lx.min():lx.max() + 1]).sum() * m > SKIRT_MARGIN
        out[r] = min(margins) > SKIRT_MARGIN and closed and apart
        one_side[r] = max(margins) > SKIRT_MARGIN and closed
    person = np.nonzero(domain.any(axis=1))[0]
    if out.any() and np.ptp(np.nonzero(out)[0]) + 1 < SKIRT_MIN_ROWS * np.ptp(person):
        out[:] = False  # a few rows where shorts or trousers part a little lower than the body's legs
    if out.any():
        first, last = np.nonzero(out)[0][[0, -1]]
        out[first:last + 1] = True
        while last + 1 < len(out) and one_side[last + 1]:
            last += 1
            out[last] = True
    return out


def wrapped_rows(maps: dict, body: np.ndarray, domain: np.ndarray, metres_per_px: np.ndarray) -> np.ndarray:
    """(H,) bool: rows where one garment may wrap the legs -- the run of the footprint (arms and hands
    left out) around the body's legs reaches more than :data:`SKIRT_MARGIN` beyond them on both sides, or
    on the one side where it does not end at an arm or a hand (a hand hanging beside the thigh hides
    that side) (a skirt, a dress, a coat or wide trousers, from the front or from the side).
    ``metres_per_px`` (H, W): the grid's pixel size in metres at each pixel's depth."""
    legs = body & np.isin(maps["front_part"], [PARTS.index("legs"), PARTS.index("feet")])
    limb = body & np.isin(maps["front_part"], [PARTS.index("arms"), PARTS.index("hands")])
    cover = domain & ~limb
    w = domain.shape[1]
    out = np.zeros(domain.shape[0], bool)
    for r in np.nonzero(legs.any(axis=1))[0]:
        lx = np.nonzero(legs[r])[0]
        a, b = lx.min(), lx.max()
        while a > 0 and cover[r, a - 1]:
            a -= 1
        while b + 1 < w and cover[r, b + 1]:
            b += 1
        m = float(metres_per_px[r, lx].mean())
        margins = [(lx.min() - a) * m if a == 0 or not limb[r, a - 1] else np.inf,
                   (b - lx.max()) * m if b + 1 == w or not limb[r, b + 1] else np.inf]
        out[r] = min(margins) > SKIRT_MARGIN and min(margins) < np.inf
    return out


def leg_layers(maps: dict, body: np.ndarray, domain: np.ndarray, fx: float) -> tuple[np.ndarray, np.ndarray]:
    """Which leg is a layer where (contract step 7): per leg of :data:`LEGS` (2, H, W bool) where it starts
    more than :data:`LAYER_GAP` behind the other leg's far side, as whole regions (closed, then opened by
    :data:`LAYER_KERNEL`; at least :data:`LAYER_MIN` of the ``body`` pixels), not in rows one garment
    wraps (:func:`wrapped_rows`); and what each layered leg takes from the sheets (2, H, W bool): where
    the photo shows it within :data:`LAYER_OWN` of the other leg, with the ``domain``'s pixels up to
    :data:`LAYER_FRINGE` beyond the body there. ``maps``: :func:`body_maps`' (grid ``fx`` pixels of focal
    length)."""
    near, far = maps["leg_near"], maps["leg_far"]
    present = near > 0
    layers = np.zeros(near.shape, bool)
    open_ = body & ~wrapped_rows(maps, body, domain, np.where(body, maps["front"], 1.0) / fx)[:, None]
    for k in range(len(LEGS)):
        behind = present[k] & present[1 - k] & (near[k] > far[1 - k] + LAYER_GAP) & open_
        # whole regions, not a pixel here and there where the legs' gap comes and goes
        behind = cv2.morphologyEx(behind.astype(np.uint8), cv2.MORPH_CLOSE, LAYER_KERNEL)
        layers[k] = cv2.morphologyEx(behind, cv2.MORPH_OPEN, LAYER_KERNEL).astype(bool) & present[k] & open_
    layers &= (layers.sum(axis=(1, 2)) >= LAYER_MIN * body.sum())[:, None, None]
    owned = np.zeros(near.shape, bool)
    if layers.any():
        shown = body & np.isin(maps["front_part"], [PARTS.index("legs"), PARTS.index("feet")])
        reach = cv2.distanceTransform((~(present[0] & present[1])).astype(np.uint8), cv2.DIST_L2, 5)
        owner = np.zeros(body.shape, np.float32)
        for k in np.nonzero(layers.any(axis=(1, 2)))[0]:
            owner[shown & (maps["front_side"] == LEGS[k]) & open_ & (reach <= LAYER_OWN)] = k + 1
        beside = domain & ~body & (cv2.distanceTransform((~body).astype(np.uint8), cv2.DIST_L2, 5) <= LAYER_FRINGE)
        owner = np.where(beside, nearest_fill(owner, body), owner).astype(np.int64)
        owned = (owner[None] == np.arange(1, len(LEGS) + 1)[:, None, None]) & domain[None]
    return layers, owned


def pixel_rays(camera: Cameras) -> np.ndarray:
    """(H, W, 3): per pixel centre of ``camera`` (one camera), its ray in camera space at depth 1."""
    yy, xx = np.mgrid[0:camera.height, 0:camera.width]
    return np.stack([xx + 0.5, yy + 0.5, np.ones(xx.shape)], axis=-1) @ np.linalg.inv(camera.K[0]).T


def horizontal_reach(camera: Cameras) -> np.ndarray:
    """(H, W): per pixel of ``camera`` (one camera), the horizontal distance in front of the camera (along
    its forward direction levelled in the world, whose up is +Y) of the point at camera depth 1 on the
    pixel's ray. A point at depth ``z`` lies ``z * reach`` in front: points of equal ``z * reach`` lie
    on one vertical plane."""
    w2c = np.asarray(camera.w2c[0], np.float64)
    up = w2c[:3, :3] @ np.array([0.0, 1.0, 0.0])
    forward = np.array([0.0, 0.0, 1.0]) - up[2] * up
    forward /= np.linalg.norm(forward)
    return np.maximum(pixel_rays(camera) @ forward, 1e-3)


def unseen_rows(front: np.ndarray, back: np.ndarray, camera: Cameras, domain: np.ndarray) -> np.ndarray:
    """(H, W) float: per pixel of ``camera`` (one camera), the image row (fractional, in pixels) of the
    same column at which the near side, held vertical, stands at the world height (+Y up) of the far
    side: the row whose colours the far side takes. ``front`` / ``back`` (H, W): the near and the far
    camera depths per pixel. On a ray that points down, the far point lies lower in the world than the
    near one (on a ray that points up, higher), so a hem, a belt or a hairline on the unseen side comes
    from the photo's rows further down (up); equal depths (the silhouette) give the pixel's own row.
    Only where the near side stands upright (its height changes faster than its distance down the
    column: a torso, standing legs), not where it lies level (a seated person's lap, whose colours do
    not go by height). The row stays within the pixel's vertical run of ``domain`` (H, W bool, the
    footprint): below a hem with nothing under it in the photo (between the legs) a coat keeps its colour."""
    w2c = np.asarray(camera.w2c[0], np.float64)
    up = w2c[:3, :3] @ np.array([0.0, 1.0, 0.0])
    h, w = camera.height, camera.width
    rays = pixel_rays(camera)
    reach = horizontal_reach(camera)
    slope = (rays @ up) / reach  # height over levelled distance: falls down each column
    near = np.asarray(front, np.float64)
    upright = np.abs(np.gradient(near * (rays @ up), axis=0)) > np.abs(np.gradient(near * reach, axis=0))
    target = np.where(upright, slope * np.asarray(back, np.float64) / np.maximum(near, 1e-6), slope)
    rows = np.arange(h, dtype=np.float64)
    out = np.stack([np.interp(-target[:, c], -slope[:, c], rows) for c in range(w)], axis=1)
    first, last = np.zeros((h, w)), np.full((h, w), h - 1.0)  # each pixel's vertical run of the domain
    for r in range(1, h):
        first[r] = np.where(domain[r] & domain[r - 1], first[r - 1], r)
    for r in range(h - 2, -1, -1):
        last[r] = np.where(domain[r] & domain[r + 1], last[r + 1], r)
    return np.clip(out, first, last)


def rim_shift(mask: np.ndarray, g: int, rim: np.ndarray) -> np.ndarray:
    """(g, g, 2) the image-plane shift (x, y, in pixels of a ``g`` grid) that takes each ``rim`` pixel's
    centre onto the outline of ``mask`` (size x size, person > 0.5): the zero of its signed distance
    (positive inside), measured at full size, brought to the grid and smoothed over
    :data:`RIM_SMOOTH` grid pixels, reached by one Newton step along its gradient and at most
    :data:`RIM_MAX_SHIFT` long. Zero off ``rim`` and where a rim pixel lies farther than
    ``RIM_MAX_SHIFT + 0.5`` grid pixels from the outline (the frame's edge across a cropped person). The
    proxy's outline then follows the mask's, not the grid's staircase (which a nearly vertical edge shows
    as a notch every few rows)."""
    person = (mask > 0.5).astype(np.uint8)
    size = mask.shape[0]
    inside = cv2.distanceTransform(person, cv2.DIST_L2, 5)
    outside = cv2.distanceTransform(1 - person, cv2.DIST_L2, 5)
    signed = np.where(person > 0, inside - 0.5, 0.5 - outside).astype(np.float32) * (g / size)
    signed = cv2.resize(signed, (g, g), interpolation=cv2.INTER_AREA) if g != size else signed
    signed = cv2.GaussianBlur(signed, (0, 0), RIM_SMOOTH)
    gy, gx = np.gradient(signed)
    norm2 = np.maximum(gx * gx + gy * gy, 0.25)
    step = -signed[..., None] * np.stack([gx, gy], axis=-1) / norm2[..., None]
    length = np.linalg.norm(step, axis=-1, keepdims=True)
    step = step * np.minimum(1.0, RIM_MAX_SHIFT / np.maximum(length, 1e-9))
    keep = rim & (np.abs(signed) <= RIM_MAX_SHIFT + 0.5)
    return np.where(keep[..., None], step, 0.0)


def smooth_rows(mid: np.ndarray, half: np.ndarray, domain: np.ndarray, border: np.ndarray,
                sigma: float = ROW_SMOOTH) -> tuple[np.ndarray, np.ndarray]:
    """``mid`` and ``half`` averaged down each column over the ``domain`` less its ``border`` (a Gaussian of
    ``sigma`` grid pixels, normalised there); the border keeps its own (``half`` 0: the sheets meet). Each
    row's depths come from its own runs (:func:`run_halfdepth`) and from the fitted body's rim as the
    rasteriser hit it, so neighbouring rows disagree by millimetres, at the rim by centimetres; seen from
    the side, each disagreement is a ridge along the row (and the photo's colours there a streak)."""
    inner = (domain & ~border).astype(np.float32)
    down = weighted_blur(inner, sigma, columns=True)
    keep = inner > 0
    return np.where(keep, down(mid), mid), np.where(keep, down(half), half)


def build_clothed_proxy(vertices: np.ndarray, faces: np.ndarray, skinning_weights: np.ndarray,
                        joint_names: list[str], camera: Cameras, rgb: np.ndarray, mask: np.ndarray,
                        head_colour: np.ndarray | None = None, grid: int = GRID,
                        legs_hidden: bool = False, profile: bool = False,
                        placed_arms: tuple[int, ...] = (), coco17: np.ndarray | None = None,
                        facing_away: bool = False) -> ClothedProxy:
    """The clothed proxy of a person (see the module docstring).

    ``vertices`` (V, 3) / ``faces`` / ``skinning_weights`` (V, J) / ``joint_names``: the fitted body in
    the world; ``camera``: the input view (one camera, ``size`` x ``size``); ``rgb`` (size, size, 3) and
    ``mask`` (size, size): the input view's photo and person mask; ``head_colour``: the colour of the
    unseen side of the head (hair), None to use the head's own median colour; ``legs_hidden``: the
    photo does not show the ankles (a long dress or coat), so the fitted legs' depth is a guess; ``profile``:
    the photo shows the person from the side, so the unseen side of the head mirrors the seen one;
    ``placed_arms``: the sides (+1 left, -1 right, the person's own) of arms whose depth a contact fixes (a
    hand on the head): they keep the fitted depth, no :data:`ARM_REACH` limit; ``coco17`` (17, 3): the
    fitted body's COCO joints in the world, which tell its face from the back of its head (contract
    step 8); ``facing_away``: the photo shows the person's back, so the unseen side of the head is the
    face (the hands' skin colour, no hair curtain over it)."""
    size = camera.width
    g = max(16, min(grid, size))
    cam_g = camera.scaled(g, g) if g != size else camera
    parts = vertex_parts(skinning_weights, joint_names)
    face = face_vertices(vertices, parts, coco17) if coco17 is not None else None
    maps = body_maps(np.asarray(vertices, np.float32), np.asarray(faces, np.int32), parts, cam_g,
                     vertex_sides(skinning_weights, joint_names), face)

    person_g = cv2.resize(mask.astype(np.float32), (g, g), interpolation=cv2.INTER_AREA) > 0.5
    domain = cv2.dilate(person_g.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    body = maps["covered"] & domain & (maps["back"] >= maps["front"])
    if body.sum() < 8:
        body = maps["covered"]
    # isolated outliers where the near and the far rasterisation hit different triangles: 5x5 medians
    for key in ("front", "back"):
        smooth = cv2.medianBlur(np.where(body, maps[key], 0.0).astype(np.float32), 5)
        inner = cv2.erode(body.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        maps[key] = np.where(inner & (np.abs(maps[key] - smooth) > 0.05), smooth, maps[key])
    fx = float(cam_g.K[0, 0, 0])
    limbs = [PARTS.index("arms"), PARTS.index("hands")]

    def placed(key: str) -> np.ndarray:
        """Where the ``key`` ("front" / "back") surface is an arm a contact places."""
        return np.isin(maps[key + "_side"], placed_arms)

    # the fitted arms and hands as the nearest surface, less those a contact places
    limb_front = body & np.isin(maps["front_part"], limbs) & ~placed("front")
    # a leg behind the other (the trailing leg of a stride, the far leg of a person seen in profile) is a
    # layer of its own (contract step 7), not where the legs are hidden (their fitted depth is a guess)
    near, far = maps["leg_near"], maps["leg_far"]
    present = near > 0
    if legs_hidden:
        layers, owned = np.zeros(near.shape, bool), np.zeros(near.shape, bool)
    else:
        layers, owned = leg_layers(maps, body, domain, fx)
    split = layers.any(axis=0)
    # an arm in front of or beside the body stands at most ARM_REACH out of the body's nearest surface: a
    # single photo's arm depth is the least certain part of the fit, and the proxy fills everything between
    # an arm and the body behind it. The pull fades out over ARM_NEAR from the body's silhouette, so an
    # arm reaching out sideways keeps its depth. Likewise behind the body: an arm that it hides (the far
    # arm of a person seen in profile) stands at most ARM_REACH out of its farthest surface. Neither where
    # a layer lies behind
    if (maps["trunk_front"] > 0).any():
        ref, fade = arm_reach_limit(maps["trunk_front"], fx)
        shift = np.where(limb_front & ~split, np.clip(ref - ARM_REACH - maps["front"], 0.0, None) * fade, 0.0)
        # the arm's far side moves with it, unless the far surface is the other arm's (a forearm folded
        # across it): that arm stays where it is
        same_arm = np.isin(maps["back_part"], limbs) & (maps["back_side"] == maps["front_side"])
        maps["front"] = maps["front"] + shift
        maps["back"] = np.maximum(maps["back"] + np.where(same_arm, shift, 0.0), maps["front"])
    if (maps["trunk_back"] > 0).any():
        ref, fade = arm_reach_limit(maps["trunk_back"], fx)
        arm = body & np.isin(maps["back_part"], limbs) & ~placed("back") & ~split
        pull = np.where(arm, np.clip(maps["back"] - ref - ARM_REACH, 0.0, None) * fade, 0.0)
        maps["back"] = np.maximum(maps["back"] - pull, maps["front"])
    for k in np.nonzero(layers.any(axis=(1, 2)))[0]:  # the sheets hold what lies before a layered leg
        there = layers[k]
        maps["back"] = np.where(there, np.maximum(maps["rest_far"][k], maps["front"]), maps["back"])
        maps["back_part"] = np.where(there, maps["rest_part"][k], maps["back_part"])
        maps["back_side"] = np.where(there, maps["rest_side"][k], maps["back_side"])
        maps["back_face"] = maps["back_face"] & ~there
    body_fraction = float(body.sum() / max(1, (person_g & domain).sum()))
    domain_all, border_all = domain, footprint_border(domain)
    if owned.any():  # the sheets cover the rest; a bit of it the body does not reach goes with the layer
        rest = domain & ~owned.any(axis=0)
        _, pieces = cv2.connectedComponents(rest.astype(np.uint8), connectivity=4)
        stray = rest & ~np.isin(pieces, np.unique(pieces[rest & body]))
        owned[np.argmax(owned.sum(axis=(1, 2)))] |= stray
        domain = rest & ~stray
        body = body & domain
    # a garment that stands out beyond the body at both sides stands as far out in front and behind
    margins = garment_margins(maps, body, person_g, float(np.median(maps["front"][body])) / fx)
    clothing = dict(CLOTHING)
    for part, metres in margins.items():
        if metres >= GARMENT_NOISE:
            clothing[part] = min(max(clothing.get(part, 0.0), metres), GARMENT_MAX)
    add_clothing(maps, body, g, clothing)
    smooth_hands(maps, body, g)
    flatten_shards(maps, body, PARTS.index("feet"), g)
    mid_body = 0.5 * (maps["front"] + maps["back"])
    mid = harmonic_extension(np.where(body, mid_body, 0.0), body, domain)
    t_body = np.where(body, 0.5 * (maps["back"] - maps["front"]), 0.0)

    # a run ends where the body part beside it changes: a sleeve touching the torso in the photo is as
    # thick as the sleeve, not as the row through both (wings from the side); the part of a loose pixel is
    # that of the nearest body pixel in its own row, so a skirt below hanging hands keeps its whole width
    beside = row_nearest(maps["front_part"], body)
    # what the mask holds beside and above the head (a hat, big hair, a bun) is round about the vertical:
    # a brim, thin in its column, is as deep as the row through it is wide
    headwear = domain & ~body & (beside == PARTS.index("head"))
    t_round = run_halfdepth(domain, beside, headwear) * mid / fx * INFLATION
    # inflate where the mask reaches beyond the body (loose clothing, hair, objects), not where it hugs it
    window = max(3, int(LOOSE_WINDOW * g) | 1)
    area = cv2.boxFilter(domain.astype(np.float32), -1, (window, window), normalize=False)
    # holes: pixels the body surrounds but does not cover (between an arm and the torso, a rasterisation gap)
    # take the surrounding body's thickness; only what lies outside the body's outline is loose
    holes = domain & ~body & ~outside_of(body)
    # hands and arms hanging beside a skirt or a coat do not make it tight: only the trunk's cover counts
    trunk_cover = body & ~limb_front
    loose = cv2.boxFilter((domain & ~trunk_cover & ~holes).astype(np.float32), -1, (window, window), normalize=False)
    looseness = np.clip((loose / np.maximum(area, 1.0) - LOOSE_RANGE[0]) / (LOOSE_RANGE[1] - LOOSE_RANGE[0]), 0, 1)
    # the garment hangs from where it fits, not from the guessed legs inside it: with legs_hidden
    # everywhere, else in the rows of a garment that wraps both legs (a skirt, a dress), feathered over
    # CLOTHING_FEATHER of the grid so no kink forms where the skirt starts; not an arm or a hand, nor what
    # lies beside one (the photo's hand beyond the fitted hand)
    fitted = body & (looseness < 0.5)
    skirt = skirt_rows(maps, body, domain, mid / fx)
    k = max(3, int(CLOTHING_FEATHER * g) | 1)
    skirt_w = cv2.GaussianBlur(skirt.astype(np.float32)[:, None], (1, k), 0)
    if legs_hidden:
        hang = looseness
    else:
        hang = looseness * skirt_w * ~np.isin(beside, limbs)
        if skirt.any():  # it hangs from above: the shins below its hem do not pull it
            fitted &= np.arange(g)[:, None] < np.nonzero(skirt)[0].min()
    # a skirt's row is one cross-section around both legs: inflated as loose across the whole run of the
    # mask (the legs, the gap between them and the hands hanging at its sides included), the fitted arms
    # and hands themselves keeping their own thickness
    t_skirt = run_halfdepth(domain) * mid / fx * INFLATION if skirt.any() else 0.0
    t_inflate = np.maximum(looseness * t_round, skirt_w * ~limb_front * t_skirt)
    if fitted.sum() >= 8 and hang.max() > 0:
        # extended as the distance along the camera's horizontal forward direction, so the garment hangs
        # plumb in the world (a constant camera depth would lean it towards a camera that looks down)
        reach = horizontal_reach(cam_g)
        hung = harmonic_extension(np.where(fitted, mid_body * reach, 0.0), fitted, domain) / reach
        mid = hang * hung + (1.0 - hang) * mid
    border = footprint_border(domain)
    t_holes = harmonic_extension(t_body, body, domain) if holes.any() else t_body
    half = np.where(border, 0.0, np.where(holes, t_holes, np.maximum(t_body, t_inflate)))
    mid, half = remove_spikes(mid, half, domain, border)
    mid, half = smooth_edge(mid, half, domain, border)
    if head_colour is not None:
        mid, half = hang_hair(mid, half, domain & ~border, maps, rgb, mask, cam_g, np.asarray(head_colour, np.float32))
    mid, half = smooth_rows(mid, half, domain, border)

    # vertices: a front and a back sheet on every domain pixel, the back's in the same order after the front's
    # (the border's meet in position, each with its own texture coordinates)
    rows, cols = np.nonzero(domain)
    n = len(rows)
    index_front = np.full((g, g), -1, np.int64)
    index_front[rows, cols] = np.arange(n)

    K_inv = np.linalg.inv(cam_g.K[0])
    c2w = cam_g.c2w[0]
    shift = rim_shift(mask, g, border)[rows, cols]  # the rim onto the mask's outline, not the grid's staircase
    px, py = cols + 0.5 + shift[:, 0], rows + 0.5 + shift[:, 1]
    pix = np.stack([px, py, np.ones(n)], axis=1)
    rays = pix @ K_inv.T  # camera-space points at z = 1

    def lift(depth: np.ndarray) -> np.ndarray:
        cam_pts = rays * depth[:, None]
        return cam_pts @ c2w[:3, :3].T + c2w[:3, 3]

    d_mid, d_half = mid[rows, cols], half[rows, cols]
    verts = np.concatenate([lift(d_mid - d_half), lift(d_mid + d_half)])

    front_faces = grid_faces(index_front)  # wound to face the camera (normals towards -z)
    back_faces = front_faces[:, ::-1] + n
    faces_out = np.concatenate([front_faces, back_faces])
    # each layered leg: its own closed surface over where it is hidden, reaching two grid pixels into where
    # the sheets hold it (so the two join), and over what the photo shows of it (its own pixels, in the
    # photo's colours there: the sheets end at the near leg's outline)
    layer_part = np.full((g, g), -1, np.int64)
    layer_side = np.zeros((g, g), np.int64)
    layer_sheets = []  # (panel per vertex, pixel x, pixel y) of each layer's vertices
    layer_front = []  # whether each layer vertex is seen in the input view
    grow = np.ones((5, 5), np.uint8)  # two grid pixels
    for k in np.nonzero(layers.any(axis=(1, 2)))[0]:
        seen = present[k]
        l_near = nearest_fill(near[k], seen)  # out to the mask beside the leg
        l_far = np.maximum(nearest_fill(far[k], seen), l_near)
        zone = ((cv2.dilate((layers[k] | owned[k]).astype(np.uint8), grow).astype(bool) & seen)
                | cv2.dilate(owned[k].astype(np.uint8), CROSS.astype(np.uint8)).astype(bool))
        zone &= domain_all
        part = nearest_fill(maps["leg_part"][k].astype(np.float32), seen).astype(np.int64)
        extra = np.zeros((g, g))
        for name, metres in clothing.items():
            extra = np.where(part == PARTS.index(name), metres, extra)
        # behind the sheets' front where both are (the photo shows the sheets there)
        l_near = np.where(domain, np.maximum(l_near, mid - half + LAYER_BEHIND), l_near)
        l_border = footprint_border(zone)
        l_mid, l_half = layer_surface(l_near, np.maximum(l_far, l_near), zone, l_border, extra)
        l_mid, l_half = remove_spikes(l_mid, l_half, zone, l_border)
        l_mid, l_half = smooth_edge(l_mid, l_half, zone, l_border)
        l_mid, l_half = smooth_rows(l_mid, l_half, zone, l_border)
        lr, lc = np.nonzero(zone)
        m = len(lr)
        index = np.full((g, g), -1, np.int64)
        index[lr, lc] = len(verts) + np.arange(m)
        l_shift = rim_shift(mask, g, l_border & border_all)[lr, lc]  # on the mask's outline, as the sheets' rim
        lx, ly = lc + 0.5 + l_shift[:, 0], lr + 0.5 + l_shift[:, 1]
        l_rays = np.stack([lx, ly, np.ones(m)], axis=1) @ K_inv.T
        for depth in (l_mid - l_half, l_mid + l_half):
            verts = np.concatenate([verts, (l_rays * depth[lr, lc][:, None]) @ c2w[:3, :3].T + c2w[:3, 3]])
        l_faces = grid_faces(index)
        # the near side's triangles outside where the other leg hides it take the photo's colours, through
        # copies of their vertices (behind the other leg: the unseen side's); where the sheets lie before
        # them they are not seen, and along the near leg's outline the photo then shows no unseen colours
        in_photo = ~layers[k][lr, lc][l_faces - len(verts) + 2 * m].any(axis=1)
        copies, inverse = np.unique(l_faces[in_photo], return_inverse=True)
        l_faces[in_photo] = len(verts) + inverse.reshape(-1, 3)
        verts = np.concatenate([verts, verts[copies]])
        faces_out = np.concatenate([faces_out, l_faces, grid_faces(index)[:, ::-1] + m])
        layer_part = np.where(zone & (layer_part < 0), part, layer_part)
        layer_side = np.where(zone, LEGS[k], layer_side)
        at = copies - (len(verts) - len(copies) - 2 * m)
        layer_sheets += [(np.full(m, 2), lx, ly), (np.full(m, 2), lx, ly), (np.zeros(len(copies)), lx[at], ly[at])]
        layer_front += [np.zeros(2 * m, bool), np.ones(len(copies), bool)]

    # colour: front = the photo (band refilled); back = the unseen side; one [front | back] texture
    front_tex = refill_band(rgb, mask)
    to_full = (size / g)
    fp = smooth_labels(maps["front_part"], size).astype(np.float32)  # no grid steps along a part's border
    bp = smooth_labels(maps["back_part"], size).astype(np.float32)
    known = fp >= 0
    fp = nearest_fill(fp, known).astype(np.int64) if known.any() else np.zeros_like(fp, np.int64)
    bknown = bp >= 0
    bp = np.where(bknown, bp, fp).astype(np.int64)
    skin = face_colour(front_tex, mask, fp, head_colour)  # before the head's own colour stands in for hair
    if skin is not None and np.linalg.norm(skin - head_colour) > HAIR_DISTANCE:  # the temples' hair
        front_tex = hair_in_band(front_tex, rgb, mask, (fp == PARTS.index("head")), head_colour)
    face_skin = hands_skin(front_tex, mask, fp) if facing_away else skin  # a photo from behind shows no face
    if head_colour is None:
        head_pixels = (fp == PARTS.index("head")) & (mask > 0.5)
        head_colour = np.median(front_tex[head_pixels], axis=0) if head_pixels.any() else None
    fs = cv2.resize(maps["front_side"].astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST)
    bs = cv2.resize(maps["back_side"].astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST)
    fs = nearest_fill(fs, known).astype(np.int64) if known.any() else np.zeros_like(fs, np.int64)
    bs = np.where(bknown, bs, fs).astype(np.int64)
    # the face's share of the farthest surface, blurred like the parts' borders: the cheek fades into the hair
    back_face = np.clip(cv2.resize(cv2.GaussianBlur(maps["back_face"].astype(np.float32), (0, 0), FACE_SMOOTH),
                                   (size, size), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
    loose_full = cv2.resize((domain & ~body).astype(np.uint8), (size, size),
                            interpolation=cv2.INTER_NEAREST).astype(bool)  # the mask outside the body
    # each point of the unseen side takes its part's colours of the photo's row at its own world height (see
    # unseen_rows): the height of the body's far surface where the body lies behind it; outside the body
    # its own row (what lies there -- a coat's flare, a held object -- has a guessed volume, and its back
    # would hang lower than its hem along the rays)
    near_d = mid - half
    far_d = np.maximum(np.where(body, np.minimum(mid + half, maps["back"]), near_d), near_d)
    far_rows = cv2.resize(((unseen_rows(near_d, far_d, cam_g, domain) + 0.5) * to_full - 0.5).astype(np.float32),
                          (size, size), interpolation=cv2.INTER_LINEAR)
    back_tex = unseen_side_colours(front_tex, mask, fp, bp, head_colour, fs, bs, skin, loose_full, profile,
                                   source_rows=far_rows, back_face=back_face, face_skin=face_skin,
                                   hair_curtain=not facing_away)
    panels = [front_tex, back_tex]
    if layer_sheets:  # the layers' own panel: the unseen side's colours of the legs they hold
        lp = smooth_labels(layer_part, size).astype(np.float32)
        lp = np.where(lp >= 0, lp, bp).astype(np.int64)
        ls = cv2.resize(layer_side.astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST).astype(np.int64)
        ls = np.where(lp >= 0, np.where(ls != 0, ls, bs), bs)
        panels.append(unseen_side_colours(front_tex, mask, fp, lp, head_colour, fs, ls, skin, loose_full, profile,
                                          face_skin=face_skin, hair_curtain=not facing_away))
    texture = (np.clip(np.concatenate(panels, axis=1), 0, 1) * 255 + 0.5).astype(np.uint8)
    # (panel, pixel x, pixel y) of each sheet's vertices, in their order: front, back, and per layer its near
    # and far sheet and the copies of its near sheet's vertices over what the photo shows of it
    sheets = [(0, px, py), (1, px, py)] + layer_sheets
    uvs = np.concatenate([np.stack([(panel + x * to_full / size) / len(panels), 1.0 - y * to_full / size], 1)
                          for panel, x, y in sheets]).astype(np.float32)

    # skinning: nearest body vertex
    skin_j, skin_w = nearest_skinning(verts, np.asarray(vertices, np.float64), skinning_weights)
    front_flags = np.concatenate([np.ones(n, bool), np.zeros(n, bool)] + layer_front)
    mesh = TexturedMesh(verts.astype(np.float32), faces_out.astype(np.int32), uvs=uvs, texture=texture)
    return ClothedProxy(mesh=mesh, skin_joints=skin_j, skin_weights=skin_w, front=front_flags,
                        body_fraction=min(1.0, body_fraction))


def smooth_labels(labels: np.ndarray, size: int, sigma: float = LABEL_SMOOTH) -> np.ndarray:
    """``labels`` (g, g) int resized to ``size`` x ``size`` with smooth borders between them: each label's
    indicator blurred (Gaussian, ``sigma`` grid px) and resized linearly, the largest one per pixel. A
    border the grid draws as a staircase (the hairline at the back of the neck) becomes a smooth line;
    a region thinner than about ``sigma`` may shrink."""
    values = np.unique(labels)
    stack = [cv2.resize(cv2.GaussianBlur((labels == v).astype(np.float32), (0, 0), sigma), (size, size),
                        interpolation=cv2.INTER_LINEAR) for v in values]
    return values[np.argmax(np.stack(stack), axis=0)]


def nearest_skinning(points: np.ndarray, body_vertices: np.ndarray, weights: np.ndarray,
                     influences: int = SKIN_INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """Skinning of ``points`` (P, 3) copied from their nearest body vertex: the top ``influences``
    joints (P, k) int32 and their weights (P, k) float32, renormalised."""
    import torch

    p = torch.as_tensor(points, dtype=torch.float32)
    b = torch.as_tensor(body_vertices, dtype=torch.float32)
    nearest = torch.cat([torch.cdist(chunk, b).argmin(dim=1) for chunk in p.split(4096)]).numpy()
    w = np.asarray(weights, np.float64)[nearest]
    k = min(influences, w.shape[1])
    top = np.argsort(-w, axis=1)[:, :k]
    tw = np.take_along_axis(w, top, axis=1)
    tw = tw / np.maximum(tw.sum(axis=1, keepdims=True), 1e-12)
    return top.astype(np.int32), tw.astype(np.float32)
