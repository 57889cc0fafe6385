"""Training of the mapping (offline; torch for ``model`` and ``export``): the EPM and how it is made and scored.

- ``model``: the EPM network (the paper's MLP), its training on paired data and its checkpoints (torch);
- ``export``: checkpoint -> ONNX, checked against torch (what ``ofera.mapping.runtime.Mapper`` runs);
- ``make_default``: the recipe of the shipped default EPM (``ofera mapping make-default``);
- ``evaluate``: the EPM against the baselines (``ofera.mapping.baselines``) on the synthetic paired benchmark
  (``ofera.training.paired``), with and without BDA (numpy; ``ofera mapping eval``).

The server never imports this package: its run-time side is ``ofera.mapping``.
"""
