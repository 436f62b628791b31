"""Ops for participating media: camera rays, ray–box clipping, trilinear volume lookups, phase functions."""

from gpupro.media.phase import henyey_greenstein, rayleigh_phase
from gpupro.media.rays import pixel_rays, ray_box
from gpupro.media.volumes import trilinear

__all__ = ["henyey_greenstein", "pixel_rays", "ray_box", "rayleigh_phase", "trilinear"]
