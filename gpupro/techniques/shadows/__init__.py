"""Shadows: shadow maps for point (cube), spot and directional lights, looked up with PCF."""
