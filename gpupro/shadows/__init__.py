"""Shadow ops: shadow maps built from the scene's lights and looked up with percentage-closer filtering
(shared by the shadow passes, shading and the volumetric fog)."""

from gpupro.shadows.maps import ShadowMaps, build_shadow_maps, shadow_factor
