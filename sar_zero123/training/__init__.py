"""Training: the step, its losses and the parts of a fine-tuning run around it (the training math).

- :mod:`~sar_zero123.training.step`: the zero-1-to-3 training step (``compute_losses``) and its batches.
- :mod:`~sar_zero123.training.losses`: x0 estimate (Eq. 19), L_simple, Eq. 21 (``LossSettings``).
- :mod:`~sar_zero123.training.pfm`: Projected Feature Matching (Eq. 20) and its frozen feature encoders.
- :mod:`~sar_zero123.training.finetuning`: the parts of a fine-tuning run around the step.
- :mod:`~sar_zero123.training.validation`: validation pairs, samples and pose following during training.

Run folders, checkpoints and starting a run live in :mod:`sar_zero123.runs`; the stage functions that
assemble both into runs in :mod:`sar_zero123.stages`. Nothing is imported here, so that importing one
module does not load the training stack.
"""
