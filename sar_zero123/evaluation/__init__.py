"""Evaluation: metrics (corrected and paper-comparable), evaluator models and scoring with them, the Table
III protocol, speed against error, tables, and frozen-feature probes. Nothing is imported here, so that
importing one module does not load the others.
"""
