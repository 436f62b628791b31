"""make_materials refuses values outside the documented ranges, naming argument, material and range."""

import numpy as np
import pytest

from gpupro.scene import make_materials

GREY = [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(roughness=[0.5, -0.5]), "materials: roughness: material 1 has -0.5; allowed: finite and in [0, 1]"),
        (dict(roughness=[1.5, 0.5]), "materials: roughness: material 0 has 1.5; allowed: finite and in [0, 1]"),
        (dict(metallic=[0.0, 2.0]), "materials: metallic: material 1 has 2; allowed: finite and in [0, 1]"),
        (dict(base_color=[GREY[0], [-1.0, 0.5, 0.5]]), "materials: base_color: material 1 has [-1, 0.5, 0.5]; allowed: finite and in [0, 1]"),
        (dict(base_color=[[1.5, 0.5, 0.5], [0.5, 0.5, 0.5]]), "materials: base_color: material 0 has [1.5, 0.5, 0.5]"),
        (dict(emission=[[0, 0, 0], [0, -1, 0]]), "materials: emission: material 1 has [0, -1, 0]; allowed: finite and >= 0"),
        (dict(emission=[[np.inf, 0, 0], [0, 0, 0]]), "materials: emission: material 0 has a NaN or infinite value"),
        (dict(roughness=[np.nan, 0.5]), "materials: roughness: material 0 has a NaN or infinite value"),
        (dict(metallic=[0.0, 0.0, 0.0]), "materials: metallic must have shape [2], got [3]"),
        (dict(opacity=[1.0, 1.5]), "materials: opacity: material 1 has 1.5; allowed: finite and in [0, 1]"),
        (dict(opacity=[-0.25, 1.0]), "materials: opacity: material 0 has -0.25; allowed: finite and in [0, 1]"),
        (dict(opacity=[np.nan, 1.0]), "materials: opacity: material 0 has a NaN or infinite value"),
        (dict(opacity=[1.0]), "materials: opacity must have shape [2], got [1]"),
    ],
)
def test_out_of_range_values_are_named(kwargs, message):
    kwargs = {"base_color": GREY, **kwargs}
    with pytest.raises(ValueError) as error:
        make_materials(**kwargs)
    assert str(error.value).startswith(message)


def test_range_ends_and_bright_emission_are_accepted():
    materials = make_materials([[0.0, 1.0, 0.0]], roughness=[0.0], metallic=[1.0], emission=[[17.0, 12.0, 4.0]])
    np.testing.assert_array_equal(materials.roughness, [0.0])
    np.testing.assert_array_equal(materials.emission, [[17.0, 12.0, 4.0]])
