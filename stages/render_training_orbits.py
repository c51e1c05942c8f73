"""Stage ``render-training-orbits``: render a textured scan along the SV3D_p orbit (training data).

Input ``scan``: a directory holding one scan (OBJ + MTL + texture, GLB/glTF or PLY; the THuman2.0
``NNNN/NNNN.obj`` layout included) or, when run by hand, the mesh file itself.

Output ``orbit``: a frame set (:mod:`humanvdm_core.frames`)::

    frames/NNNN.exr    RGBA half: unlit albedo (sRGB values) over the background colour, A = coverage
    depth/NNNN.exr     camera-space z, 0 where empty (one channel)
    normals/NNNN.exr   world-space unit normals, 0 where empty
    cameras.npz        the orbit cameras; extra: background (3,), world_from_scan (4, 4),
                       subject_height, fill

The scan is turned by ``yaw_deg`` about +Y (scans must end up Y up, facing +Z), centred and scaled
to ``subject_height`` world units; the orbit radius makes it span ``fill`` of the frame height
(:func:`humanvdm_core.scans.framing_radius`). Azimuths are ``linspace(0, 360, num_frames + 1)[1:]``,
so the last frame (azimuth 0) is the front view.
"""

from __future__ import annotations

from humanvdm_core.workflow.stage import Param, StageContext, StageSpec

NAMED_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "gray": (0.5, 0.5, 0.5),
                     "grey": (0.5, 0.5, 0.5)}

SPEC = StageSpec(
    name="render-training-orbits",
    summary="Render a textured scan along the SV3D_p orbit: RGBA frames, depth, normals and cameras.",
    inputs={"scan": "textured scan: a folder with one OBJ(+MTL+texture)/GLB/glTF/PLY, or the mesh file"},
    outputs={"orbit": "frame set: frames/ (RGBA), depth/, normals/, cameras.npz"},
    params={
        "num_frames": Param(21, "frames on the orbit; the last is azimuth 0 (front view)"),
        "resolution": Param(576, "frame width and height in pixels"),
        "elevation_deg": Param(10.0, "camera elevation in degrees"),
        "fov_deg": Param(33.8, "vertical field of view in degrees"),
        "fill": Param(0.85, "fraction of the frame height the subject spans at elevation 0"),
        "subject_height": Param(1.7, "the scan's vertical extent after normalisation, in world units"),
        "yaw_deg": Param(0.0, "turn the scan about +Y by this many degrees first (180 for a scan facing -Z)"),
        "background": Param("random", "'random' (drawn from seed), 'white', 'black', 'gray' or 'r,g,b' in [0, 1]"),
        "seed": Param(0, "seed for the random background colour"),
        "samples": Param(4, "MSAA samples per pixel (antialiasing)", choices=(1, 2, 4)),
    },
)


def background_colour(spec: str, seed: int) -> tuple[float, float, float]:
    """The background colour a ``background`` param names (``random``: uniform in [0, 1]^3 from ``seed``)."""
    import numpy as np

    from humanvdm_core.workflow.errors import ConfigError

    key = spec.strip().lower()
    if key == "random":
        return tuple(float(c) for c in np.random.default_rng(seed).uniform(0.0, 1.0, 3))
    if key in NAMED_BACKGROUNDS:
        return NAMED_BACKGROUNDS[key]
    try:
        values = tuple(float(c) for c in key.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0.0 <= c <= 1.0 for c in values):
        raise ConfigError(f"param background: {spec!r} is not 'random', one of {sorted(NAMED_BACKGROUNDS)} "
                          "or three comma-separated floats in [0, 1]")
    return values


def _check_params(p: dict) -> None:
    from humanvdm_core.workflow.errors import ConfigError

    checks = [
        (p["num_frames"] >= 1, "num_frames must be >= 1"),
        (8 <= p["resolution"] <= 8192, "resolution must be in [8, 8192]"),
        (-89.0 <= p["elevation_deg"] <= 89.0, "elevation_deg must be in [-89, 89]"),
        (1.0 <= p["fov_deg"] <= 170.0, "fov_deg must be in [1, 170]"),
        (0.0 < p["fill"] <= 2.0, "fill must be in (0, 2]"),
        (p["subject_height"] > 0.0, "subject_height must be > 0"),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"stage {SPEC.name}: {message}")


def run(ctx: StageContext) -> None:
    import numpy as np

    from humanvdm_core.cameras import orbit_cameras
    from humanvdm_core.frames import write_frames
    from humanvdm_core.render import render_views
    from humanvdm_core.scans import framing_radius, load_scan, normalization_transform

    p = ctx.params
    _check_params(p)
    background = background_colour(p["background"], p["seed"])
    ctx.progress(0, 3, "steps", "load the scan")
    scan = load_scan(ctx.inputs["scan"])
    world_from_scan = normalization_transform(scan, p["subject_height"], p["yaw_deg"])
    mesh = scan.transformed(world_from_scan)
    radius = framing_radius(p["subject_height"], p["fov_deg"], p["fill"])
    cameras = orbit_cameras(p["num_frames"], p["resolution"], p["fov_deg"], p["elevation_deg"], radius)
    cameras.extra.update({
        "background": np.asarray(background, dtype=np.float64),
        "world_from_scan": world_from_scan,
        "subject_height": np.float64(p["subject_height"]),
        "fill": np.float64(p["fill"]),
    })
    ctx.log.info("scan: %d vertices, %d faces, texture %s; orbit radius %.3f, background %s",
                 len(mesh.vertices), mesh.num_faces,
                 "none" if mesh.texture is None else f"{mesh.texture.shape[1]}x{mesh.texture.shape[0]}",
                 radius, ", ".join(f"{c:.3f}" for c in background))
    ctx.progress(1, 3, "steps", "render the orbit")
    result = render_views(mesh, cameras, background, samples=p["samples"])
    ctx.progress(2, 3, "steps", "write the frames")
    out = ctx.outputs["orbit"]
    attrs = ctx.attrs()
    write_frames(out, result.rgba, cameras, {**attrs, "layer": "rgba"})
    write_frames(out, result.depth, None, {**attrs, "layer": "depth"}, layer="depth")
    write_frames(out, result.normals, None, {**attrs, "layer": "normals"}, layer="normals")
    ctx.progress(3, 3, "steps", "write the frames")


if __name__ == "__main__":
    raise SystemExit(SPEC.main(run))
