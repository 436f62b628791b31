"""Post-processing passes: exposure, tone mapping and sRGB encoding; edge-detect antialiasing."""
