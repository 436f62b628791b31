"""Tone mapping and sRGB: closed forms, known values, monotonicity, gradients, jit; the post pass's
exposure refused outside its declared range."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.pipeline import default_pipeline, make_pass
from gpupro.post import (
    OPERATORS,
    aces_fitted,
    apply_exposure,
    reinhard,
    srgb_decode,
    srgb_encode,
    tonemap,
)
from gpupro.scene import by_name
from gpupro.technique import OptionError

RAMP = jnp.concatenate([jnp.linspace(0.0, 1.0, 97), jnp.linspace(1.0, 100.0, 50)[1:]])
IMAGE = jnp.asarray(np.random.default_rng(3).uniform(-0.5, 20.0, (4, 4, 3)), jnp.float32)


def test_srgb_known_values():
    # IEC 61966-2-1 breakpoint: 12.92 · 0.0031308 = 0.04045 (to 5 digits), and both ends fixed
    np.testing.assert_allclose(srgb_encode(jnp.array([0.0, 0.0031308, 1.0])), [0, 0.0404499, 1], atol=1e-6)
    np.testing.assert_allclose(srgb_decode(jnp.array([0.0, 0.04045, 1.0])), [0, 0.0031308, 1], atol=1e-6)
    np.testing.assert_allclose(srgb_encode(0.5), 0.7353570, atol=1e-6)  # 1.055 · 0.5^(1/2.4) − 0.055
    np.testing.assert_allclose(srgb_decode(0.5), 0.2140411, atol=1e-6)  # ((0.5 + 0.055) / 1.055)^2.4
    np.testing.assert_allclose(srgb_encode(0.001), 0.01292, rtol=1e-6)  # linear segment


def test_srgb_round_trip():
    x = jnp.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=2e-6)
    np.testing.assert_allclose(srgb_encode(srgb_decode(x)), x, atol=2e-6)


@pytest.mark.parametrize(
    "curve",
    [srgb_encode, srgb_decode, reinhard, aces_fitted]
    + [lambda x, o=o: tonemap(x, operator=o) for o in OPERATORS],
)
def test_curves_monotone(curve):
    assert np.all(np.diff(np.asarray(curve(RAMP))) >= 0)


def test_reinhard_closed_forms():
    np.testing.assert_allclose(reinhard(jnp.array([0.0, 1.0, 3.0])), [0.0, 0.5, 0.75])
    # eq. 4 maps x = L_w to exactly 1
    np.testing.assert_allclose(reinhard(jnp.array([0.0, 2.0, 4.0]), white=4.0), [0.0, 0.75, 1.0])
    np.testing.assert_allclose(reinhard(RAMP, white=1e6), reinhard(RAMP), rtol=1e-6)
    assert np.all(np.asarray(reinhard(RAMP)) < 1.0)


def test_aces_fitted_values():
    assert float(aces_fitted(0.0)) == 0.0
    np.testing.assert_allclose(aces_fitted(1.0), 2.54 / 3.16, rtol=1e-6)  # pre-exposed: 1 → ≈ 0.8
    assert float(aces_fitted(1e4)) == 1.0
    assert float(aces_fitted(20.0)) > 0.99


def test_tonemap_dispatch_and_exposure():
    x = jnp.array([-1.0, 0.25, 0.5, 3.0])
    np.testing.assert_allclose(tonemap(x, operator="linear"), [0.0, 0.25, 0.5, 1.0])
    np.testing.assert_allclose(tonemap(x, operator="linear", exposure=1.0), [0.0, 0.5, 1.0, 1.0])
    np.testing.assert_allclose(
        tonemap(x, operator="reinhard", exposure=-1.0), reinhard(jnp.maximum(x, 0) / 2)
    )
    np.testing.assert_allclose(tonemap(x), aces_fitted(jnp.maximum(x, 0)))
    np.testing.assert_allclose(apply_exposure(x, 2.0), 4 * x)
    with pytest.raises(ValueError, match=r"'filmic'.*\('linear', 'reinhard', 'aces'\)"):
        tonemap(x, operator="filmic")


def test_gradients_finite_at_zero():
    zero = jnp.zeros(3)
    np.testing.assert_allclose(jax.grad(lambda x: srgb_encode(x).sum())(zero), 12.92)
    np.testing.assert_allclose(jax.grad(lambda x: srgb_decode(x).sum())(zero), 1 / 12.92)
    np.testing.assert_allclose(jax.grad(lambda x: reinhard(x).sum())(zero), 1.0)
    # d/dLw of x (1 + x / Lw²) / (1 + x) = −2 x² / (Lw³ (1 + x)); at x = 1, Lw = 2, three channels
    np.testing.assert_allclose(jax.grad(lambda w: reinhard(jnp.ones(3), white=w).sum())(2.0), -3 * 2 / 8 / 2)
    for operator in OPERATORS:
        image_grad = jax.grad(lambda x: srgb_encode(tonemap(x, operator=operator)).sum())(zero)
        ev_grad = jax.grad(lambda ev: srgb_encode(tonemap(IMAGE, operator=operator, exposure=ev)).sum())(0.0)
        assert np.all(np.isfinite(image_grad)) and np.isfinite(ev_grad), operator
    np.testing.assert_allclose(
        jax.grad(lambda ev: apply_exposure(3.0, ev))(1.0), 3.0 * 2.0 * np.log(2.0), rtol=1e-6
    )


def test_jit_matches_eager():
    jitted = jax.jit(tonemap, static_argnames="operator")
    for operator in OPERATORS:
        np.testing.assert_allclose(
            jitted(IMAGE, operator=operator, exposure=0.5), tonemap(IMAGE, operator=operator, exposure=0.5),
            rtol=1e-6, atol=1e-7,
        )
    np.testing.assert_allclose(jax.jit(srgb_encode)(IMAGE), srgb_encode(IMAGE), rtol=1e-6)
    np.testing.assert_allclose(jax.jit(srgb_decode)(IMAGE), srgb_decode(IMAGE), rtol=1e-6)


def test_tone_curves_stay_finite_for_huge_finite_radiance():
    from gpupro.post.tonemapping import tonemap

    huge = jnp.array([1e19, 1.2e19, 3e38, 1e3], jnp.float32)
    for operator in ("aces", "reinhard", "linear"):
        y = np.asarray(tonemap(huge, operator=operator))
        np.testing.assert_allclose(y, 1.0, atol=1e-3, err_msg=operator)
    assert np.isfinite(np.asarray(tonemap(jnp.float32(1.0), operator="aces", exposure=200.0)))


@pytest.mark.parametrize("value, message", [
    (200.0, r"expected values in \[-64\.0, 64\.0\] \(stops\), got 200\.0"),  # 2^200 is inf in float32
    (-65.0, r"expected values in \[-64\.0, 64\.0\] \(stops\), got -65\.0"),
    (np.nan, r"expected finite numbers, got nan"),
])
def test_exposure_outside_its_range_is_refused_where_it_is_set(value, message):
    """As a pass's params (configs, notebooks) and in a frame's params (gp.render, before any frame is
    traced), an exposure that gives a non-finite or all-NaN ldr is refused, naming it."""
    with pytest.raises(OptionError, match=rf"^exposure: {message}$"):
        make_pass("post", params={"exposure": value})
    pipeline = default_pipeline()
    params = {**pipeline.init_params(), "post": {"exposure": value}}
    with pytest.raises(OptionError, match=rf"^post\.exposure: {message}$"):
        gp.render(by_name("box", resolution=(16, 16)), pipeline, params, quiet=True)
