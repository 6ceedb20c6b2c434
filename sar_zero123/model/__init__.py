"""The model: the SAR zero-1-to-3 pipeline and what it is built from (``docs/ARCHITECTURE.md`` lists the
modules). Nothing is imported here, so that a light module (``loading``) does not load the pipeline.
"""
