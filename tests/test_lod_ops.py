"""The shared LOD ops: the procedural heightfield and the drawing of generated geometry over a frame."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.lod import draw_generated, fbm_height, height_normals, terrain_materials
from gpupro.scene.mesh import Mesh


def test_heights_are_bounded_continuous_and_seeded():
    x = np.linspace(-300.0, 300.0, 4001, dtype=np.float32)
    h = np.asarray(fbm_height(x, 0.37 * x, amplitude=5.0, wavelength=40.0, octaves=4))
    assert np.all(np.abs(h) <= 5.0) and h.std() > 0.5  # within [−A, A], and not flat
    assert np.max(np.abs(np.diff(h))) < 0.2  # 0.15-unit steps: no jumps at lattice cells
    other = np.asarray(fbm_height(x, 0.37 * x, amplitude=5.0, wavelength=40.0, octaves=4, seed=1))
    assert np.mean(np.abs(other - h)) > 0.5


def test_height_gradient_is_continuous_across_lattice_cells():
    """The quintic fade makes the noise C¹ (C² indeed): the slope just left and right of a lattice line agree."""
    slope = jax.vmap(jax.grad(lambda x: fbm_height(x, 3.3, wavelength=1.0, octaves=1)))
    left, right = slope(jnp.array([2.0 - 1e-3, 5.0 - 1e-3])), slope(jnp.array([2.0 + 1e-3, 5.0 + 1e-3]))
    np.testing.assert_allclose(left, right, atol=2e-2)


def test_normals_of_a_plane_are_its_normal():
    x, z = np.meshgrid(np.arange(5.0), np.arange(4.0))
    n = np.asarray(height_normals(0.5 * x - 0.25 * z, 1.0))
    expected = np.array([-0.5, 1.0, 0.25]) / np.linalg.norm([-0.5, 1.0, 0.25])
    np.testing.assert_allclose(n, np.broadcast_to(expected, n.shape), atol=1e-6)


def _square(y: float) -> Mesh:
    """A 4×4 horizontal square at height y facing up."""
    p = jnp.array([[-2.0, y, -2.0], [2.0, y, -2.0], [2.0, y, 2.0], [-2.0, y, 2.0]])
    return Mesh(p, jnp.array([[0, 2, 1], [0, 3, 2]], jnp.int32), jnp.tile(jnp.array([0.0, 1.0, 0.0]), (4, 1)),
                jnp.zeros((4, 2)), jnp.zeros(2, jnp.int32))


@pytest.mark.slow  # 18 s on the 2-core CPU; each LOD pass's own test draws over a frame by depth by default
def test_generated_surface_shows_only_where_nearer_than_the_frame():
    scene = gp.scenes.plane(resolution=(32, 32))
    scene = scene.replace(camera=gp.scene.make_camera((0.0, 5.0, 0.01), (0.0, 0.0, 0.0), resolution=(32, 32)))
    materials = terrain_materials([[0.5, 0.5, 0.5]])
    below, _ = draw_generated(_square(-1.0), materials, scene, ambient=(1.0, 1.0, 1.0))
    above, counters = draw_generated(_square(1.0), materials, scene, ambient=(1.0, 1.0, 1.0), background=(0.2, 0.0, 0.0))
    assert int(counters["triangles_drawn"]) == 2
    assert 0.1 < float(below["coverage"].mean()) < float(above["coverage"].mean()) < 1.0  # nearer looks bigger
    # Over the frame of the lower square, the upper one wins where both are, and the lower shows elsewhere.
    over, _ = draw_generated(_square(1.0), materials, scene, ambient=(1.0, 1.0, 1.0), hdr=below["hdr"], depth=below["depth"])
    np.testing.assert_array_equal(over["coverage"], above["coverage"])
    np.testing.assert_allclose(over["hdr"], jnp.where(above["coverage"][..., None] > 0, above["hdr"], below["hdr"]))
    # Behind the frame: nothing of it shows.
    under, _ = draw_generated(_square(-1.0), materials, scene, hdr=above["hdr"], depth=above["depth"] * 0.0)
    assert float(under["coverage"].max()) == 0.0
    np.testing.assert_array_equal(under["hdr"], above["hdr"])
    np.testing.assert_allclose(above["hdr"][0, 0], [0.2, 0.0, 0.0])  # the background where nothing is


@pytest.mark.slow  # 25 s on the 2-core CPU; tests/test_antialias.py checks these gradients on its own meshes
def test_antialias_gives_gradients_at_silhouettes():
    """Under ambient light the square's radiance is constant, so only its silhouette moves with its size:
    the hard-edged image has no gradient, the antialiased one the sign and size of a finite difference."""
    scene = gp.scenes.plane(resolution=(32, 32))
    scene = scene.replace(camera=gp.scene.make_camera((0.0, 5.0, 0.01), (0.0, 0.0, 0.0), resolution=(32, 32)),
                          lights=gp.scene.make_lights([], position=np.zeros((0, 3)), color=np.zeros((0, 3))))
    materials = terrain_materials([[0.5, 0.5, 0.5]])

    def brightness(scale, antialias):
        mesh = _square(0.0)
        mesh = Mesh(mesh.positions * jnp.array([scale, 1.0, 1.0]), mesh.faces, mesh.normals, mesh.uv, mesh.material_ids)
        return jnp.sum(draw_generated(mesh, materials, scene, ambient=(1.0, 1.0, 1.0), antialias=antialias)[0]["hdr"])

    assert float(jax.grad(brightness)(1.0, False)) == 0.0
    analytic = float(jax.grad(brightness)(1.0, True))
    numeric = float(brightness(1.05, True) - brightness(0.95, True)) / 0.1
    assert analytic > 0.0 and abs(analytic - numeric) < 0.25 * abs(numeric)
