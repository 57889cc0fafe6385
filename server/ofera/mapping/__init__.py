"""The mapping at run time (numpy + onnxruntime; what the server imports): headset blendshapes -> avatar input.

``layouts`` (blendshape layouts, adapters to arkit51), ``bda`` (Blendshape Distribution Alignment),
``runtime`` (the EPM on ONNX Runtime: ``Mapper``, the reference), ``epm_program`` (an EPM's graph as a program),
``map_fast`` (the map's numba fast path: the layout's product, the EPM program), ``flame_values`` (the 68 FLAME
values), ``baselines`` (linear mappers the EPM is compared with), ``provenance`` (how a shipped EPM was made, read
from its metadata).
Training, export and evaluation of the EPM, and its paired data, live in ``ofera.training`` (``epm``, ``paired``).
"""
