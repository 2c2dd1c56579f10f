"""fitting: recover material, light and fog parameters from images (builds on diffshade)."""
