"""Validation cases of the diagnosis: measured frames (and series) with effects the model lacks."""
