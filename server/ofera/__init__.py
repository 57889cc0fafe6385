"""OFERA server: blendshape-driven 3D Gaussian head avatars, streamed in real time."""

__version__ = "0.1.0"
