"""gpupro: a JAX laboratory for real-time rendering techniques."""

from gpupro import scene
