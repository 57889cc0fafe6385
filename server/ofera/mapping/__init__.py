"""Blendshape layouts and the mappings from headset blendshapes to the avatar's expression input."""
