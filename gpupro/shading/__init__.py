"""Shading: BRDFs and the evaluation of lights at surface points."""

from gpupro.shading.brdfs import (
    ALPHA_MIN,
    DIELECTRIC_F0,
    DISTRIBUTIONS,
    beckmann_to_phong_power,
    blinn_phong,
    brdf,
    cook_torrance,
    d_beckmann,
    d_ggx,
    d_phong,
    fresnel_schlick,
    g1_smith_beckmann,
    g1_smith_ggx,
    g_smith,
    lambert,
    phong_power_to_beckmann,
)
from gpupro.shading.light_falloff import (
    DISTANCE_EPSILON_SQ,
    SPOT_MIN_COS_WIDTH,
    distance_falloff,
    incident_light,
    spot_falloff,
)
from gpupro.shading.deferred import DEFERRED_INPUTS, accumulate_lights, shade_deferred, shade_surfaces
from gpupro.shading.forward import shade_forward
