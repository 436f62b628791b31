"""Edge-detect antialiasing (gpupro.techniques.post.edge_aa) against its definition, GPU Gems 2 Listing 9-2."""

import jax
import numpy as np
import pytest

import gpupro as gp

SIZE = (12, 12)
SCENE = gp.scenes.plane(resolution=SIZE)  # only its camera is read: far plane and viewing axis
AA = gp.make_pass("edge_aa")
DEFAULTS = {k: float(v) for k, v in AA.params.items()}


@jax.jit
def run(params, buffers):
    outputs, counters, _ = AA.run(params, buffers, SCENE)
    return outputs, counters


def with_params(**changes):
    return {**AA.params, **{k: np.float32(v) for k, v in changes.items()}}


def gbuffer(depth, normal, coverage=None, seed=0):
    """A synthetic G-buffer of ``SIZE`` and a random image."""
    rng = np.random.default_rng(seed)
    normal = np.broadcast_to(np.asarray(normal, np.float32), SIZE + (3,))
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    return {"hdr": rng.uniform(0.0, 4.0, SIZE + (3,)).astype(np.float32),
            "view_depth": np.broadcast_to(np.asarray(depth, np.float32), SIZE),
            "normal": normal, "coverage": np.ones(SIZE, np.float32) if coverage is None else coverage}


def two_surfaces(seed=0):
    """Columns 0–5 a wall at depth 2 facing the camera, columns 6–11 a floor-like surface at depth 6."""
    left = np.arange(SIZE[1]) < 6
    depth = np.where(left, 2.0, 6.0)[None, :] * np.ones(SIZE)
    normal = np.where(left[None, :, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]) * np.ones(SIZE + (3,))
    return gbuffer(depth, normal, seed=seed)


# --- the chapter's shader, transcribed in NumPy (texture coordinates, bilinear fetches, HLSL step) ---

def tex2d(image, u, v):
    """Bilinear fetch at continuous pixel coordinates (u right, v down, texel centres at integers),
    clamp-to-edge addressing, as a texture unit does."""
    h, w = image.shape[:2]
    u0, v0 = int(np.floor(u)), int(np.floor(v))
    fu, fv = u - u0, v - v0
    texel = lambda x, y: image[min(max(y, 0), h - 1), min(max(x, 0), w - 1)]
    return ((1 - fu) * (1 - fv) * texel(u0, v0) + fu * (1 - fv) * texel(u0 + 1, v0)
            + (1 - fu) * fv * texel(u0, v0 + 1) + fu * fv * texel(u0 + 1, v0 + 1))


def hlsl_step(edge, x):
    return 1.0 if x >= edge else 0.0


def listing_9_2(hdr, depth, normal, b):
    """Listing 9-2 pixel by pixel: tc1 LT, tc2 RB, tc3 RT, tc4 LB, tc5 L/R, tc6 T/B."""
    out, weights = np.zeros_like(hdr), np.zeros(hdr.shape[:2])
    for y in range(hdr.shape[0]):
        for x in range(hdr.shape[1]):
            tc = [(x, y), (x - 1, y - 1), (x + 1, y + 1), (x + 1, y - 1), (x - 1, y + 1)]
            left_right, top_bottom = ((x - 1, y), (x + 1, y)), ((x, y - 1), (x, y + 1))
            nc = tex2d(normal, *tc[0])
            nd = [np.dot(nc, tex2d(normal, *tc[i])) - b["normal_barrier"] for i in (1, 2, 3, 4)]
            ne = min(max(sum(hlsl_step(0.0, d) for d in nd) * 0.25, 0.0), 1.0)
            z = lambda c: tex2d(depth, *c)
            dd = [z(tc[1]) + z(tc[2]), z(tc[3]) + z(tc[4]), z(left_right[0]) + z(left_right[1]),
                  z(top_bottom[0]) + z(top_bottom[1])]
            dd = [abs(2 * z(tc[0]) - d) - b["depth_barrier"] for d in dd]
            de = min(max(sum(hlsl_step(d, 0.0) for d in dd) * 0.25, 0.0), 1.0)
            w = (1 - de * ne) * b["kernel"]
            offset = np.array(tc[0]) * (1 - w)
            taps = [tex2d(hdr, *(offset + np.array(tc[i]) * w)) for i in (1, 2, 3, 4)]
            out[y, x], weights[y, x] = sum(taps) / 4, w
    return out, weights


def test_constant_and_affine_depth_planes_are_left_unchanged():
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:SIZE[0], :SIZE[1]]
    # a head-on plane; a tilted one (affine depth), whose clamped border taps at two corners make the
    # second difference a first difference (0.7 > b_d: the border is an edge there, as on a texture unit)
    for depth, inside in ((np.full(SIZE, 3.0), np.s_[:, :]), (2.0 + 0.4 * xx + 0.3 * yy, np.s_[1:-1, 1:-1])):
        buffers = gbuffer(depth, rng.normal(size=3))
        outputs, counters = run(AA.params, buffers)
        np.testing.assert_array_equal(outputs["edge_weight"][inside], 0.0)
        np.testing.assert_allclose(outputs["hdr_aa"][inside], buffers["hdr"][inside], rtol=1e-6)
    assert int(counters["blended_pixels"]) == 2  # the two corners


