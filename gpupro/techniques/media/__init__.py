"""Participating media: atmosphere, fog, clouds, sparse volumes, explosions, volume AO."""
