"""Training: the step, its losses (Eq. 19-21) and the parts of a fine-tuning run around it.

Run folders and checkpoints live in :mod:`sar_zero123.runs`, the stages that assemble runs in
:mod:`sar_zero123.stages`. Nothing is imported here, so one module does not load the training stack.
"""