def test_an_edge_between_two_surfaces_is_blended():
    buffers = two_surfaces()
    outputs, counters = run(AA.params, buffers)
    weight, hdr, aa = (np.asarray(x) for x in (outputs["edge_weight"], buffers["hdr"], outputs["hdr_aa"]))
    # next to the seam: 2 of 4 diagonal normals agree (n_e = 1/2), 1 of 4 opposite pairs is straight
    # (d_e = 1/4): w = (1 − 1/8) k
    np.testing.assert_allclose(weight[:, 5:7], 0.875 * DEFAULTS["kernel"], rtol=1e-6)
    np.testing.assert_array_equal(np.delete(weight, [5, 6], axis=1), 0.0)
    assert int(counters["blended_pixels"]) == 2 * SIZE[0]
    w = weight[4, 5]  # one pixel's blend, from its eight neighbours (bilinear taps at ±w)
    patch = hdr[3:6, 4:7]
    tent = np.array([[w * w / 4, w * (1 - w) / 2, w * w / 4], [w * (1 - w) / 2, (1 - w) ** 2, w * (1 - w) / 2],
                     [w * w / 4, w * (1 - w) / 2, w * w / 4]])
    np.testing.assert_allclose(aa[4, 5], np.einsum("ij,ijc->c", tent, patch), rtol=1e-5)
    np.testing.assert_allclose(aa[:, :4], hdr[:, :4], rtol=1e-6)  # away from the seam: unchanged


def test_matches_a_transcription_of_listing_9_2():
    rng = np.random.default_rng(2)
    depth = 3.0 + np.where(rng.uniform(size=SIZE) < 0.3, rng.uniform(0.0, 2.0, SIZE), 0.0)  # bumps of either side of b_d
    normal = np.array([0.0, 0.0, 1.0]) + np.where(rng.uniform(size=SIZE + (1,)) < 0.3, rng.normal(size=SIZE + (3,)), 0.0)
    coverage = (rng.uniform(size=SIZE) > 0.1).astype(np.float32)
    buffers = gbuffer(depth, normal, coverage, seed=3)
    params = dict(DEFAULTS, normal_barrier=0.7, depth_barrier=0.8, kernel=0.8)
    outputs, _ = run(with_params(**params), buffers)
    # empty pixels: the far plane facing the camera (the module's convention, given to the shader as data)
    forward = np.asarray(SCENE.camera.target - SCENE.camera.eye)
    empty = coverage[..., None] == 0
    expected, weights = listing_9_2(buffers["hdr"].astype(np.float64),
                                    np.where(coverage == 0, float(SCENE.camera.far), depth),
                                    np.where(empty, -forward / np.linalg.norm(forward), buffers["normal"]), params)
    assert 0 < np.count_nonzero(weights) < weights.size
    np.testing.assert_allclose(outputs["edge_weight"], weights, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(outputs["hdr_aa"], expected, rtol=1e-5, atol=1e-5)


def test_the_relaxed_filter_tends_to_the_listing_s():
    buffers = two_surfaces(seed=4)
    buffers["view_depth"] = buffers["view_depth"] + 0.3 * np.random.default_rng(5).uniform(size=SIZE)
    discrete, _ = run(AA.params, buffers)
    for temperature, close in ((1e-6, True), (0.05, False)):
        relaxed, _ = run(with_params(normal_temperature=temperature, depth_temperature=temperature), buffers)
        for name in ("edge_weight", "hdr_aa"):
            same = np.allclose(relaxed[name], discrete[name], rtol=1e-6, atol=1e-6)
            assert same == close, (temperature, name)


def test_barriers_and_kernel_have_gradients():
    """With temperatures > 0 the barriers move the image (a non-zero gradient) and central differences agree."""
    buffers = two_surfaces(seed=6)
    buffers["view_depth"] = buffers["view_depth"] + np.random.default_rng(7).uniform(0.0, 1.0, SIZE)
    weights = np.random.default_rng(8).normal(size=SIZE + (3,)).astype(np.float32)
    loss = jax.jit(lambda p: (weights * run(p, buffers)[0]["hdr_aa"]).sum())
    params = with_params(normal_temperature=0.1, depth_temperature=0.2)
    gradient = jax.grad(loss)(params)
    eps = 1e-2
    for name in ("normal_barrier", "depth_barrier", "kernel"):
        moved = lambda s: {**params, name: params[name] + np.float32(s * eps)}
        numeric = (float(loss(moved(1))) - float(loss(moved(-1)))) / (2 * eps)
        assert abs(float(gradient[name])) > 1e-2, name
        assert float(gradient[name]) == pytest.approx(numeric, rel=0.05), name


def test_jitted_and_eager_runs_agree():
    """The generic jit-against-eager case, on synthetic buffers (tests/test_techniques.py runs it with -m slow:
    there it compiles the rasterizer, G-buffer and shading that produce the inputs)."""
    buffers = two_surfaces(seed=9)
    jitted, counters = run(AA.params, buffers)
    eager, eager_counters, _ = AA.run(AA.params, buffers, SCENE)
    for name in ("hdr_aa", "edge_weight"):
        np.testing.assert_allclose(jitted[name], eager[name], rtol=1e-6)
    assert set(counters) == set(eager_counters) == {c.name for c in AA.technique.counters}
