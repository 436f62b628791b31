"""Shadows: shadow maps for point (cube), spot and directional lights, looked up with PCF."""

from gpupro.shadow.shadow_maps import (
    ShadowMaps,
    build_shadow_maps,
    cube_face,
    directional_light_matrix,
    frustum_corners,
    light_matrices,
    point_light_matrices,
    project_to_shadow_maps,
    render_shadow_map,
    shadow_factor,
    spot_light_matrix,
)
