"""Training: the step, its losses, the run around it, and the run-folder rule.

- :mod:`~sar_zero123.training.step`: the zero-1-to-3 training step (``compute_losses``) and its batches.
- :mod:`~sar_zero123.training.losses`: x0 estimate (Eq. 19), L_simple, PFM and Eq. 21 (``LossSettings``).
- :mod:`~sar_zero123.training.finetuning`: the parts of a fine-tuning run around the step.
- :mod:`~sar_zero123.training.validation`: validation pairs, samples and pose following during training.
- :mod:`~sar_zero123.training.runs`: starting a run (``start_run``); :mod:`~sar_zero123.training.run_state`:
  training checkpoints, resuming and ending a run (``end_run``).
- :mod:`~sar_zero123.training.run_folder`: the run-folder rule every stage applies before any work.

The stage functions that assemble these into runs live in :mod:`sar_zero123.stages`. Nothing is imported
here, so that a light module (``run_folder``) does not load the training stack.
"""
