"""A procedural pelvis population (plain anatomical templates), and which population to load.

The offline default is no longer this one but patients sampled from the packaged pelvis model
(:mod:`pelvicnav.phantom.sampled`); the templates stay for tests that want exactly known joints
and a population without any model (``--atlas procedural``).

Each bone is first built once as a *template*: an implicit solid (signed-distance-like field)
made of anatomical parts blended with a smooth minimum, meshed with marching cubes and decimated
to exactly ``n_vertices`` vertices. Subjects are then smooth deformations of the templates, so
vertex ``i`` is the same anatomical point in every subject (exact correspondence by construction).

Template anatomy (pelvis frame, LPS mm, origin between the hip centres; the right innominate is
the mirror image of the left):

* innominate: acetabulum (a hemispherical cup of radius 25 mm opening laterally, anteriorly and
  inferiorly), iliac wing (a thin plate, concave medially, with a thickened rounded crest from
  the anterior to the posterior superior iliac spine), a thick posterior ilium ending in a flat
  auricular face, the superior pubic ramus, the pubic body with its symphyseal face, the
  inferior pubic and ischial rami, the ischial body, spine and tuberosity; the rami frame the
  obturator foramen (the innominate has genus 1);
* sacrum: a kyphotic tapering plate (S1 to the apex) with the S1 body and promontory on top, the
  alae, and flat auricular faces cut by the sacroiliac joint planes.

The sacroiliac faces lie on shared planes ``SI_GAP_MM`` apart and the symphyseal faces on
``x = +-PS_GAP_MM / 2``, so the joints of every subject are narrow and collision-free.

Subjects vary by (1) a global scale and anisotropic axis scales, (2) a smooth random displacement
field (Gaussian radial basis functions) shared by the three bones, so shapes vary but joints stay
congruent, (3) a small rigid motion of each innominate about its sacroiliac joint, and (4) a
random placement in its "CT" frame. All draws come from one seeded generator.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pelvicnav.io.atlas import BONES, Atlas

__all__ = [
    "MODEL",
    "PROCEDURAL",
    "PS_GAP_MM",
    "SI_GAP_MM",
    "PopulationOptions",
    "atlas_statistics",
    "load_population",
    "procedural_population",
    "template_bones",
]

SI_GAP_MM = 3.0
PS_GAP_MM = 4.0

# Left sacroiliac joint plane: a point and the outward (lateral, slightly posterior) normal.
_SI_POINT = np.array([53.0, 52.0, 42.0])
_SI_NORMAL = np.array([1.0, 0.3, 0.0]) / np.hypot(1.0, 0.3)
# Mean axis scale of the population relative to the templates (matches the atlas's mean sizes).
_AXIS_SCALE = np.array([1.0, 0.99, 0.98])
# Acetabulum: centre, radius and opening direction (lateral, anterior, inferior).
_ACET_CENTRE = np.array([84.0, 0.0, 0.0])
_ACET_RADIUS = 25.0
_ACET_AXIS = np.array([0.72, -0.3, -0.62]) / np.linalg.norm([0.72, -0.3, -0.62])


# ---------------------------------------------------------------------------------------------
# implicit primitives (negative inside, roughly a distance in mm near the surface)


def _smin(a: NDArray, b: NDArray, k: float) -> NDArray:
    """Polynomial smooth minimum (a fillet of about ``k`` mm)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _cone(p: NDArray, a, b, ra: float, rb: float) -> NDArray:
    """Capsule from ``a`` to ``b`` with radius varying linearly from ``ra`` to ``rb``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    d = np.linalg.norm(p - (a + t[:, None] * ab), axis=1)
    return d - (ra + (rb - ra) * t)


def _chain(p: NDArray, points, radii) -> NDArray:
    """Union of cones through consecutive ``points`` with per-point radii."""
    out = np.full(len(p), np.inf)
    for i in range(len(points) - 1):
        out = np.minimum(out, _cone(p, points[i], points[i + 1], radii[i], radii[i + 1]))
    return out


def _ellipsoid(p: NDArray, centre, radii) -> NDArray:
    q = (p - np.asarray(centre, float)) / np.asarray(radii, float)
    return (np.linalg.norm(q, axis=1) - 1.0) * float(np.min(radii))


def _sheet(p: NDArray, surface: NDArray, half_thickness: NDArray) -> NDArray:
    """A thick sheet: distance to densely sampled ``surface`` points minus the half thickness."""
    from scipy.spatial import cKDTree

    reach = float(half_thickness.max()) + 6.0
    d, j = cKDTree(surface).query(p, distance_upper_bound=reach)
    far = ~np.isfinite(d)
    j[far] = 0
    return np.where(far, reach, d - half_thickness[j])


def _plane(p: NDArray, point, normal) -> NDArray:
    """Signed distance to a plane, positive along ``normal``."""
    return (p - np.asarray(point, float)) @ np.asarray(normal, float)


def _grid_uv(n_u: int, n_v: int) -> tuple[NDArray, NDArray]:
    u, v = np.meshgrid(np.linspace(0, 1, n_u), np.linspace(0, 1, n_v), indexing="ij")
    return u.ravel(), v.ravel()


def _curve(knots: NDArray, t: NDArray) -> NDArray:
    """Catmull-Rom-like smooth curve through ``knots`` (k, 3) at parameters ``t`` in [0, 1]."""
    from scipy.interpolate import CubicSpline

    s = np.linspace(0, 1, len(knots))
    return CubicSpline(s, knots, axis=0, bc_type="natural")(t)


def _left_innominate_field(p: NDArray) -> NDArray:
    c, r, ax = _ACET_CENTRE, _ACET_RADIUS, _ACET_AXIS
    # Iliac wing: a sheet between a lower curve (above the acetabulum, down to the sciatic notch)
    # and the crest (anterior superior iliac spine -> iliac tubercle -> posterior superior spine).
    u, v = _grid_uv(150, 110)
    crest = _curve(
        np.array([[110, -48, 64], [128, -20, 94], [128, 16, 108], [104, 48, 104], [68, 70, 78]]),
        u,
    )
    lower = _curve(
        np.array([[104, -36, 28], [100, -8, 32], [90, 18, 34], [72, 38, 32], [58, 52, 26]]), u
    )
    bulge = 9.0 * np.sin(np.pi * u) * np.sin(np.pi * v)  # gluteal surface convex laterally
    surface = (1 - v)[:, None] * lower + v[:, None] * crest
    surface[:, 0] += bulge
    half = 2.6 + 7.0 * (1 - v) ** 3 + 3.2 * v**10 + 9.0 * u**5 * (0.5 + 0.5 * v)
    wing = _sheet(p, surface, half)
    # Posterior ilium with the auricular face (cut by the sacroiliac plane below).
    auricular = _chain(
        p, [[66, 34, 18], [64, 50, 42], [66, 62, 64], [70, 72, 76]], [14.0, 17.0, 16.0, 11.0]
    )
    ilium = _smin(wing, auricular, 6.0)
    ilium = np.maximum(ilium, -_plane(p, _SI_POINT, _SI_NORMAL) + SI_GAP_MM / 2)
    # Acetabular body.
    body = _ellipsoid(p, c - 6.0 * ax + [0, 0, 2], (35.0, 34.0, 36.0))
    # Pubis: superior ramus -> body (cut at the symphysis) -> inferior ramus; ischium.
    sup_ramus = _chain(p, [[74, -22, -4], [52, -38, -14], [26, -50, -24]], [12.0, 8.5, 9.5])
    pubic_body = _chain(p, [[12, -56, -20], [12, -52, -40], [16, -46, -56]], [11.0, 12.0, 9.0])
    pubic_body = np.maximum(pubic_body, PS_GAP_MM / 2 - p[:, 0])
    inf_ramus = _chain(p, [[18, -48, -58], [36, -34, -76], [54, -14, -86]], [8.0, 7.0, 7.5])
    ischium = _chain(
        p, [[80, 10, -14], [78, 14, -50], [74, 12, -78], [60, -6, -88]], [17.0, 14.0, 14.0, 9.0]
    )
    spine = _cone(p, [72, 24, -22], [58, 40, -28], 7.0, 2.5)
    lower_bone = _smin(_smin(sup_ramus, pubic_body, 5.0), inf_ramus, 5.0)
    lower_bone = _smin(lower_bone, ischium, 6.0)
    out = _smin(_smin(body, ilium, 10.0), lower_bone, 8.0)
    out = _smin(out, spine, 4.0)
    # The cup: remove the femoral head's sphere and the cylinder through the opening.
    rel = p - c
    along = rel @ ax
    radial = np.linalg.norm(rel - along[:, None] * ax, axis=1)
    cylinder = np.where(along > 0, radial - r, np.hypot(radial, along) - r)
    return np.maximum(out, -cylinder)


def _sacrum_field(p: NDArray) -> NDArray:
    u, v = _grid_uv(121, 121)
    u = 2 * u - 1  # right (-1) to left (+1)
    centre = _curve(np.array([[0, 38, 48], [0, 58, 31], [0, 76, 13], [0, 94, -7]]), v)
    centre[:, 1] += 6.0 * np.sin(np.pi * v)  # kyphosis: concave anteriorly
    half_width = 70.0 * (1 - v) ** 1.15 + 9.0 * v
    surface = centre.copy()
    surface[:, 0] = u * half_width
    # Alae: curve back and slope down laterally.
    surface[:, 1] += 8.0 * u**2 * (1 - v)
    surface[:, 2] -= 9.0 * u**2 * (1 - v) ** 2
    half = 12.0 * (1 - v) ** 1.4 + 3.5
    plate = _sheet(p, surface, half)
    s1 = _ellipsoid(p, [0, 32, 47], (25.0, 18.0, 16.0))
    out = _smin(plate, s1, 6.0)
    for side in (1.0, -1.0):
        q = np.array([side, 1.0, 1.0])
        out = np.maximum(out, _plane(p, _SI_POINT * q, _SI_NORMAL * q) + SI_GAP_MM / 2)
    return out


# ---------------------------------------------------------------------------------------------
# meshing


def _mesh_field(field, lo, hi, spacing: float, n_vertices: int) -> tuple[NDArray, NDArray]:
    """Marching cubes of ``field < 0`` on a grid, largest component, decimated to n_vertices."""
    import igl
    from scipy.ndimage import zoom
    from scipy.sparse.csgraph import connected_components
    from skimage.measure import marching_cubes

    # Narrow band: evaluate on a grid 4x coarser, then exactly only near the zero level (the
    # field is about a distance, so points far from it in the coarse grid keep their sign).
    step = 4
    n = [int(np.ceil((b - a) / (spacing * step))) * step + 1 for a, b in zip(lo, hi, strict=True)]
    axes = [a + spacing * np.arange(k) for a, k in zip(lo, n, strict=True)]
    coarse_axes = [ax[::step] for ax in axes]
    coarse = field(np.stack(np.meshgrid(*coarse_axes, indexing="ij"), -1).reshape(-1, 3))
    coarse = coarse.reshape([len(a) for a in coarse_axes])
    if (
        min(coarse[0].min(), coarse[-1].min(), coarse[:, 0].min(), coarse[:, -1].min()) < 0
        or min(coarse[:, :, 0].min(), coarse[:, :, -1].min()) < 0
    ):
        raise RuntimeError("template solid touches its grid boundary")
    # corner-aligned linear upsampling: output shape n, spacing exactly 1/step of the coarse grid
    values = zoom(coarse, [k / c for k, c in zip(n, coarse.shape, strict=True)], order=1)
    band = np.argwhere(np.abs(values) < 1.5 * spacing * step)
    values[tuple(band.T)] = field(np.asarray(lo, float) + spacing * band)
    verts, faces, _, _ = marching_cubes(values, 0.0, spacing=(spacing,) * 3)
    verts = verts + np.asarray(lo, float)
    faces = faces.astype(np.int64)  # skimage orders them outward (towards positive values)
    # Largest connected component.
    import scipy.sparse as sp

    n = len(verts)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    keep = comp == np.bincount(comp).argmax()
    faces = faces[keep[faces[:, 0]]]
    used = np.unique(faces)
    remap = np.full(n, -1)
    remap[used] = np.arange(len(used))
    verts, faces = verts[used], remap[faces]
    # A closed mesh has V - E + F = 2 - 2g and E = 3F/2, so F = 2 (V - 2 + 2g).
    chi = len(verts) - len(faces) // 2
    genus = (2 - chi) // 2
    target_faces = 2 * (n_vertices - 2 + 2 * genus)
    U, G, _, _ = igl.decimate(
        np.asfortranarray(verts), np.asfortranarray(faces, dtype=np.int32), target_faces
    )
    used = np.unique(G)  # decimate may keep collapsed vertices unreferenced
    remap = np.full(len(U), -1)
    remap[used] = np.arange(len(used))
    U, G = U[used], remap[G]
    if len(U) != n_vertices or len(G) != target_faces:
        raise RuntimeError(
            f"decimation gave {len(U)} vertices / {len(G)} faces, wanted {n_vertices} / "
            f"{target_faces} (genus {genus})"
        )
    return np.ascontiguousarray(U, dtype=np.float64), np.ascontiguousarray(G, dtype=np.int64)


@functools.lru_cache(maxsize=4)
def template_bones(
    n_vertices: int = 5000, spacing: float = 1.25
) -> tuple[tuple[NDArray, NDArray, NDArray], tuple[NDArray, NDArray, NDArray]]:
    """The three template bones in the pelvis frame.

    Returns
    -------
    vertices : three (n_vertices, 3) float64 arrays, mm (sacrum, left, right)
    faces : three (n_faces, 3) int64 arrays, outward-oriented
    """
    sac_v, sac_f = _mesh_field(_sacrum_field, (-80, -10, -50), (80, 130, 90), spacing, n_vertices)
    left_v, left_f = _mesh_field(
        _left_innominate_field, (-4, -90, -115), (170, 115, 140), spacing, n_vertices
    )
    right_v = left_v * np.array([-1.0, 1.0, 1.0])
    right_f = left_f[:, ::-1].copy()
    for a in (sac_v, left_v, right_v, sac_f, left_f, right_f):
        a.setflags(write=False)
    return (sac_v, left_v, right_v), (sac_f, left_f, right_f)


# ---------------------------------------------------------------------------------------------
# population


@dataclass(frozen=True)
class PopulationOptions:
    """Spread of the procedural population (standard deviations).

    Attributes
    ----------
    scale_sd : float
        Global isotropic scale (fraction).
    axis_scale_sd : float
        Independent scale of each axis (fraction).
    field_sd_mm, field_width_mm, field_centres : float, float, int
        Shared smooth displacement field: ``field_centres`` Gaussian bumps of width
        ``field_width_mm`` with displacement amplitudes of ``field_sd_mm`` per axis.
    joint_rotation_deg, joint_translation_mm : float
        Rigid motion of each innominate about its sacroiliac joint (per axis).
    placement_rotation_deg : (3,) float
        Rotation of the whole pelvis in its CT frame about x (pelvic tilt), y and z.
    placement_translation_mm : float
        Translation of the whole pelvis in its CT frame (per axis).
    """

    scale_sd: float = 0.035
    axis_scale_sd: float = 0.02
    field_sd_mm: float = 1.5
    field_width_mm: float = 50.0
    field_centres: int = 10
    joint_rotation_deg: float = 1.0
    joint_translation_mm: float = 0.5
    placement_rotation_deg: tuple[float, float, float] = (3.0, 1.0, 1.0)
    placement_translation_mm: float = 15.0


def _rotation(rotvec: NDArray) -> NDArray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rotvec).as_matrix()


def procedural_population(
    n_subjects: int = 40,
    *,
    seed: int = 0,
    n_vertices: int = 5000,
    options: PopulationOptions | None = None,
) -> Atlas:
    """Draw ``n_subjects`` pelvises with exact vertex correspondence.

    Parameters
    ----------
    n_subjects : int
        Number of subjects (ids 1..n_subjects).
    seed : int
        Seed of the population; the same seed gives the same population.
    n_vertices : int
        Vertices per bone (5000 like the atlas).
    options : PopulationOptions, optional

    Returns
    -------
    Atlas
        ``source="procedural"``, bones ``sacrum, left_hip, right_hip``, each subject in its own
        "CT" frame (LPS mm, pelvis near the origin).
    """
    if n_subjects < 1:
        raise ValueError(f"n_subjects must be >= 1, got {n_subjects}")
    if n_vertices < 500:
        raise ValueError(f"n_vertices must be >= 500, got {n_vertices}")
    opt = options or PopulationOptions()
    verts, faces = template_bones(n_vertices)
    template = np.stack(verts)  # (3, V, 3)
    all_points = template.reshape(-1, 3)
    rng = np.random.default_rng(seed)
    out = np.empty((n_subjects, 3, n_vertices, 3))
    si_centres = [None, _SI_POINT, _SI_POINT * [-1, 1, 1]]
    for s in range(n_subjects):
        scale = 1.0 + opt.scale_sd * np.clip(rng.standard_normal(), -2.0, 2.0)
        axis = _AXIS_SCALE + opt.axis_scale_sd * np.clip(rng.standard_normal(3), -2.0, 2.0)
        centres = all_points[rng.integers(0, len(all_points), opt.field_centres)]
        amplitudes = opt.field_sd_mm * rng.standard_normal((opt.field_centres, 3))
        joint_r = np.deg2rad(opt.joint_rotation_deg) * rng.standard_normal((3, 3))
        joint_t = opt.joint_translation_mm * rng.standard_normal((3, 3))
        place_r = _rotation(np.deg2rad(opt.placement_rotation_deg) * rng.standard_normal(3))
        place_t = opt.placement_translation_mm * rng.standard_normal(3)
        for b in range(3):
            p = template[b]
            d2 = np.sum((p[:, None, :] - centres[None]) ** 2, axis=-1)
            p = p + np.exp(-0.5 * d2 / opt.field_width_mm**2) @ amplitudes
            if b > 0:  # innominate: small rigid motion about its sacroiliac joint
                c = si_centres[b]
                p = (p - c) @ _rotation(joint_r[b]).T + c + joint_t[b]
            p = p * (scale * axis)
            out[s, b] = p @ place_r.T + place_t
    return Atlas(
        subject_ids=tuple(range(1, n_subjects + 1)),
        vertices=out,
        faces=faces,
        source="procedural",
        bones=BONES,
    )


def atlas_statistics(atlas: Atlas) -> dict[str, NDArray[np.float64]]:
    """Per-subject sizes: each bone's axis extents (mm) and the pelvic width.

    Returns
    -------
    dict with ``"{bone}_extent"`` (n_subjects, 3) x/y/z extents in the subject's frame and
    ``"pelvic_width"`` (n_subjects,) — the largest left-right distance between the two innominate
    bones — and ``"inter_acetabular"`` (n_subjects,) — the distance between the hip centres.
    """
    from pelvicnav.phantom.ctsynth import femoral_head

    out: dict[str, NDArray[np.float64]] = {}
    V = atlas.vertices
    for b, bone in enumerate(atlas.bones):
        out[f"{bone}_extent"] = V[:, b].max(axis=1) - V[:, b].min(axis=1)
    out["pelvic_width"] = V[:, 1, :, 0].max(axis=1) - V[:, 2, :, 0].min(axis=1)
    centres = np.empty((atlas.n_subjects, 2, 3))
    for s in range(atlas.n_subjects):
        for k, (b, lateral) in enumerate(((1, (1, 0, 0)), (2, (-1, 0, 0)))):
            centres[s, k] = femoral_head(V[s, b], atlas.faces[b], lateral=lateral)[0]
    out["inter_acetabular"] = np.linalg.norm(centres[:, 0] - centres[:, 1], axis=1)
    return out


PROCEDURAL = "procedural"
MODEL = "model"


def load_population(
    location: str | os.PathLike | None = None,
    *,
    n_subjects: int = 40,
    seed: int = 0,
    subject_ids: Sequence[int] | None = None,
) -> Atlas:
    """The real atlas when there is one, else patients sampled from the packaged pelvis model.

    Parameters
    ----------
    location : path, ``"model"``, ``"procedural"`` or None
        An atlas folder (must hold an atlas); ``"model"`` for patients sampled from the pelvis
        model (:func:`pelvicnav.phantom.sampled.sampled_population`); ``"procedural"`` for the
        procedural templates; or None: ``$PELVICNAV_ATLAS`` when set (must hold an atlas), else the
        user cache, falling back to the model's population when the cache has none.
    n_subjects, seed : int
        Size and seed of a generated population.
    subject_ids : sequence of int, optional
        For the model's population: draw only these subjects (the same as in the full one).

    Raises
    ------
    AtlasNotFoundError
        An explicit folder, or ``$PELVICNAV_ATLAS``, without an atlas.
    """
    from pelvicnav.io.atlas import ATLAS_ENV, AtlasNotFoundError, load_atlas
    from pelvicnav.phantom.sampled import sampled_population

    def generated() -> Atlas:
        if location is not None and str(location) == PROCEDURAL:
            return procedural_population(n_subjects, seed=seed)
        return sampled_population(n_subjects, seed=seed, subject_ids=subject_ids)

    if location is not None and str(location) in (PROCEDURAL, MODEL):
        return generated()
    try:
        return load_atlas(location)
    except AtlasNotFoundError:
        if location is not None or os.environ.get(ATLAS_ENV):
            raise
        return generated()
