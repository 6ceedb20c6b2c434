"""Runs: where a stage writes, and how it starts, checkpoints, resumes and finishes.

Nothing is imported here, so that a light module (``runs.folder``) does not load accelerate or torch.
"""
