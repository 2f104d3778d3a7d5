"""Evaluation: padding-free prediction metrics, limit errors, paired tests and claims tables."""
