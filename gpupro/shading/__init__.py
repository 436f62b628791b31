"""Shading models shared by every technique: BRDFs, light falloff, light bounds and the light loop."""

from gpupro.shading.brdfs import (ALPHA_MIN, DIELECTRIC_F0, DISTRIBUTIONS, beckmann_to_phong_power, blinn_phong, brdf,
                                  brdf_towards, cook_torrance, d_beckmann, d_ggx, d_phong, fresnel_schlick,
                                  g1_smith_beckmann, g1_smith_ggx, g_smith, lambert, phong_power_to_beckmann,
                                  view_terms)
from gpupro.shading.light_bounds import (SLACK, box_meets_light, light_boxes, light_spheres, segment_box_distance,
                                         sphere_meets_cones, sphere_meets_light, transform_lights)
from gpupro.shading.light_falloff import (DISTANCE_EPSILON_SQ, SPOT_MIN_COS_WIDTH, distance_falloff, incident_light,
                                          nearest_on_segment, representative_points, spot_falloff)
from gpupro.shading.light_loop import (accumulate_light_lists, accumulate_lights, check_shading_inputs,
                                       compose_radiance, light_reaches, shade_surfaces, view_directions)
from gpupro.shading.light_terms import default_light_chunk, light_radiance, sum_over_lights, surface_terms
