"""Terrain and level of detail: geometry clipmaps, dynamic GPU terrain, grass and water."""
