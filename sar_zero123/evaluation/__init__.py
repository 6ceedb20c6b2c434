"""Evaluation: metrics, evaluator models and the Table III protocol.

- :mod:`~sar_zero123.evaluation.metrics`: image and pose metrics of the reference implementation.
- :mod:`~sar_zero123.evaluation.paper_metrics`: the paper-comparable SSIM variants.
- :mod:`~sar_zero123.evaluation.evaluators`: the classifier and azimuth regressor that score views.
- :mod:`~sar_zero123.evaluation.scoring`: scoring generated views and pose following with them.
- :mod:`~sar_zero123.evaluation.protocol`: the Table III protocol (pairs, generation, scoring).
- :mod:`~sar_zero123.evaluation.speed`: speed against error over pipelines, schedulers and step counts.
- :mod:`~sar_zero123.evaluation.tables`: the protocol's results as tables.
- :mod:`~sar_zero123.evaluation.probes`: frozen features of a SAR encoder and the 1-NN probe (the trained
  probes: :mod:`sar_zero123.training.probes`).

Nothing is imported here, so that importing one module does not load the others.
"""
