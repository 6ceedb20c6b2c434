"""The model: the SAR zero-1-to-3 pipeline and what it is built from.

- :mod:`~sar_zero123.model.pipeline`: ``SARZero123Pipeline``, novel views in numbered stages.
- :mod:`~sar_zero123.model.pipeline_loading`, :mod:`~sar_zero123.model.pipeline_checks`,
  :mod:`~sar_zero123.model.view_request`, :mod:`~sar_zero123.model.guidance`: its loading and recorded
  settings, its checks, a call's request, and the guidance branches of its UNet call.
- :mod:`~sar_zero123.model.conditioning`: the pose vector (``embed_pose``), ``PoseProjection``, image
  and latent conditioning.
- :mod:`~sar_zero123.model.orientation`: the estimated absolute azimuth (``AzimuthEstimator``).
- :mod:`~sar_zero123.model.build`: the model sizes, ``build_sar_zero123`` and ``load_sar_zero123``.
- :mod:`~sar_zero123.model.zero123_checkpoints`: loading zero-1-to-3 weights (Stable Diffusion layout).
- :mod:`~sar_zero123.model.loading`: loading saved components with errors that name them.

Nothing is imported here, so that a light module (``loading``) does not load the pipeline.
"""
