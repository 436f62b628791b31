"""Edge-detect antialiasing of a deferred frame (S.T.A.L.K.E.R.): ``hdr`` → ``hdr_aa``.

Source: O. Shishkovtsov, "Deferred Shading in S.T.A.L.K.E.R.", GPU Gems 2, ch. 9 (seed 001), sec. 9.5
"Antialiasing" and Listing 9-2. A deferred renderer cannot use the hardware's multisampling, so the
composited image is blurred where the G-buffer shows a discontinuity of depth or normal, and left
intact elsewhere. At pixel p, with the centre c, the four diagonal taps LT, RB, RT, LB and the four
axial taps L, R, T, B (one pixel away; clamp-to-edge addressing):

    normal detector   s_i = step(n_c·n_i − b_n),                 i ∈ {LT, RB, RT, LB}
                      n_e = saturate(w_n Σ_i s_i) = ¼ Σ_i s_i
    depth detector    t_j = step(b_d − |2 z_c − (z_a + z_b)|),   (a, b) ∈ {(LT, RB), (RT, LB), (L, R), (T, B)}
                      d_e = saturate(w_d Σ_j t_j) = ¼ Σ_j t_j
    edge weight       w = (1 − d_e · n_e) · k                    (0: no antialiasing, k: a full edge)
    image             I'(p) = ¼ Σ_{o ∈ {(−1,−1), (1,1), (1,−1), (−1,1)}} I_bilinear(p + w o)

with step(x) = 1 for x ≥ 0 (HLSL's ``step(0, x)``), saturate = clamp to [0, 1], b_n, b_d the normal
and depth barriers (the listing's comment: "norm(~.8f)", "depth(~.5f)"), w_n, w_d its ``e_weights``
and k its ``e_kernel.x``. |2 z_c − (z_a + z_b)| is the depth's second difference along the line through
the opposite taps: the distance of the centre from "the ideal line passed through opposite corner
points", zero on a plane seen head-on (and small on any plane: view depth is not affine in the
screen under perspective). For 0 ≤ w ≤ 1 the bilinear tap at p + w (s_x, s_y) is
(1 − w)² I(p) + w (1 − w) (I(p + (s_x, 0)) + I(p + (0, s_y))) + w² I(p + (s_x, s_y)), so w = 0 leaves
the pixel unchanged and w = ½ gives the 3 × 3 tent filter [1 2 1]ᵀ[1 2 1] / 16.

Continuous relaxation (not in the chapter; for fits): with a temperature τ > 0 each step becomes a
logistic, step(x) → σ(x / τ), with τ_n (``normal_temperature``, for n·n) and τ_d
(``depth_temperature``, world units) apart since the two detectors have different units; at τ = 0 the
filter is the listing's, and it is the limit of the relaxed filter as τ → 0 wherever no argument is 0.

Departures and choices:
- depth is ``view_depth`` (distance along the viewing axis) where the listing reads the view-space
  position's z: the same up to sign, so the second differences are equal; normals are the G-buffer's
  world-space normals, whose dot products equal the view-space ones;
- an empty pixel (no surface) is taken as the far plane facing the camera (z = far, n = −forward), so
  the sky's interior is no edge and a silhouette against the sky is one (the chapter does not say what
  its position buffer holds there);
- the listing does not print ``e_weights`` or ``e_kernel``: w_n = w_d = ¼, fixed (n_e and d_e are the
  fractions of agreeing taps, so one disagreeing tap makes an edge, and saturate never clips, which
  keeps the relaxed filter smooth: as parameters, a weight above ¼ would put saturate's kink inside the
  range), and k = ½ by default (a full edge gets the tent filter; k = 1, "full aa", replaces the pixel
  by its diagonal neighbours' mean);
- the listing's opposite taps ``tc5r = I.tc5.wzyx`` swap the components of the packed right (or
  bottom) coordinate: either its vertex shader packs them as (u_L, v_L, v_R, u_R) or the swizzle should
  read ``.zwxy``; the text says "opposite corner points", which is what is done here (a doubt, not a
  change).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.raster import normalize
from gpupro.technique import Buffer, Counter, Param, Technique, register

CORNERS = ((-1, -1), (1, 1), (1, -1), (-1, 1))
"""Pixel offsets (x right, y down) of the diagonal taps LT, RB, RT, LB (the listing's tc1…tc4)."""

TAP_WEIGHT = 0.25
"""w_n = w_d: n_e and d_e are the fractions of agreeing taps (module docstring)."""

OPPOSITE_PAIRS = (((-1, -1), (1, 1)), ((1, -1), (-1, 1)), ((-1, 0), (1, 0)), ((0, -1), (0, 1)))
"""The depth detector's opposite taps: the two diagonals, left/right, top/bottom."""


def neighbour(image, dx: int, dy: int):
    """``image`` [H, W, ...] read one step (``dx`` right, ``dy`` down, static) away, clamped to the edge."""
    height, width = image.shape[:2]
    rows = jnp.clip(jnp.arange(height) + dy, 0, height - 1)
    cols = jnp.clip(jnp.arange(width) + dx, 0, width - 1)
    return image[rows][:, cols]


def soft_step(x, temperature):
    """step(x) = [x ≥ 0] at ``temperature`` 0, σ(x / temperature) above (arrays broadcast; the unused branch's
    gradient is kept finite at 0)."""
    safe = jnp.where(temperature > 0.0, temperature, 1.0)
    return jnp.where(temperature > 0.0, jax.nn.sigmoid(x / safe), (x >= 0.0).astype(jnp.float32))


def edge_weight(view_depth, normal, coverage, far, forward, params):
    """The listing's edge weight w [H, W] (module docstring) of the G-buffer's ``view_depth`` [H, W] (world
    units), unit ``normal`` [H, W, 3] and ``coverage`` [H, W]; empty pixels are the plane at ``far`` (world
    units) facing the camera, whose unit viewing axis is ``forward`` [3]. ``params``: the technique's."""
    covered = jnp.asarray(coverage) > 0
    depth = jnp.where(covered, jnp.asarray(view_depth, jnp.float32), far)
    normal = jnp.where(covered[..., None], jnp.asarray(normal, jnp.float32), -forward)
    similar = sum(soft_step(jnp.sum(normal * neighbour(normal, dx, dy), axis=-1) - params["normal_barrier"],
                            params["normal_temperature"]) for dx, dy in CORNERS)
    normal_edge = TAP_WEIGHT * similar
    straight = sum(soft_step(params["depth_barrier"] - jnp.abs(2.0 * depth - neighbour(depth, *a) - neighbour(depth, *b)),
                             params["depth_temperature"]) for a, b in OPPOSITE_PAIRS)
    depth_edge = TAP_WEIGHT * straight
    return (1.0 - depth_edge * normal_edge) * params["kernel"]


def blend_taps(image, weight):
    """¼ Σ over the four diagonal directions o of the bilinear tap of ``image`` [H, W, C] at p + w o (clamped
    to the edge), for per-pixel ``weight`` w [H, W] in [0, 1]: [H, W, C]."""
    w = weight[..., None]
    taps = [(1.0 - w) ** 2 * image + w * (1.0 - w) * (neighbour(image, dx, 0) + neighbour(image, 0, dy))
            + w * w * neighbour(image, dx, dy) for dx, dy in CORNERS]
    return 0.25 * sum(taps)


def apply(params, inputs, scene, options):
    """``hdr`` [H, W, 3] blended across the G-buffer's edges → ``hdr_aa`` [H, W, 3] and ``edge_weight`` [H, W]."""
    camera = scene.camera
    weight = edge_weight(inputs["view_depth"], inputs["normal"], inputs["coverage"], camera.far,
                         normalize(camera.target - camera.eye), params)
    hdr_aa = blend_taps(jnp.asarray(inputs["hdr"], jnp.float32), weight)
    return {"hdr_aa": hdr_aa, "edge_weight": weight}, {
        "blended_pixels": jnp.sum(weight > 0.0, dtype=jnp.int32),
        "mean_edge_weight": jnp.mean(weight),
    }


register(Technique(
    id="edge_aa",
    title="Edge-detect antialiasing of a deferred frame: depth second differences and normal dots blend 4 bilinear taps",
    source="O. Shishkovtsov, Deferred Shading in S.T.A.L.K.E.R., GPU Gems 2 ch. 9 (seed 001): sec. 9.5, Listing 9-2",
    family="post",
    status="implemented",
    apply=apply,
    inputs=(Buffer("hdr", "linear radiance of the composited frame", "RGB"),
            Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
            Buffer("normal", "unit shading normal", "XYZ"),
            Buffer("coverage", "1 where a triangle is visible, 0 where empty", "Y")),
    outputs=(Buffer("hdr_aa", "linear radiance blended across depth and normal edges", "RGB"),
             Buffer("edge_weight", "w = (1 − d_e n_e) k: 0 where left intact, k on a full edge", "Y")),
    params=(
        Param("normal_barrier", 0.8, "1", "b_n: diagonal neighbours with n_c·n_i below it make a normal edge "
                                          "(the listing's ~0.8)", lower=-1.0, upper=1.0),
        Param("depth_barrier", 0.5, "world units", "b_d: opposite taps whose depth second difference exceeds it make "
                                                   "a depth edge (the listing's ~0.5)", lower=0.0),
        Param("kernel", 0.5, "pixels", "k: the taps' offset on a full edge (0: no antialiasing, 1: the diagonal "
                                       "neighbours)", lower=0.0, upper=1.0),
        Param("normal_temperature", 0.0, "1", "τ_n of the normal steps' relaxation σ(x / τ_n); 0: the listing's step",
              lower=0.0),
        Param("depth_temperature", 0.0, "world units", "τ_d of the depth steps' relaxation σ(x / τ_d); 0: the "
                                                       "listing's step", lower=0.0),
    ),
    counters=(Counter("blended_pixels", "pixels with an edge weight above 0 (int32)", headline=True),
              Counter("mean_edge_weight", "the mean edge weight over the image")),
    notes=("The listing's e_weights and e_kernel values are not printed: w_n = w_d = 1/4 (fixed) and k = 1/2 are "
           "this project's choices. Empty pixels are the far plane facing the camera. The temperatures relax the "
           "steps for fits; at 0 the filter is the listing's."),
))
