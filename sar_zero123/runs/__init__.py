"""Runs: where a stage writes, and how it starts, checkpoints, resumes and finishes.

- :mod:`~sar_zero123.runs.folder`: the run-folder rule every stage and command applies before any work
  (``open_run_folder``, ``finish_run``).
- :mod:`~sar_zero123.runs.restart`: the one restart rule (``check_restart_target``, ``move_aside``).
- :mod:`~sar_zero123.runs.lock`: one writer per output folder.
- :mod:`~sar_zero123.runs.stage`: the rule under ``accelerate launch`` (``open_stage_folder``) and the
  withdrawal of a run whose setup failed (``withdrawn_if_setup_fails``).
- :mod:`~sar_zero123.runs.launch`: starting a training run (``start_run``) and checks of its batches.
- :mod:`~sar_zero123.runs.checkpoints`: crash-safe checkpoints, resuming and ending a run (``end_run``).
- :mod:`~sar_zero123.runs.manifest`: sealed folders (``manifest.json``: size and SHA-256 of every file).

Nothing is imported here, so that a light module (``runs.folder``) does not load accelerate or torch.
"""
